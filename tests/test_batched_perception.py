"""The perceived left-turn stack on the batch (av_gym/batched/perception.py) against the per-env stack
(Detector → ObjectTracker on filterpy → TurnFeatures(source=tracks) → TurnIntent), same seeds, same actions.

Tolerances, and why:
- detections (``obs["detector"]``): equal bit for bit. Each env draws from the per-env detector's own generator
  (``episode_rng(episode_seed, "detector")``) in the same order, and the noise is the same elementwise arithmetic.
- tracker states (each track's filter mean and covariance, float64): within 1e-9 (relative and absolute). The batch
  multiplies stacks of 4x4 matrices (``np.matmul``) where filterpy calls ``np.dot`` per track; both are the same
  formulas in the same order (Joseph-form update), but another BLAS or CPU may round a product's last bit
  differently (measured here: equal bit for bit on every step of every episode below). Track ids, confirmation and
  the number of tracks must be equal: they are decisions, and a decision split is reported by seed and step.
- ``obs["tracks"]``, ``obs["turn"]``, ``obs["intent"]`` (float32): within 1e-4, one float32 step of a coordinate of
  ~100 m (7.6e-6 m) being what a last-bit difference of the double may flip.
- episode outcomes with a policy on these features: equal in >= 99 % of 200 episodes (slow test; a few in the fast
  suite). A split (a gate or an assignment at a tie decided by a last bit, then a different GO) is named by seed.
"""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.batched.vec_env import BatchedLeftTurnBatch
from av_gym.estimation.object_tracking import ObjectTracker
from av_gym.make import make_env
from av_gym.presets import compose_group
from av_gym.sensors.base import find_wrapper

KEYS = ("detector", "tracks", "turn", "intent")
STATE_TOL = 1e-9
OBS_TOL = 1e-4
ENV = {"name": "left_turn"}


def _sensors(preset: str = "turn_perceived", **detector) -> dict:
    s = {k: v for k, v in compose_group("sensors", preset).items() if k != "observe"}
    s["detector"] = {**s["detector"], **detector}
    return s


def _actions(seed: int, n: int = 400) -> np.ndarray:
    """A seeded meta-action sequence (SLOWER / IDLE / FASTER), the same for both stacks."""
    return np.random.default_rng(seed).choice(3, size=n, p=[0.2, 0.5, 0.3])


def _track_state(tracker) -> dict:
    tracks = tracker._tracks
    return {"id": np.array([t.id for t in tracks], int), "confirmed": np.array([t.confirmed for t in tracks], bool),
            "x": np.array([t.kf.x.reshape(-1) for t in tracks]).reshape(-1, 4),
            "P": np.array([t.kf.P for t in tracks]).reshape(-1, 4, 4)}


def _batch_track_state(tracker, r: int) -> dict:
    n = tracker.n[r]
    return {"id": tracker.id[r, :n].copy(), "confirmed": tracker.confirmed[r, :n].copy(),
            "x": tracker.x[r, :n, :, 0].copy(), "P": tracker.P[r, :n].copy()}


def per_env(seed: int, sensors: dict, n_steps: int = 400) -> list[tuple[dict, dict]]:
    """(observation, track state) of every step of the per-env stack's episode ``seed`` (its first ``n_steps``)."""
    env = make_env(ENV, sensors)
    tracker = find_wrapper(env, ObjectTracker).tracker
    obs, _ = env.reset(seed=seed)
    steps = [({k: obs[k].copy() for k in KEYS}, _track_state(tracker))]
    for a in _actions(seed)[:n_steps]:
        obs, _, term, trunc, _ = env.step(int(a))
        steps.append(({k: obs[k].copy() for k in KEYS}, _track_state(tracker)))
        if term or trunc:
            break
    env.close()
    return steps


def batched(seeds: list[int], sensors: dict) -> dict[int, list[tuple[dict, dict]]]:
    """The same for every seed, all on one batch (one env per seed)."""
    venv = BatchedLeftTurnBatch(ENV, {**sensors, "observe": list(KEYS)}, None, len(seeds), pool=0)
    tracker = venv.perception.tracker
    obs = venv.play(iter(seeds))
    out = {s: [({k: obs[k][i].copy() for k in KEYS}, _batch_track_state(tracker, i))] for i, s in enumerate(seeds)}
    acts = np.stack([_actions(s) for s in seeds], axis=1)
    step = 0
    while not venv.idle.all():
        live = ~venv.idle
        obs, _, ended, infos = venv.step(acts[step])
        step += 1
        for i in np.flatnonzero(live):
            o = infos[i]["terminal_observation"] if ended[i] else {k: obs[k][i] for k in KEYS}
            out[seeds[i]].append(({k: np.array(o[k]) for k in KEYS}, _batch_track_state(tracker, i)))
    return out


