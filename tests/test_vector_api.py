"""Gymnasium's vector API and SB3's SubprocVecEnv on both registered ids, with sensor stacks."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import av_gym  # noqa: F401 - registers the ids
from av_gym.errors import ConfigError

TURN, LANE = "av_gym/UnprotectedLeftTurn-v0", "av_gym/LaneKeepingLap-v0"
# short episodes so that every env ends (and autoresets) within the test
SHORT = {TURN: {"duration": 1.0}, LANE: {"time_limit": 1.0}}


def _drive(venv, steps: int = 14) -> dict:
    obs, info = venv.reset(seed=0)
    ended = 0
    for _ in range(steps):
        obs, _, terminated, truncated, info = venv.step(venv.action_space.sample())
        assert venv.observation_space.contains(obs)
        ended += int(np.sum(terminated | truncated))
    assert ended >= venv.num_envs  # every env ended an episode and went on
    return info


@pytest.mark.parametrize("mode", ["sync", "async"])
@pytest.mark.parametrize("env_id,sensors,shield", [(TURN, None, None), (TURN, "turn_truth", None),
                                                   (LANE, None, None), (LANE, "gnss_imu", None)])
def test_make_vec(mode, env_id, sensors, shield) -> None:
    """make_vec crashed at reset on the left turn (info["truth"]["others"] changes length from env to env)."""
    kwargs = {"sensors": sensors, "shield": shield, "env": SHORT[env_id]} if sensors else {"config": SHORT[env_id]}
    venv = gym.make_vec(env_id, num_envs=2, vectorization_mode=mode, **kwargs)
    try:
        info = _drive(venv)
        truth = info["truth"]  # object-typed: each env's own truth
        assert truth.dtype == object and truth[0]["others"].shape[1] == 7
    finally:
        venv.close()


def _leaves(info: dict, path: str = "") -> list[tuple[str, np.ndarray]]:
    """Every batched value of a vector env's ``info`` (nested dicts walked; the ``_key`` masks left out)."""
    out = []
    for key, value in info.items():
        if isinstance(value, dict):
            out += _leaves(value, f"{path}{key}.")
        elif not key.startswith("_"):
            out.append((f"{path}{key}", np.asarray(value)))
    return out


AEB_INFO = ("aeb_stage", "aeb_ttc", "aeb_horizon", "aeb_override", "aeb_target_id", "aeb_active", "aeb_infeasible",
            "aeb_brake_time", "aeb_stop_position", "aeb_action", "aeb_withheld")


def _kind(value) -> str:
    """What a vector env batches a value into: numpy and Python numbers of one kind alike."""
    for kind, types in (("bool", (bool, np.bool_)), ("int", (int, np.integer)), ("float", (float, np.floating))):
        if isinstance(value, types):
            return kind
    return f"array {value.dtype} {value.shape}" if isinstance(value, np.ndarray) else type(value).__name__


@pytest.mark.parametrize("env_id,kwargs", [
    (TURN, {"sensors": "turn_perceived", "shield": "aeb"}),
    (TURN, {"sensors": "turn_truth", "shield": "aeb_standard", "env": {"action": "continuous"}}),
    (LANE, {"sensors": "lane_localized"}),
])
def test_every_info_key_has_one_kind_at_reset_and_in_every_step(env_id, kwargs) -> None:
    """What every info producer (the scenario, sensors, localizer, shield, metrics recorder) gives, over two short
    episodes, reset included: one kind per key (a vector env types its array by the first env's value: None beside
    an int raised, an int before a float would truncate it), and no None anywhere."""
    env = gym.make(env_id, **{**kwargs, "env": {**kwargs.get("env", {}), **SHORT[env_id]}})
    kinds: dict[str, set] = {}
    for seed in (3, 4):
        _, info = env.reset(seed=seed)
        infos, done = [info], False
        while not done:
            action = np.ones(env.action_space.shape, np.float32) if env.action_space.shape else 2
            _, _, terminated, truncated, info = env.step(action)
            infos.append(info)
            done = terminated or truncated
        for info in infos:
            for path, value in _leaf_values(info):
                kinds.setdefault(path, set()).add(_kind(value))
    env.close()
    assert {path: k for path, k in kinds.items() if len(k) > 1 or "NoneType" in k} == {}
    assert any(p.startswith("episode_metrics.") for p in kinds) and ("aeb_action" in kinds) == ("shield" in kwargs)


