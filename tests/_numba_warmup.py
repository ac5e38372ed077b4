"""Fill numba's on-disk cache before ``pytest -n`` starts its workers (tests/conftest.py: pytest_configure).

Why: the kernels (``@numba.njit(cache=True)``: av_gym/sim, sensors, shields) compile on first use and are cached
beside their source; a fresh checkout (CI) has no cache, so each xdist worker compiled the same kernels at the
same time (the cache is written only after a compile ends). Here two processes, one per part, drive each stack a
few steps with every kernel's argument types, so the workers find the cache filled. Nothing is asserted: a
kernel this misses compiles on first use as before.

    python tests/_numba_warmup.py batch|per_env
"""

from __future__ import annotations

import os
import sys

TURN, LANE = "av_gym/UnprotectedLeftTurn-v0", "av_gym/LaneKeepingLap-v0"


def _batch(kw: dict) -> None:
    """The batched engine (``gymnasium.make_vec``) with ``kw``, 4 envs, 40 random steps."""
    import gymnasium as gym
    import numpy as np

    import av_gym  # noqa: F401  (registers the envs)

    venv = gym.make_vec(TURN, num_envs=4, **kw)
    venv.reset(seed=0)
    venv.single_action_space.seed(0)
    for _ in range(40):
        venv.step(np.array([venv.single_action_space.sample() for _ in range(4)]))
    venv.close()


def _per_env(env_id: str, kw: dict) -> None:
    """The per-env stack (``gymnasium.make``) of ``env_id`` with ``kw``, 30 random steps."""
    import gymnasium as gym

    import av_gym  # noqa: F401  (registers the envs)

    env = gym.make(env_id, **kw)
    env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(30):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset(seed=1)
    env.close()


# Why this split: the batched engine is the longest chain (ground truth alone ~80 CPU-s compiled into an empty cache),
# so one part compiles the engine (perceived first, then ground truth and its variants) and then the fog cameras'
# depth painting; the other the AEB shield per env (it needs no engine kernel), the cameras' rasters, the LiDAR and
# the perceived stack, per env and shielded on the batch last, when the engine's kernels are most likely cached (a
# kernel both parts reach before the other has cached it is compiled twice, not missed). Both parts at once into an
# empty cache in a fresh clone (-n 2, load ~2): batch 61, per_env 69 CPU-s.
def batch() -> None:
    """The batched engine: perceived sensors, ground truth, memory features, CCFtap and continuous actions; then the
    cameras' depth painting in fog (per env; it balances the parts). Perceived first: its
    detector kernels (detector_view_rows, frame_draws_span) are then cached before the per_env part's perceived
    stack needs them; after ground truth, both parts compiled them at once (~2.6 CPU-s twice, compile log)."""
    for kw in ({"sensors": "turn_perceived"}, {"sensors": "turn_truth"}, {"sensors": "turn_truth_memory"},
               {"sensors": "turn_truth", "env": {"mode": "ccftap"}},
               {"sensors": "turn_truth", "env": {"action": "continuous"}}):
        _batch(kw)
    _per_env(LANE, {"sensors": _foggy_cameras()})


def _foggy_cameras() -> dict:
    """The shipped cameras in fog: fog and night paint with a depth buffer (raster.paint_depth), kernels the clear
    cameras never compile (test_camera's weather tests compiled them in a worker: ~4 CPU-s); in the batch part,
    the shorter one with them."""
    from av_gym.presets import compose_group

    sensors = compose_group("sensors", "cameras")
    sensors["cameras"] = {**sensors["cameras"], "fog_visibility": 80.0}
    return sensors


def per_env() -> None:
    """The AEB shield (per env, then on the batch with perceived sensors), the cameras' rasters and the LiDAR."""
    _per_env(TURN, {"sensors": "turn_truth", "shield": "aeb"})
    _per_env(LANE, {"sensors": "cameras"})
    # the LiDAR here, before the perceived stack: the batch part's detector kernels are then cached when that
    # needs them (at the same time, both parts compiled them: compile log, ~4 CPU-s twice)
    _per_env(LANE, {"sensors": "lidar"})
    _per_env(TURN, {"sensors": "turn_perceived", "shield": "aeb"})
    _batch({"sensors": "turn_perceived", "shield": "aeb"})


PARTS = {"batch": batch, "per_env": per_env}

if __name__ == "__main__":
    PARTS[sys.argv[1]]()
    # Done: numba wrote each kernel's cache files as it compiled it. Leave without the interpreter's teardown
    # (~1-2 s of wall for the compiled libraries, after the last compile): conftest waits for this process before any
    # test starts. An exception above exits as usual, with its traceback and status 1.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
