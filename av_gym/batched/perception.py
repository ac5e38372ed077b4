"""The perceived left-turn stack (``sensors=turn_perceived``) for every env of a :class:`BatchedLeftTurn` at once:
the object detector (:class:`BatchedDetector`), the multi-object Kalman tracker (:class:`BatchedTracker`) and the
turn features and intent on its tracks (:class:`BatchedPerception`).

The per-env stack stays the reference (:mod:`av_gym.sensors.detector`, :mod:`av_gym.estimation.tracker` on
filterpy, :mod:`av_gym.estimation.object_tracking`, :mod:`av_gym.estimation.turn_features`); this module gives its
readings on the batch:

- **detector**: env i draws from ``episode_rng(episode_seed_i, "detector")``, the per-env detector's generator,
  the same draws in the same order (per vehicle in view, in road order: its miss chain's draw, then seven normals
  when detected; then the clutter count and each clutter's three draws), so its detections are the per-env ones
  bit for bit. Each env's frame is drawn in one compiled call on its own generator
  (:func:`av_gym.sensors.kernels.frame_draws_span`; one generator each: they cannot be drawn for the batch at once
  and stay the same numbers), once :func:`av_gym.sensors.draws_check.compiled_draws` has found its draws numpy's,
  else with the per-env code (:func:`av_gym.sensors.detector.frame_draws`); the field of view and occlusion are
  the per-env detector's own code (:meth:`Detector._view`, its numba kernel).
- **tracker**: the constant-velocity Kalman filter of :class:`~av_gym.estimation.tracker.MultiObjectTracker` over
  arrays of every track of every env (predict and update as stacked matrix products, filterpy's formulas in
  filterpy's order: Joseph-form covariance update), the same gates (Euclidean ``max_distance``, squared Mahalanobis
  ``gate`` on the position innovation), Hungarian association per env with
  ``scipy.optimize.linear_sum_assignment`` on the same cost matrix, the same confirmation, coasting, deletion and
  track order. Stacked products may differ from filterpy's ``dot`` in the last bits (tests/test_batched_perception.py
  states the tolerance), so a gate or an assignment at a tie can, rarely, go the other way.
- **features**: :func:`~av_gym.estimation.turn_features.turn_features` and
  :class:`~av_gym.estimation.turn_features.IntentHistory` (the per-env wrappers' own functions) on the confirmed
  tracks, as ``obs["tracks"]`` gives them (float32, nearest first).
"""

from __future__ import annotations

import numpy as np
from filterpy.common import Q_discrete_white_noise
from scipy.optimize import linear_sum_assignment

from av_gym.envs.left_turn import CONFLICT_POINT
from av_gym.errors import ConfigError
from av_gym.estimation.object_tracking import BOUND as TRACK_BOUND
from av_gym.estimation.object_tracking import FIELDS as TRACK_FIELDS
from av_gym.estimation.object_tracking import ObjectTrackerParams
from av_gym.estimation.object_tracking import tracker_params as object_tracker_params
from av_gym.estimation.tracker import _BIG, TrackerParams, TrackingModel
from av_gym.estimation.turn_features import turn_features
from av_gym.sensors.base import episode_rng, guarded_rows
from av_gym.sensors.detector import FIELDS as DETECTOR_FIELDS
from av_gym.sensors.detector import KERNELS as DETECTOR_KERNELS
from av_gym.sensors.detector import (PROBES, Detector, DetectorParams, assemble_frames, contiguous_columns,
                                   frame_draws, miss_chain)
from av_gym.sensors.draws_check import compiled_draws
from av_gym.sensors.kernels import detector_view_rows, frame_draws_span
from av_gym.sim.batched import LENGTH, WIDTH


def perceived(sensors_cfg: dict | None) -> bool:
    """Whether a sensors section asks for the turn features on tracks (``turn_features.source: tracks``)."""
    return ((sensors_cfg or {}).get("turn_features") or {}).get("source", "truth") == "tracks"


def check_perceived(sensors_cfg: dict) -> None:
    """One ConfigError line for a perceived sensors section the batch cannot run as the per-env stack would."""
    s = dict(sensors_cfg)
    for key in ("detector", "tracker"):
        if key not in s:
            raise ConfigError(f"sensors.turn_features.source=tracks needs sensors.{key} (the per-env stack's "
                              f"detector -> tracker -> features; sensors=turn_perceived has them)")
    params = DetectorParams.from_mapping(s.get("detector") or {}, "sensors.detector")
    if params.frame != "world":
        raise ConfigError(f"sensors.tracker needs sensors.detector.frame=world, got {params.frame!r}")
    tracker_params(s.get("tracker") or {}, params)