def first_split(a: list, b: list) -> str | None:
    """Where the batch's episode first differs from the per-env one beyond the stated tolerances (None: nowhere)."""
    if len(a) != len(b):
        return f"episode lengths {len(a)} vs {len(b)} steps"
    for n, ((oa, sa), (ob, sb)) in enumerate(zip(a, b)):
        if not np.array_equal(oa["detector"], ob["detector"]):
            return f"step {n}: detections"
        for key in ("id", "confirmed"):
            if not np.array_equal(sa[key], sb[key]):
                return f"step {n}: track {key} {sa[key]} vs {sb[key]}"
        for key in ("x", "P"):
            if not np.allclose(sa[key], sb[key], rtol=STATE_TOL, atol=STATE_TOL):
                return f"step {n}: track {key} off by {np.abs(sa[key] - sb[key]).max():.3g}"
        for key in ("tracks", "turn", "intent"):
            if not np.allclose(oa[key], ob[key], rtol=0, atol=OBS_TOL):
                return f"step {n}: obs[{key!r}] off by {np.abs(oa[key] - ob[key]).max():.3g}"
    return None


def _splits(seeds: list[int], sensors: dict) -> dict[int, str]:
    got = batched(seeds, sensors)
    splits = {s: first_split(per_env(s, sensors), got[s]) for s in seeds}
    return {s: v for s, v in splits.items() if v is not None}


def test_detections_tracks_and_features_are_the_per_env_ones():
    """turn_perceived: every step of 2 episodes (seeded varied actions) gives the per-env detections, the same
    tracks (ids, confirmation) with the same filter states, and the same obs["tracks"], obs["turn"], obs["intent"].
    (The batch steps them side by side, so two envs exercise the per-row indexing; more seeds run in the slow
    suite's 200-episode outcome test.)"""
    assert _splits([3, 1_000_000], _sensors()) == {}


def test_bursty_misses_clutter_and_a_front_camera_are_the_per_env_ones():
    """The detector's other branches: Gilbert-Elliott bursts (both chain states), heavy clutter (many births and
    deletions of tentative tracks), a 120° field of view, and a tracker without velocity measurements."""
    s = _sensors(miss_rate=0.3, burst_length=3.0, clutter_rate=2.0, fov_deg=120.0)
    s["tracker"] = {**s["tracker"], "use_velocity": False, "min_hits": 3}
    assert _splits([7, 8], s) == {}


def test_memory_intent_on_tracks_is_the_per_env_one():
    """turn_perceived_memory: the turn beliefs carried along the tracks (IntentHistory on the batch's tracks)."""
    assert _splits([11], _sensors("turn_perceived_memory")) == {}


def test_the_tracker_is_not_blind_to_its_model():
    """The comparison can fail: a batch tracker with another process noise gives other states from the first
    prediction (so a wrong Q, gate or update would be caught)."""
    from av_gym.batched import perception

    s = _sensors()
    venv = BatchedLeftTurnBatch(ENV, {**s, "observe": list(KEYS)}, None, 1, pool=0)
    venv.perception.tracker.params = perception.TrackerParams(**{**venv.perception.tracker.params.__dict__,
                                                                   "sigma_acc": 2.5})
    venv.play(iter([3]))
    ref = per_env(3, s, n_steps=20)  # 2 s: the states part from the first prediction
    got = [ref[0]]
    for a in _actions(3)[: len(ref) - 1]:
        obs, _, ended, infos = venv.step(np.array([a]))
        o = infos[0]["terminal_observation"] if ended[0] else {k: obs[k][0] for k in KEYS}
        got.append(({k: np.array(o[k]) for k in KEYS}, _batch_track_state(venv.perception.tracker, 0)))
        if ended[0]:
            break
    split = first_split(ref, got)
    assert split is not None and "track" in split, split


def _outcomes(spec: str, seeds: list[int], batched_: bool) -> list[dict]:
    from eval.agents import plan_agent, resolve_agent
    from eval.batched import run_episodes_batched
    from eval.runner import run_episodes

    from tests.conftest import conf

    env_cfg = conf("env", "left_turn")
    plan = plan_agent(spec, "left_turn", conf("sensors", "truth"), {"name": "none", "kind": "none"}, "checkpoints")
    env = make_env(env_cfg, plan.sensors, plan.shield)
    label, policy = resolve_agent(plan.spec, env, "left_turn", "checkpoints")
    if batched_:
        env.close()
        return run_episodes_batched(env_cfg, plan, policy, seeds, min(50, len(seeds)), label, progress=False)
    try:
        return run_episodes(env, policy, seeds, label, progress=False)
    finally:
        env.close()


