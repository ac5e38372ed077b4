"""``env.ccftap.target_speed_kmh`` is bounded at 144 km/h = 40 m/s, highway-env's Vehicle.MAX_SPEED: a faster target
is slowed to 40 m/s on every step, never drives its set speed and reaches the conflict point late, so the case's
``dt`` would be wrong. 150 is refused in one line naming the field and its range; 144 runs at its set speed."""

from __future__ import annotations

import gymnasium as gym
import pytest

from av_gym.params import ParamError

ID = "av_gym/UnprotectedLeftTurn-v0"


def _make(target_kmh: float) -> gym.Env:
    return gym.make(ID, env={"mode": "ccftap", "ccftap": {"target_speed_kmh": target_kmh}}, sensors="turn_truth")


def test_target_above_vehicle_max_speed_is_refused():
    with pytest.raises(ParamError) as err:
        _make(150)  # as a command line gives it
    assert str(err.value) == "env.ccftap.target_speed_kmh must be a number in [1, 144], got 150"


def test_target_at_144_kmh_drives_its_set_speed():
    env = _make(144.0)
    try:
        env.reset(seed=0)
        road = env.unwrapped.road
        target = [v for v in road.vehicles if v is not env.unwrapped.vehicle]
        assert len(target) == 1 and target[0].speed == pytest.approx(40.0)
        for _ in range(5):  # not slowed by the cap: at exactly 40 m/s it holds its speed
            env.step(1)
        assert target[0].speed == pytest.approx(40.0, abs=1e-6)
    finally:
        env.close()
