"""The fast simulation core (``fast=True``, the default) gives exactly the trajectories of highway-env's own code
(``fast=False``): for several seeds and fixed seeded action sequences, in both scenarios and the CCFtap mode —
every vehicle's position and heading to 1e-9 (in practice bit for bit), the same lanes, crashes, observations,
rewards, ground truth (TTC included) and the same termination step. Plus the exactness of the pieces on random
inputs (lane geometry, closest-lane search, TTC)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from highway_env.road.road import RoadNetwork

import av_gym  # noqa: F401
from av_gym.geometry import box_corners, boxes_overlap, constant_velocity_ttc
from av_gym.sim import lanes as fast_lanes

LANE, TURN = "av_gym/LaneKeepingLap-v0", "av_gym/UnprotectedLeftTurn-v0"
CONTINUOUS = {"action": {"type": "continuous", "target_speeds": [0, 4.5, 9], "acceleration_range": [-8, 3]}}


_RUNS: dict = {}


def trajectory(env_id: str, config: dict, seed: int, steps: int = 200):
    """Cached :func:`_trajectory` (the coverage test reuses the runs)."""
    key = (env_id, repr(sorted(config.items())), seed, steps)
    if key not in _RUNS:
        _RUNS[key] = _trajectory(env_id, config, seed, steps)
    return _RUNS[key]


def _trajectory(env_id: str, config: dict, seed: int, steps: int = 200):
    """Per step: every vehicle's (x, y, heading, speed, crashed), lanes, observation, reward, flags and truth,
    under a fixed seeded action sequence; stops at the end of the episode."""
    env = gym.make(env_id, config=config)
    obs, _ = env.reset(seed=seed)
    actions = np.random.default_rng(seed)
    out = []
    for _ in range(steps):
        if env_id == LANE:
            a = np.array([actions.uniform(-0.3, 0.3)], dtype=np.float32)
        elif config.get("action", {}).get("type") == "continuous":
            a = np.array([actions.uniform(-0.5, 1.0)], dtype=np.float32)
        else:
            a = int(actions.choice(3, p=[0.2, 0.5, 0.3]))
        obs, reward, terminated, truncated, info = env.step(a)
        road = env.unwrapped.road
        out.append({"state": np.array([[*v.position, v.heading, v.speed, v.crashed] for v in road.vehicles]),
                    "lanes": [v.lane_index for v in road.vehicles], "obs": obs["state"].copy(), "reward": reward,
                    "flags": (terminated, truncated), "truth": info["truth"]})
        if terminated or truncated:
            break
    return out


CASES = [(TURN, {}, s) for s in range(5)] + [
    (TURN, CONTINUOUS, 7),
    (TURN, {**CONTINUOUS, "spawn_probability": 1.0}, 8),
    (TURN, {"mode": "ccftap", "ccftap_dt": 0.0}, 0),  # timed to meet (the seeded actions avoid it)
    (TURN, {"mode": "ccftap", "ccftap_dt": -1.5, "ccftap_target_speed": 60 / 3.6}, 1),
    (TURN, {**CONTINUOUS, "mode": "ccftap", "ccftap_dt": 0.5}, 2),
    (LANE, {}, 0), (LANE, {}, 1), (LANE, {"track": "B"}, 3),
]
# The fast suite's cases: a collision (seed 2) and an arrival (seed 1) in traffic, CCFtap with continuous actions
# and every lane-keeping case; the others (dense traffic, more seeds and timings) are slow: highway-env's own code
# plays 2-9 CPU-s per case (58 CPU-s for all, 12 for these, at load 4)
FAST = [1, 2, 9, 10, 11, 12]


@pytest.mark.parametrize("env_id, config, seed", [
    case if i in FAST else pytest.param(*case, marks=pytest.mark.slow) for i, case in enumerate(CASES)])
def test_fast_core_reproduces_stock_trajectories(env_id, config, seed):
    stock = trajectory(env_id, {**config, "fast": False}, seed)
    fast = trajectory(env_id, {**config, "fast": True}, seed)
    assert len(stock) == len(fast), "same termination step"
    for s, f in zip(stock, fast):
        assert s["state"].shape == f["state"].shape, "same vehicles"
        assert np.max(np.abs(s["state"] - f["state"]), initial=0.0) <= 1e-9  # positions, headings, speeds, crashes
        np.testing.assert_array_equal(s["state"][:, 4], f["state"][:, 4])  # the same collisions
        assert s["lanes"] == f["lanes"]
        np.testing.assert_array_equal(s["obs"], f["obs"])
        assert s["reward"] == f["reward"] and s["flags"] == f["flags"]
        assert s["truth"].keys() == f["truth"].keys()
        for key, value in s["truth"].items():
            np.testing.assert_array_equal(np.asarray(value, dtype=object if value is None else None),
                                          np.asarray(f["truth"][key], dtype=object if value is None else None),
                                          err_msg=key)


def test_the_cases_cover_collisions_and_both_endings():
    """The fast suite's cases alone (the slow ones add seeds and CCFtap timings)."""
    turn = [trajectory(TURN, {**config, "fast": True}, seed) for i, (env_id, config, seed) in enumerate(CASES)
            if env_id == TURN and i in FAST]
    assert any(t[-1]["truth"]["collision"] for t in turn)
    assert any(t[-1]["truth"]["arrived"] for t in turn)