def tracker_params(cfg: dict, detector: DetectorParams) -> tuple[TrackerParams, int]:
    """:class:`ObjectTracker`'s tracker parameters for a ``sensors.tracker`` section over ``detector`` and its
    ``max_tracks``."""
    p = ObjectTrackerParams.from_mapping(cfg, "sensors.tracker")
    return object_tracker_params(p, detector), int(p.max_tracks)


class BatchedDetector:
    """:class:`~av_gym.sensors.detector.Detector` (``frame: world``) for B envs: ``obs["detector"]`` (n,
    max_objects, 9) float32 per call of :meth:`measure`, each env's frames drawn from its own generator."""

    # the per-env detector's field of view, occlusion, observation space and invalid-row code (a row that held
    # NaN/inf dropped, as its guard drops it), run on this object's attributes
    _view, _occluded, invalidate = Detector._view, Detector._occluded, Detector.invalidate
    sensor_space = Detector.sensor_space

    def __init__(self, n_envs: int, params: DetectorParams, stream: str = "detector") -> None:
        p = self.params = params
        self.stream = stream  # the per-env sensor's key of its generator (the AEB shield's: "aeb_detector")
        if p.frame != "world":
            raise ConfigError(f"sensors.tracker needs sensors.detector.frame=world, got {p.frame!r}")
        # Detector.__init__'s two-state miss chain: leave a run with q, enter it with p so that P(miss) = miss_rate
        self.p, self.q = miss_chain(p.miss_rate, p.burst_length)
        self.rate_hz, self.max_range, self.half_fov = p.rate_hz, p.max_range, np.radians(p.fov_deg) / 2
        self.miss_rate, self.occlusion, self.occlusion_fraction = p.miss_rate, bool(p.occlusion), p.occlusion_fraction
        self.max_objects = int(p.max_objects)
        space = self.sensor_space()
        self.low, self.high = space.low, space.high
        B = int(n_envs)
        self.rngs: list = [None] * B
        self.chains: list[dict] = [{} for _ in range(B)]  # per env: miss-chain state by vehicle id
        # the compiled draws' miss chains (:func:`frame_draws_span`), by vehicle id: missed last frame, and the
        # episode (``token``) each belongs to, so that a new episode starts with none, as its empty dict does
        self.missed, self.owner = np.zeros(1024, np.bool_), np.full(1024, -1, np.int64)
        self.token, self.episodes = np.zeros(B, np.int64), 0
        self.next_frame, self.frame_time = np.zeros(B), np.zeros(B)
        self.rows = np.zeros((B, self.max_objects, len(DETECTOR_FIELDS)), np.float32)

    def reset(self, rows, episode_seeds) -> None:
        """New episodes in the envs ``rows`` (Detector.reset / on_reset): their generators from the episode seeds."""
        for r, seed in zip(np.asarray(rows, dtype=int), episode_seeds):
            self.rngs[r] = episode_rng(int(seed), self.stream)
            self.chains[r] = {}
            self.episodes += 1
            self.token[r] = self.episodes
        self.next_frame[rows], self.frame_time[rows] = 0.0, 0.0
        self.rows[rows] = 0.0

    def measure(self, rows, t: np.ndarray, ego: np.ndarray, others: np.ndarray, vids: np.ndarray,
                off: np.ndarray) -> np.ndarray:
        """Detector.measure for the envs ``rows`` at times ``t`` (s): ``ego`` (n, 3) ``[x, y, heading]``,
        ``others`` (k, 7) ``[x, y, vx, vy, heading, length, width]`` every env's road users one env after the other
        (env n's ``off[n]:off[n + 1]``, in road order) with their vehicle ids ``vids`` (k,) (the miss chains' keys)
        (:func:`others_state`). Returns (n, max_objects, 9) float32."""
        rows = np.asarray(rows, dtype=int)
        due = np.flatnonzero(t + 1e-9 >= self.next_frame[rows])
        if len(due):
            self._frames(rows[due], ego[due], others, vids, off, due)
            self.frame_time[rows[due]] = t[due]
            self.next_frame[rows[due]] = t[due] + 1.0 / self.rate_hz
        out = self.rows[rows]
        out[:, :, 8] = np.where(out[:, :, 0] > 0, (t - self.frame_time[rows])[:, None], 0.0)
        return np.clip(out, self.low, self.high)

    def _frames(self, rows: np.ndarray, ego: np.ndarray, others: np.ndarray, vids: np.ndarray, off: np.ndarray,
                at: np.ndarray) -> None:
        """Detector._frame (world frame) of the envs ``rows``, entries ``at`` of :meth:`measure`'s flat road users:
        the per-env detector's view of every frame in one compiled call, each env's draws from its own generator in
        the per-env order (:func:`frame_draws`), every frame's rows at once (:func:`assemble_frames`, what the
        per-env detector runs on its one frame)."""
        counts = np.diff(off)
        due = np.zeros(len(counts), bool)
        due[at] = True
        mine = due[np.repeat(np.arange(len(counts)), counts)]
        sub = others[mine]
        sub_off = np.concatenate([[0], np.cumsum(counts[at])])
        r, in_view, hidden = self._views(ego, sub, sub_off)
        draw = self._draws_compiled if compiled_draws() else self._draws  # "draws" in KERNELS, checked once
        src, frame_of, draws, clutter_frame, clutter = draw(rows, vids[mine], in_view, hidden, sub_off)
        det, _, _ = assemble_frames(self.params, self.max_range, self.max_objects, ego, sub, src, frame_of, r[src],
                                    draws, clutter_frame, clutter)
        det[..., 5] = (det[..., 5] + np.pi) % (2 * np.pi) - np.pi
        self.rows[rows] = 0.0
        self.rows[rows, :, :8] = det

    def _draws(self, rows: np.ndarray, vids: np.ndarray, in_view: np.ndarray, hidden: np.ndarray,
               off: np.ndarray) -> tuple[np.ndarray, ...]:
        """The frames' draws, frame f of env ``rows[f]`` over the road users ``off[f]:off[f + 1]`` of the flat
        ``vids``, ``in_view``, ``hidden``: :func:`frame_draws` per frame from its env's generator and miss chains
        (the reference of :meth:`_draws_compiled`). Returns the detections' flat rows (m,) and frames (m,), their
        draws (m, 7), the clutter's frames (c,) and uniforms (c, 3)."""
        keys = vids.astype(int).tolist()
        src, frame_of, draws, clutter_frame, clutter = [], [], [], [], []
        for f, row in enumerate(rows.tolist()):
            a, b = off[f], off[f + 1]
            ids, d, c = frame_draws(self, self.rngs[row], self.chains[row], keys[a:b], in_view[a:b], hidden[a:b])
            src += [a + i for i in ids]
            frame_of += [f] * len(ids)
            draws += d
            clutter_frame += [f] * len(c)
            clutter += c
        return (np.array(src, dtype=int), np.array(frame_of, dtype=int), np.array(draws).reshape(-1, 7),
                np.array(clutter_frame, dtype=int), np.array(clutter).reshape(-1, 3))

    def _draws_compiled(self, rows: np.ndarray, vids: np.ndarray, in_view: np.ndarray, hidden: np.ndarray,
                        off: np.ndarray) -> tuple[np.ndarray, ...]:
        """:meth:`_draws` with one compiled call per frame (:func:`frame_draws_span`: the same draws from each env's
        generator in the same order, its miss chains in arrays by vehicle id): a frame's ~20 numpy calls and
        Python loop over its road users were ~8 % of the shielded batch's time. The same arrays."""
        keys = np.ascontiguousarray(vids, dtype=np.int64)
        if len(keys) and keys.max() >= len(self.missed):  # vehicle ids grow with the process: room for them
            grown = max(2 * len(self.missed), int(keys.max()) + 1)
            self.missed = np.concatenate([self.missed, np.zeros(grown - len(self.missed), np.bool_)])
            self.owner = np.concatenate([self.owner, np.full(grown - len(self.owner), -1, np.int64)])
        N, hf, rate = len(keys), float(self.half_fov), float(self.params.clutter_rate)
        src, frame_of, draws = np.empty(N, np.int64), np.empty(N, np.int64), np.empty((N, 7))
        room = self._clutter_room(len(rows))
        clutter, clutter_frame = np.empty((room, 3)), np.empty(room, np.int64)
        n = n_c = 0
        miss_rate, p, q = float(self.miss_rate), float(self.p), float(self.q)
        for f, (row, a, b) in enumerate(zip(rows.tolist(), off[:-1].tolist(), off[1:].tolist())):
            rng = self.rngs[row]
            n, n_c, over = frame_draws_span(rng, self.missed, self.owner, int(self.token[row]), keys, in_view, hidden,
                                            a, b, miss_rate, p, q, rate, hf, f, src, frame_of, draws, n, clutter,
                                            clutter_frame, n_c)
            if over >= 0:  # more false positives than the buffer holds: drawn here, in frame_draws' order
                room = max(2 * len(clutter), n_c + over)
                clutter = np.concatenate([clutter[:n_c], np.empty((room - n_c, 3))])
                clutter_frame = np.concatenate([clutter_frame[:n_c], np.empty(room - n_c, np.int64)])
                for j in range(n_c, n_c + over):
                    clutter[j] = (rng.random(), rng.uniform(-hf, hf), rng.uniform(-np.pi, np.pi))
                    clutter_frame[j] = f
                n_c += over
        return src[:n], frame_of[:n], draws[:n], clutter_frame[:n_c], clutter[:n_c]

    def _clutter_room(self, frames: int) -> int:
        """Rows for the false positives of ``frames`` frames: twice their mean and some (more are drawn in Python)."""
        return int(2 * self.params.clutter_rate * frames) + 16

    def _views(self, ego: np.ndarray, others: np.ndarray, off: np.ndarray) -> tuple[np.ndarray, ...]:
        """Detector._view of each frame (ego ``ego[f]``, road users ``others[off[f]:off[f + 1]]``) at once: flat
        ranges (m), in view, occluded; the compiled view of every frame in one call where the per-env detector
        compiles it (``KERNELS``)."""
        if "occlusion" in DETECTOR_KERNELS:
            c, s = np.cos(others[:, 4]), np.sin(others[:, 4])
            # contiguous columns: the per-env detector's layout, one specialization of the kernels (detector.py)
            ex, ey, epsi = contiguous_columns(ego, (0, 1, 2))
            x, y, length, width = contiguous_columns(others, (0, 1, 5, 6))
            return detector_view_rows(ex, ey, epsi, off, x, y, c, s, length, width, float(self.max_range),
                                      float(self.half_fov), bool(self.occlusion), PROBES,
                                      float(self.occlusion_fraction))
        views = [self._view(np.array([x, y]), float(psi), others[a:b]) for (x, y, psi), a, b in
                 zip(ego.tolist(), off[:-1].tolist(), off[1:].tolist())]
        return tuple(np.concatenate([v[i] for v in views]) if views else np.zeros(0) for i in range(3))


