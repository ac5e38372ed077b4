"""Arrival ends the left turn's episode in every mode and action type, and pays ``rewards.arrived`` once; the batch
(av_gym/batched/left_turn.py) ends and pays it as the per-env env does.

Before: a CCFtap ego arriving before the target had passed (continuous acceleration at full throttle, or a target
``dt`` seconds late) was paid the arrival every step, drove off the end of the exit lane at up to 40 m/s and the
batch split from the per-env env there; a fast continuous ego (or a target above 144 km/h) passed highway-env's
Vehicle.MAX_SPEED = 40 m/s on the per-env stack only. Full throttle is action +1 (3 m/s², ``acceleration_range``)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from av_gym.sim import batched as sim_batched
from test_batched_sim import _ccftap, run_pair

ID = "av_gym/UnprotectedLeftTurn-v0"
FULL = np.array([1.0], dtype=np.float32)  # full throttle: +3 m/s²


def _episode(env_cfg: dict, action, seed: int) -> list[tuple[float, bool, dict]]:
    """(reward, terminated, truth) of every step of one per-env episode driven by ``action``."""
    env = gym.make(ID, env=env_cfg, sensors="turn_truth")
    env.reset(seed=seed)
    steps = []
    for _ in range(2000):
        _, r, te, tr, info = env.step(action)
        steps.append((r, te, info["truth"]))
        if te or tr:
            break
    env.close()
    return steps


# (ego km/h, target km/h, dt s): the stock case, the target late (the ego arrives first even in discrete) and early
CASES = [(15.0, 45.0, 0.0), (20.0, 30.0, 15.0), (10.0, 30.0, -1.0)]


@pytest.mark.parametrize("case, action", [(c, "continuous") for c in CASES] + [(CASES[1], "discrete")])
def test_arrival_ends_the_ccftap_episode_and_is_paid_once(case, action):
    """Full throttle (continuous +1; discrete FASTER: the test speed, which meets the target unless it is late)
    crashes in none of these: the episode ends on the first step the ego has arrived, terminated, with one arrival
    reward (3) in its return."""
    steps = _episode(_ccftap(*case, action), FULL if action == "continuous" else 2, seed=3)
    arrived = [t["arrived"] for _, _, t in steps]
    assert arrived.count(True) == 1 and arrived[-1], f"arrived on {arrived.count(True)} steps of {len(steps)}"
    assert steps[-1][1] and not steps[-1][2]["collision"]
    rewards = np.array([r for r, _, _ in steps])
    # every other term is small per step (speed off, progress 2 over the route, comfort <= 0.001 per step)
    assert (rewards[:-1] < 0.5).all() and rewards[-1] > 2.9
    assert rewards.sum() == pytest.approx(3.0 + 2.0, abs=0.1)  # arrival once + the whole route's progress


@pytest.mark.parametrize("case", [(15.0, 45.0, 0.0), (20.0, 60.0, 1.5), (10.0, 30.0, 30.0), (100.0, 100.0, 0.0)])
def test_batch_ends_full_throttle_ccftap_as_the_per_env_env(case):
    """Whole episodes at full throttle, continuous, 3 seeds (CCFtap draws nothing, so they must agree exactly): states,
    rewards, ends, obs["turn"] and TTC of the batch = the per-env env's at every step (run_pair). 100 km/h passes
    40 m/s before arriving (Vehicle.MAX_SPEED)."""
    seeds = [1, 2, 3]
    ends: dict = {}
    split = run_pair(seeds, horizon=400, env=_ccftap(*case, "continuous"), actions=np.ones((400, 3)), ends=ends)
    assert split == [None] * 3, split
    assert all(te and not tu and not crash for te, tu, crash, _ in ends.values()), ends


def test_numpy_path_clips_speed_as_highway_env():
    """The batch's numpy path (no tick kernel) keeps Vehicle.MAX_SPEED too: an ego at 100 km/h on full throttle
    passes 40 m/s on step ~40 of 52 and is slowed as the per-env stack's (a target may no longer be set above 144
    km/h = 40 m/s: env.ccftap.target_speed_kmh's bound)."""
    with sim_batched.using_kernels(sim_batched.KERNELS - {"tick"}):
        split = run_pair([1], horizon=60, env=_ccftap(100.0, 144.0, 0.0, "continuous"), actions=np.ones((60, 1)))
    assert split == [None], split