def _outcome_splits(spec: str, seeds: list[int]) -> list[str]:
    ref, bat = _outcomes(spec, seeds, False), _outcomes(spec, seeds, True)
    assert [r["seed"] for r in bat] == [r["seed"] for r in ref] == seeds
    keys = ("collision", "success", "length", "truncated")
    return [f"seed {a['seed']}: " + ", ".join(f"{k} {a[k]} vs {b[k]}" for k in keys if a[k] != b[k])
            for a, b in zip(ref, bat) if any(a[k] != b[k] for k in keys)]


def test_a_perceived_student_ends_its_episodes_as_on_the_per_env_stack():
    """dagger_turn_perceived (the reference checkpoint, go/yield on turn + intent from tracks) on 2 validation
    seeds: the same collision, success, length and truncation, per-env and on the batch (200 seeds: slow test)."""
    assert _outcome_splits("dagger_turn_perceived", list(range(1_000_000, 1_000_002))) == []


@pytest.mark.slow  # ~3 CPU-minutes: 200 per-env perceived episodes with a network
def test_a_perceived_student_ends_200_episodes_as_on_the_per_env_stack():
    """The same over 200 validation seeds: equal outcomes in >= 99 % (198); the splits are named (measured here:
    200 of 200 equal)."""
    seeds = list(range(1_000_000, 1_000_200))
    splits = _outcome_splits("dagger_turn_perceived", seeds)
    assert len(splits) <= 2, splits


def test_make_vec_gives_the_perceived_stack():
    """gymnasium.make_vec(id, n, sensors="turn_perceived"): the batched engine, with the preset's observation."""
    import gymnasium as gym

    from av_gym.batched.vec_env import BatchedLeftTurnVectorEnv

    venv = gym.make_vec("av_gym/UnprotectedLeftTurn-v0", num_envs=3, sensors="turn_perceived")
    assert isinstance(venv, BatchedLeftTurnVectorEnv) and set(venv.single_observation_space) == {"turn", "intent"}
    obs, _ = venv.reset(seed=5)
    for _ in range(5):
        obs, *_ = venv.step(np.ones(3, dtype=int))
    assert venv.observation_space.contains(obs)
    # the first env's features are the per-env stack's for its seed (reset(seed=5): env 0 plays seed 5)
    env = make_env(ENV, compose_group("sensors", "turn_perceived"))
    o, _ = env.reset(seed=5)
    for _ in range(5):
        o, *_ = env.step(1)
    assert np.allclose(o["turn"], obs["turn"][0], atol=OBS_TOL) and np.abs(o["turn"]).sum() > 0


@pytest.mark.slow  # ~40 CPU-s: the per-env oracle simulates a future per decision
def test_the_lookahead_oracle_on_perceived_features_drives_as_on_the_per_env_stack():
    """lookahead@turn_perceived: the oracle reads only the ego's own features of obs["turn"] (the same from truth
    or tracks), so on the batch it must end 6 validation seeds as on the per-env stack (measured: 6 of 6)."""
    assert _outcome_splits("lookahead@turn_perceived", list(range(1_000_500, 1_000_506))) == []


def test_what_the_batch_still_refuses_on_tracks_is_one_line():
    """belief_lookahead on tracks runs on the batch for evaluation (its planner on the tracker's tracks and a prior
    over what it has not confirmed, agents/track_prior.py); as DAgger's teacher on tracks it is still refused in
    one line naming why; the same teacher on truth is not."""
    from hydra import compose, initialize_config_module

    from eval.agents import plan_agent
    from eval.batched import check_batched_plan
    from train.dagger import validate

    from tests.conftest import conf

    env_cfg = conf("env", "left_turn")
    plan = plan_agent("belief_lookahead@turn_perceived", "left_turn", conf("sensors", "truth"),
                      {"name": "none", "kind": "none"}, "checkpoints")
    check_batched_plan(plan, env_cfg)  # accepted: no ConfigError
    with initialize_config_module("conf", version_base="1.3"):
        own = compose("train", overrides=["agent=dagger_turn_memory"])
        tracks = compose("train", overrides=["agent=dagger_turn_memory", "sensors=turn_perceived_memory"])
    assert validate(own) == []
    (problem,) = validate(tracks)
    assert "kind belief_lookahead" in problem and "source=tracks" in problem and "\n" not in problem
