"""Vehicle subclasses whose per-tick work runs on Python floats (``av_gym.sim.fmath``, ``av_gym.sim.lanes``)
instead of numpy scalars: the same operations in the same order as highway-env's, so the same bits.

Why: ``Vehicle.step``, the lateral controller and IDM build 2-element arrays and call numpy ufuncs on single
floats; the dispatch overhead (~1 µs a call) is most of their cost. The models (kinematic bicycle, IDM, MOBIL,
the lateral and speed controllers, route following) are highway-env's: only *how* the formulas are evaluated
changes. Anything these classes do not handle (other lane types, overridden methods) goes to the stock code.
"""

from __future__ import annotations

import numpy as np
from highway_env.road.road import LaneIndex
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle, MDPVehicle
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import RoadObject

from av_gym.sim import fmath
from av_gym.sim import lanes as fast_lanes


def kinematic_step(vehicle: Vehicle, dt: float) -> None:
    """``highway_env.vehicle.kinematics.Vehicle.step`` (modified bicycle model), float by float."""
    vehicle.clip_actions()
    action = vehicle.action
    beta = fmath.atan(1 / 2 * fmath.tan(action["steering"]))
    speed = vehicle.speed
    angle = vehicle.heading + beta
    position = vehicle.position  # updated in place, as the stock ``self.position += v * dt``
    position[0] = position[0] + speed * fmath.cos(angle) * dt
    position[1] = position[1] + speed * fmath.sin(angle) * dt
    if vehicle.impact is not None:
        position += vehicle.impact
        vehicle.crashed = True
        vehicle.impact = None
    vehicle.heading += speed * fmath.sin(beta) / (vehicle.LENGTH / 2) * dt
    vehicle.speed += action["acceleration"] * dt
    vehicle.on_state_update()


def _plain_velocity(obj) -> bool:
    return type(obj).velocity in (Vehicle.velocity, RoadObject.velocity)


class FastControlMixin:
    """``ControlledVehicle``'s lane following on floats. Mix in before a ``ControlledVehicle`` class."""

    def follow_road(self) -> None:
        # Stock: get_lane(target).after_end(position), i.e. local s > length - VEHICLE_LENGTH / 2.
        lane = self.road.network.get_lane(self.target_lane_index)
        s, _ = fast_lanes.local_coordinates(lane, float(self.position[0]), float(self.position[1]))
        if s > lane.length - lane.VEHICLE_LENGTH / 2:
            self.target_lane_index = self.road.network.next_lane(
                self.target_lane_index, route=self.route, position=self.position, np_random=self.road.np_random)

    def steering_control(self, target_lane_index: LaneIndex) -> float:
        """``ControlledVehicle.steering_control``, operation for operation."""
        target_lane = self.road.network.get_lane(target_lane_index)
        s, lat = fast_lanes.local_coordinates(target_lane, float(self.position[0]), float(self.position[1]))
        lane_future_heading = fast_lanes.heading_at(target_lane, s + self.speed * self.TAU_PURSUIT)
        lateral_speed_command = -self.KP_LATERAL * lat
        heading_command = fmath.asin(fmath.clip(lateral_speed_command / fmath.not_zero(self.speed), -1, 1))
        heading_ref = lane_future_heading + fmath.clip(heading_command, -np.pi / 4, np.pi / 4)
        heading_rate_command = self.KP_HEADING * fmath.wrap_to_pi(heading_ref - self.heading)
        slip_angle = fmath.asin(fmath.clip(self.LENGTH / 2 / fmath.not_zero(self.speed) * heading_rate_command,
                                           -1, 1))
        steering_angle = fmath.atan(2 * fmath.tan(slip_angle))
        steering_angle = fmath.clip(steering_angle, -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE)
        return float(steering_angle)

    def lane_distance_to(self, other: RoadObject, lane=None) -> float:
        if not other:
            return np.nan
        if not lane:
            lane = self.lane
        return (fast_lanes.local_coordinates(lane, float(other.position[0]), float(other.position[1]))[0]
                - fast_lanes.local_coordinates(lane, float(self.position[0]), float(self.position[1]))[0])


class FastVehicle(Vehicle):
    """``Vehicle`` with :func:`kinematic_step` (e.g. the CCFtap target)."""

    def step(self, dt: float) -> None:
        kinematic_step(self, dt)