def _networks():
    nets = []
    for env_id, config in ((LANE, {"track": "A"}), (LANE, {"track": "B"}), (TURN, {})):
        env = gym.make(env_id, config=config)
        env.reset(seed=0)
        nets.append(env.unwrapped.road.network)
    return nets


def test_lane_geometry_and_closest_lane_are_bit_identical_on_random_points():
    rng = np.random.default_rng(1)
    for net in _networks():
        for lane in net.lanes_list():
            for p, h, s, lat in zip(rng.uniform(-150, 150, (40, 2)), rng.uniform(-7, 7, 40),
                                    rng.uniform(-20, 120, 40), rng.uniform(-5, 5, 40)):
                x, y = float(p[0]), float(p[1])
                assert tuple(lane.local_coordinates(p)) == fast_lanes.local_coordinates(lane, x, y)
                assert lane.distance_with_heading(p, h) == fast_lanes.distance_with_heading(lane, x, y, h)
                assert lane.distance_with_heading(p, None) == fast_lanes.distance_with_heading(lane, x, y, None)
                assert lane.heading_at(s) == fast_lanes.heading_at(lane, s)
                assert tuple(lane.position(s, lat)) == fast_lanes.position(lane, s, lat)
        points = np.concatenate([rng.uniform(-120, 120, (400, 2)), rng.uniform(-20, 20, (400, 2))])
        for p, h in zip(points, rng.uniform(-4, 4, len(points))):
            assert RoadNetwork.get_closest_lane_index(net, p, h) == net.get_closest_lane_index(p, h)
            assert RoadNetwork.get_closest_lane_index(net, p, None) == net.get_closest_lane_index(p, None)


def _ttc_every_pair(ego, others, horizon=5.0, dt=0.05):
    """The definition: the separating-axis test on every (step, vehicle) pair."""
    if len(others) == 0:
        return float("inf")
    t = np.arange(0.0, horizon + 1e-9, dt)[:, None]
    ego_c = ego[None, None, 0:2] + t[..., None] * ego[None, None, 2:4]
    oth_c = others[None, :, 0:2] + t[..., None] * others[None, :, 2:4]
    hit = boxes_overlap(box_corners(ego_c, ego[4], ego[5], ego[6]),
                        box_corners(oth_c, others[:, 4], others[:, 5], others[:, 6])).any(-1)
    return float(t[np.argmax(hit), 0]) if hit.any() else float("inf")


def test_ttc_equals_testing_every_pair():
    rng = np.random.default_rng(0)
    finite = 0
    for _ in range(400):
        n = int(rng.integers(0, 8))
        ego = np.array([*rng.uniform(-20, 20, 2), *rng.uniform(-10, 10, 2), rng.uniform(-4, 4), 5.0, 2.0])
        others = np.column_stack([rng.uniform(-40, 40, (n, 2)), rng.uniform(-12, 12, (n, 2)),
                                  rng.uniform(-4, 4, n), rng.uniform(3, 6, n), rng.uniform(1.5, 2.5, n)])
        expected = _ttc_every_pair(ego, others)
        assert constant_velocity_ttc(ego, others) == expected
        finite += np.isfinite(expected)
    touching = np.array([[5.0, 0.0, 0.0, 0.0, 0.0, 5.0, 2.0]])  # boxes sharing an edge now: overlap at t = 0
    assert constant_velocity_ttc(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 5.0, 2.0]), touching) == 0.0
    assert finite > 20
