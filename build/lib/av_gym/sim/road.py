"""``FastRegulatedRoad``: highway-env's ``RegulatedRoad`` (intersection priority rules) with the same decisions,
computed without the quadratic waste of the stock code:

- ``enforce_road_rules`` (every 0.5 s): the stock ``is_conflict_possible(v1, v2)`` re-predicts *both* vehicles'
  3 s trajectories for every pair — O(n²) predictions of 11 points each, through ``position_heading_along_route``
  — although a vehicle's prediction does not depend on the other vehicle. Here each vehicle is predicted once per
  call (``av_gym.sim.vehicles.predict_constant_speed``, same floats), and every pair runs the stock test on those
  points: the stock distance pre-check, then the stock ``utils.rotated_rectangles_intersect``.
- ``neighbour_vehicles`` (IDM's leader/follower, twice per vehicle per tick, each scanning all vehicles): during
  ``act()`` no vehicle moves, so each lane's local coordinates of every vehicle are computed once per tick and
  reused; the scan and its tie-breaking are the stock ones.
- ``step``'s collision checks: pairs farther apart than the stock spherical pre-check's radius are skipped without
  building polygons; every other pair goes to the stock ``handle_collisions``, in the stock order.
"""

from __future__ import annotations

import numpy as np
from highway_env import utils
from highway_env.road.regulation import RegulatedRoad
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.controller import ControlledVehicle, MDPVehicle
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Landmark, RoadObject

from av_gym.sim import fmath
from av_gym.sim import lanes as fast_lanes
from av_gym.sim.fast_network import centreline_box
from av_gym.sim.vehicles import predict_constant_speed


def _stock_collisions(obj) -> bool:
    return (type(obj).handle_collisions is RoadObject.handle_collisions
            and type(obj)._is_colliding is RoadObject._is_colliding)


class FastRoadMixin:
    """Fast ``act``/``step``/``neighbour_vehicles`` for a ``Road`` subclass (same results)."""

    _nb_cache: dict | None = None

    def act(self) -> None:
        self._nb_cache = {}  # valid while no vehicle moves
        try:
            for vehicle in self.vehicles:
                vehicle.act()
        finally:
            self._nb_cache = None

    def step(self, dt: float) -> None:
        for vehicle in self.vehicles:
            vehicle.step(dt)
        self.handle_all_collisions(dt)

    def handle_all_collisions(self, dt: float) -> None:
        """``Road.step``'s collision loops, same pairs in the same order, minus the pairs the stock spherical
        pre-check would reject (``norm(Δp) > (d1 + d2) / 2 + v1·dt``: no effect at all)."""
        vehicles = self.vehicles
        xs = [float(v.position[0]) for v in vehicles]
        ys = [float(v.position[1]) for v in vehicles]
        plain = [_stock_collisions(v) for v in vehicles]
        for i, vehicle in enumerate(vehicles):
            for j in range(i + 1, len(vehicles)):
                other = vehicles[j]
                if plain[i] and plain[j]:
                    dx, dy = xs[j] - xs[i], ys[j] - ys[i]
                    if fmath.sqrt(dx * dx + dy * dy) > (vehicle.diagonal + other.diagonal) / 2 + vehicle.speed * dt:
                        continue
                vehicle.handle_collisions(other, dt)
            for other in self.objects:
                vehicle.handle_collisions(other, dt)

    def neighbour_vehicles(self, vehicle, lane_index: LaneIndex = None):
        cache = self._nb_cache
        if cache is None or self.neighbour_vehicles_connected_lanes or self.objects:
            return super().neighbour_vehicles(vehicle, lane_index)
        lane_index = lane_index or vehicle.lane_index
        if not lane_index:
            return None, None
        lane = self.network.get_lane(lane_index)
        if fast_lanes.params(lane)[0] == fast_lanes.OTHER:
            return super().neighbour_vehicles(vehicle, lane_index)
        on_lane = cache.get(id(lane))
        if on_lane is None:
            on_lane = cache[id(lane)] = self._on_lane(lane)
        s = fast_lanes.local_coordinates(lane, float(vehicle.position[0]), float(vehicle.position[1]))[0]
        s_front = s_rear = None
        v_front = v_rear = None
        for v, s_v in on_lane:  # the stock scan, over the vehicles on the lane, in road order
            if v is vehicle:
                continue
            if s <= s_v and (s_front is None or s_v <= s_front):
                s_front = s_v
                v_front = v
            if s_v < s and (s_rear is None or s_v > s_rear):
                s_rear = s_v
                v_rear = v
        return v_front, v_rear


    def _on_lane(self, lane) -> list:
        """(vehicle, s) of the vehicles the stock scan accepts on ``lane`` (``on_lane`` with a 1 m margin), in road
        order. A vehicle outside the lane's centreline box grown by VEHICLE_LENGTH + width / 2 + 1 m cannot be on
        it (s runs at most VEHICLE_LENGTH past either end, |lateral| at most width / 2 + 1), so its lane
        coordinates are not needed."""
        half_width, vl, length = lane.width_at(0) / 2 + 1, lane.VEHICLE_LENGTH, lane.length
        box = lane.__dict__.get("_fast_box")
        if box is None:
            grow = vl + half_width + 1e-6
            b = centreline_box(lane)
            box = lane._fast_box = (b[0] - grow, b[1] - grow, b[2] + grow, b[3] + grow)
        out = []
        for v in self.vehicles:
            if isinstance(v, Landmark):
                continue
            x, y = float(v.position[0]), float(v.position[1])
            if not (box[0] <= x <= box[2] and box[1] <= y <= box[3]):
                continue
            s_v, lat_v = fast_lanes.local_coordinates(lane, x, y)
            if abs(lat_v) <= half_width and -vl <= s_v < length + vl:
                out.append((v, s_v))
        return out


