"""The fast simulation paths (``fast=True``, the default) give exactly the trajectories of highway-env's own code."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import av_gym  # noqa: F401

LANE, TURN = "av_gym/LaneKeepingLap-v0", "av_gym/UnprotectedLeftTurn-v0"


def trajectory(env_id: str, config: dict, seed: int, steps: int = 200):
    """Every vehicle's position and heading, the crash flags and the observation at every step, under a fixed
    seeded action sequence; stops at the end of the episode."""
    env = gym.make(env_id, config=config)
    obs, _ = env.reset(seed=seed)
    actions = np.random.default_rng(seed)
    out = []
    for k in range(steps):
        if env_id == LANE:
            a = np.array([actions.uniform(-0.3, 0.3)], dtype=np.float32)
        elif config.get("action", {}).get("type") == "continuous":
            a = np.array([actions.uniform(-0.5, 1.0)], dtype=np.float32)
        else:
            a = int(actions.choice(3, p=[0.2, 0.5, 0.3]))
        obs, _, terminated, truncated, _ = env.step(a)
        road = env.unwrapped.road
        out.append((np.array([[*v.position, v.heading, v.speed, v.crashed] for v in road.vehicles]),
                    [v.lane_index for v in road.vehicles], obs["state"].copy(), terminated, truncated))
        if terminated or truncated:
            break
    return out


CASES = [(TURN, {}, s) for s in range(4)] + [
    (TURN, {"action": {"type": "continuous", "target_speeds": [0, 4.5, 9], "acceleration_range": [-8, 3]}}, 7),
    (TURN, {"mode": "ccftap", "ccftap_dt": 0.0}, 0),
    (TURN, {"mode": "ccftap", "ccftap_dt": -1.5, "ccftap_target_speed": 60 / 3.6}, 1),
    (LANE, {}, 0), (LANE, {"track": "B"}, 3),
]


@pytest.mark.parametrize("env_id, config, seed", CASES)
def test_fast_core_reproduces_stock_trajectories(env_id, config, seed):
    stock = trajectory(env_id, {**config, "fast": False}, seed)
    fast = trajectory(env_id, {**config, "fast": True}, seed)
    assert len(stock) == len(fast), "same termination step"
    for (s_state, s_lanes, s_obs, s_term, s_trunc), (f_state, f_lanes, f_obs, f_term, f_trunc) in zip(stock, fast):
        assert s_state.shape == f_state.shape
        assert np.max(np.abs(s_state - f_state), initial=0.0) <= 1e-9  # positions, headings, speeds, crashes
        assert s_lanes == f_lanes
        np.testing.assert_array_equal(s_obs, f_obs)
        assert (s_term, s_trunc) == (f_term, f_trunc)
