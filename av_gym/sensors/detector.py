"""Object detector: the vehicle list a perception stack would give, with the error profile of paper 004's setting
(a fast detector whose misses a tracker can fill in, digest 004 §10.2).

Per detector frame (at ``rate_hz``, held in between), for each other vehicle within ``max_range`` and the field of
view:

- **misses**: independent (``burst_length`` = None) or bursty: a two-state Markov chain per vehicle with stationary
  miss probability ``miss_rate`` and mean run length ``burst_length`` frames (Gilbert–Elliott, our choice), plus
  **occlusion**: a vehicle whose bearing interval is at least ``occlusion_fraction`` covered by nearer vehicles is
  not detected;
- **position noise** σ(r) = ``sigma_pos0`` + ``sigma_pos_k``·r (digest 004: 0.3 m + 0.01·r), velocity noise
  ``sigma_vel``, box size noise ``sigma_size``, heading noise ``sigma_heading``;
- **false positives**: Poisson(``clutter_rate``) per frame, uniform in range and field of view (004: λ = 0.2).

Observation ``Box(max_objects, 9)``, rows sorted by range, zero rows unused: ``[present, x, y, vx, vy, heading,
length, width, age]`` — positions and velocities in the world frame (m, m/s; set ``frame="ego"`` for x forward,
y right of the ego), heading rad, size m, ``age`` s since this detector frame was taken.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.geometry import box_corners
from av_gym.sensors.base import SensorWrapper, ego_pose, others_state, sim_time

FIELDS = ("present", "x", "y", "vx", "vy", "heading", "length", "width", "age")
FRAMES = ("world", "ego")
BOUND = 1e4


class Detector(SensorWrapper):
    """Adds ``obs["detector"]``. Defaults: ``rate_hz`` 10 (policy rate, half the 20 Hz simulation; 004 found ≥ 15
    fps needed by its tracker on real video — here the scene is simpler), ``max_range`` 60 m, ``fov_deg`` 360
    (surround perception, our choice; 120 models one front camera like 004), ``miss_rate`` 0.1, ``burst_length``
    None (independent), ``occlusion`` True, ``occlusion_fraction`` 0.8, ``sigma_pos0`` 0.3 m, ``sigma_pos_k`` 0.01, ``sigma_vel``
    0.5 m/s, ``sigma_size`` 0.1 m, ``sigma_heading`` 0.05 rad, ``clutter_rate`` 0.2 per frame, ``max_objects`` 16.
    """

    key = "detector"

    def __init__(self, env: gym.Env, rate_hz: float = 10.0, max_range: float = 60.0, fov_deg: float = 360.0,
                 miss_rate: float = 0.1, burst_length: float | None = None, occlusion: bool = True,
                 occlusion_fraction: float = 0.8,
                 sigma_pos0: float = 0.3, sigma_pos_k: float = 0.01, sigma_vel: float = 0.5,
                 sigma_size: float = 0.1, sigma_heading: float = 0.05, clutter_rate: float = 0.2,
                 max_objects: int = 16, frame: str = "world") -> None:
        if not 0.0 <= miss_rate < 1.0:
            raise ValueError(f"sensors.detector.miss_rate must be in [0, 1), got {miss_rate}")
        if not 0.0 < occlusion_fraction <= 1.0:
            raise ValueError(f"sensors.detector.occlusion_fraction must be in (0, 1], got {occlusion_fraction}")
        if frame not in FRAMES:
            raise ValueError(f"sensors.detector.frame must be one of {list(FRAMES)}, got {frame!r}")
        for name, value in (("rate_hz", rate_hz), ("max_range", max_range), ("fov_deg", fov_deg),
                            ("max_objects", max_objects)):
            if not value > 0:
                raise ValueError(f"sensors.detector.{name} must be > 0, got {value}")
        for name, value in (("sigma_pos0", sigma_pos0), ("sigma_pos_k", sigma_pos_k), ("sigma_vel", sigma_vel),
                            ("sigma_size", sigma_size), ("sigma_heading", sigma_heading),
                            ("clutter_rate", clutter_rate)):
            if not value >= 0:
                raise ValueError(f"sensors.detector.{name} must be >= 0, got {value}")
        # Two-state chain (detect ↔ miss): leave a miss run with q = 1/L, enter it with p so that P(miss) = m.
        if burst_length is None:
            self.q = 1.0 - miss_rate  # memoryless: P(miss | missed before) = P(miss) = m
        else:
            if burst_length < 1.0:
                raise ValueError(f"sensors.detector.burst_length must be >= 1 frame or null, got {burst_length}")
            self.q = 1.0 / burst_length
        self.p = self.q * miss_rate / (1.0 - miss_rate) if miss_rate > 0 else 0.0
        if self.p > 1.0:
            raise ValueError(f"sensors.detector: miss_rate {miss_rate} needs burst_length >= "
                             f"{miss_rate / (1 - miss_rate):.2f} frames")
        self.rate_hz, self.max_range, self.half_fov = rate_hz, max_range, np.radians(fov_deg) / 2
        self.miss_rate, self.occlusion, self.occlusion_fraction = miss_rate, bool(occlusion), occlusion_fraction
        self.sigma_pos0, self.sigma_pos_k, self.sigma_vel = sigma_pos0, sigma_pos_k, sigma_vel
        self.sigma_size, self.sigma_heading, self.clutter_rate = sigma_size, sigma_heading, clutter_rate
        self.max_objects, self.frame = int(max_objects), frame
        super().__init__(env)

    def sensor_space(self) -> spaces.Box:
        low = np.tile(np.array([0] + [-BOUND] * 4 + [-np.pi, 0, 0, 0], dtype=np.float32), (self.max_objects, 1))
        high = np.tile(np.array([1] + [BOUND] * 4 + [np.pi, 20, 10, BOUND], dtype=np.float32), (self.max_objects, 1))
        return spaces.Box(low, high, dtype=np.float32)

    def on_reset(self) -> None:
        # Per-vehicle chain state, keyed by the vehicle object (not id(), which a deep copy of the stack would
        # leave pointing at the original's vehicles, and which a new vehicle could reuse).
        self._missing: dict[object, bool] = {}
        self._next_frame = 0.0
        self._frame_time = 0.0
        self._rows = np.zeros((self.max_objects, len(FIELDS)), dtype=np.float32)
        self.truth_ids = np.full(self.max_objects, -1)  # index into others_state() of each row; -1 = clutter/empty

    # ------------------------------------------------------------------------------------------- model
    def _occluded(self, ego_xy: np.ndarray, others: np.ndarray) -> np.ndarray:
        """Per vehicle: is at least ``occlusion_fraction`` of its bearing interval behind nearer vehicles?"""
        n = len(others)
        if n < 2:
            return np.zeros(n, dtype=bool)
        corners = box_corners(others[:, :2], others[:, 4], others[:, 5], others[:, 6]) - ego_xy  # (N, 4, 2)
        bearings = np.arctan2(corners[..., 1], corners[..., 0])
        centre = np.arctan2(others[:, 1] - ego_xy[1], others[:, 0] - ego_xy[0])
        rel = (bearings - centre[:, None] + np.pi) % (2 * np.pi) - np.pi  # unwrap around each vehicle's centre
        lo, hi = centre + rel.min(1), centre + rel.max(1)
        dist = np.linalg.norm(others[:, :2] - ego_xy, axis=1)
        probes = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.05, 0.95, 9)[None]  # (N, 9) bearings
        occluded = np.zeros(n, dtype=bool)
        for i in range(n):
            nearer = dist < dist[i]
            if not nearer.any():
                continue
            d = (probes[i][:, None] - (lo[nearer] + hi[nearer])[None] / 2 + np.pi) % (2 * np.pi) - np.pi
            covered = np.any(np.abs(d) <= (hi[nearer] - lo[nearer])[None] / 2, axis=1)
            occluded[i] = covered.mean() >= self.occlusion_fraction
        return occluded

    def _frame(self) -> None:
        x, y, psi, _ = ego_pose(self.env)
        ego_xy = np.array([x, y])
        others = others_state(self.env)
        rows, ids = [], []
        if len(others):
            rel = others[:, :2] - ego_xy
            r = np.linalg.norm(rel, axis=1)
            bearing = np.arctan2(rel[:, 1], rel[:, 0]) - psi
            in_view = (r <= self.max_range) & (np.abs((bearing + np.pi) % (2 * np.pi) - np.pi) <= self.half_fov)
            occluded = self._occluded(ego_xy, others) if self.occlusion else np.zeros(len(others), dtype=bool)
            vehicles = [v for v in self.env.unwrapped.road.vehicles if v is not self.env.unwrapped.vehicle]
            for i in np.flatnonzero(in_view):
                key = vehicles[i]
                if key not in self._missing:  # first sight: start in the chain's stationary distribution
                    missing = bool(self.rng.random() < self.miss_rate)
                elif self._missing[key]:
                    missing = bool(self.rng.random() >= self.q)
                else:
                    missing = bool(self.rng.random() < self.p)
                self._missing[key] = missing
                if missing or occluded[i]:
                    continue
                sp = self.sigma_pos0 + self.sigma_pos_k * r[i]
                o = others[i]
                rows.append([1.0, o[0] + self.rng.normal(0, sp), o[1] + self.rng.normal(0, sp),
                             o[2] + self.rng.normal(0, self.sigma_vel), o[3] + self.rng.normal(0, self.sigma_vel),
                             o[4] + self.rng.normal(0, self.sigma_heading),
                             o[5] + self.rng.normal(0, self.sigma_size), o[6] + self.rng.normal(0, self.sigma_size)])
                ids.append(int(i))
        for _ in range(self.rng.poisson(self.clutter_rate)):
            rng_r = self.max_range * np.sqrt(self.rng.random())  # uniform over the area
            b = psi + self.rng.uniform(-self.half_fov, self.half_fov)
            rows.append([1.0, x + rng_r * np.cos(b), y + rng_r * np.sin(b), 0.0, 0.0, self.rng.uniform(-np.pi, np.pi),
                         5.0, 2.0])
            ids.append(-1)
        det = np.array(rows, dtype=float).reshape(-1, 8)
        order = np.argsort(np.linalg.norm(det[:, 1:3] - ego_xy, axis=1), kind="stable")[: self.max_objects]
        det, ids = det[order], np.array(ids, dtype=int).reshape(-1)[order]
        if self.frame == "ego":
            c, s = np.cos(psi), np.sin(psi)
            rot = np.array([[c, s], [-s, c]])  # world → ego (x forward, y right in highway-env's y-down frame)
            det[:, 1:3] = (det[:, 1:3] - ego_xy) @ rot.T
            det[:, 3:5] = det[:, 3:5] @ rot.T
            det[:, 5] = det[:, 5] - psi
        det[:, 5] = (det[:, 5] + np.pi) % (2 * np.pi) - np.pi
        self._rows = np.zeros((self.max_objects, len(FIELDS)), dtype=np.float32)
        self._rows[: len(det), :8] = det
        self.truth_ids = np.full(self.max_objects, -1)
        self.truth_ids[: len(ids)] = ids

    def measure(self) -> np.ndarray:
        t = sim_time(self.env)
        if t + 1e-9 >= self._next_frame:
            self._frame()
            self._frame_time = t
            self._next_frame = t + 1.0 / self.rate_hz
        out = self._rows.copy()
        out[:, 8] = np.where(out[:, 0] > 0, t - self._frame_time, 0.0)
        space = self.observation_space[self.key]
        return np.clip(out, space.low, space.high)
