"""Fill numba's on-disk cache before ``pytest -n`` starts its workers (tests/conftest.py: pytest_configure).

Why: the kernels (``@numba.njit(cache=True)``: av_gym/sim, sensors, shields) compile on first use and are cached
beside their source; a fresh checkout (CI) has no cache, so each xdist worker compiled the same kernels at the
same time (the cache is written only after a compile ends). Here two processes, one per part, drive each stack a
few steps with every kernel's argument types, so the workers find the cache filled. Nothing is asserted: a
kernel this misses compiles on first use as before.

    python tests/_numba_warmup.py batch|per_env
"""

from __future__ import annotations

import sys

TURN, LANE = "av_gym/UnprotectedLeftTurn-v0", "av_gym/LaneKeepingLap-v0"


def batch() -> None:
    """The batched engine (``gymnasium.make_vec``): perceived sensors with the AEB shield, memory features,
    CCFtap and continuous actions."""
    import gymnasium as gym
    import numpy as np

    import av_gym  # noqa: F401  (registers the envs)

    for kw in ({"sensors": "turn_perceived", "shield": "aeb"}, {"sensors": "turn_truth_memory"},
               {"sensors": "turn_truth", "env": {"mode": "ccftap"}},
               {"sensors": "turn_truth", "env": {"action": "continuous"}}):
        venv = gym.make_vec(TURN, num_envs=4, **kw)
        venv.reset(seed=0)
        venv.single_action_space.seed(0)
        for _ in range(40):
            venv.step(np.array([venv.single_action_space.sample() for _ in range(4)]))
        venv.close()


def per_env() -> None:
    """The per-env stacks (``gymnasium.make``): perceived sensors and the shield on the left turn, the cameras'
    and the LiDAR's rasters on the lane-keeping lap."""
    import gymnasium as gym

    import av_gym  # noqa: F401  (registers the envs)

    for env_id, kw in ((TURN, {"sensors": "turn_perceived", "shield": "aeb"}), (LANE, {"sensors": "cameras"}),
                       (LANE, {"sensors": "lidar"}), (TURN, {"sensors": "turn_truth", "shield": "aeb"})):
        env = gym.make(env_id, **kw)
        env.reset(seed=0)
        env.action_space.seed(0)
        for _ in range(30):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset(seed=1)
        env.close()


PARTS = {"batch": batch, "per_env": per_env}

if __name__ == "__main__":
    PARTS[sys.argv[1]]()
