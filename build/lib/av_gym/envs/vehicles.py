"""Ego vehicles and action types for our scenarios, as small subclasses of highway-env's.

highway-env offers steering-only control only with zero acceleration, and longitudinal-only continuous control only
with zero steering. Our scenarios need the complementary halves: the lap holds speed with a controller while the
agent steers, and the left turn follows its route laterally while the agent commands acceleration.
"""

from __future__ import annotations

import functools
from typing import Callable

import numpy as np
from gymnasium import spaces
from highway_env import utils
from highway_env.envs.common.action import ContinuousAction, DiscreteMetaAction
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from av_gym.sim.vehicles import FastControlMixin, FastMDPVehicle, kinematic_step


class SpeedHeldVehicle(Vehicle):
    """Kinematic bicycle whose speed is held at ``target_speed`` (m/s) by a proportional controller
    (time constant ``TAU_ACC`` = 0.6 s, highway-env's own cruise-control constant); steering comes from the action."""

    TAU_ACC = ControlledVehicle.TAU_ACC

    def __init__(self, road, position, heading: float = 0.0, speed: float = 0.0, target_speed: float = 10.0):
        super().__init__(road, position, heading, speed)
        self.target_speed = target_speed

    def act(self, action: dict | None = None) -> None:
        if action:
            self.action = dict(action)
        self.action["acceleration"] = (self.target_speed - self.speed) / self.TAU_ACC


class FastSpeedHeldVehicle(SpeedHeldVehicle):
    """Same model, stepped by ``av_gym.sim.vehicles.kinematic_step`` (same bits, no numpy-scalar overhead)."""

    def step(self, dt: float) -> None:
        kinematic_step(self, dt)


class SteeringAction(ContinuousAction):
    """Continuous steering in [-1, 1] mapped to ``steering_range`` (rad); + steers right. Speed is held."""

    def __init__(self, env, steering_range=(-np.radians(25), np.radians(25)), target_speed: float = 10.0,
                 fast: bool = False, **kwargs):
        super().__init__(env, steering_range=steering_range, longitudinal=False, lateral=True, dynamical=False)
        self.target_speed = target_speed
        self.fast = fast  # FastSpeedHeldVehicle: same trajectories, faster step

    def get_action(self, action: np.ndarray):
        if not (self.fast and self.clip and not self.speed_range):
            return super().get_action(action)
        # ContinuousAction.get_action (lateral only): np.clip's Python-level wrapper costs more than the rest of
        # the action; minimum(maximum(.)) is the same operation (same dtype, NaN kept).
        action = np.minimum(np.maximum(action, -1), 1)
        return {"acceleration": 0, "steering": utils.lmap(action[0], [-1, 1], self.steering_range)}

    @property
    def vehicle_class(self) -> Callable:
        cls = FastSpeedHeldVehicle if self.fast else SpeedHeldVehicle
        return lambda road, position, heading=0.0, speed=0.0: cls(
            road, position, heading, speed, target_speed=self.target_speed)


class RouteFollowingVehicle(ControlledVehicle):
    """Follows its planned route with highway-env's lateral controller; acceleration (m/s²) is commanded directly."""

    def __init__(self, road, position, heading: float = 0.0, speed: float = 0.0, **kwargs):
        super().__init__(road, position, heading, speed, **kwargs)
        self.commanded_acceleration = 0.0

    def act(self, action: dict | str | None = None) -> None:
        if isinstance(action, dict) and "acceleration" in action:
            self.commanded_acceleration = float(action["acceleration"])
        self.follow_road()
        steering = np.clip(self.steering_control(self.target_lane_index),
                           -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE)
        # No reversing: a standstill is held rather than integrated into negative speed.
        acceleration = max(self.commanded_acceleration, -self.speed / 0.05)
        Vehicle.act(self, {"steering": steering, "acceleration": acceleration})


class FastRouteFollowingVehicle(FastControlMixin, RouteFollowingVehicle):
    """Same model; lane following on floats and ``kinematic_step`` (av_gym.sim.vehicles: same bits)."""

    def step(self, dt: float) -> None:
        kinematic_step(self, dt)


class LongitudinalAction(ContinuousAction):
    """Continuous longitudinal command in [-1, 1] mapped to ``acceleration_range`` (m/s²); steering follows route."""

    def __init__(self, env, acceleration_range=(-8.0, 3.0), fast: bool = False, **kwargs):
        super().__init__(env, acceleration_range=acceleration_range, longitudinal=True, lateral=False)
        self.fast = fast

    @property
    def vehicle_class(self) -> Callable:
        return FastRouteFollowingVehicle if self.fast else RouteFollowingVehicle

    def space(self) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)

    def acceleration(self, action: np.ndarray) -> float:
        """The acceleration (m/s²) ``action`` commands (also what the AEB shield predicts the ego under)."""
        return utils.lmap(self._command(action), [-1, 1], self.acceleration_range)

    @staticmethod
    def _command(action: np.ndarray) -> float:
        return float(np.clip(np.asarray(action, dtype=float).reshape(-1)[0], -1.0, 1.0))

    def act(self, action: np.ndarray) -> None:
        self.controlled_vehicle.act({"acceleration": self.acceleration(action)})
        self.last_action = np.array([self._command(action)])


class FastDiscreteMetaAction(DiscreteMetaAction):
    """highway-env's meta-actions driving a ``FastMDPVehicle`` (same model, same trajectories, faster step)."""

    @property
    def vehicle_class(self) -> Callable:
        return functools.partial(FastMDPVehicle, target_speeds=self.target_speeds)
