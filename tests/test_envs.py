"""Scenario envs: registration, API conformance, ground truth, determinism, lap and CCFtap geometry."""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from highway_env.envs.common.observation import KinematicObservation
from highway_env.road.lane import CircularLane, StraightLane

import av_gym
from agents import AlwaysProceed, PIDSteering
from av_gym.envs.track import LAYOUTS, build_track
from av_gym.make import highway_config
from conftest import Scripted, ccftap_cfg, conf, rollout, zeros_action


@pytest.mark.parametrize("env_id, config", [
    ("av_gym/LaneKeepingLap-v0", {}),
    ("av_gym/LaneKeepingLap-v0", {"track": "B", "target_speed": 8.0, "policy_frequency": 20,
                                  "simulation_frequency": 40, "lane_width": 3.5}),
    ("av_gym/UnprotectedLeftTurn-v0", {}),
    ("av_gym/UnprotectedLeftTurn-v0", {"mode": "ccftap", "ccftap_dt": 1.0}),
    ("av_gym/UnprotectedLeftTurn-v0", {"action": {"type": "continuous", "target_speeds": [0, 4.5, 9],
                                                  "acceleration_range": [-8.0, 3.0]}, "spawn_probability": 0.9}),
])
def test_check_env_passes(env_id, config):
    env = gym.make(env_id, config=config)
    check_env(env.unwrapped, skip_render_check=True)


def test_an_action_array_the_caller_reuses_is_recorded_per_step():
    """highway-env puts the caller's action object into ``info``; one array reused for every step (a constant
    STRAIGHT, an agent's output buffer) would rewrite every earlier step's record."""
    env = gym.make("av_gym/LaneKeepingLap-v0")
    env.reset(seed=0)
    action = np.zeros(env.action_space.shape, env.action_space.dtype)
    *_, first = env.step(action)
    action[:] = env.action_space.high
    *_, second = env.step(action)
    assert np.all(first["action"] == 0) and np.all(second["action"] == env.action_space.high)


def test_importing_av_gym_registers_both_envs():
    assert set(av_gym.ENV_IDS.values()) <= set(gym.registry)


def test_yaml_configs_map_to_si_units(lane_cfg, turn_cfg):
    _, lk = highway_config(lane_cfg)
    assert lk["target_speed"] == pytest.approx(10.0)  # 36 km/h
    assert lk["max_steering"] == pytest.approx(np.radians(25))
    _, lt = highway_config(ccftap_cfg(20, 60, 0.5))
    assert lt["ccftap_ego_speed"] == pytest.approx(20 / 3.6) and lt["ccftap_target_speed"] == pytest.approx(60 / 3.6)


# ------------------------------------------------------------------------------------------------ lap geometry
@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_layouts_are_closed_circuits_with_a_sharp_curve_after_a_straight(name):
    track = build_track(name)
    assert track.length >= 400
    first, last = track.lanes[0], track.lanes[-1]
    np.testing.assert_allclose(last.position(last.length, 0), first.position(0, 0), atol=1e-6)
    arcs = [lane for lane in track.lanes if isinstance(lane, CircularLane)]
    assert {lane.direction for lane in arcs} == {1, -1}, "needs both left and right curves"
    sharp_after_straight = [i for i, lane in enumerate(track.lanes) if isinstance(lane, CircularLane)
                            and lane.radius <= 30 and isinstance(track.lanes[i - 1], StraightLane)
                            and track.lanes[i - 1].length >= 50]
    assert sharp_after_straight


def test_cte_sign_is_positive_right_of_centre(make, lane_cfg):
    env = make(dict(lane_cfg, initial_lateral_std=0.0, initial_heading_std_deg=0.0))
    env.reset(seed=0)
    u = env.unwrapped
    # The lap starts heading +x; highway-env draws y downwards, so +y is the driver's right.
    u.vehicle.position = u.vehicle.position + np.array([0.0, 1.0])
    assert u.lane_state()["cte"] == pytest.approx(1.0)
    assert PIDSteering().act({"state": np.array([1.0])})[0] < 0, "right of centre must steer left"