class FastRoad(FastRoadMixin, Road):
    """``Road`` with the fast paths of :class:`FastRoadMixin`."""


class FastRegulatedRoad(FastRoadMixin, RegulatedRoad):
    """``RegulatedRoad`` with the fast paths above; build with :meth:`from_road`."""

    @classmethod
    def from_road(cls, road: RegulatedRoad, network: RoadNetwork | None = None) -> "FastRegulatedRoad":
        fast = cls(network=network or road.network, vehicles=road.vehicles, obstacles=road.objects,
                   np_random=road.np_random, record_history=road.record_history,
                   neighbour_vehicles_connected_lanes=road.neighbour_vehicles_connected_lanes)
        fast.vehicles, fast.objects, fast.steps = road.vehicles, road.objects, road.steps
        return fast

    def step(self, dt: float) -> None:
        self.steps += 1
        if self.steps % int(1 / dt / self.REGULATION_FREQUENCY) == 0:
            self.enforce_road_rules()
        FastRoadMixin.step(self, dt)

    def enforce_road_rules(self) -> None:
        """``RegulatedRoad.enforce_road_rules`` with one prediction per vehicle (see the module docstring)."""
        for v in self.vehicles:  # unfreeze previous yielding vehicles (stock code)
            if getattr(v, "is_yielding", False):
                if v.yield_timer >= self.YIELD_DURATION * self.REGULATION_FREQUENCY:
                    v.target_speed = v.lane.speed_limit
                    delattr(v, "color")
                    v.is_yielding = False
                else:
                    v.yield_timer += 1
        vehicles = self.vehicles
        predictions = [predict_constant_speed(v) for v in vehicles]
        for i in range(len(vehicles) - 1):
            for j in range(i + 1, len(vehicles)):
                if self._conflict(vehicles[i], vehicles[j], predictions[i], predictions[j]):
                    yielding_vehicle = self.respect_priorities(vehicles[i], vehicles[j])
                    if (yielding_vehicle is not None and isinstance(yielding_vehicle, ControlledVehicle)
                            and not isinstance(yielding_vehicle, MDPVehicle)):
                        yielding_vehicle.color = self.YIELDING_COLOR
                        yielding_vehicle.target_speed = 0
                        yielding_vehicle.is_yielding = True
                        yielding_vehicle.yield_timer = 0

    @staticmethod
    def _conflict(v1: Vehicle, v2: Vehicle, p1: list, p2: list) -> bool:
        """``RegulatedRoad.is_conflict_possible`` on precomputed predictions (same pre-check, same exact test)."""
        for (x1, y1, h1), (x2, y2, h2) in zip(p1, p2):
            dx, dy = x2 - x1, y2 - y1
            if fmath.sqrt(dx * dx + dy * dy) > v1.LENGTH:
                continue
            if utils.rotated_rectangles_intersect((np.array([x1, y1]), 1.5 * v1.LENGTH, 0.9 * v1.WIDTH, h1),
                                                  (np.array([x2, y2]), 1.5 * v2.LENGTH, 0.9 * v2.WIDTH, h2)):
                return True
        return False
