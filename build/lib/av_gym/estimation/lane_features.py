"""``LaneFeatures``: the lane-keeping state a learned steering policy reads, from the simulator (``source: truth``)
or from the localizer's estimate (``source: estimate``, ``obs["ego_estimate"]``), in one layout.

Why: the localizer reports the estimated pose as ``[cte, heading_error, x, y, heading, speed, valid, position_std,
path_s]`` — absolute coordinates an MLP should not steer by. This wrapper turns it into the same vector as the
privileged ``LaneKeepingState`` (CTE, heading error, speed, the car's own yaw rate and steering angle, map curvature
ahead of the *estimated* position), scaled to [-1, 1], so a policy trained on one source can be run on the other and
both train without running observation normalisation. The layout is read through the env (``env.unwrapped.STATE``,
av_gym/envs/observations.py): envs sit above estimation and are not imported here (tests/test_imports.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.sim.vehicles import ego_kinematics
from av_gym.errors import ConfigError
from av_gym.params import Params, param
from av_gym.sensors.base import SensorWrapper

@dataclass(frozen=True)
class LaneFeaturesParams(Params):
    source: Literal["truth", "estimate"] = param("estimate", doc="estimate (obs['ego_estimate'], the localizer's) "
                                                                "or truth (the simulator's lane state)")


class LaneFeatures(SensorWrapper):
    """Adds ``obs["lane"]``: the lane state's ``FEATURES`` divided by its ``HIGH``
    (``Box(-1, 1, (10,))``). Parameters: :class:`LaneFeaturesParams`. Yaw rate and steering angle are the car's
    own signals in both sources (a car reads them off its CAN bus)."""

    key = "lane"
    Params = LaneFeaturesParams

    def __init__(self, env: gym.Env, params: LaneFeaturesParams | None = None, **overrides) -> None:
        p = self.params = LaneFeaturesParams.build(params, **overrides)
        source = p.source
        if env.unwrapped.scenario != "lane_keeping":
            raise ConfigError(f"sensors.lane_features is for env=lane_keeping, not env={env.unwrapped.scenario}")
        if source == "estimate" and "ego_estimate" not in env.observation_space.spaces:
            raise ConfigError("sensors.lane_features.source=estimate needs the localizer below it "
                              "(`localizer:` in the sensors preset)")
        self.source = source
        self.layout = env.unwrapped.STATE  # LaneKeepingState: FEATURES, PREVIEW, HIGH (envs sit above this layer)
        super().__init__(env)

    def sensor_space(self) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, shape=(len(self.layout.FEATURES),), dtype=np.float32)

    def observation(self, observation: dict) -> dict:
        return {**observation, self.key: self._features(observation)}

    def _features(self, observation: dict) -> np.ndarray:
        env = self.env.unwrapped
        if self.source == "truth":
            t = env.lane_state()
            cte, heading_error, speed, s = t["cte"], t["heading_error"], t["speed"], t["lap_s"]
        else:
            from av_gym.estimation.localization import CTE, HEADING_ERROR, PATH_S, SPEED

            est = observation["ego_estimate"]
            cte, heading_error, speed, s = est[CTE], est[HEADING_ERROR], est[SPEED], est[PATH_S]
        kin = ego_kinematics(env.vehicle)
        curvature = env.track.curvature(s + self.layout.PREVIEW)
        v = np.array([cte, heading_error, speed, kin["yaw_rate"], kin["steering"], *curvature])
        v = np.nan_to_num(v / self.layout.HIGH, nan=0.0)
        return np.clip(v, -1.0, 1.0).astype(np.float32)

    def measure(self) -> np.ndarray:  # observation() is overridden: the features need the other keys
        raise NotImplementedError
