"""Privileged ("truth") observation types. Both scenarios observe a ``Dict`` with one key per source; the base env
gives only ``"state"`` (privileged kinematics). Sensor wrappers add their own keys beside it and a preset decides
whether ``"state"`` stays (``sensors=truth``) or is removed."""

from __future__ import annotations

import bisect

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.observation import ObservationType
from highway_env.road.lane import CircularLane


class StateDict(ObservationType):
    """Wraps any highway-env observation type as ``{"state": inner}``."""

    def __init__(self, env, inner: ObservationType) -> None:
        super().__init__(env)
        self.inner = inner

    def space(self) -> spaces.Dict:
        return spaces.Dict({"state": self.inner.space()})

    def observe(self) -> dict:
        return {"state": self.inner.observe()}


class LaneKeepingState(ObservationType):
    """Lane-relative state of the ego on the lap, float32 vector:

    ``[cte (m, + right), heading_error (rad), speed (m/s), yaw_rate (rad/s), steering (rad),
    curvature at 0/5/10/20/30 m ahead (1/m, + right turn)]`` — clipped to the declared bounds."""

    FEATURES = ("cte", "heading_error", "speed", "yaw_rate", "steering",
                "curvature_0", "curvature_5", "curvature_10", "curvature_20", "curvature_30")
    PREVIEW = np.array([0.0, 5.0, 10.0, 20.0, 30.0])
    HIGH = np.array([10.0, np.pi, 50.0, 5.0, 1.0, 0.2, 0.2, 0.2, 0.2, 0.2], dtype=np.float32)

    def space(self) -> spaces.Box:
        return spaces.Box(-self.HIGH, self.HIGH, dtype=np.float32)

    def observe(self) -> np.ndarray:
        t = self.env.lane_state()
        if self.env.config.get("fast"):
            curv = fast_curvature(self.env.track, t["lap_s"] + self.PREVIEW)
        else:
            curv = self.env.track.curvature(t["lap_s"] + self.PREVIEW)
        v = np.array([t["cte"], t["heading_error"], t["speed"], t["yaw_rate"], t["steering"], *curv])
        if self.env.config.get("fast"):  # np.clip's Python wrapper costs more than the two ufuncs (same result)
            return np.minimum(np.maximum(v, self._low64), self._high64).astype(np.float32)
        return np.clip(v, -self.HIGH, self.HIGH).astype(np.float32)

    _low64, _high64 = -HIGH.astype(float), HIGH.astype(float)


def fast_curvature(path, s: np.ndarray) -> np.ndarray:
    """``LanePath.curvature`` by table look-up (the stock method loops over every lane with a boolean mask per
    lane); same values: the table holds the same ``direction / radius`` floats."""
    cached = path.__dict__.get("_curvature_table")
    if cached is None:
        table = [lane.direction / lane.radius if isinstance(lane, CircularLane) else 0.0 for lane in path.lanes]
        cached = path._curvature_table = (table, [float(x) for x in path.starts])
    table, starts = cached
    n, length, closed = len(table) - 1, path.length, path.closed
    out = []
    for x in s.tolist() if isinstance(s, np.ndarray) else s:  # a handful of points: floats beat numpy calls
        x = float(x)
        x = x % length if closed else min(max(x, 0.0), length)  # float % == np.mod (same fmod-based rule)
        k = bisect.bisect_right(starts, x) - 1  # == np.searchsorted(starts, x, side="right") - 1
        out.append(table[min(max(k, 0), n)])
    return np.array(out)


class FastKinematics(ObservationType):
    """highway-env's ``KinematicObservation`` computed with numpy instead of pandas (same values, same order: ego
    first, then the nearest ``vehicles_count - 1`` vehicles sorted by lane distance, zero rows for padding).

    Why: on the intersection the stock version spends ~13 ms per call building DataFrames, half of a policy step;
    this one takes a fraction of that. ``tests/test_envs.py`` checks it against the stock class every step."""

    SUPPORTED = ("presence", "x", "y", "vx", "vy", "heading", "cos_h", "sin_h")

    def __init__(self, env, features=None, vehicles_count: int = 5, features_range=None, absolute: bool = False,
                 order: str = "sorted", normalize: bool = True, clip: bool = True, see_behind: bool = False,
                 observe_intentions: bool = False, include_obstacles: bool = True, **kwargs) -> None:
        super().__init__(env)
        self.features = list(features or ["presence", "x", "y", "vx", "vy"])
        unknown = set(self.features) - set(self.SUPPORTED)
        if unknown:
            raise ValueError(f"FastKinematics supports features {self.SUPPORTED}, not {sorted(unknown)}")
        if order != "sorted" or not features_range:
            raise ValueError("FastKinematics needs order='sorted' and an explicit features_range")
        self.vehicles_count = vehicles_count
        self.features_range = features_range
        self.absolute, self.normalize, self.clip = absolute, normalize, clip
        self.see_behind, self.include_obstacles = see_behind, include_obstacles

    def space(self) -> spaces.Box:
        bound = 1.0 if (self.normalize and self.clip) else np.inf
        return spaces.Box(-bound, bound, shape=(self.vehicles_count, len(self.features)), dtype=np.float32)

    @staticmethod
    def _row(v) -> dict:
        return {"presence": 1.0, "x": v.position[0], "y": v.position[1], "vx": v.velocity[0], "vy": v.velocity[1],
                "heading": v.heading, "cos_h": np.cos(v.heading), "sin_h": np.sin(v.heading)}

    def observe(self) -> np.ndarray:
        obs = np.zeros((self.vehicles_count, len(self.features)))
        if not self.env.road:
            return obs.astype(np.float32)
        ego = self.observer_vehicle
        close = self.env.road.close_objects_to(ego, self.env.PERCEPTION_DISTANCE, count=self.vehicles_count - 1,
                                               see_behind=self.see_behind, sort=True,
                                               vehicles_only=not self.include_obstacles)
        ego_row = self._row(ego)
        rows = [ego_row]
        for v in close[-self.vehicles_count + 1:]:
            row = self._row(v)
            if not self.absolute:
                for key in ("x", "y", "vx", "vy"):
                    row[key] -= ego_row[key]
            rows.append(row)
        values = np.array([[row[f] for f in self.features] for row in rows], dtype=float)
        if self.normalize:
            for j, f in enumerate(self.features):
                if f in self.features_range:
                    lo, hi = self.features_range[f]
                    values[:, j] = -1.0 + 2.0 * (values[:, j] - lo) / (hi - lo)
                    if self.clip:
                        values[:, j] = np.clip(values[:, j], -1, 1)
        obs[: len(rows)] = values
        return obs.astype(np.float32)