def _leaf_values(info: dict, path: str = ""):
    """(path, value) of every non-dict value of one env's ``info``."""
    for key, value in info.items():
        if isinstance(value, dict):
            yield from _leaf_values(value, f"{path}{key}.")
        else:
            yield f"{path}{key}", value


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_info_keeps_one_type_when_the_envs_episodes_end_at_different_steps(mode) -> None:
    """R7 finding 1: with the shield, an env's autoreset step (NEXT_STEP: its reset's info) while the other env
    drives gave ``aeb_action`` None beside an int, and Gymnasium's ``_add_info`` raised a TypeError (before: the
    shield said None for "no action yet" and for an unknown brake time / stop position). Env 0 starts again 4
    steps in, so the two envs' 1-s episodes end 4 steps apart; every step, every info value must batch into a
    typed array (an object array only of values that are objects in each env: ``truth``, highway-env's tuples),
    with the documented sentinels where an env just reset."""
    from av_gym.shields.aeb import NO_ACTION, NOT_YET

    venv = gym.make_vec(TURN, num_envs=2, vectorization_mode=mode, sensors="turn_truth", shield="aeb",
                        env=SHORT[TURN])
    try:  # not finally: see the except below
        venv.reset(seed=[7, 8])
        for _ in range(4):
            venv.step(np.full(2, 2))
        venv.reset(options={"reset_mask": np.array([True, False])})
        ended, restarted = [], 0
        for _ in range(24):
            _, _, terminated, truncated, info = venv.step(np.full(2, 2))
            ended.append(terminated | truncated)
            for path, a in _leaves(info):  # object arrays only for values that are objects in every env
                kinds = {type(v) for v in a} if a.dtype == object else set()
                assert type(None) not in kinds and len(kinds) <= 1, (path, a)
            assert all(info[k].dtype != object for k in AEB_INFO), {k: info[k] for k in AEB_INFO}
            just_reset = np.asarray([t["time"] == 0.0 for t in info["truth"]])
            restarted += int(just_reset.sum())
            assert np.all((info["aeb_action"] == NO_ACTION) == just_reset)  # FASTER (2) while driving
            assert np.all(np.isinf(info["aeb_brake_time"][just_reset]) & (info["aeb_brake_time"][just_reset] > 0))
            assert np.all((info["aeb_stop_position"] == NOT_YET)[just_reset])
        steps = [np.nonzero(np.array(ended)[:, i])[0] for i in range(2)]
        assert len(steps[0]) and len(steps[1]) and steps[0][0] != steps[1][0]  # the episodes ended apart
        assert restarted >= 2
    except BaseException:
        # a step that failed in _add_info leaves AsyncVectorEnv waiting for it: its plain close() blocked forever
        venv.close(terminate=True)
        raise
    venv.close()


@pytest.mark.slow  # 2-20 s each on a loaded 2-core machine
@pytest.mark.parametrize("mode", ["sync", "async"])
@pytest.mark.parametrize("env_id,sensors,shield", [(TURN, "turn_perceived", "aeb"), (TURN, "localized", "aeb")] + [
    (env_id, p, None) for env_id, p in [(LANE, p) for p in ("gnss_raw", "lidar", "camera_centre", "cameras",
                                                                 "detector", "full", "localized", "lane_localized")]
                         + [(TURN, p) for p in ("truth", "turn_perceived", "localized")]])
def test_make_vec_every_preset(mode, env_id, sensors, shield) -> None:
    venv = gym.make_vec(env_id, num_envs=2, vectorization_mode=mode, sensors=sensors, shield=shield,
                        env=SHORT[env_id])
    try:
        _drive(venv)
    finally:
        venv.close()


@pytest.mark.slow  # ~10 s: the batch's numba kernels compile on first use
def test_vector_entry_point_is_the_batched_engine() -> None:
    from av_gym.batched.vec_env import BatchedLeftTurnVectorEnv

    venv = gym.make_vec(TURN, num_envs=4, sensors="turn_truth", env=SHORT[TURN])
    assert isinstance(venv, BatchedLeftTurnVectorEnv)
    obs, _ = venv.reset(seed=0)
    assert obs["turn"].shape == (4, venv.single_observation_space["turn"].shape[0])
    for _ in range(12):
        venv.step(venv.action_space.sample())


def _episode_end_infos(venv, steps: int = 14) -> list[dict]:
    """The ``info`` of every step on which an env's episode ended (FASTER throughout, seeds 7 and 8)."""
    venv.reset(seed=[7, 8])
    out = []
    for _ in range(steps):
        _, _, terminated, truncated, info = venv.step(np.full(2, 2))
        if np.any(terminated | truncated):
            assert np.array_equal(info["_episode_metrics"], terminated | truncated)
            out.append(info)
    return out


