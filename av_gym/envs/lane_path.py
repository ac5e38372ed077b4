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

    def locate_rows(self, x: np.ndarray, y: np.ndarray, hint: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                    np.ndarray]:
        """:meth:`locate` of R points at once: ``x``, ``y`` (R,) m from the hint lanes ``hint`` (R,); each point's
        lane (R,) int, s on it (R,) m and lateral offset (R,) m, the method's walk and floats for each point (one
        compiled call, :func:`av_gym.shields.kernels.locate_rows`; why: the AEB shield on the batch locates every
        row's ego each step, ~10 us a point through ``locate``'s numpy calls on 2-vectors). Paths of lanes other
        than straight and circular, or a numpy whose 2-vector dot the kernel cannot reproduce: :meth:`locate`
        point by point."""
        from av_gym.shields.kernels import DOT_FUSED, locate_rows

        x, y = np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(y, dtype=float)
        hint = np.ascontiguousarray(hint, dtype=np.int64)
        table = self._kernel_table()
        if table is None or DOT_FUSED is None:
            got = [self.locate(np.array([a, b]), k) for a, b, k in zip(x.tolist(), y.tolist(), hint.tolist())]
            k, s, lat = zip(*got) if got else ((), (), ())
            return np.array(k, dtype=np.int64), np.array(s, dtype=float), np.array(lat, dtype=float)
        lanes, lengths = table
        # numpy's own arctan2 of each point from each lane's centre (the stock local_coordinates' call; an
        # AVX-512 numpy's is not the C library's), unread for straight lanes
        phi = np.arctan2(y[:, None] - lanes[None, :, 2], x[:, None] - lanes[None, :, 1])
        out_k, out_s, out_lat = np.empty(len(x), np.int64), np.empty(len(x)), np.empty(len(x))
        locate_rows(lanes, lengths, bool(self.closed), hint, x, y, phi, DOT_FUSED, out_k, out_s, out_lat)
        return out_k, out_s, out_lat

    def _kernel_table(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The lanes' kernel rows (L, 8) and lengths (L,) m for :meth:`locate_rows`, kept; None where a lane is
        neither straight nor circular."""
        if "_table" not in self.__dict__:
            from av_gym.shields.conflicts import _geometry

            rows = [_geometry(lane) for lane in self.lanes]
            self._table = None if any(r is None for r in rows) else (
                np.array(rows, dtype=float), np.array([lane.length for lane in self.lanes], dtype=float))
        return self._table

    def path_s(self, k: int, s: float) -> float:
        """Arc length along the whole path (m) of longitudinal ``s`` on lane ``k``."""
        return float(self.starts[k] + s)
