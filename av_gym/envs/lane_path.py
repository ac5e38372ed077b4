"""A chain of highway-env lanes driven in order (a lap or a route), with arc-length bookkeeping."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane


@dataclass
class LanePath:
    """Lanes in driving order, where each starts along the path (m), and whether the path is a closed loop."""

    lanes: list[AbstractLane]
    closed: bool = False

    def __post_init__(self) -> None:
        lengths = np.array([lane.length for lane in self.lanes], dtype=float)
        self.starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        self.length = float(lengths.sum())

    def curvature(self, s: np.ndarray) -> np.ndarray:
        """Signed centreline curvature (1/m, + = right turn) at path positions ``s`` (m; wrapped on a loop)."""
        s = np.asarray(s, dtype=float)
        s = np.mod(s, self.length) if self.closed else np.clip(s, 0.0, self.length)
        k = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.lanes) - 1)
        out = np.zeros_like(s)
        for i, lane in enumerate(self.lanes):
            if isinstance(lane, CircularLane):
                out[k == i] = lane.direction / lane.radius
        return out

    def locate(self, position: np.ndarray, hint: int) -> tuple[int, float, float]:
        """Lane index, longitudinal s on that lane (m) and signed lateral offset (m, + = right of centre).

        Walks forward or backward from ``hint`` (the lane the car was on) rather than searching every lane, so a
        car cutting across an infield never snaps to a lane it is not driving on (highway-env's closest-lane
        search would)."""
        n = len(self.lanes)
        k = hint
        s, lat = self.lanes[k].local_coordinates(position)
        step = 1 if s > self.lanes[k].length else -1 if s < 0 else 0
        for _ in range(n if step else 0):
            nxt = k + step
            if not self.closed and not 0 <= nxt < n:
                break
            k = nxt % n
            s, lat = self.lanes[k].local_coordinates(position)
            if (step > 0 and s <= self.lanes[k].length) or (step < 0 and s >= 0):
                break
        return k, float(s), float(lat)

    def path_s(self, k: int, s: float) -> float:
        """Arc length along the whole path (m) of longitudinal ``s`` on lane ``k``."""
        return float(self.starts[k] + s)