class FastMDPVehicle(FastControlMixin, MDPVehicle):
    """``MDPVehicle`` (the discrete-action ego) with float lane following and :func:`kinematic_step`."""

    def step(self, dt: float) -> None:
        kinematic_step(self, dt)


class FastIDMVehicle(FastControlMixin, IDMVehicle):
    """``IDMVehicle``: the same IDM + MOBIL decisions, evaluated on floats; neighbours come from the road (see
    ``av_gym.sim.road.FastRegulatedRoad.neighbour_vehicles``)."""

    def step(self, dt: float) -> None:
        self.timer += dt
        kinematic_step(self, dt)

    def act(self, action: dict | str = None) -> None:
        """``IDMVehicle.act``, line for line, with float clipping."""
        if self.crashed:
            return
        action = {}
        self.follow_road()
        if self.enable_lane_change:
            self.change_lane_policy()
        action["steering"] = fmath.clip(self.steering_control(self.target_lane_index),
                                        -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE)
        front_vehicle, rear_vehicle = self.road.neighbour_vehicles(self, self.lane_index)
        action["acceleration"] = self.acceleration(self, front_vehicle, rear_vehicle)
        if self.lane_index != self.target_lane_index:
            front_vehicle, rear_vehicle = self.road.neighbour_vehicles(self, self.target_lane_index)
            target_idm_acceleration = self.acceleration(self, front_vehicle, rear_vehicle)
            action["acceleration"] = min(action["acceleration"], target_idm_acceleration)
        action["acceleration"] = fmath.clip(action["acceleration"], -self.ACC_MAX, self.ACC_MAX)
        Vehicle.act(self, action)

    def acceleration(self, ego_vehicle: ControlledVehicle, front_vehicle: Vehicle = None,
                     rear_vehicle: Vehicle = None) -> float:
        """``IDMVehicle.acceleration`` (the IDM), operation for operation."""
        if not ego_vehicle or not isinstance(ego_vehicle, Vehicle):
            return 0
        ego_target_speed = getattr(ego_vehicle, "target_speed", 0)
        if ego_vehicle.lane and ego_vehicle.lane.speed_limit is not None:
            ego_target_speed = fmath.clip(ego_target_speed, 0, ego_vehicle.lane.speed_limit)
        acceleration = self.COMFORT_ACC_MAX * (
            1 - fmath.power(max(ego_vehicle.speed, 0) / abs(fmath.not_zero(ego_target_speed)), self.DELTA))
        if front_vehicle:
            d = ego_vehicle.lane_distance_to(front_vehicle)
            acceleration -= self.COMFORT_ACC_MAX * fmath.square(
                self.desired_gap(ego_vehicle, front_vehicle) / fmath.not_zero(d))
        return acceleration

    def desired_gap(self, ego_vehicle: Vehicle, front_vehicle: Vehicle = None, projected: bool = True) -> float:
        # The expanded dot product equals the stock ``np.dot`` only where BLAS does no fused multiply-add.
        if not (projected and fmath.DOT_EXACT and _plain_velocity(ego_vehicle) and _plain_velocity(front_vehicle)):
            return super().desired_gap(ego_vehicle, front_vehicle, projected)
        d0 = self.DISTANCE_WANTED
        tau = self.TIME_WANTED
        ab = -self.COMFORT_ACC_MAX * self.COMFORT_ACC_MIN
        c, s = fmath.cos(ego_vehicle.heading), fmath.sin(ego_vehicle.heading)
        cf, sf = fmath.cos(front_vehicle.heading), fmath.sin(front_vehicle.heading)
        ve, vf = ego_vehicle.speed, front_vehicle.speed
        dv = (ve * c - vf * cf) * c + (ve * s - vf * sf) * s  # np.dot(v_ego - v_front, direction_ego)
        return d0 + ego_vehicle.speed * tau + ego_vehicle.speed * dv / (2 * fmath.sqrt(ab))


# ----------------------------------------------------------------------------------------------- predictions
PREDICTION_TIMES = np.arange(0.25, 3, 0.25)  # RegulatedRoad.is_conflict_possible's default horizon and step
_PREDICTION_DT = [float(t) for t in np.diff(np.concatenate(([0.0], PREDICTION_TIMES)))]