class BatchedTracker:
    """:class:`~av_gym.estimation.tracker.MultiObjectTracker` for B envs: every env's tracks in arrays (B, K, ...),
    each env's tracks in the per-env tracker's list order (survivors in order, then births in detection order)."""

    def __init__(self, n_envs: int, params: TrackerParams, capacity: int = 16) -> None:
        p = self.params = params
        self.dim_z = 4 if p.use_velocity else 2
        self.H = np.eye(4)[: self.dim_z]
        B, K = int(n_envs), int(capacity)
        self.n = np.zeros(B, dtype=int)  # tracks per env, in slots [0, n)
        self.x, self.P = np.zeros((B, K, 4, 1)), np.zeros((B, K, 4, 4))
        self.t, self.t_update = np.zeros((B, K)), np.zeros((B, K))
        self.length, self.width, self.heading = np.zeros((B, K)), np.zeros((B, K)), np.zeros((B, K))
        self.hits, self.confirmed, self.id = np.zeros((B, K), int), np.zeros((B, K), bool), np.zeros((B, K), int)
        self.next_id = np.zeros(B, dtype=int)
        self.last_frame, self.fused_at = np.full(B, -np.inf), np.full(B, -np.inf)
        self.faults = np.zeros(B, dtype=int)
        self._q_cache: dict[float, np.ndarray] = {}

    _PER_TRACK = ("x", "P", "t", "t_update", "length", "width", "heading", "hits", "confirmed", "id")

    def reset(self, rows) -> None:
        """MultiObjectTracker.reset for the envs ``rows``."""
        self.n[rows], self.next_id[rows], self.faults[rows] = 0, 0, 0
        self.last_frame[rows], self.fused_at[rows] = -np.inf, -np.inf

    def _R(self, ranges: np.ndarray) -> np.ndarray:
        """MultiObjectTracker._R for each of ``ranges`` (m): (m, dim_z, dim_z)."""
        p = self.params
        sp = p.sigma_pos0 + p.sigma_pos_k * ranges
        R = np.zeros((len(ranges), self.dim_z, self.dim_z))
        R[:, 0, 0] = R[:, 1, 1] = sp**2
        if p.use_velocity:
            R[:, 2, 2] = R[:, 3, 3] = p.sigma_vel**2
        return R

    def _Q(self, dt: float) -> np.ndarray:
        if dt not in self._q_cache:  # the per-env tracker's own Q (filterpy's), once per time step length
            self._q_cache[dt] = Q_discrete_white_noise(dim=2, dt=dt, var=self.params.sigma_acc**2, block_size=2,
                                                       order_by_dim=False)
        return self._q_cache[dt]

    def _predict(self, rows: np.ndarray, t: np.ndarray) -> None:
        """Every track of the envs ``rows`` to their times ``t`` (s): filterpy's predict, x = F x, P = F P Fᵀ + Q."""
        live = np.arange(self.x.shape[1])[None] < self.n[rows][:, None]
        dt = t[:, None] - self.t[rows]
        b, k = np.nonzero(live & (dt > 1e-12))
        if not len(b):
            return
        r, d = rows[b], dt[b, k]
        F = np.tile(np.eye(4), (len(b), 1, 1))
        F[:, 0, 2] = F[:, 1, 3] = d
        steps, which = np.unique(d, return_inverse=True)  # one Q per time step length (all tracks: one or two)
        Q = np.stack([self._Q(float(v)) for v in steps])[which.reshape(-1)]
        self.x[r, k] = F @ self.x[r, k]
        self.P[r, k] = 1.0 * ((F @ self.P[r, k]) @ F.transpose(0, 2, 1)) + Q
        self.t[r, k] = t[b]

    def _cost(self, rows: np.ndarray, zs: np.ndarray, nz: np.ndarray, ranges: np.ndarray) -> np.ndarray:
        """MultiObjectTracker._associate's cost matrices (n, K, D): the squared Mahalanobis distance of the
        position innovation where both gates pass, ``_BIG`` elsewhere (and past each env's tracks/detections)."""
        p = self.params
        K, D = self.x.shape[1], zs.shape[1]
        cost = np.full((len(rows), K, D), _BIG)
        pair = (np.arange(K)[None, :, None] < self.n[rows][:, None, None]) & (np.arange(D)[None, None] <
                                                                               nz[:, None, None])
        y = zs[:, None, :, :2] - self.x[rows][:, :, None, :2, 0]  # (n, K, D, 2)
        pair &= ~(np.hypot(y[..., 0], y[..., 1]) > p.max_distance)
        b, i, j = np.nonzero(pair)
        if not len(b):
            return cost
        sp = p.sigma_pos0 + p.sigma_pos_k * ranges[b, j]
        S = self.P[rows[b], i, :2, :2] + np.eye(2) * (sp**2)[:, None, None]
        yy = y[b, i, j]
        try:
            sol = np.linalg.solve(S, yy[..., None])[..., 0]
            ok = np.ones(len(b), bool)
        except np.linalg.LinAlgError:  # one singular S: per pair, as the per-env tracker skips that pair
            sol, ok = np.zeros_like(yy), np.zeros(len(b), bool)
            for m in range(len(b)):
                try:
                    sol[m], ok[m] = np.linalg.solve(S[m], yy[m]), True
                except np.linalg.LinAlgError:
                    pass
        d2 = yy[:, 0] * sol[:, 0] + yy[:, 1] * sol[:, 1]
        keep = ok & (d2 <= p.gate)
        cost[b[keep], i[keep], j[keep]] = d2[keep]
        return cost

    def _update(self, r: np.ndarray, k: np.ndarray, z: np.ndarray, det: np.ndarray, ranges: np.ndarray,
                t: np.ndarray) -> None:
        """filterpy's update of the tracks (r, k) with measurements ``z`` (m, dim_z), then the bookkeeping of
        MultiObjectTracker.step (hits, confirmation, running box size and heading)."""
        p, H = self.params, self.H
        R = self._R(ranges)
        x, P = self.x[r, k], self.P[r, k]
        y = z[..., None] - H @ x
        PHT = P @ H.T
        S = H @ PHT + R
        Kg = PHT @ np.linalg.inv(S)
        x = x + Kg @ y
        I_KH = np.eye(4) - Kg @ H
        self.x[r, k] = x
        self.P[r, k] = (I_KH @ P) @ I_KH.transpose(0, 2, 1) + (Kg @ R) @ Kg.transpose(0, 2, 1)
        self.t_update[r, k] = t
        self.hits[r, k] += 1
        self.confirmed[r, k] |= self.hits[r, k] >= p.min_hits
        a = p.size_alpha
        self.length[r, k] = (1 - a) * self.length[r, k] + a * det[:, 6]
        self.width[r, k] = (1 - a) * self.width[r, k] + a * det[:, 7]
        dh = (det[:, 5] - self.heading[r, k] + np.pi) % (2 * np.pi) - np.pi
        self.heading[r, k] = self.heading[r, k] + 0.5 * dh

    def step(self, rows, detections: np.ndarray, t: np.ndarray, ego_xy: np.ndarray) -> None:
        """MultiObjectTracker.step for the envs ``rows``: to times ``t`` (s) with their detector rows
        ``detections`` (n, D, 9) (``obs["detector"]``, world frame), ``ego_xy`` (n, 2) giving the ranges."""
        rows, t = np.asarray(rows, dtype=int), np.asarray(t, dtype=float)
        det = np.asarray(detections, dtype=float)
        keep = (det[..., 0] > 0) & np.all(np.isfinite(det), axis=-1)
        self.faults[rows] += ((det[..., 0] > 0) & ~keep).sum(axis=1)  # a non-finite detection is dropped
        order = np.argsort(~keep, axis=1, kind="stable")  # each env's detections first, in their order
        det = np.take_along_axis(det, order[..., None], axis=1)
        nz = keep.sum(axis=1)
        age = np.where(nz > 0, det[:, 0, 8] if det.shape[1] else 0.0, 0.0)
        self._predict(rows, t)
        new = t - age > self.last_frame[rows] + 1e-9  # else the same detector frame again: nothing to fuse
        if not new.any():
            return
        rows, t, det, nz, ego_xy = rows[new], t[new], det[new], nz[new], np.asarray(ego_xy, dtype=float)[new]
        self.last_frame[rows], self.fused_at[rows] = (t - age[new]), t
        ranges = np.linalg.norm(det[..., 1:3] - ego_xy[:, None], axis=-1)
        zs = det[..., [1, 2, 3, 4]][..., : self.dim_z]
        cost = self._cost(rows, zs, nz, ranges)
        matched = np.zeros(cost.shape[:2], bool)
        used = np.zeros(cost.shape[::2], bool)
        mb, mk, md = self._assign(cost, self.n[rows], nz)
        if len(mb):
            self._update(rows[mb], mk, zs[mb, md], det[mb, md], ranges[mb, md], t[mb])
            matched[mb, mk], used[mb, md] = True, True
        self._manage(rows, t, det, zs, nz, ranges, matched, used)

    def _assign(self, cost: np.ndarray, n_tracks: np.ndarray, nz: np.ndarray) -> tuple[np.ndarray, ...]:
        """MultiObjectTracker._associate's matches in the cost matrices ``cost`` (n, K, D) of envs with
        ``n_tracks`` (n,) tracks and ``nz`` (n,) detections: (env, track, detection), by env then track.
        ``linear_sum_assignment`` per env where gated pairs (cost < ``_BIG``) compete for a track or a detection;
        in an env where none does, exactly its gated pairs, which every optimal assignment holds: they are
        disjoint, so an assignment of min(tracks, detections) pairs without one of them, (k, d) at cost c, pairs
        k or d (or both) at ``_BIG``; taking (k, d) instead (and pairing their two partners, at most ``_BIG``)
        saves at least ``_BIG - c`` > 0. That needs only c < ``_BIG`` for every pair the tracker gates
        (c <= ``gate``), i.e. ``gate`` < ``_BIG``."""
        gated = cost < _BIG
        clash = (gated.sum(axis=2) > 1).any(axis=1) | (gated.sum(axis=1) > 1).any(axis=1)
        if self.params.gate >= _BIG:  # a gated pair could cost _BIG: the argument above does not hold
            clash[:] = True
        mb, mk, md = np.nonzero(gated & ~clash[:, None, None])
        parts = [(mb, mk, md)]
        for b in np.flatnonzero(clash & (n_tracks > 0) & (nz > 0)).tolist():
            c = cost[b, : n_tracks[b], : nz[b]]
            i, j = linear_sum_assignment(c)
            ok = c[i, j] < _BIG
            parts.append((np.full(int(ok.sum()), b), i[ok], j[ok]))
        mb, mk, md = (np.concatenate(x).astype(int) for x in zip(*parts))
        order = np.argsort(mb, kind="stable")
        return mb[order], mk[order], md[order]

    def _manage(self, rows: np.ndarray, t: np.ndarray, det: np.ndarray, zs: np.ndarray, nz: np.ndarray,
                ranges: np.ndarray, matched: np.ndarray, used: np.ndarray) -> None:
        """Deletion (tentative on their first miss, confirmed after ``max_coast``), births from the unused
        detections, non-finite filters dropped; each env's tracks compacted in the per-env tracker's order."""
        p = self.params
        K = self.x.shape[1]
        live = np.arange(K)[None] < self.n[rows][:, None]
        stale = t[:, None] - self.t_update[rows] > p.max_coast + 1e-9
        survive = live & (matched | (self.confirmed[rows] & ~stale))
        born = (np.arange(det.shape[1])[None] < nz[:, None]) & ~used
        need = int((survive.sum(axis=1) + born.sum(axis=1)).max(initial=0))
        if need > K:
            self._grow(need)
            survive = np.concatenate([survive, np.zeros((len(rows), need - K), bool)], axis=1)
            K = need
        key = np.where(survive, np.arange(K)[None], np.inf)  # survivors in order, then births in detection order
        order = np.argsort(key, axis=1, kind="stable")
        n_keep = survive.sum(axis=1)
        moved = np.flatnonzero((order != np.arange(K)[None]).any(axis=1))  # the others keep their slots
        for name in self._PER_TRACK:
            a = getattr(self, name)
            sub = a[rows[moved]]
            idx = order[moved].reshape((len(moved), K) + (1,) * (sub.ndim - 2))
            a[rows[moved]] = np.take_along_axis(sub, idx, axis=1)
        self.n[rows] = n_keep
        b, j = np.nonzero(born)
        if len(b):
            self._birth(rows, b, j, t, det, zs, ranges)
        self._drop_nonfinite(rows)

    def _birth(self, rows, b, j, t, det, zs, ranges) -> None:
        """MultiObjectTracker._birth for the detections (b, j), appended to their envs' tracks in order."""
        p = self.params
        r = rows[b]
        first = np.r_[True, b[1:] != b[:-1]]
        start = np.flatnonzero(first)
        rank = np.arange(len(b)) - np.repeat(start, np.diff(np.r_[start, len(b)]))
        k = self.n[r] + rank
        R = self._R(ranges[b, j])
        d = det[b, j]
        v0 = d[:, 3:5] if p.use_velocity else np.zeros((len(b), 2))
        self.x[r, k] = np.stack([d[:, 1], d[:, 2], v0[:, 0], v0[:, 1]], axis=1)[..., None]
        vs = p.sigma_vel if p.use_velocity else p.init_vel_sigma
        P = np.zeros((len(b), 4, 4))
        P[:, 0, 0], P[:, 1, 1], P[:, 2, 2], P[:, 3, 3] = R[:, 0, 0], R[:, 1, 1], vs**2, vs**2
        self.P[r, k] = P
        self.t[r, k], self.t_update[r, k] = t[b], t[b]
        self.length[r, k], self.width[r, k], self.heading[r, k] = d[:, 6], d[:, 7], d[:, 5]
        self.hits[r, k], self.confirmed[r, k] = 1, p.min_hits <= 1
        self.id[r, k] = self.next_id[r] + rank
        np.add.at(self.next_id, r, 1)
        np.add.at(self.n, r, 1)

    def _drop_nonfinite(self, rows: np.ndarray) -> None:
        """A filter that went non-finite never recovers (MultiObjectTracker.step deletes it): dropped likewise."""
        live = np.arange(self.x.shape[1])[None] < self.n[rows][:, None]
        bad = live & ~(np.isfinite(self.x[rows]).all(axis=(2, 3)) & np.isfinite(self.P[rows]).all(axis=(2, 3)))
        if not bad.any():
            return
        for b in np.flatnonzero(bad.any(axis=1)).tolist():
            r, keep = rows[b], np.flatnonzero(live[b] & ~bad[b])
            for name in self._PER_TRACK:
                a = getattr(self, name)
                a[r, : len(keep)] = a[r, keep]
            self.faults[r] += int(bad[b].sum())
            self.n[r] = len(keep)

    def _grow(self, K: int) -> None:
        for name in self._PER_TRACK:
            a = getattr(self, name)
            grown = np.zeros((a.shape[0], K, *a.shape[2:]), a.dtype)
            grown[:, : a.shape[1]] = a
            setattr(self, name, grown)

    def tracks(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """MultiObjectTracker.tracks for the envs ``rows``: (n, K, 7) ``[x, y, vx, vy, heading, length, width]``
        in track order and which of them are confirmed tracks (n, K)."""
        rows = np.asarray(rows, dtype=int)
        x = self.x[rows, :, :, 0]
        speed = np.hypot(x[..., 2], x[..., 3])
        heading = np.where(speed > 1.0, np.arctan2(x[..., 3], x[..., 2]), self.heading[rows])
        out = np.concatenate([x, heading[..., None], self.length[rows][..., None], self.width[rows][..., None]],
                             axis=-1)
        shown = (np.arange(x.shape[1])[None] < self.n[rows][:, None]) & self.confirmed[rows]
        return out, shown


def tracks_observation(tracks: np.ndarray, shown: np.ndarray, ego_xy: np.ndarray, max_tracks: int) -> np.ndarray:
    """ObjectTracker's ``obs["tracks"]`` (n, max_tracks, 8) float32 from :meth:`BatchedTracker.tracks`: the finite
    confirmed tracks nearest the ego first, ``[present, x, y, vx, vy, heading, length, width]``."""
    n = len(tracks)
    shown = shown & np.isfinite(tracks).all(axis=-1)  # a diverged filter never reaches the agent
    d = np.where(shown, np.hypot(tracks[..., 0] - ego_xy[:, None, 0], tracks[..., 1] - ego_xy[:, None, 1]), np.inf)
    order = np.argsort(d, axis=1, kind="stable")[:, :max_tracks]
    rows = np.zeros((n, max_tracks, len(TRACK_FIELDS)), np.float32)
    m = order.shape[1]
    present = np.take_along_axis(shown, order, axis=1)
    picked = np.take_along_axis(tracks, order[..., None], axis=1)
    rows[:, :m, 0] = present
    rows[:, :m, 1:] = np.where(present[..., None], np.clip(picked, -TRACK_BOUND, TRACK_BOUND), 0.0)
    return rows


def others_state(engine, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The detector's input for the envs ``rows``: every env's road users one env after the other, (k, 7) ``[x, y,
    vx, vy, heading, length, width]`` in road order (m, m/s, rad), their vehicle ids (k,) (the miss chains' keys)
    and each env's offset (n + 1,): env n's are ``off[n]:off[n + 1]``."""
    t, rows = engine.traffic, np.asarray(rows, dtype=int)
    keep = t.alive[rows] & ~t.ego[rows]
    v, h = t.v[rows][keep], t.h[rows][keep]
    o = np.empty((len(v), 7))
    o[:, 0], o[:, 1], o[:, 2], o[:, 3] = t.x[rows][keep], t.y[rows][keep], v * np.cos(h), v * np.sin(h)
    o[:, 4], o[:, 5], o[:, 6] = h, LENGTH, WIDTH
    return o, t.vid[rows][keep], np.concatenate([[0], np.cumsum(keep.sum(axis=1))])


class BatchedPerception:
    """``turn_perceived`` on a :class:`~av_gym.batched.left_turn.BatchedLeftTurn`: detector → tracker → turn
    features (and, for :class:`~av_gym.batched.left_turn.BatchedIntent`, the intent on the tracks)."""

    def __init__(self, engine, sensors_cfg: dict) -> None:
        check_perceived(sensors_cfg)
        s = dict(sensors_cfg)
        self.e = engine
        det_params = DetectorParams.from_mapping(s.get("detector") or {}, "sensors.detector")
        params, self.max_tracks = tracker_params(s.get("tracker") or {}, det_params)
        self.detector = BatchedDetector(engine.B, det_params)
        self.tracker = BatchedTracker(engine.B, params)
        self.last_detections = np.zeros((engine.B, self.detector.max_objects, len(DETECTOR_FIELDS)), np.float32)
        self.last_tracks = np.zeros((engine.B, self.max_tracks, len(TRACK_FIELDS)), np.float32)
        self.described: tuple | None = None
        self.faults = np.zeros(0, dtype=int)  # per row of the last observe: the detector's non-finite entries

    def reset(self, rows) -> None:
        """New episodes in the envs ``rows`` (after the engine started them)."""
        rows = np.asarray(rows, dtype=int)
        self.detector.reset(rows, self.e.episode_seed[rows])
        self.tracker.reset(rows)

    def observe(self, rows) -> np.ndarray:
        """``obs["turn"]`` (n, width) float32 of the envs ``rows`` from their tracks, after one detector reading
        and one tracker step each (the per-env stack's observation); sets the engine's ``last_truth``."""
        e, rows = self.e, np.asarray(rows, dtype=int)
        tr = e.truth(rows)
        e.last_truth = tr
        e.described = None  # the engine's truth objects are not what obs["turn"] describes here: no stale reader
        now = e.ticks[rows] / e.config["simulation_frequency"]  # sim_time: tick resolution
        ego = np.stack([tr["x"], tr["y"], tr["heading"]], axis=1)
        det = self.detector.measure(rows, now, ego, *others_state(e, rows))
        # the per-env Detector's guard (SensorWrapper._guarded), before the tracker reads the rows, as per env
        det, self.faults = guarded_rows(det, self.detector.sensor_space(), self.detector.invalidate)
        self.last_detections[rows] = det
        self.tracker.step(rows, det, now, ego[:, :2])
        tracks = tracks_observation(*self.tracker.tracks(rows), ego[:, :2], self.max_tracks)
        self.last_tracks[rows] = tracks
        objects = tracks[..., 1:5].astype(float)
        valid = (tracks[..., 0] > 0) & np.isfinite(objects).all(axis=-1)
        out, order, present = turn_features(tr, np.where(valid[..., None], objects, 0.0), valid, e.path, e.path_s,
                                            CONFLICT_POINT, e.features)
        self.described = (rows, objects, valid, order, present, now)
        return out

    def intent(self, intent, rows, signals: np.ndarray | None) -> np.ndarray:
        """``obs["intent"]`` of the envs ``rows`` (after :meth:`observe` on them) by ``intent``'s
        :class:`~av_gym.estimation.turn_features.IntentHistory`, on the tracks as TurnIntent takes them: the
        described tracks nearest first, every track as the snapshot."""
        seen, objects, valid, order, present, now = self.described
        if not np.array_equal(seen, np.asarray(rows)):
            raise ValueError("BatchedPerception.intent: call observe() on the same rows first")
        M = self.e.max_objects
        described = np.zeros((len(seen), M), bool)
        described[:, : present.shape[1]] = present
        picked = np.zeros((len(seen), M, 4))
        picked[:, : order.shape[1]] = np.take_along_axis(objects, order[..., None], axis=1)
        picked[~described] = 0.0
        snapshot = np.where(valid[..., None], objects, 0.0)  # (a NaN row would win signal_readings' argmin)
        return intent.past.observe(seen, now, picked, described, snapshot, valid, signals)