def test_zero_steering_leaves_the_road_at_the_first_curve(make, lane_cfg):
    truths, info, terminated, truncated = rollout(make(lane_cfg), Scripted(zeros_action), seed=0)
    assert terminated and not truncated
    assert not truths[-1]["on_road"] and not truths[-1]["lap_completed"]
    assert 100 < truths[-1]["progress"] < 200  # straight is 120 m, then the hairpin
    assert info["episode_metrics"]["lap_completed"] == 0.0


@pytest.mark.parametrize("track", ["A", "B"])
def test_pid_completes_a_lap_and_stays_in_lane(make, lane_cfg, track):
    truths, info, terminated, _ = rollout(make(dict(lane_cfg, track=track)), PIDSteering(), seed=1)
    assert terminated and truths[-1]["lap_completed"]
    assert truths[-1]["progress"] == pytest.approx(truths[-1]["lap_length"], abs=1.5)
    m = info["episode_metrics"]
    assert m["lap_completed"] == 1.0 and m["cte_max_abs_m"] < 1.5
    assert m["cte_mean_abs_units"] == pytest.approx(100 * m["cte_mean_abs_m"] / 4.0)


def test_lap_time_limit_truncates(make, lane_cfg):
    _, _, terminated, truncated = rollout(make(dict(lane_cfg, time_limit=3.0)), PIDSteering(), seed=0)
    assert truncated and not terminated


def test_policy_rate_at_least_10hz(lane_cfg, turn_cfg):
    for cfg in (lane_cfg, turn_cfg):
        assert highway_config(cfg)[1]["policy_frequency"] >= 10
    with pytest.raises(ValueError, match="policy_frequency"):
        gym.make("av_gym/LaneKeepingLap-v0", config={"policy_frequency": 5, "simulation_frequency": 20})


# ------------------------------------------------------------------------------------------------ determinism
def _trajectory(truths):
    return np.array([[t["x"], t["y"], t["heading"], t["speed"], t["ttc"] if np.isfinite(t["ttc"]) else -1]
                     for t in truths])


@pytest.mark.parametrize("scenario", ["lane_keeping", "left_turn"])
def test_same_seed_same_truth_different_seed_different(make, scenario):
    env = make(conf("env", scenario))

    def policy():
        return PIDSteering() if scenario == "lane_keeping" else AlwaysProceed(env.unwrapped.cruise_action())

    a, b, c = (_trajectory(rollout(env, policy(), seed=s)[0]) for s in (3, 3, 4))
    np.testing.assert_array_equal(a, b)
    assert a.shape != c.shape or not np.array_equal(a, c)


def test_fast_kinematics_matches_highway_env_observation(make, turn_cfg):
    env = make(turn_cfg)
    u = env.unwrapped
    steps = 0
    for seed in range(1):  # one whole episode: every step's observation compared (> 50 steps, asserted)
        env.reset(seed=seed)
        stock = KinematicObservation(u, **{k: v for k, v in u.config["observation"].items() if k != "type"})
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(1)
            done = terminated or truncated
            np.testing.assert_array_equal(u.observation_type.observe()["state"], stock.observe())
            steps += 1
    assert steps > 50


# ------------------------------------------------------------------------------------------------ left turn
def test_traffic_truth_fields_and_always_proceed_crosses_the_oncoming_lane(make, turn_cfg):
    env = make(turn_cfg)
    policy = AlwaysProceed(env.unwrapped.cruise_action())
    truths, info, _, _ = rollout(env, policy, seed=0)
    first = truths[0]
    assert first["stop_line_offset"] < 0 and first["oncoming_gap"] > 0  # starts in its own lane, before the line
    assert first["others"].shape[1] == 7 and len(first["others"]) > 0
    offsets = [t["stop_line_offset"] for t in truths]
    assert np.all(np.diff(offsets) >= -1e-9), "front bumper only moves forward along the route"
    if truths[-1]["arrived"]:
        assert min(t["oncoming_gap"] for t in truths) < 0  # a left turn crosses the oncoming lane


