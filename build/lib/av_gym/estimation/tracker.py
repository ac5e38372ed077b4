"""Multi-object Kalman tracker: turns the detector's noisy, gappy object list into tracks (digest 004 §10.3,
the "improved", SORT-like mode).

Per object, a filterpy ``KalmanFilter`` on the constant-velocity (CV) state ``[x, y, vx, vy]`` (world frame, m and
m/s):

- **F** = ``[[I, dt·I], [0, I]]`` with the actual time ``dt`` since the track's last prediction;
- **Q** = white-noise acceleration, ``Q_discrete_white_noise(dim=2, dt, var=sigma_acc², block_size=2,
  order_by_dim=False)`` — i.e. per axis ``σ_a²·[[dt⁴/4, dt³/2], [dt³/2, dt²]]``; ``sigma_acc`` = 2 m/s² (004 §10.3;
  covers IDM braking at −3 m/s² for a few frames and any turn at the intersection);
- **H, R**: the detector measures position (and, ``use_velocity=True``, velocity) with independent noise:
  ``R = diag(σ_p², σ_p², σ_v², σ_v²)`` with ``σ_p = sigma_pos0 + sigma_pos_k·range`` (0.3 m + 0.01·r, the
  detector's own error model, :mod:`av_gym.sensors.detector`) and ``σ_v = sigma_vel`` (0.5 m/s);
- **P0**: ``diag(σ_p², σ_p², σ_v², σ_v²)`` (``init_vel_sigma`` = 10 m/s instead of σ_v without velocity).

Association: Hungarian (``scipy.optimize.linear_sum_assignment``) on the squared Mahalanobis distance of the
position innovation, gated at ``gate`` = 13.8 (χ²₂ at 99.9 %) and ``max_distance`` = 6 m.

Track management: *birth* of a tentative track on every unassigned detection; *confirmation* after ``min_hits``
= 2 consecutive hits (the paper's "detected in two consecutive images"); a tentative track is *deleted* on its
first miss; a confirmed track *coasts* on the CV prediction through misses and is deleted once it has not been
updated for more than ``max_coast`` = 2.0 s (covers bursts of misses at 10 Hz). Only confirmed tracks are
output. Box size is a running mean of the detections; heading follows the velocity above 1 m/s, else the
(smoothed) detected heading.

Detector frames held between detector updates (``age`` > 0 in its rows) are recognised by their frame time
``t − age`` and only predicted, not re-applied.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.optimize import linear_sum_assignment

from av_gym.params import Params, param

TRACK_FIELDS = ("x", "y", "vx", "vy", "heading", "length", "width")
"""Columns of :meth:`MultiObjectTracker.tracks`: the same layout as ``info["truth"]["others"]``."""
_BIG = 1e9


@dataclass
class Track:
    """One tracked object: its filter and bookkeeping (times in s)."""

    id: int
    kf: KalmanFilter
    t: float  # time the filter state refers to
    t_update: float  # time of the last measurement update
    length: float
    width: float
    heading: float
    hits: int = 1  # consecutive hits since birth (for confirmation)
    n_updates: int = 1
    confirmed: bool = False

    @property
    def state(self) -> np.ndarray:
        return self.kf.x.reshape(-1)


@dataclass(frozen=True)
class TrackingModel(Params):
    """The tracker's motion model, gates and track management (digest 004 §10.3): everything but the measurement
    noise, which :class:`TrackerParams` adds (and :class:`~av_gym.estimation.object_tracking.ObjectTrackerParams`
    takes from the detector below it)."""

    sigma_acc: float = param(2.0, "m/s²", gt=0, doc="white-noise acceleration of the CV model (Q); covers IDM "
                                                   "braking at -3 m/s² for a few frames and any turn (004 §10.3)")
    use_velocity: bool = param(True, doc="the detector's velocity is measured too (H has 4 rows), else only the "
                                         "position")
    init_vel_sigma: float = param(10.0, "m/s", gt=0, doc="initial velocity std of a new track when velocity is not "
                                                        "measured")
    gate: float = param(13.8, gt=0, doc="association gate on the squared Mahalanobis distance of the position "
                                        "innovation (chi²₂ at 99.9 %)")
    max_distance: float = param(6.0, "m", gt=0, doc="association gate on the Euclidean distance")
    min_hits: int = param(2, ge=1, doc="consecutive hits to confirm a track (004: detected in two consecutive "
                                       "images)")
    max_coast: float = param(2.0, "s", ge=0, doc="a confirmed track not updated for longer is deleted (covers "
                                                 "bursts of misses at 10 Hz)")
    size_alpha: float = param(0.2, le=1, ge=0, doc="weight of a new detection in the running mean of the box size")


@dataclass(frozen=True)
class TrackerParams(TrackingModel):
    """:class:`MultiObjectTracker`'s parameters (also the AEB shield's own tracker): the model plus the measurement
    noise R = diag(σ_p², σ_p², σ_v², σ_v²), σ_p = sigma_pos0 + sigma_pos_k·range; defaults = the detector's own
    error model (:class:`~av_gym.sensors.detector.DetectorParams`, digest 004 §10.2)."""

    sigma_pos0: float = param(0.3, "m", gt=0, doc="position noise at zero range (004: 0.3)")
    sigma_pos_k: float = param(0.01, "m/m", ge=0, doc="position noise growth per metre of range (004: 0.01)")
    sigma_vel: float = param(0.5, "m/s", gt=0, doc="velocity noise (the detector's)")


class MultiObjectTracker:
    """CV Kalman tracker with Hungarian association; see the module docstring for the model and
    :class:`TrackerParams` for the parameters."""

    Params = TrackerParams

    def __init__(self, params: TrackerParams | None = None, **overrides) -> None:
        p = self.params = TrackerParams.build(params, **overrides)
        self.sigma_acc, self.sigma_pos0, self.sigma_pos_k = p.sigma_acc, p.sigma_pos0, p.sigma_pos_k
        self.sigma_vel, self.use_velocity, self.init_vel_sigma = p.sigma_vel, bool(p.use_velocity), p.init_vel_sigma
        self.gate, self.max_distance = p.gate, p.max_distance
        self.min_hits, self.max_coast, self.size_alpha = int(p.min_hits), p.max_coast, p.size_alpha
        self.dim_z = 4 if self.use_velocity else 2
        self.H = np.eye(4)[: self.dim_z]
        self.reset()

    def reset(self) -> None:
        self.faults = 0  # non-finite detections dropped and non-finite tracks deleted, this episode
        self._tracks: list[Track] = []
        self._next_id = 0
        self._last_frame = -np.inf
        self._fused_at = -np.inf
        self.time = 0.0

    # ------------------------------------------------------------------------------------------- model
    def _R(self, rng: float) -> np.ndarray:
        sp = self.sigma_pos0 + self.sigma_pos_k * rng
        diag = [sp**2, sp**2] + ([self.sigma_vel**2] * 2 if self.use_velocity else [])
        return np.diag(diag)

    def _predict(self, tr: Track, t: float) -> None:
        dt = t - tr.t
        if dt <= 1e-12:
            return
        F = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float)
        Q = Q_discrete_white_noise(dim=2, dt=dt, var=self.sigma_acc**2, block_size=2, order_by_dim=False)
        tr.kf.predict(F=F, Q=Q)
        tr.t = t

    def _birth(self, z: np.ndarray, det: np.ndarray, t: float, rng: float) -> Track:
        kf = KalmanFilter(dim_x=4, dim_z=self.dim_z)
        kf.H = self.H.copy()
        R = self._R(rng)
        kf.R = R
        v0 = det[3:5] if self.use_velocity else np.zeros(2)
        kf.x = np.array([det[1], det[2], v0[0], v0[1]], dtype=float).reshape(4, 1)
        vs = self.sigma_vel if self.use_velocity else self.init_vel_sigma
        kf.P = np.diag([R[0, 0], R[1, 1], vs**2, vs**2])
        tr = Track(self._next_id, kf, t, t, float(det[6]), float(det[7]), float(det[5]))
        tr.confirmed = self.min_hits <= 1
        self._next_id += 1
        return tr

    # ------------------------------------------------------------------------------------------- step
    def step(self, detections: np.ndarray, t: float, ego_xy: np.ndarray | None = None) -> np.ndarray:
        """Advance to time ``t`` (s) with the detector rows ``detections`` (K, ≥8) ``[present, x, y, vx, vy,
        heading, length, width(, age)]`` (world frame; rows with ``present`` = 0 ignored). ``ego_xy`` gives the
        range for the range-dependent R. Returns :meth:`tracks`."""
        t = float(t)
        det = np.asarray(detections, dtype=float)
        det = det[det[:, 0] > 0] if det.size else np.zeros((0, 9))
        finite = np.all(np.isfinite(det), axis=1)
        if not finite.all():  # a detection with NaN/inf would poison its track's filter for good: dropped
            self.faults += int((~finite).sum())
            det = det[finite]
        age = float(det[0, 8]) if det.shape[1] > 8 and len(det) else 0.0
        frame_t = t - age
        for tr in self._tracks:
            self._predict(tr, t)
        self.time = t
        if frame_t <= self._last_frame + 1e-9:  # the same detector frame again: nothing new to fuse
            return self.tracks()
        self._last_frame = frame_t
        self._fused_at = t
        ego = np.zeros(2) if ego_xy is None else np.asarray(ego_xy, dtype=float)
        ranges = np.linalg.norm(det[:, 1:3] - ego, axis=1) if ego_xy is not None else np.zeros(len(det))
        zs = det[:, [1, 2, 3, 4]][:, : self.dim_z] if len(det) else np.zeros((0, self.dim_z))

        matched_t, matched_d = self._associate(zs, ranges)
        for ti, di in zip(matched_t, matched_d):
            tr = self._tracks[ti]
            tr.kf.update(zs[di], R=self._R(ranges[di]))
            tr.t_update = t
            tr.hits += 1
            tr.n_updates += 1
            if tr.hits >= self.min_hits:
                tr.confirmed = True
            a = self.size_alpha
            tr.length = (1 - a) * tr.length + a * det[di, 6]
            tr.width = (1 - a) * tr.width + a * det[di, 7]
            dh = (det[di, 5] - tr.heading + np.pi) % (2 * np.pi) - np.pi
            tr.heading = tr.heading + 0.5 * dh
        matched = set(matched_t)
        survivors = []
        for i, tr in enumerate(self._tracks):
            if i not in matched and (not tr.confirmed or t - tr.t_update > self.max_coast + 1e-9):
                continue  # tentative: deleted on its first miss; confirmed: coasted too long
            survivors.append(tr)
        for di in sorted(set(range(len(det))) - set(matched_d)):
            survivors.append(self._birth(zs[di], det[di], t, ranges[di]))
        # A filter that went non-finite (a singular update) can never recover: delete it, the object is re-born
        # from its next detection.
        healthy = [tr for tr in survivors if np.all(np.isfinite(tr.kf.x)) and np.all(np.isfinite(tr.kf.P))]
        self.faults += len(survivors) - len(healthy)
        self._tracks = healthy
        return self.tracks()

    def _associate(self, zs: np.ndarray, ranges: np.ndarray) -> tuple[list[int], list[int]]:
        if not self._tracks or not len(zs):
            return [], []
        cost = np.full((len(self._tracks), len(zs)), _BIG)
        for i, tr in enumerate(self._tracks):
            x, P = tr.state, tr.kf.P
            for j, z in enumerate(zs):
                y = z[:2] - x[:2]
                if np.hypot(*y) > self.max_distance:
                    continue
                sp = self.sigma_pos0 + self.sigma_pos_k * ranges[j]
                S = P[:2, :2] + np.eye(2) * sp**2
                try:
                    d2 = float(y @ np.linalg.solve(S, y))
                except np.linalg.LinAlgError:
                    continue
                if d2 <= self.gate:
                    cost[i, j] = d2
        rows, cols = linear_sum_assignment(cost)
        keep = cost[rows, cols] < _BIG
        return list(rows[keep]), list(cols[keep])

    # ------------------------------------------------------------------------------------------- output
    def tracks(self, include_tentative: bool = False) -> np.ndarray:
        """Confirmed tracks (coasting ones included) at the current time, (N, 7) in :data:`TRACK_FIELDS` order."""
        rows = []
        for tr in self._tracks:
            if not (tr.confirmed or include_tentative):
                continue
            x = tr.state
            speed = np.hypot(x[2], x[3])
            heading = np.arctan2(x[3], x[2]) if speed > 1.0 else tr.heading
            rows.append([x[0], x[1], x[2], x[3], heading, tr.length, tr.width])
        return np.array(rows, dtype=float).reshape(-1, len(TRACK_FIELDS))

    def track_ids(self, include_tentative: bool = False) -> np.ndarray:
        """Ids of the rows of :meth:`tracks`, in the same order."""
        return np.array([tr.id for tr in self._tracks if tr.confirmed or include_tentative], dtype=int)

    def coasting(self) -> np.ndarray:
        """Per confirmed track: True when it was not updated by the latest detector frame."""
        return np.array([tr.t_update < self._fused_at - 1e-9 for tr in self._tracks if tr.confirmed], dtype=bool)