@pytest.mark.slow  # ~10 s: the batch's numba kernels compile on first use
def test_the_batch_gives_the_episode_end_info_as_the_per_env_vector_env() -> None:
    """``gymnasium.make_vec(id, n, shield="aeb")`` (the batch) batches an ended episode's ``episode_metrics`` and
    the shield's ``aeb_brake_time`` / ``aeb_stop_position`` under the same keys, with the same dtypes and masks, as
    ``vectorization_mode="sync"`` (it gave a list of dicts, None where an env went on)."""
    kwargs = {"sensors": "turn_truth", "shield": "aeb", "env": SHORT[TURN]}
    sync, batch = gym.make_vec(TURN, 2, vectorization_mode="sync", **kwargs), gym.make_vec(TURN, 2, **kwargs)
    try:
        want, got = _episode_end_infos(sync), _episode_end_infos(batch)
    finally:
        sync.close(), batch.close()
    assert len(want) == len(got) >= 1
    for w, g in zip(want, got):
        ended = w["_episode_metrics"]
        assert np.array_equal(g["_episode_metrics"], ended)
        assert {k: a.dtype for k, a in _leaves(g["episode_metrics"])} == \
            {k: a.dtype for k, a in _leaves(w["episode_metrics"])}
        for key in ("aeb_brake_time", "aeb_stop_position"):  # never braked in 1 s: the sentinel in both
            assert np.array_equal(g[f"_{key}"], ended), key  # the batch says it for the ended envs
            assert g[key].dtype == w[key].dtype == np.float64, (key, g[key])
            assert np.array_equal(g[key][ended], w[key][ended]) and np.all(g[key][ended] == np.inf), (key, g[key])


@pytest.mark.parametrize("kwargs,says", [
    ({}, 'the batched engine needs sensors="turn_truth"'),
    ({"sensors": {"name": "turn_perceived", "detector": {"frame": "ego"}}},
     "sensors.tracker needs sensors.detector.frame=world"),
    ({"sensors": "turn_truth", "shield": "aeb_paper"}, "shield.variant=paper is not available with the batched engine"),
    ({"sensors": "turn_truth", "render_mode": "rgb_array"}, "render_mode is not available"),
    # make()'s keywords that only a per-env stack takes, named with the engine's own keywords
    ({"checkpoint": "dagger_turn"}, "checkpoint= is not available with the batched engine (it takes env=, sensors="),
    ({"sensors": "turn_truth", "record_metrics": False}, "record_metrics= is not available with the batched engine"),
    ({"checkpoint": "dagger_turn", "record_metrics": True}, "checkpoint=, record_metrics= are not available"),
])
def test_vector_entry_point_refuses_in_one_line(kwargs, says) -> None:
    with pytest.raises(ConfigError) as err:
        gym.make_vec(TURN, num_envs=2, **kwargs)
    # a value every mode refuses (the tracker's frame=ego) gets no hint to use another mode
    hint = "needs sensors.detector.frame" not in says
    assert says in str(err.value) and ('vectorization_mode="sync"' in str(err.value)) == hint
    assert "\n" not in str(err.value)


@pytest.mark.slow  # ~35 s: each worker is a fresh interpreter importing SB3, torch and av_gym
@pytest.mark.parametrize("env_id,kwargs", [(TURN, {"sensors": "turn_truth"}), (LANE, {"sensors": "gnss_imu"})])
def test_sb3_subproc_vec_env(env_id, kwargs) -> None:
    """SB3's make_vec_env with SubprocVecEnv: fresh worker processes (forkserver) import av_gym through the
    "av_gym:" module prefix of the id (Gymnasium 1.x has no plugin entry points)."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    venv = make_vec_env(f"av_gym:{env_id}", n_envs=2, seed=0, vec_env_cls=SubprocVecEnv,
                        env_kwargs={**kwargs, "env": SHORT[env_id]})
    try:
        venv.reset()
        dones = 0
        for _ in range(12):
            _, _, done, infos = venv.step(np.array([venv.action_space.sample() for _ in range(2)]))
            dones += int(done.sum())
        assert dones >= 2 and "truth" in infos[0]
    finally:
        venv.close()


@pytest.mark.slow  # ~35 s, as above
def test_sb3_subproc_vec_env_plain_id() -> None:
    """The plain id in forkserver workers: av_gym asks the forkserver to preload it ("Namespace av_gym not
    found" in every worker)."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    venv = make_vec_env(TURN, n_envs=2, seed=0, vec_env_cls=SubprocVecEnv, env_kwargs={"sensors": "turn_truth"},
                        vec_env_kwargs={"start_method": "forkserver"})
    try:
        assert venv.reset()["turn"].shape[0] == 2
    finally:
        venv.close()
