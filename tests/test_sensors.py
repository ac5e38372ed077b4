"""Sensor wrappers: noise statistics match their parameters, seeding, composition, presets (GNSS, IMU, detector)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from hydra import compose, initialize_config_module

import av_gym  # noqa: F401
from agents import PIDSteering
from av_gym.errors import ConfigError
from av_gym.make import make_env
from av_gym.sensors.detector import Detector
from av_gym.sensors.gnss import GNSS
from av_gym.sensors.imu import IMU

LANE = "av_gym/LaneKeepingLap-v0"
TURN = "av_gym/UnprotectedLeftTurn-v0"


def lap(**config):
    return gym.make(LANE, config=config)


def drive(env, steps, seed=0, action=None):
    """Run ``steps`` policy steps with a PID on the true CTE (lap) or IDLE (turn); returns (obs list, truth list)."""
    obs, info = env.reset(seed=seed)
    pid = PIDSteering()
    observations, truths = [obs], [info["truth"]]
    for _ in range(steps):
        if action is not None:
            a = action
        elif env.unwrapped.scenario == "lane_keeping":
            a = pid.act({"state": np.array([info["truth"]["cte"]])})
        else:
            a = 1
        obs, _, terminated, truncated, info = env.step(a)
        observations.append(obs)
        truths.append(info["truth"])
        if terminated or truncated:
            break
    return observations, truths


def compose_cfg(*overrides):
    with initialize_config_module("conf", version_base="1.3"):
        return compose("train", overrides=list(overrides))


# ------------------------------------------------------------------------------------------------ GNSS
def test_gnss_white_noise_matches_sigma():
    env = GNSS(lap(), sigma=2.0, sigma_bias=0.0, latency=0.0, velocity_sigma=0.3)
    obs, truths = drive(env, 400)
    g = np.array([o["gnss"] for o in obs])
    fresh = g[:, 4] == 1
    err = g[fresh, :2] - np.array([[t["x"], t["y"]] for t, f in zip(truths, fresh) if f])
    assert err.std() == pytest.approx(2.0, rel=0.1)
    assert abs(err.mean()) < 0.3
    speed_err = np.hypot(g[fresh, 2], g[fresh, 3]) - np.array([t["speed"] for t, f in zip(truths, fresh) if f])
    assert speed_err.std() == pytest.approx(0.3, rel=0.2)


def test_gnss_bias_is_a_slow_gauss_markov_process():
    # Stationary std: the first fix of many episodes (white noise off).
    first = []
    env = GNSS(lap(), sigma=0.0, sigma_bias=2.0, bias_tau=20.0, latency=0.0)
    for seed in range(300):
        obs, info = env.reset(seed=seed)
        first.append(obs["gnss"][:2] - [info["truth"]["x"], info["truth"]["y"]])
    assert np.std(first) == pytest.approx(2.0, rel=0.12)
    # Slow: between fixes 0.1 s apart the bias moves by sigma_bias·sqrt(1 - exp(-2·0.1/20)) ≈ 0.2 m (std).
    steps = []
    for seed in range(3):
        obs, truths = drive(env, 150, seed=seed)
        bias = np.array([o["gnss"][:2] - [t["x"], t["y"]] for o, t in zip(obs, truths)])
        steps.append(np.diff(bias, axis=0))
    assert np.concatenate(steps).std() == pytest.approx(2.0 * np.sqrt(1 - np.exp(-0.01)), rel=0.15)


def test_gnss_rate_hold_and_age():
    env = GNSS(lap(), rate_hz=1.0)
    obs, _ = drive(env, 35)
    g = np.array([o["gnss"] for o in obs])
    assert np.flatnonzero(g[:, 4]).tolist() == [0, 10, 20, 30]  # a fix every 10 policy steps at 10 Hz
    np.testing.assert_array_equal(g[1:10, :4], np.repeat(g[:1, :4], 9, axis=0))  # held between fixes
    np.testing.assert_allclose(g[1:10, 6], np.arange(1, 10) * 0.1, atol=1e-5)  # age grows


def test_gnss_latency_reports_the_past_position():
    env = GNSS(lap(), sigma=0.0, sigma_bias=0.0, velocity_sigma=0.0, latency=0.5)
    obs, truths = drive(env, 30)
    np.testing.assert_allclose(obs[20]["gnss"][:2], [truths[15]["x"], truths[15]["y"]], atol=1e-3)


def test_gnss_scripted_outage_holds_the_last_fix_and_flags_it():
    env = GNSS(lap(), outage="scripted", outage_windows=[[1.0, 3.0]])
    obs, _ = drive(env, 40)
    g = np.array([o["gnss"] for o in obs])
    t = np.arange(len(g)) * 0.1
    inside = (t >= 1.0 - 1e-9) & (t < 3.0 - 1e-9)
    assert np.all(g[inside, 5] == 0) and np.all(g[inside, 4] == 0)
    np.testing.assert_array_equal(g[inside, :4], np.repeat(g[9:10, :4], inside.sum(), axis=0))
    assert np.all(g[~inside, 5] == 1) and g[30, 4] == 1
    assert g[29, 6] == pytest.approx(2.0, abs=1e-4)


def test_gnss_random_outages_happen_at_the_configured_rate():
    env = GNSS(lap(), outage="random", outage_rate=0.2, outage_mean=2.0)
    valid = np.concatenate([np.array([o["gnss"][5] for o in drive(env, 600, seed=s)[0]]) for s in range(3)])
    # Stationary fraction in outage = rate·mean / (1 + rate·mean) = 0.4 / 1.4 ≈ 0.29.
    assert 1 - valid.mean() == pytest.approx(0.29, abs=0.1)


# ------------------------------------------------------------------------------------------------ IMU
def test_imu_noise_and_true_yaw_rate_in_the_hairpin():
    env = IMU(lap(initial_lateral_std=0.0, initial_heading_std=0.0), accel_sigma=0.1, gyro_sigma=0.02,
              accel_bias_sigma=0.0, gyro_bias_sigma=0.0, accel_bias_walk=0.0, gyro_bias_walk=0.0, scale_error=0.0)
    obs, truths = drive(env, 400)
    imu = np.concatenate([o["imu"] for o in obs[1:]])  # (2 samples per step)
    straight = np.repeat([40 < t["progress"] < 110 for t in truths[1:]], 2)
    assert imu[straight, 0].std() == pytest.approx(0.1, rel=0.15)
    assert imu[straight, 2].std() == pytest.approx(0.02, rel=0.15)
    hairpin = np.repeat([130 < t["progress"] < 150 for t in truths[1:]], 2)
    # 10 m/s on a 25 m-radius LEFT curve: yaw rate -0.4 rad/s (heading decreases), lateral accel -4 m/s².
    assert imu[hairpin, 2].mean() == pytest.approx(-0.4, rel=0.15)
    assert imu[hairpin, 1].mean() == pytest.approx(-4.0, rel=0.15)


def test_imu_bias_and_saturation():
    env = IMU(lap(), accel_sigma=0.0, gyro_sigma=0.0, gyro_bias_sigma=0.01, gyro_bias_walk=0.0, scale_error=0.0)
    biases = [env.reset(seed=s)[0]["imu"][0, 2] for s in range(300)]  # steady straight: reading = bias
    assert np.std(biases) == pytest.approx(0.01, rel=0.12)
    env = IMU(lap(), accel_range=0.05, gyro_range=0.01)
    obs, _ = drive(env, 200)
    imu = np.concatenate([o["imu"] for o in obs])
    assert np.abs(imu[:, :2]).max() <= 0.05 + 1e-6 and np.abs(imu[:, 2]).max() <= 0.01 + 1e-6


# ------------------------------------------------------------------------------------------------ detector
def _detections(env, episodes, steps=80):
    rows = []
    for seed in range(episodes):
        obs, truths = drive(env, steps, seed=seed)
        rows.append((obs, truths))
    return rows


def test_detector_miss_rate_noise_and_clutter():
    env = Detector(gym.make(TURN), miss_rate=0.3, occlusion=False, clutter_rate=0.0, sigma_pos0=0.5,
                   sigma_pos_k=0.0, max_range=1000.0)
    det = env
    visible = detected = 0
    errors = []
    for seed in range(4):
        obs, info = env.reset(seed=seed)
        for _ in range(60):
            obs, _, term, trunc, info = env.step(1)
            ids = det.truth_ids[det.truth_ids >= 0]
            visible += len(info["truth"]["others"])
            detected += len(ids)
            rows = obs["detector"][det.truth_ids >= 0]
            errors.append(rows[:, 1:3] - info["truth"]["others"][ids, :2])
            if term or trunc:
                break
    assert 1 - detected / visible == pytest.approx(0.3, abs=0.04)
    assert np.concatenate(errors).std() == pytest.approx(0.5, rel=0.1)
    env = Detector(gym.make(TURN), clutter_rate=2.0, miss_rate=0.0)
    clutter = []
    for seed in range(3):
        env.reset(seed=seed)
        for _ in range(50):
            env.step(1)
            clutter.append(int(np.sum((env.truth_ids == -1) & (env._rows[:, 0] > 0))))
    assert np.mean(clutter) == pytest.approx(2.0, rel=0.2)


def test_detector_bursty_misses_have_the_configured_run_length():
    env = Detector(gym.make(TURN, config={"mode": "ccftap"}), miss_rate=0.3, burst_length=5.0,
                   occlusion=False, clutter_rate=0.0, max_range=1000.0)
    seen = []
    for seed in range(20):
        env.reset(seed=seed)
        trace = []
        for _ in range(60):
            *_, term, trunc, _ = env.step(1)
            trace.append(bool(np.any(env.truth_ids >= 0)))
            if term or trunc:
                break
        seen.append(np.array(trace))
    misses = np.concatenate([~s for s in seen])
    runs = [len(r) for s in seen for r in np.split(~s, np.flatnonzero(np.diff(~s)) + 1) if r[0]]
    assert misses.mean() == pytest.approx(0.3, abs=0.08)
    assert np.mean(runs) == pytest.approx(5.0, rel=0.3)


def test_detector_occlusion_hides_a_car_behind_another():
    from highway_env.vehicle.kinematics import Vehicle

    env = Detector(lap(), miss_rate=0.0, clutter_rate=0.0)
    env.reset(seed=0)
    u = env.unwrapped
    road = u.road
    ego = u.vehicle
    ahead = ego.position + np.array([15.0, 0.0])
    road.vehicles += [Vehicle(road, ahead, ego.heading, 0.0), Vehicle(road, ahead + [15.0, 0.0], ego.heading, 0.0)]
    obs, *_ = env.step(np.zeros(1, dtype=np.float32))
    assert env.truth_ids.tolist().count(0) == 1 and 1 not in env.truth_ids.tolist()


# ------------------------------------------------------------------------------------------------ common
def test_same_seed_same_readings_and_order_does_not_matter():
    a = drive(GNSS(IMU(lap())), 30, seed=5)[0]
    b = drive(IMU(GNSS(lap())), 30, seed=5)[0]
    c = drive(GNSS(IMU(lap())), 30, seed=6)[0]
    for key in ("gnss", "imu"):
        np.testing.assert_array_equal(np.array([o[key] for o in a]), np.array([o[key] for o in b]))
        assert not np.array_equal(np.array([o[key] for o in a]), np.array([o[key] for o in c]))


def test_sensors_never_change_the_truth():
    plain = drive(lap(), 50, seed=2)[1]
    sensed = drive(Detector(IMU(GNSS(lap()))), 50, seed=2)[1]
    assert [t["x"] for t in plain] == [t["x"] for t in sensed]
    assert [t["cte"] for t in plain] == [t["cte"] for t in sensed]


PRESETS = ["truth", "gnss_imu", "lidar", "cameras", "detector", "full"]


# Every preset on the lap, and on the left turn its two kinds (truth; full: every sensor at once); the left turn's
# single-sensor presets (~3.3 CPU-s together) are the slow suite's.
@pytest.mark.parametrize("scenario, preset", [
    *[("lane_keeping", p) for p in PRESETS],
    *[("left_turn", p) if p in ("truth", "full") else pytest.param("left_turn", p, marks=pytest.mark.slow)
      for p in PRESETS]])
def test_presets_pass_check_env(preset, scenario):
    cfg = compose_cfg(f"env={scenario}", f"sensors={preset}")
    env = make_env(cfg.env, cfg.sensors, cfg.shield, record_metrics=False)
    assert ("state" in env.observation_space.spaces) == (preset == "truth")
    check_env(env, skip_render_check=True)


def test_bad_sensor_parameters_name_the_field():
    with pytest.raises(ConfigError, match=r"sensors.gnss.sigma must be a number >= 0, got -1"):
        cfg = compose_cfg("sensors=gnss_imu", "sensors.gnss.sigma=-1")
        make_env(cfg.env, cfg.sensors, cfg.shield)
    with pytest.raises(ConfigError, match=r"sensors.detector.miss_rate must be a number in \[0, 1\), got 1.5"):
        cfg = compose_cfg("sensors=detector", "sensors.detector.miss_rate=1.5")
        make_env(cfg.env, cfg.sensors, cfg.shield)
    with pytest.raises(ConfigError, match="sensors.gnss.outage must be one of"):
        cfg = compose_cfg("sensors=gnss_imu", "sensors.gnss.outage=tunnel")
        make_env(cfg.env, cfg.sensors, cfg.shield)


def test_full_preset_has_every_sensor_and_its_own_error_prefix():
    cfg = compose_cfg("sensors=full")
    env = make_env(cfg.env, cfg.sensors, cfg.shield)
    assert set(env.observation_space.spaces) == {"gnss", "imu", "lidar", "cameras", "detector"}
    with pytest.raises(ConfigError, match=r"^sensors.cameras.hfov_deg must be a number in \[1, 170\], got 500"):
        cfg = compose_cfg("sensors=cameras", "sensors.cameras.hfov_deg=500")
        make_env(cfg.env, cfg.sensors, cfg.shield)
    with pytest.raises(ConfigError, match=r"^sensors.lidar.range_sigma must be a number >= 0, got -0.1"):
        cfg = compose_cfg("sensors=lidar", "sensors.lidar.range_sigma=-0.1")
        make_env(cfg.env, cfg.sensors, cfg.shield)
