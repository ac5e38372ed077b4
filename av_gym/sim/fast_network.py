"""``FastRoadNetwork``: highway-env's ``RoadNetwork`` with a closest-lane search that returns exactly the same
lane, an order of magnitude faster.

Every vehicle calls ``get_closest_lane_index`` on every tick, and the stock version evaluates
``lane.distance_with_heading`` for *every* lane of the map in Python (about 37 % of an intersection tick),
although only the few lanes near the vehicle can win. Here the lanes that can win are found first, and only they
are evaluated, with the stock ``distance_with_heading``:

- The stock distance ``|r| + max(s − L, 0) + max(−s, 0) + |Δψ|`` of a straight or circular lane is never smaller
  than the Euclidean distance from the point to the lane's centreline (segment or arc): ``|r|`` plus the
  longitudinal overshoot is the length of a path from the point to the centreline (radially, then along the
  line/arc), and ``|Δψ| ≥ 0``. So the distance to the centreline's axis-aligned bounding box is a lower bound.
- The plane is cut into ``CELL`` m cells (built lazily); each cell keeps the lanes sorted by the lower bound over
  the whole cell. A query walks that list, evaluates lanes exactly (``av_gym.sim.lanes``: the stock formula on
  floats, same bits), and stops as soon as the next lower bound
  exceeds the best distance found: every lane that could be closer — or tie — has been evaluated.
- Among the evaluated lanes the stock rule picks the answer (smallest distance, ties → first in graph order, as
  ``np.argmin``). The answer is therefore always the stock one; ``tests/test_fast_sim.py`` checks it along whole
  trajectories. Lanes of other types (sine, poly) get a lower bound of 0, i.e. are always evaluated.
"""

from __future__ import annotations

import math

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, StraightLane
from highway_env.road.road import LaneIndex, RoadNetwork

from av_gym.sim import lanes as fast_lanes

CELL = 4.0  # m, grid cell size
MARGIN = 1e-6  # m, lower bounds are lowered by this, so float rounding can never prune a lane that could win


def centreline_box(lane: AbstractLane) -> tuple[float, float, float, float] | None:
    """(xmin, ymin, xmax, ymax) of a lane's centreline, or None when no bound is known (lane always evaluated)."""
    if type(lane) is StraightLane:
        (x0, y0), (x1, y1) = lane.start, lane.end
        return min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)
    if type(lane) is CircularLane:
        a0 = lane.start_phase
        a1 = lane.start_phase + lane.direction * lane.length / lane.radius  # = end_phase
        lo, hi = min(a0, a1), max(a0, a1)
        angles = [lo, hi] + [k * math.pi / 2 for k in range(math.ceil(lo / (math.pi / 2)),
                                                             math.floor(hi / (math.pi / 2)) + 1)]
        cx, cy = float(lane.center[0]), float(lane.center[1])
        xs = [cx + lane.radius * math.cos(a) for a in angles]
        ys = [cy + lane.radius * math.sin(a) for a in angles]
        return min(xs), min(ys), max(xs), max(ys)
    return None


class FastRoadNetwork(RoadNetwork):
    """Same graph, same answers. Build with :meth:`from_network` (shares the graph). Lanes added through
    :meth:`add_lane` invalidate the index; mutate ``graph`` directly only before the first query."""

    @classmethod
    def from_network(cls, network: RoadNetwork) -> "FastRoadNetwork":
        fast = cls()
        fast.graph = network.graph
        return fast

    def add_lane(self, _from: str, _to: str, lane: AbstractLane) -> None:
        super().add_lane(_from, _to, lane)
        self.__dict__.pop("_index", None)

    def _build_index(self) -> dict:
        indexes, lanes = [], []
        for _from, to in self.graph.items():
            for _to, ls in to.items():
                for _id, lane in enumerate(ls):
                    indexes.append((_from, _to, _id))
                    lanes.append(lane)
        index = {"indexes": indexes, "lanes": lanes, "boxes": [centreline_box(lane) for lane in lanes],
                 "cells": {}}
        self._index = index
        return index

    def _cell(self, index: dict, ix: int, iy: int) -> list[tuple[float, int]]:
        x0, y0 = ix * CELL, iy * CELL
        x1, y1 = x0 + CELL, y0 + CELL
        bounds = []
        for k, box in enumerate(index["boxes"]):
            if box is None:
                lb = -math.inf
            else:
                dx = max(0.0, box[0] - x1, x0 - box[2])
                dy = max(0.0, box[1] - y1, y0 - box[3])
                lb = math.sqrt(dx * dx + dy * dy)
                lane = index["lanes"][k]
                if type(lane) is CircularLane:  # an arc lies on its circle: distance to the circle's ring
                    cx, cy, radius = float(lane.center[0]), float(lane.center[1]), lane.radius
                    nx, ny = min(max(cx, x0), x1) - cx, min(max(cy, y0), y1) - cy  # nearest cell point
                    fx, fy = max(abs(x0 - cx), abs(x1 - cx)), max(abs(y0 - cy), abs(y1 - cy))  # farthest
                    near, far = math.sqrt(nx * nx + ny * ny), math.sqrt(fx * fx + fy * fy)
                    lb = max(lb, near - radius, radius - far)
                lb -= MARGIN
            bounds.append((lb, k))
        bounds.sort()
        index["cells"][(ix, iy)] = bounds
        return bounds

    def get_closest_lane_index(self, position: np.ndarray, heading: float | None = None) -> LaneIndex:
        index = self.__dict__.get("_index") or self._build_index()
        x, y = position.tolist() if type(position) is np.ndarray else (float(position[0]), float(position[1]))
        try:
            key = (math.floor(x / CELL), math.floor(y / CELL))
        except (ValueError, OverflowError):  # NaN or infinite position
            return super().get_closest_lane_index(position, heading)
        cell = index["cells"].get(key) or self._cell(index, *key)
        lanes = index["lanes"]
        best, best_k = math.inf, -1
        distance = fast_lanes.distance_with_heading
        for lb, k in cell:
            if lb > best:
                break
            d = distance(lanes[k], x, y, heading)
            if d < best or (d == best and k < best_k):
                best, best_k = d, k
        if best_k < 0:  # only NaN distances: let the stock code decide
            return super().get_closest_lane_index(position, heading)
        return index["indexes"][best_k]
