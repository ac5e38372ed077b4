"""A reading that holds NaN/inf is not only made finite (tests/test_numerics.py) but marked not usable in the
sensor's own terms, so that the 0 put in its place is never a confident reading (R6 finding 2): GNSS clears
fresh/valid, the lidar reads the beam as no return, the detector drops the row. Faults stay counted in info."""

from __future__ import annotations

import numpy as np

from av_gym.make import make_env
from av_gym.sensors.detector import Detector
from av_gym.sensors.gnss import GNSS
from av_gym.sensors.lidar import Lidar
from conftest import conf

STRAIGHT = np.zeros(1, dtype=np.float32)


def _poison(monkeypatch, cls, edit) -> None:
    real = cls.measure

    def poisoned(self):
        out = np.array(real(self), dtype=np.float32)
        edit(out)
        return out

    monkeypatch.setattr(cls, "measure", poisoned)


def test_a_nan_gnss_fix_reads_not_fresh_not_valid(monkeypatch):
    env = make_env(conf("env", "lane_keeping"), {"name": "gnss_imu", "gnss": conf("sensor", "gnss"),
                                                 "imu": conf("sensor", "imu")})
    env.reset(seed=0)
    obs, *_ = env.step(STRAIGHT)
    assert obs["gnss"][4] == 1.0 and obs["gnss"][5] == 1.0  # a healthy fix first: the flags can be 1 here

    def nan_xy(out):
        out[0] = out[1] = np.nan

    _poison(monkeypatch, GNSS, nan_xy)
    obs, _, _, _, info = env.step(STRAIGHT)
    assert np.all(np.isfinite(obs["gnss"])) and env.observation_space["gnss"].contains(obs["gnss"])
    assert obs["gnss"][4] == 0.0 and obs["gnss"][5] == 0.0  # not fresh, not valid: no fix at the origin
    assert info["sensor_faults"] == {"gnss": 2}


def test_a_nan_lidar_beam_reads_no_return(monkeypatch):
    env = make_env(conf("env", "lane_keeping"), {"name": "lidar", "keep_state": False, "lidar": conf("sensor", "lidar")})
    env.reset(seed=0)

    def nan_beam(out):
        out[0, 0], out[0, 1] = np.nan, -np.inf

    _poison(monkeypatch, Lidar, nan_beam)
    obs, _, _, _, info = env.step(STRAIGHT)
    max_range = env.observation_space["lidar"].high[0, 0]
    assert obs["lidar"][0, 0] == max_range and obs["lidar"][0, 1] == max_range  # not 0 m, not the low bound
    assert info["sensor_faults"] == {"lidar": 2}


def test_a_nan_detection_row_is_dropped(monkeypatch):
    env = make_env(conf("env", "lane_keeping"), {"name": "detector", "keep_state": False, "detector": conf("sensor", "detector")})
    env.reset(seed=0)

    def nan_row(out):
        out[0, :] = 0.0
        out[0, 0], out[0, 1], out[0, 3] = 1.0, 12.0, np.nan  # a present object whose vx is NaN

    _poison(monkeypatch, Detector, nan_row)
    obs, _, _, _, info = env.step(STRAIGHT)
    assert np.all(obs["detector"][0] == 0.0)  # present = 0: dropped, not an object at 12 m moving at 0 m/s
    assert info["sensor_faults"] == {"detector": 1}


def test_a_dropped_non_finite_gnss_fix_is_counted_in_info_and_the_episode(monkeypatch):
    """GNSS drops a fix that is not finite before the guard sees it (held, as in an outage): it is still a fault,
    reported in info["sensor_faults"] and summed into the episode's sensor_faults (the results column)."""
    env = make_env(conf("env", "lane_keeping"), {"name": "gnss_imu", "gnss": conf("sensor", "gnss"),
                                                 "imu": conf("sensor", "imu")})
    env.reset(seed=0)
    real = GNSS._true_state
    monkeypatch.setattr(GNSS, "_true_state", lambda self, t: real(self, t) * np.nan)
    reported = 0
    for _ in range(3):  # GNSS's fixes come at its own rate: three steps hold at least one
        obs, _, _, _, info = env.step(STRAIGHT)
        reported += info.get("sensor_faults", {}).get("gnss", 0)
        assert np.all(np.isfinite(obs["gnss"]))
    assert reported > 0 and reported % 4 == 0  # x, y, vx, vy of each dropped fix
    assert env.summary()["sensor_faults"] == reported
