"""No NaN/inf reaches an observation, and an estimator that fails (a diverging EKF, a kiss-icp error or empty scan,
a numerical exception) is detected, reported in ``info`` and re-initialised from GNSS, never a dead process.
Failures are injected with monkeypatch; each test runs a few dozen steps."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.estimation.ekf import PX, LocalizationEKF
from av_gym.estimation.lidar_odometry import LidarOdometry
from av_gym.estimation.tracker import MultiObjectTracker
from av_gym.make import make_env
from av_gym.sensors.gnss import GNSS
from av_gym.sensors.imu import IMU
from conftest import conf

STRAIGHT = np.zeros(1, dtype=np.float32)


def localized(mode: str, **extra) -> dict:
    sensors = {"name": "localized", "gnss": conf("sensor", "gnss"), "imu": conf("sensor", "imu"),
               "localizer": {**conf("sensor", "localizer"), "mode": mode, "map_matching": False, **extra}}
    if mode in ("lidar", "fused"):
        sensors["lidar"] = conf("sensor", "lidar")
    return sensors


def finite(obs) -> bool:
    if isinstance(obs, dict):
        return all(finite(v) for v in obs.values())
    a = np.asarray(obs)
    return a.dtype.kind not in "fc" or bool(np.all(np.isfinite(a)))


def drive(env, steps: int, hook=None) -> list[dict]:
    """Step straight ahead; ``hook(k, env)`` runs before step k. Returns every info; asserts finite observations."""
    infos = []
    for k in range(steps):
        if hook:
            hook(k, env)
        obs, _, terminated, truncated, info = env.step(STRAIGHT)
        assert finite(obs), f"non-finite observation at step {k}"
        infos.append(info)
        assert not (terminated or truncated)
    return infos


def pipeline(env):
    from av_gym.estimation.localization import find_wrapper

    return find_wrapper(env, "ego_estimate").pipeline


def error_m(env, obs_or_info=None) -> float:
    est = pipeline(env).last
    return float(np.hypot(est[2] - env.unwrapped.vehicle.position[0], est[3] - env.unwrapped.vehicle.position[1]))


# ------------------------------------------------------------------------------------------------ sensors
def test_a_non_finite_gnss_truth_is_dropped_like_an_outage(monkeypatch):
    env = make_env(conf("env", "lane_keeping"), {"name": "gnss_imu", "gnss": conf("sensor", "gnss"),
                                                 "imu": conf("sensor", "imu")})
    env.reset(seed=0)
    real = GNSS._true_state
    monkeypatch.setattr(GNSS, "_true_state", lambda self, t: real(self, t) * np.nan)
    obs, *_ = env.step(STRAIGHT)
    obs, *_ = env.step(STRAIGHT)
    assert finite(obs) and obs["gnss"][5] == 0.0  # held fix, not valid
    monkeypatch.setattr(GNSS, "_true_state", real)
    obs, *_ = env.step(STRAIGHT)
    assert obs["gnss"][5] == 1.0 and obs["gnss"][4] == 1.0  # the next good fix is valid again


def test_a_non_finite_reading_is_replaced_and_reported_in_info(monkeypatch):
    env = make_env(conf("env", "lane_keeping"), {"name": "gnss_imu", "gnss": conf("sensor", "gnss"),
                                                 "imu": conf("sensor", "imu")})
    env.reset(seed=0)
    real = IMU.measure

    def poisoned(self):
        out = real(self)
        out[0, 0], out[0, 2], out[1, 1] = np.nan, np.inf, -np.inf
        return out

    monkeypatch.setattr(IMU, "measure", poisoned)
    obs, _, _, _, info = env.step(STRAIGHT)
    imu_space = env.observation_space["imu"]
    assert finite(obs) and imu_space.contains(obs["imu"])
    assert obs["imu"][0, 0] == 0.0 and obs["imu"][0, 2] == imu_space.high[0, 2] and obs["imu"][1, 1] == imu_space.low[1, 1]
    assert info["sensor_faults"] == {"imu": 3}
    monkeypatch.setattr(IMU, "measure", real)
    _, _, _, _, info = env.step(STRAIGHT)
    assert "sensor_faults" not in info


# ------------------------------------------------------------------------------------------------ EKF
@pytest.mark.parametrize("poison, reason", [
    (lambda kf: kf.P.__setitem__((PX, PX), np.nan), "unhealthy"),
    (lambda kf: kf.x.__setitem__(PX, np.inf), "unhealthy"),
    (lambda kf: kf.P.__setitem__((PX, PX), 1e6), "unhealthy"),  # covariance blow-up: std 1000 m > 50 m
])
def test_a_diverged_ekf_is_reinitialised_from_gnss(poison, reason):
    env = make_env(conf("env", "lane_keeping"), localized("gnss_imu"))
    env.reset(seed=1)
    drive(env, 10)

    infos = drive(env, 30, hook=lambda k, e: poison(pipeline(e).ekf.kf) if k == 0 else None)
    loc = [i["localization"] for i in infos]
    assert reason in loc[0]["reinit_reason"] and loc[0]["reinit_count"] == 1
    assert any(i["reinit"] for i in loc[:3])  # from the next GNSS fix
    assert loc[-1]["valid"] and error_m(env) < 6.0


def test_a_numerical_exception_in_the_estimator_is_reported_and_recovered(monkeypatch):
    env = make_env(conf("env", "lane_keeping"), localized("gnss_imu"))
    env.reset(seed=2)
    drive(env, 5)
    real = LocalizationEKF.update_gnss_position
    calls = {"n": 0}

    def fails_once(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 1:
            raise np.linalg.LinAlgError("Singular matrix")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(LocalizationEKF, "update_gnss_position", fails_once)
    infos = drive(env, 20)
    loc = [i["localization"] for i in infos]
    assert loc[0]["fault"] == "LinAlgError: Singular matrix" and loc[0]["fault_count"] == 1
    assert "fault" in loc[0]["reinit_reason"] and not loc[0]["valid"]
    assert loc[-1]["valid"] and loc[-1]["fault"] == "" and error_m(env) < 6.0


def test_non_finite_imu_samples_are_skipped_not_integrated():
    from av_gym.estimation.localization import LocalizationPipeline

    env = make_env(conf("env", "lane_keeping"), localized("gnss_imu"))
    obs, _ = env.reset(seed=3)
    obs, *_ = env.step(STRAIGHT)
    p: LocalizationPipeline = pipeline(env)
    bad = {**obs, "imu": np.full_like(obs["imu"], np.nan)}
    est, info = p.step(bad)
    assert info["imu_skipped"] == len(obs["imu"]) and info["fault"] == "" and np.all(np.isfinite(est))


def test_an_update_that_would_go_non_finite_is_refused(monkeypatch):
    ekf = LocalizationEKF()
    ekf.initialize([0.0, 0.0], 0.0, 10.0)
    x0 = ekf.x

    def nan_update(self, *args, **kwargs):
        self.x = self.x * np.nan

    monkeypatch.setattr(type(ekf.kf), "update", nan_update)
    up = ekf.update_gnss_position([0.5, 0.5])
    assert not up.accepted and np.array_equal(ekf.x, x0) and ekf.is_healthy()


# ------------------------------------------------------------------------------------------------ kiss-icp
def kiss_fails(monkeypatch, when):
    from kiss_icp.kiss_icp import KissICP

    real = KissICP.register_frame
    calls = {"n": 0}

    def register_frame(self, *args, **kwargs):
        calls["n"] += 1
        if when(calls["n"]):
            raise RuntimeError("simulated kiss-icp failure")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(KissICP, "register_frame", register_frame)


def test_a_kiss_icp_exception_restarts_lidar_only_odometry_from_gnss(monkeypatch):
    env = make_env(conf("env", "lane_keeping"), localized("lidar"))
    env.reset(seed=0)
    drive(env, 5)
    kiss_fails(monkeypatch, lambda n: n == 1)
    infos = drive(env, 15)
    loc = [i["localization"] for i in infos]
    failed = [i for i, x in enumerate(loc) if x["lidar_failed"]]
    assert failed and "kiss-icp raised RuntimeError: simulated kiss-icp failure" in loc[failed[0]]["lidar_failed"]
    assert "LiDAR odometry failed" in loc[failed[0]]["reinit_reason"]
    assert any(x["reinit"] for x in loc[failed[0]:])  # the pose restarts from the next GNSS fix
    assert loc[-1]["valid"] and loc[-1]["lidar_used"] and error_m(env) < 6.0


def test_an_empty_scan_in_fused_mode_is_reported_and_the_ekf_carries_on(monkeypatch):
    from av_gym.sensors.lidar import Lidar

    env = make_env(conf("env", "lane_keeping"), localized("fused"))
    env.reset(seed=0)
    drive(env, 5)
    monkeypatch.setattr(Lidar, "points", lambda self: (np.zeros((0, 3)), np.zeros(0)))
    loc = [i["localization"] for i in drive(env, 10)]
    assert any("too few points (0 < 30)" in x["lidar_failed"] for x in loc)
    assert all(x["valid"] for x in loc) and error_m(env) < 6.0
    monkeypatch.undo()
    kiss_fails(monkeypatch, lambda n: True)  # kiss-icp failing on every scan: GNSS and IMU still localize
    loc = [i["localization"] for i in drive(env, 10)]
    assert any("kiss-icp raised" in x["lidar_failed"] for x in loc) and loc[-1]["valid"] and error_m(env) < 6.0


def test_lidar_odometry_turns_any_library_exception_into_a_failed_result(monkeypatch):
    odo = LidarOdometry(max_range=50.0)
    kiss_fails(monkeypatch, lambda n: n == 2)
    rng = np.random.default_rng(0)
    scan = np.column_stack([rng.uniform(-20, 20, (400, 2)), np.zeros(400)])
    assert odo.register(scan).ok
    res = odo.register(scan)
    assert not res.ok and "kiss-icp raised RuntimeError" in res.reason and odo.restarts == 1
    assert odo.register(scan).ok and odo.register(scan).ok


# ------------------------------------------------------------------------------------------------ tracker
def test_tracker_drops_non_finite_detections():
    tr = MultiObjectTracker(min_hits=1)
    det = np.array([[1, 10.0, 0.0, 5.0, 0.0, 0.0, 5.0, 2.0, 0.0],
                    [1, np.nan, 3.0, 5.0, 0.0, 0.0, 5.0, 2.0, 0.0],
                    [1, 30.0, 3.0, np.inf, 0.0, 0.0, 5.0, 2.0, 0.0]])
    for k in range(5):
        det[:, 1] += 0.5 * (k > 0)
        tracks = tr.step(det, 0.1 * k)
        assert np.all(np.isfinite(tracks)) and len(tracks) == 1
    assert tr.faults == 10