def test_left_turn_spawn_rate_is_per_second(make, turn_cfg):
    """At 10 Hz the per-step spawn probability is 0.6 / 10, so the expected number of new vehicles per second is
    stock highway-env's 0.6 (one attempt per second at its 1 Hz policy rate)."""
    env = make(turn_cfg)
    u = env.unwrapped
    attempts = spawned = 0
    original = u._spawn_vehicle

    def counting(*args, **kwargs):
        nonlocal attempts, spawned
        if args or "spawn_probability" not in kwargs:  # the initial scene at reset
            return original(*args, **kwargs)
        attempts += 1
        n0 = len(u.road.vehicles)
        out = original(*args, **kwargs)
        spawned += len(u.road.vehicles) > n0
        assert kwargs["spawn_probability"] == pytest.approx(0.06)
        return out

    u._spawn_vehicle = counting
    for seed in range(3):
        env.reset(seed=seed)
        for _ in range(100):
            *_, terminated, truncated, _ = env.step(0)
            if terminated or truncated:
                break
    assert attempts > 150 and spawned / attempts <= 0.06 + 3 * np.sqrt(0.06 * 0.94 / attempts)


# the grid's diagonal (slowest ego with slowest target ... fastest with fastest) in the fast suite, the other six
# cases (~0.5 CPU-s each, the same code at other speeds) in the slow one
@pytest.mark.parametrize("ego_kmh, target_kmh", [
    (e, t) if (e, t) in ((10, 30), (15, 45), (20, 60)) else pytest.param(e, t, marks=pytest.mark.slow)
    for e, t in itertools.product((10, 15, 20), (30, 45, 60))])
def test_ccftap_dt0_collides_and_large_dt_does_not(make, ego_kmh, target_kmh):
    for dt, expect in ((0.0, True), (-3.0, False), (3.0, False)):
        env = make(ccftap_cfg(ego_kmh, target_kmh, dt))
        truths, info, terminated, _ = rollout(env, AlwaysProceed(1), seed=0)
        assert truths[-1]["collision"] is expect, f"{ego_kmh}/{target_kmh} km/h, dt={dt}"
        if not expect:
            assert terminated and truths[-1]["arrived"]


def test_ccftap_ego_stopped_in_the_path_is_hit_after_standstill(make):
    """The episode runs on after the ego stops: braking inside the oncoming lane still ends in a collision."""
    env = make(ccftap_cfg(10, 30, 3.0))

    def stop_in_conflict_zone(_k, _obs):
        return 0 if env.unwrapped.truth()["distance_to_conflict"] < 1.0 else 1

    truths, _, terminated, _ = rollout(env, Scripted(stop_in_conflict_zone), seed=0)
    assert terminated and truths[-1]["collision"]
    speeds = np.array([t["speed"] for t in truths])
    assert speeds[:-1].min() < 0.1, "the ego had come to a standstill before it was hit"


def test_ccftap_ego_that_waits_before_the_line_is_not_hit_and_episode_waits_for_target(make):
    env = make(ccftap_cfg(15, 45, 0.0))
    truths, info, terminated, truncated = rollout(env, Scripted(lambda k, o: 0), seed=0)  # SLOWER: stop
    assert not truths[-1]["collision"] and truncated and not terminated
    m = info["episode_metrics"]
    assert m["stopped"] == 1.0 and m["stop_line_offset_at_stop_m"] < 0


def test_continuous_action_brakes_to_standstill_without_reversing(make, turn_cfg):
    cfg = dict(turn_cfg, action="continuous", mode="ccftap")
    truths, *_ = rollout(make(cfg), Scripted(lambda k, o: np.array([-1.0], dtype=np.float32)), seed=0)
    speeds = np.array([t["speed"] for t in truths])
    assert speeds.min() >= 0.0 and speeds[-1] == pytest.approx(0.0, abs=1e-6)
    assert truths[-1]["acceleration"] <= 0


def test_bad_env_config_names_the_field(make, turn_cfg):
    from av_gym.errors import ConfigError

    with pytest.raises(ConfigError, match=r"env.mode must be one of \['traffic', 'ccftap'\]"):
        make(dict(turn_cfg, mode="rush_hour"))
    with pytest.raises(ConfigError, match="env.name must be one of"):
        make(dict(turn_cfg, name="roundabout"))
