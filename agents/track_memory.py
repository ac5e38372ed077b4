"""The planner on tracks' own memory of the road users whose track the tracker dropped (``recall``, s).

The tracker (digest 004 §10.3; av_gym/estimation/tracker.py) deletes a tentative track on its first miss and a
confirmed one after ``max_coast`` s without a detection. A car whose track died that way is still there: one missed
frame in plain view (its next detection starts a new tentative track, a road user again a frame later), or hidden
behind another car for more than ``max_coast``. :class:`TrackMemory` keeps such a car for the planner, from what the
car has (the tracker's tracks, tentative too, and the detector's detections of each fused frame; never the simulator's
vehicles): each track that vanished from the tracker between two readings is remembered with its last filter state
and detected heading, predicted on at constant velocity, and is a road user of the futures' start (as a tentative
track is: no indicator readings, routes from the prior) until

- a track (tentative or confirmed) or a detection comes within :data:`MEMORY_GATE` m of its predicted place (the car
  is tracked again, under a new id), or
- a fused detector frame after its death has its predicted place in view (within range, the field of view and not
  behind a track the detector updated in that frame) and no detection there: a look that sees nothing, or
- ``recall`` s have passed since its death.

Where the car is out of view (occluded, out of range) the memory holds it at most ``recall`` s; where it is in view
the next frame settles it. Shapes: per row at most :data:`MEMORY_SLOTS` remembered cars (the oldest forgotten
first)."""

from __future__ import annotations

import numpy as np

from agents.detector_view import in_view

__all__ = ["MEMORY_GATE", "MEMORY_SLOTS", "TrackMemory"]

MEMORY_GATE = 4.0  # m: a track or detection this close to a remembered car's predicted place is that car's
MEMORY_SLOTS = 8  # remembered cars per row
PREV_SLOTS = 32  # tracks per row compared between two readings (the tracker holds far fewer)


