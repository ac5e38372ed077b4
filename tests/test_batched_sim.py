"""The batched left turn (av_gym/sim/batched.py, av_gym/envs/left_turn_batched.py) against the per-env stack
(``fast: true``, itself equal to stock highway-env, tests/test_fast_sim.py): same seeds, same action sequences,
every vehicle's position, heading and speed within 1e-6 for the first 5 s, and the same rewards, terminations
and obs["turn"] (issue 16)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from omegaconf import OmegaConf

from av_gym.envs.left_turn_batched import BatchedLeftTurn
from av_gym.make import highway_config

TOL = 1e-6
HORIZON = 50  # policy steps at 10 Hz: 5 s


def _config():
    return highway_config(OmegaConf.load("conf/env/left_turn.yaml"))


def _state(env) -> np.ndarray:
    return np.array([[*v.position, v.heading, v.speed] for v in env.road.vehicles])


def _batched_state(bt: BatchedLeftTurn, b: int) -> np.ndarray:
    t = bt.traffic
    a = t.alive[b]
    return np.stack([t.x[b, a], t.y[b, a], t.h[b, a], t.v[b, a]], axis=1)


def _split_event(env, bt: BatchedLeftTurn, b: int, p: np.ndarray, q: np.ndarray) -> str:
    """What made the two runs differ first: a vehicle count (spawn / clear), a crash, a yield, or a drift."""
    t = bt.traffic
    if p.shape != q.shape:
        return f"vehicle count {len(p)} (per-env) vs {len(q)} (batched): a spawn or a clear differed"
    crashed = np.array([v.crashed for v in env.road.vehicles])
    if (crashed != t.crashed[b, t.alive[b]]).any():
        return f"crash flags differ for vehicles {np.nonzero(crashed != t.crashed[b, t.alive[b]])[0].tolist()}"
    yielding = np.array([bool(getattr(v, "is_yielding", False)) for v in env.road.vehicles])
    if (yielding != t.yielding[b, t.alive[b]]).any():
        return f"regulation: yielding differs for vehicles {np.nonzero(yielding != t.yielding[b, t.alive[b]])[0]}"
    i = int(np.abs(p - q).max(axis=1).argmax())
    return f"vehicle {i} drifted by {np.abs(p - q)[i].max():.2e} (lane {env.road.vehicles[i].lane_index})"


def run_pair(seeds: list[int], horizon: int = HORIZON, action_seed: int = 0) -> list[str | None]:
    """Per seed: None if both stacks agree for ``horizon`` policy steps (or to the episode's end), else the first
    split event with its time."""
    from av_gym.estimation.turn_features import TurnFeatures

    env_id, config = _config()
    bt = BatchedLeftTurn(len(seeds), config)
    obs_b = bt.reset(seeds)
    envs = [TurnFeatures(gym.make(env_id, config=config)) for _ in seeds]
    obs = [e.reset(seed=s)[0]["turn"] for e, s in zip(envs, seeds)]
    actions = np.random.default_rng(action_seed).integers(0, 3, size=(horizon, len(seeds)))
    split: list[str | None] = [None] * len(seeds)
    done = np.zeros(len(seeds), bool)
    for k in range(horizon + 1):
        for b, e in enumerate(envs):
            if done[b] or split[b]:
                continue
            p, q = _state(e.unwrapped), _batched_state(bt, b)
            if p.shape != q.shape or np.abs(p - q).max() > TOL:
                split[b] = f"t={0.1 * k:.1f}s: " + _split_event(e.unwrapped, bt, b, p, q)
            elif np.abs(obs[b] - obs_b[b]).max() > 1e-5:
                split[b] = f"t={0.1 * k:.1f}s: obs['turn'] differs at {np.abs(obs[b] - obs_b[b]).argmax()}"
        if k == horizon:
            break
        reward, term, trunc = bt.step(actions[k], active=~done)
        obs_b = bt.observe()
        for b, e in enumerate(envs):
            if done[b]:
                continue
            o, r, te, tu, _ = e.step(int(actions[k, b]))
            obs[b] = o["turn"]
            if not split[b] and (abs(r - reward[b]) > TOL or te != term[b] or tu != trunc[b]):
                split[b] = f"t={0.1 * (k + 1):.1f}s: reward/termination {r, te, tu} vs {reward[b], term[b], trunc[b]}"
            done[b] |= te or tu
    return split


def test_batched_matches_per_env_stack_for_5_s():
    seeds = list(range(7000, 7024))
    split = run_pair(seeds)
    same = [s is None for s in split]
    report = "\n".join(f"seed {seed}: {s}" for seed, s in zip(seeds, split) if s)
    assert np.mean(same) >= 0.95, f"{np.mean(same):.0%} identical; first split events:\n{report}"


def test_batched_envs_are_independent_of_the_batch():
    """Env i given seed s plays the episode seed s gives, whatever the other envs of the batch do."""
    env_id, config = _config()
    one = BatchedLeftTurn(1, config)
    many = BatchedLeftTurn(3, config)
    o1, o3 = one.reset([11]), many.reset([5, 11, 6])
    np.testing.assert_array_equal(o1[0], o3[1])
    for k in range(30):
        one.step(np.array([k % 3]))
        many.step(np.array([0, k % 3, 2]))
        np.testing.assert_array_equal(one.observe()[0], many.observe()[1])


def test_batched_refuses_what_it_cannot_run():
    env_id, config = _config()
    with pytest.raises(ValueError, match="traffic only"):
        BatchedLeftTurn(2, {**config, "mode": "ccftap"})