def predict_constant_speed(vehicle: Vehicle, times: np.ndarray = PREDICTION_TIMES) -> list[tuple[float, float, float]]:
    """``vehicle.predict_trajectory_constant_speed(times)`` as (x, y, heading) floats, without the stock cost:

    - a ``ControlledVehicle`` follows its route at constant speed (``position_heading_along_route``);
    - a plain ``Vehicle`` is integrated with its current steering and zero acceleration — the stock code
      deep-copies the vehicle, *and with it the whole road*, to do so.
    Vehicles whose class overrides these methods get the stock call."""
    kind = type(vehicle).predict_trajectory_constant_speed
    if kind is ControlledVehicle.predict_trajectory_constant_speed:
        return _predict_along_route(vehicle, times)
    if (kind is Vehicle.predict_trajectory_constant_speed and type(vehicle).step in (Vehicle.step, FastVehicle.step)
            and type(vehicle).clip_actions is Vehicle.clip_actions and times is PREDICTION_TIMES):
        return _predict_integrated(vehicle)
    positions, headings = vehicle.predict_trajectory_constant_speed(times)
    return [(float(p[0]), float(p[1]), h) for p, h in zip(positions, headings)]


def _predict_along_route(v: ControlledVehicle, times) -> list[tuple[float, float, float]]:
    network = v.road.network
    s0, _ = fast_lanes.local_coordinates(v.lane, float(v.position[0]), float(v.position[1]))
    full_route = v.route or [v.lane_index]
    current = v.lane_index

    def head(route_):
        lane_index_ = route_[0]
        if lane_index_[2] is None:
            id_ = current[2] if current[2] < len(network.graph[current[0]][current[1]]) else 0
            lane_index_ = (lane_index_[0], lane_index_[1], id_)
        return lane_index_

    out = []
    for t in times:
        longitudinal = s0 + v.speed * t
        route = full_route
        lane_index = head(route)
        while len(route) > 1 and longitudinal > network.get_lane(lane_index).length:
            longitudinal -= network.get_lane(lane_index).length
            route = route[1:]
            lane_index = head(route)
        lane = network.get_lane(lane_index)
        x, y = fast_lanes.position(lane, longitudinal, 0)
        out.append((x, y, fast_lanes.heading_at(lane, longitudinal)))
    return out


def _predict_integrated(v: Vehicle) -> list[tuple[float, float, float]]:
    if v.prediction_type == "zero_steering":
        steering = 0.0
    elif v.prediction_type == "constant_steering":
        steering = v.action["steering"]
    else:
        raise ValueError("Unknown predition type")
    acceleration = 0.0
    x, y, heading, speed = float(v.position[0]), float(v.position[1]), v.heading, v.speed
    crashed, impact = v.crashed, v.impact
    half_length = v.LENGTH / 2
    out = []
    for dt in _PREDICTION_DT:  # Vehicle.clip_actions + Vehicle.step, on a copy
        if crashed:
            steering = 0
            acceleration = -1.0 * speed
        steering, acceleration = float(steering), float(acceleration)
        if speed > v.MAX_SPEED:
            acceleration = min(acceleration, 1.0 * (v.MAX_SPEED - speed))
        elif speed < v.MIN_SPEED:
            acceleration = max(acceleration, 1.0 * (v.MIN_SPEED - speed))
        beta = fmath.atan(1 / 2 * fmath.tan(steering))
        x, y = x + speed * fmath.cos(heading + beta) * dt, y + speed * fmath.sin(heading + beta) * dt
        if impact is not None:
            x, y = x + float(impact[0]), y + float(impact[1])
            crashed, impact = True, None
        heading += speed * fmath.sin(beta) / half_length * dt
        speed += acceleration * dt
        out.append((x, y, heading))
    return out


def ego_kinematics(vehicle) -> dict:
    """Applied steering (rad), acceleration (m/s²) and the kinematic bicycle's yaw rate (rad/s, + = right turn:
    ψ̇ = v·sin β / (L/2), β = atan(tan δ / 2), highway-env's model) of a vehicle."""
    action = vehicle.action or {}
    steering = float(action.get("steering", 0.0))
    beta = fmath.atan(0.5 * fmath.tan(steering))  # = np.arctan(0.5 * np.tan(steering)), see av_gym.sim.fmath
    return {"steering": steering, "acceleration": float(action.get("acceleration", 0.0)),
            "yaw_rate": float(vehicle.speed * fmath.sin(beta) / (vehicle.LENGTH / 2))}