class TrackMemory:
    """Remembered road users of the B rows of a batch (:mod:`agents.track_memory`); :meth:`update` at every
    reading, :meth:`users` for the futures' start."""

    def __init__(self, n_rows: int, recall_s: float, max_range: float, half_fov: float, occlusion: bool,
                 rate_hz: float) -> None:
        B = int(n_rows)
        self.recall = float(recall_s)
        self.max_range, self.half_fov, self.occlusion = float(max_range), float(half_fov), bool(occlusion)
        self.rate = float(rate_hz)
        # remembered cars: state [x, y, vx, vy, heading, length, width] at time t0 (s), detected heading (rad),
        # time of their last detection (s), of their track's death (s), track id
        self.alive = np.zeros((B, MEMORY_SLOTS), bool)
        self.state = np.zeros((B, MEMORY_SLOTS, 7))
        self.t0 = np.zeros((B, MEMORY_SLOTS))
        self.heading = np.zeros((B, MEMORY_SLOTS))
        self.t_update = np.zeros((B, MEMORY_SLOTS))
        self.died = np.zeros((B, MEMORY_SLOTS))
        self.id = np.full((B, MEMORY_SLOTS), -1)
        # the tracker's tracks at the last reading: ids, states, detected heading, last detection time
        self.prev_id = np.full((B, PREV_SLOTS), -1)
        self.prev_state = np.zeros((B, PREV_SLOTS, 7))
        self.prev_heading = np.zeros((B, PREV_SLOTS))
        self.prev_update = np.zeros((B, PREV_SLOTS))
        self.prev_t = np.zeros(B)

    def reset(self, rows) -> None:
        """New episodes in ``rows``: nothing remembered."""
        rows = np.asarray(rows, dtype=int)
        self.alive[rows] = False
        self.prev_id[rows] = -1

    def update(self, perception, rows: np.ndarray, ego: np.ndarray, now: np.ndarray) -> None:
        """The readings of ``rows`` at times ``now`` (s, (n,)), the ego poses ``ego`` (n, 3) ``[x, y, heading]``:
        tracks that vanished since the last reading remembered; remembered cars dropped by the rules above."""
        rows = np.asarray(rows, dtype=int)
        if not len(rows):
            return
        tr = perception.tracker
        tracks, _ = tr.tracks(rows)
        K = min(tracks.shape[1], PREV_SLOTS)
        live = (np.arange(tracks.shape[1])[None] < tr.n[rows][:, None]) & np.isfinite(tracks).all(axis=-1)
        ids = np.where(live, tr.id[rows][:, : tracks.shape[1]], -1)[:, :K]
        tracks, live = tracks[:, :K], live[:, :K]
        # tracks at the last reading that the tracker no longer holds: remembered from their last state
        gone = (self.prev_id[rows] >= 0) & ~(self.prev_id[rows][:, :, None] == np.where(live, ids, -2)[:, None, :]
                                              ).any(axis=-1)
        for b in np.flatnonzero(gone.any(axis=1)).tolist():
            r = int(rows[b])
            for j in np.flatnonzero(gone[b]).tolist():
                free = np.flatnonzero(~self.alive[r])
                s = int(free[0]) if len(free) else int(np.argmin(self.died[r]))  # full: forget the oldest
                self.alive[r, s] = True
                self.state[r, s] = self.prev_state[r, j]
                self.t0[r, s] = self.prev_t[r]
                self.heading[r, s] = self.prev_heading[r, j]
                self.t_update[r, s] = self.prev_update[r, j]
                self.died[r, s] = now[b]
                self.id[r, s] = self.prev_id[r, j]
        self.prev_id[rows] = -1
        self.prev_id[rows, :K] = ids
        self.prev_state[rows, :K] = np.where(live[..., None], tracks, 0.0)
        self.prev_heading[rows, :K] = tr.heading[rows][:, :K]
        self.prev_update[rows, :K] = tr.t_update[rows][:, :K]
        self.prev_t[rows] = now
        # the remembered cars' predicted places, and the rules that drop them
        mem = self.alive[rows]
        if not mem.any():
            return
        x, y = self.places(rows, now)
        det = np.asarray(perception.last_detections[rows], dtype=float)
        fresh = np.abs(tr.fused_at[rows] - now) < 1e-9  # a detector frame was fused at this reading
        d_trk = np.hypot(x[..., None] - tracks[:, None, :, 0], y[..., None] - tracks[:, None, :, 1])
        near = (np.where(live[:, None, :], d_trk, np.inf) < MEMORY_GATE).any(axis=-1)
        if det.shape[1]:
            d_det = np.hypot(x[..., None] - det[:, None, :, 1], y[..., None] - det[:, None, :, 2])
            near |= fresh[:, None] & (np.where(det[:, None, :, 0] > 0, d_det, np.inf) < MEMORY_GATE).any(axis=-1)
        updated = live & (np.abs(tr.t_update[rows][:, :K] - now[:, None]) < 1e-9)
        occ = np.concatenate([tracks[..., :2], tracks[..., 4:7]], axis=-1)
        seen = in_view(x, y, ego, occ, updated, self.max_range, self.half_fov, self.occlusion)
        looked = fresh[:, None] & seen & (self.died[rows] < now[:, None] - 1e-9)  # not the frame it died in
        old = now[:, None] - self.died[rows] > self.recall + 1e-9
        self.alive[rows] = mem & ~(near | looked | old)

    def places(self, rows: np.ndarray, now: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, S) m: the remembered cars' places at ``now`` (s), at constant velocity from their last state."""
        dt = np.asarray(now, dtype=float)[:, None] - self.t0[rows]
        s = self.state[rows]
        return s[..., 0] + s[..., 2] * dt, s[..., 1] + s[..., 3] * dt

    def users(self, rows: np.ndarray, now: np.ndarray, fused_at: np.ndarray) -> tuple[np.ndarray, ...]:
        """The remembered cars of ``rows`` as extra road users: positions (n, S, 7) ``[x, y, vx, vy, heading,
        length, width]`` (predicted to ``now``), track ids (n, S), which slots hold one (n, S), (n, S, 2) detected
        heading (rad) and detector frames since the last detection (from the last fused frame ``fused_at``)."""
        rows = np.asarray(rows, dtype=int)
        x, y = self.places(rows, now)
        pos = self.state[rows].copy()
        pos[..., 0], pos[..., 1] = x, y
        alive = self.alive[rows]
        missed = np.rint((np.asarray(fused_at, dtype=float)[:, None] - self.t_update[rows]) * self.rate)
        seen = np.stack([self.heading[rows], missed], axis=-1)
        return np.where(alive[..., None], pos, 0.0), np.where(alive, self.id[rows], -1), alive, seen
