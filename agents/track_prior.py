"""The belief planner on tracks (``belief_lookahead@turn_perceived``): what it starts its futures from.

On ``sensors=turn_perceived`` the car knows the road users its tracker holds, not the simulator's vehicles. The
planner's futures (:meth:`agents.belief.BeliefPlanner.futures`) then start from:

- **the confirmed tracks** (:class:`TrackBelief`, :meth:`~TrackBelief.read`): position, velocity and heading as the
  tracker has them (the rows ``obs["tracks"]`` gives, nearest first, so that the indicator readings of
  ``obs["intent"]`` attach to the track the features describe), the closest lane from that pose, the acceleration
  the intent features measure, the track id as the driver's identity; the ego's own state;
- **the tentative tracks** (``tentative: road_user``): road users too (their routes and behaviour from the prior; no
  indicator reading is attached to them), or nothing (``ignore``: the tracker's own rule, what the features show);
- **the road users nobody has confirmed** (:class:`UnseenTraffic`): each future fills the approach lanes with
  drivers drawn from the traffic's own spawn process (``IntersectionEnv._spawn_vehicle`` as
  :meth:`av_gym.batched.left_turn.BatchedLeftTurn._spawn` draws it: a try per policy step with probability
  ``spawn_probability / policy_frequency``, an approach drawn uniformly, entering 5 m along it at a speed from
  :data:`av_gym.sim.batched.SPAWN_PRIOR`, no spawn within ``SPAWN_CLEAR`` of another vehicle), thinned by what the
  sensor saw: a driver that entered ``a`` policy steps ago at speed ``v`` is now ``5 + v·a·dt`` m along its
  approach, and every detector frame in which that place was in range, in the field of view and not behind a
  confirmed track was a look at it. A driver present there stays unconfirmed with the probability the tracker's
  rule gives over those looks (each missed with ``miss_rate``; ``min_hits`` consecutive detections confirm; a
  tentative track is dropped at its first miss): ``miss_rate ** looks`` for one hit to confirm, a little more for
  two. The density of a driver at that place is the spawn density times that probability (times ``unseen``, the
  prior's scale, chosen on validation), so the lanes out of range, behind other cars or seen only for a frame keep
  their traffic, and the ones the sensor has watched are nearly empty.

Nothing here reads the simulator's other vehicles: the ego's own state and clock, the tracker's tracks and
``obs["intent"]``, the env's configuration (spawn rate, frequencies) and the detector's and tracker's parameters
(tests/test_belief_tracks.py moves and removes hidden vehicles and re-draws hidden routes: the same decisions).
Every draw comes from ``SeedSequence([seed, episode_seed, tick, 1])`` (the futures' own stream is ``[seed,
episode_seed, tick]``).
"""

from __future__ import annotations

import copy

import numpy as np
from scipy.stats import norm

from agents.detector_view import in_view
from agents.track_memory import TrackMemory
from av_gym.batched.left_turn import SPAWN_CLEAR
from av_gym.estimation.turn_features import ACC_SCALE
from av_gym.sensors.turn_signal import node_index
from av_gym.sim.batched import Traffic

__all__ = ["SLOTS", "SPEED_CLASSES", "SPAWN_S", "DetectedMotion", "TrackBelief", "UnseenTraffic", "alone",
           "draw_width", "ego_pose", "twins"]

SPAWN_S = 5.0  # m along the approach where a spawn enters (IntersectionEnv._spawn_vehicle: longitudinal + 5)
SPEED_CLASSES = 3  # spawn speeds per cohort: the middles of equal-probability slices of the spawn speed's normal
FIT_SLOTS = 256  # track ids kept per row by DetectedMotion (id mod this: ids live far fewer births than that)
FIT_GATE = 2.0  # m: the detection that updated a track is the nearest one to its updated place, within this
SLOTS = 64  # road users per row whose draws (the futures', the spread's) are fixed by their slot alone, whatever N
LINE_ZONE = 5.0  # m into a crossing lane: a car standing there waits at its stop line (its front past it)
RELEASE_STREAM = 5  # stopped_release's draws: SeedSequence([seed, episode, tick, 5, *stream]) (1 unseen, 2 spread)
FIT_MIN = 3  # detector frames a least-squares line needs (two give no check on a noisy pair)


def draw_width(N: int) -> int:
    """The draws per future a stream gives (``SLOTS``) for a futures' start of ``N`` slots, so that a road user's
    draws depend on its slot alone. A start of more slots would need wider streams, which would change every draw
    of the narrower starts: refused rather than widened. The batch's start on tracks holds at most 42 slots (the
    ego, 16 described tracks, the tracker's 16, 8 remembered cars, 1 spare: TrackBelief._observed)."""
    if N > SLOTS:
        raise ValueError(f"the futures' start holds {N} slots, more than SLOTS = {SLOTS} whose draws are fixed by "
                         f"their slot alone (the batch's start on tracks holds at most 42); raise SLOTS in "
                         f"agents/track_prior.py")
    return SLOTS


def ego_pose(engine, rows) -> np.ndarray:
    """(n, 3) the ego's own pose ``[x m, y m, heading rad]`` in ``rows`` of ``engine`` (from its ego slot): what the
    car knows of itself, from which the detector looks."""
    rows = np.asarray(rows, dtype=int)
    t, slot = engine.traffic, engine.ego_slot(rows)
    return np.stack([t.x[rows, slot], t.y[rows, slot], t.h[rows, slot]], axis=1)


def lane_kinds(T) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per lane id: kind (0 approach o→ir, 1 crossing ir→il, 2 exit il→o), origin approach, destination exit (-1
    where the lane does not say)."""
    kind, origin, dest = [], [], []
    for f, t, _ in T.index:
        if f.startswith("o") and t.startswith("ir"):
            kind.append(0), origin.append(node_index(t, "ir")), dest.append(-1)
        elif f.startswith("ir"):
            kind.append(1), origin.append(node_index(f, "ir")), dest.append(node_index(t, "il"))
        else:
            kind.append(2), origin.append(-1), dest.append(node_index(t, "o"))
    return np.array(kind), np.array(origin), np.array(dest)


class UnseenTraffic:
    """The spawn process's drivers on the four approach lanes that the tracker may not have confirmed, for the B
    rows of a batch: cohorts (approach lane, speed class, policy steps since the spawn) with the probability that a
    driver of that cohort, present, is still unconfirmed (:meth:`look` after every detector frame) and the draws of
    such drivers into the planner's futures (:meth:`fill`)."""

    def __init__(self, engine, detector, tracker, n_rows: int, scale: float = 1.0, tentative: str = "ignore",
                 ahead: int = 0) -> None:
        T = self.T = engine.T
        kind, origin, dest = lane_kinds(T)
        self.approach = np.array([int(np.flatnonzero((kind == 0) & (origin == o))[0]) for o in range(4)])
        self.cross = {(int(o), int(d)): k for k, (kd, o, d) in enumerate(zip(kind, origin, dest)) if kd == 1}
        self.exit = {int(d): k for k, (kd, d) in enumerate(zip(kind, dest)) if kd == 2}
        c = engine.config
        self.dt = 1.0 / float(c["policy_frequency"])  # s per policy step: one spawn try each
        self.frames = int(c["simulation_frequency"] // c["policy_frequency"])  # engine ticks per policy step
        prior = engine.prior
        z = norm.ppf((np.arange(SPEED_CLASSES) + 0.5) / SPEED_CLASSES)
        self.speeds = prior.speed + prior.speed_sd * z  # m/s
        length = T.length[self.approach]
        ages = int(np.ceil((length.max() - SPAWN_S) / (max(self.speeds.min(), 1.0) * self.dt))) + 1
        # where each cohort is now: (4, C, A) m along its approach, and which of them are still on it
        self.s = SPAWN_S + self.speeds[None, :, None] * self.dt * np.arange(ages)[None, None, :]
        self.s = np.broadcast_to(self.s, (4, SPEED_CLASSES, ages)).copy()
        self.on_lane = self.s <= length[:, None, None]
        lane = np.broadcast_to(self.approach[:, None, None], self.s.shape)
        self.x, self.y = T.position(lane, np.minimum(self.s, length[:, None, None]), 0.0)
        self.h = T.heading_at(lane, self.s)
        # one try per policy step, on one of the four approaches; spread over the speed classes
        self.rate = float(c["spawn_probability"]) * self.dt / 4.0 / SPEED_CLASSES * float(scale)
        self.tentative = tentative
        self.max_range, self.half_fov = float(detector.max_range), float(np.radians(detector.fov_deg) / 2)
        self.miss, self.occlusion = float(detector.miss_rate), bool(detector.occlusion)
        self.hits = max(1, int(tracker.min_hits))
        # q[k]: P(unconfirmed and k consecutive detections so far | a driver of the cohort is there)
        self.q = np.zeros((self.hits, int(n_rows), *self.s.shape))
        # the cohort places in view at the last detector frame, and what a driver there keeps of its density by
        # the next decision: missed in each of ``ahead`` more frames (miss_rate ** ahead)
        self.seen = np.zeros((int(n_rows), *self.s.shape), bool)
        self.ahead = self.miss ** int(ahead)
        self.step = np.full(int(n_rows), -1)
        self.reset(np.arange(int(n_rows)))

    def reset(self, rows) -> None:
        """New episodes in ``rows``: nothing seen yet (the drivers already on the map are as unseen as new ones)."""
        rows = np.asarray(rows, dtype=int)
        self.q[:, rows] = 0.0
        self.q[0, rows] = 1.0
        self.seen[rows] = False
        self.step[rows] = -1

    def age(self, rows: np.ndarray, steps: np.ndarray) -> None:
        """Move the cohorts of ``rows`` on to the policy steps ``steps``: each one step older per step, a fresh
        (never seen) cohort entering at the spawn point."""
        first = self.step[rows] < 0
        d = np.where(first, 0, steps - self.step[rows])
        self.step[rows] = steps
        for shift in np.unique(d[d > 0]).tolist():
            r = rows[d == shift]
            k = min(int(shift), self.q.shape[-1])
            sub = self.q[:, r]
            sub[..., k:] = sub[..., :-k] if k < sub.shape[-1] else sub[..., :0]
            sub[..., :k] = 0.0
            sub[0, ..., :k] = 1.0
            self.q[:, r] = sub

    def in_view(self, ego: np.ndarray, occluders: np.ndarray, present: np.ndarray) -> np.ndarray:
        """(n, 4, C, A): each cohort's place within range and the field of view of the ego poses ``ego`` (n, 3)
        ``[x, y, heading]`` and not behind a nearer confirmed track (``occluders`` (n, M, 5) ``[x, y, heading,
        length, width]``, ``present`` (n, M)): the detector's view, its occlusion by the occluders the car knows."""
        seen = in_view(self.x[None], self.y[None], ego, occluders, present, self.max_range, self.half_fov,
                       self.occlusion)
        return seen & self.on_lane[None]

    def look(self, rows: np.ndarray, seen: np.ndarray) -> None:
        """One detector frame of ``rows`` whose cohorts ``seen`` (n, 4, C, A) were in view: a driver there is
        detected with 1 - miss_rate; ``min_hits`` consecutive detections confirm it; a tentative track is dropped at
        its first frame without a detection (missed, or out of view)."""
        q = self.q[:, rows]
        total = q.sum(axis=0)
        new = np.zeros_like(q)
        new[0] = np.where(seen, self.miss * total, total)
        for k in range(1, self.hits):
            new[k] = np.where(seen, (1.0 - self.miss) * q[k - 1], 0.0)
        self.q[:, rows] = new
        self.seen[rows] = seen

    def density(self, rows: np.ndarray) -> np.ndarray:
        """(n, 4, C, A): the probability that a driver of each cohort is there and not among the road users the
        planner already has (the confirmed tracks; also the tentative ones with ``tentative: road_user``), and, at a
        place in view at the last frame, still missed in ``unseen_ahead`` more frames (by the next decision)."""
        q = self.q[0, rows] if self.tentative == "road_user" else self.q[:, rows].sum(axis=0)
        if self.ahead < 1.0:  # unseen_ahead > 0 (off: every place keeps its density)
            q = np.where(self.seen[rows], q * self.ahead, q)
        return np.where(self.on_lane[None], np.clip(self.rate * q, 0.0, 1.0), 0.0)

    def draws(self, rows: np.ndarray, users: np.ndarray, users_alive: np.ndarray, gens: list, K: int) -> tuple:
        """The unseen drivers of K futures per row: (future row, approach, speed class, cohort, destination draw,
        delta draw) arrays. A cohort within ``SPAWN_CLEAR`` of a road user the planner has (``users`` (n, M, 2)
        positions, ``users_alive`` (n, M)) or of an unseen driver drawn before it on its lane holds none: the spawn
        rule, which keeps the drivers of a lane that far apart when they enter."""
        p = self.density(rows)  # (n, 4, C, A)
        d = np.hypot(self.x[None, ..., None] - users[:, None, None, None, :, 0],
                     self.y[None, ..., None] - users[:, None, None, None, :, 1])
        p = np.where((np.where(users_alive[:, None, None, None, :], d, np.inf) < SPAWN_CLEAR).any(axis=-1), 0.0, p)
        A = p.shape[-1]
        u = np.stack([g.random((4, K, 4, A)) for g in gens], axis=1)  # (4 kinds of draw, n, K, 4, A)
        total = p.sum(axis=2)  # (n, 4, A): a driver of the cohort in any speed class
        cdf = np.cumsum(p, axis=2) / np.where(total > 0, total, 1.0)[:, :, None]
        last = np.full((len(rows), K, 4), -np.inf)
        out = []
        for a in range(A):
            arrive = u[0, ..., a] < total[:, None, :, a]  # (n, K, 4)
            if not arrive.any():
                continue
            cls = np.minimum((u[1, ..., a][..., None] >= cdf[:, None, :, :, a]).sum(axis=-1), SPEED_CLASSES - 1)
            s = self.s[np.arange(4)[None, None], cls, a]
            ok = arrive & (np.abs(s - last) >= SPAWN_CLEAR)
            last = np.where(ok, s, last)
            n, k, j = np.nonzero(ok)
            out.append((n * K + k, j, cls[n, k, j], np.full(len(n), a), u[2, n, k, j, a], u[3, n, k, j, a]))
        if not out:
            return tuple(np.zeros(0, dtype=int) for _ in range(4)) + (np.zeros(0), np.zeros(0))
        return tuple(np.concatenate(c) for c in zip(*out))

    def fill(self, f, rows: np.ndarray, users: np.ndarray, users_alive: np.ndarray, gens: list, K: int) -> None:
        """Add the unseen drivers of :meth:`draws` to the future engine ``f`` (len(rows)·K rows, row-major): on
        their approach at their cohort's place and speed (also their set-point, as a spawn's), a destination
        uniform over the three other approaches, delta from the spawn prior; after the road users already there."""
        fr, j, c, a, u_dest, u_delta = self.draws(rows, users, users_alive, gens, K)
        if not len(fr):
            return
        t, T = f.traffic, self.T
        order = np.argsort(fr, kind="stable")
        fr, j, c, a, u_dest, u_delta = fr[order], j[order], c[order], a[order], u_dest[order], u_delta[order]
        start = np.r_[0, np.flatnonzero(np.diff(fr)) + 1]
        rank = np.arange(len(fr)) - np.repeat(start, np.diff(np.r_[start, len(fr)]))
        slot = t.alive.sum(axis=1)[fr] + rank
        if slot.max() >= t.N:
            t.grow(int(slot.max()) + 1 - t.N)
        lane = self.approach[j]
        dest = (j + 1 + np.minimum((u_dest * 3).astype(int), 2)) % 4
        speed = self.speeds[c]
        lo, hi = f.prior.delta
        for name in ("ego", "plain", "mdp", "crashed", "yielding", "has_impact"):
            getattr(t, name)[fr, slot] = False
        t.alive[fr, slot] = True
        t.x[fr, slot], t.y[fr, slot], t.h[fr, slot] = self.x[j, c, a], self.y[j, c, a], self.h[j, c, a]
        t.v[fr, slot] = t.target[fr, slot] = speed
        t.delta[fr, slot] = lo + (hi - lo) * u_delta
        t.steer[fr, slot] = t.acc[fr, slot] = t.impact_x[fr, slot] = t.impact_y[fr, slot] = 0.0
        t.lane[fr, slot] = t.tlane[fr, slot] = lane
        t.route[fr, slot] = np.stack([lane, [self.cross[(int(o), int(d))] for o, d in zip(j, dest)],
                                      [self.exit[int(d)] for d in dest]], axis=1)
        t.rpos[fr, slot], t.vid[fr, slot] = 0, 0


class DetectedMotion:
    """The planner's own view of each track's motion (``track_fit``), for the B rows of a batch: the detector's
    velocities (m/s, world frame; sd ``sigma_vel`` each, unbiased) of the frames that updated a track, kept per track
    id, and a least-squares line through their components along the track's heading over the last ``window`` s:
    its value now (the speed) and its slope (the acceleration). The constant-velocity filter weighs the same
    readings against its model and so trails a car that accelerates (0.2 s x a in steady state); the line does not.
    The tracker does not say which detection updated which track: the nearest detection to the track's updated
    place, within ``FIT_GATE`` (its update moved it most of the way there)."""

    def __init__(self, n_rows: int, window: float, rate_hz: float) -> None:
        self.window = float(window)
        depth = int(np.ceil(self.window * float(rate_hz) + 1e-9)) + 1  # frames a window can hold
        self.id = np.full((int(n_rows), FIT_SLOTS), -1)
        self.t = np.full((int(n_rows), FIT_SLOTS, depth), -np.inf)  # s, newest first
        self.v = np.zeros((int(n_rows), FIT_SLOTS, depth, 2))

    def reset(self, rows) -> None:
        """New episodes in ``rows``: no track seen."""
        self.id[np.asarray(rows, dtype=int)] = -1

    def record(self, rows: np.ndarray, ids: np.ndarray, updated: np.ndarray, places: np.ndarray,
               detections: np.ndarray, now: np.ndarray) -> None:
        """One detector frame fused at times ``now`` (s, (n,)) in ``rows``: the tracks ``ids`` (n, K) that it
        ``updated`` (n, K), at their updated ``places`` (n, K, 2) m, get the velocity of their nearest detection
        (``detections`` (n, D, >=5) ``[present, x, y, vx, vy, ...]``, world frame) within ``FIT_GATE``."""
        det = np.asarray(detections, dtype=float)
        d = np.hypot(places[:, :, None, 0] - det[:, None, :, 1], places[:, :, None, 1] - det[:, None, :, 2])
        d = np.where((det[:, None, :, 0] > 0) & updated[..., None], d, np.inf)
        if d.shape[-1] == 0:
            return
        j = np.argmin(d, axis=-1)
        b, k = np.nonzero(np.take_along_axis(d, j[..., None], -1)[..., 0] <= FIT_GATE)
        if not len(b):
            return
        r, tid = np.asarray(rows)[b], ids[b, k]
        s = tid % FIT_SLOTS
        fresh = self.id[r, s] != tid  # a new track in this slot: its history starts now
        self.id[r, s] = tid
        self.t[r[fresh], s[fresh]] = -np.inf
        t = np.asarray(now, dtype=float)[b]
        again = self.t[r, s, 0] == t  # the same frame read twice: its reading replaced, not added
        keep = np.where(again[:, None], self.t[r, s][:, 1:], self.t[r, s][:, :-1])
        vkeep = np.where(again[:, None, None], self.v[r, s][:, 1:], self.v[r, s][:, :-1])
        self.t[r, s] = np.concatenate([t[:, None], keep], axis=1)
        self.v[r, s] = np.concatenate([det[b, j[b, k], 3:5][:, None], vkeep], axis=1)

    def estimate(self, rows: np.ndarray, ids: np.ndarray, heading: np.ndarray, now: np.ndarray) -> tuple:
        """(speed m/s, acceleration m/s², whether there is a line) (n, M) for the tracks ``ids`` (n, M) of ``rows``
        along ``heading`` (n, M) rad at times ``now`` (n,) s: the least-squares line of the detected velocities'
        components along the heading against time over the last ``window`` s, at ``now`` and its slope; a line
        needs ``FIT_MIN`` frames."""
        rows = np.asarray(rows, dtype=int)[:, None]
        s = ids % FIT_SLOTS
        dt = self.t[rows, s] - np.asarray(now, dtype=float)[:, None, None]  # (n, M, depth) s, <= 0
        w = ((self.id[rows, s] == ids)[..., None] & (dt >= -self.window - 1e-9)).astype(float)
        v = self.v[rows, s]
        u = v[..., 0] * np.cos(heading)[..., None] + v[..., 1] * np.sin(heading)[..., None]
        dt = np.where(w > 0, dt, 0.0)
        n = w.sum(axis=-1)
        safe_n = np.maximum(n, 1.0)
        mt, mu = (w * dt).sum(axis=-1) / safe_n, (w * u).sum(axis=-1) / safe_n
        stt = (w * (dt - mt[..., None]) ** 2).sum(axis=-1)
        stu = (w * (dt - mt[..., None]) * (u - mu[..., None])).sum(axis=-1)
        ok = (n >= FIT_MIN) & (stt > 1e-9)
        a = np.where(ok, stu / np.where(ok, stt, 1.0), 0.0)
        return np.where(ok, mu - a * mt, 0.0), a, ok


class TrackBelief:
    """The planner's road on tracks for the rows of a batch with a
    :class:`~av_gym.batched.perception.BatchedPerception`: :meth:`read` (every env step, after the observation)
    builds the engine the planner reads indicators on and the one its futures start from, and updates the unseen
    traffic's looks; :meth:`fill` adds the unseen drivers to the futures."""

    def __init__(self, params, perception, n_rows: int) -> None:
        self.perception, self.params = perception, params
        e = perception.e
        self.tentative = str(params.tentative)
        self.unseen = UnseenTraffic(e, perception.detector.params, perception.tracker.params, n_rows,
                                    float(params.unseen), self.tentative, int(params.unseen_ahead)
                                    ) if float(params.unseen) > 0 else None
        self.engine = None  # the futures' start (ego, confirmed [and tentative] tracks), all rows
        self.tent = None  # (B, N) its slots that hold a tentative track
        self.ghost = None  # (B, N) its slots whose track the detector has missed while in view (not in the futures)
        self.along = None  # (B, N, 2, 2) its slots' filter covariance of (place, speed) along their heading
        self._ticks = None
        self.lane_kind = lane_kinds(e.T)[0]  # per lane id: 0 approach, 1 crossing, 2 exit
        fit = float(params.track_fit)
        self.motion = DetectedMotion(n_rows, fit, float(perception.detector.params.rate_hz)) if fit > 0 else None
        recall = float(getattr(params, "recall", 0.0))
        det = perception.detector.params
        # the planner's own memory of the cars whose track the tracker dropped (agents/track_memory.py)
        self.memory = TrackMemory(n_rows, recall, float(det.max_range), float(np.radians(det.fov_deg) / 2),
                                  bool(det.occlusion), float(det.rate_hz)) if recall > 0 else None
        self.remembered = None  # (B, N) the futures' start's slots that hold a remembered car

    def reset(self, rows) -> None:
        if self.unseen is not None:
            self.unseen.reset(rows)
        if self.motion is not None:
            self.motion.reset(rows)
        if self.memory is not None:
            self.memory.reset(rows)

    def _tracks(self, rows: np.ndarray) -> tuple:
        """The tracker's tracks of ``rows`` as ``obs["tracks"]`` orders them (confirmed and finite, nearest the
        ego first: tracks_observation's order), then the tentative ones: positions (n, M, 7), ids (n, M),
        confirmed (n, M), tentative (n, M), (n, M, 2) each track's detected heading (rad, the tracker's running
        mean of the detector's) and the detector frames since a detection last updated it, and (n, M, 4, 4) its
        filter's covariance of ``[x, y, vx, vy]`` (m², m²/s, m²/s²)."""
        p = self.perception
        tracks, shown = p.tracker.tracks(rows)
        ids = p.tracker.id[rows]
        live = np.arange(tracks.shape[1])[None] < p.tracker.n[rows][:, None]
        finite = np.isfinite(tracks).all(axis=-1)
        confirmed = shown & finite
        e = p.e
        slot = e.ego_slot(rows)  # the ego's own position, from which obs["tracks"] orders them
        ego = np.stack([e.traffic.x[rows, slot], e.traffic.y[rows, slot]], axis=1)
        d = np.hypot(tracks[..., 0] - ego[:, 0, None], tracks[..., 1] - ego[:, 1, None])
        key = np.where(confirmed, d, np.inf)
        order = np.argsort(key, axis=1, kind="stable")[:, : p.max_tracks]
        take = lambda a: np.take_along_axis(a, order if a.ndim == 2 else order[..., None], axis=1)  # noqa: E731
        conf = take(confirmed)
        rows_obs = p.last_tracks[rows][:, : order.shape[1]]  # the float32 rows the features saw, same order
        pos = np.where(conf[..., None], rows_obs[..., 1:8].astype(float), 0.0)
        tent = live & finite & ~shown & (self.tentative == "road_user")
        rate = float(p.detector.params.rate_hz)
        missed = np.rint((p.tracker.fused_at[rows][:, None] - p.tracker.t_update[rows]) * rate)
        seen = np.stack([p.tracker.heading[rows], missed], axis=-1)
        P = p.tracker.P[rows][:, : tracks.shape[1]]
        cov = np.concatenate([np.take_along_axis(P, order[..., None, None], axis=1), P], axis=1)
        users = np.concatenate([conf, tent], axis=1)
        return (np.concatenate([pos, np.where(tent[..., None], tracks, 0.0)], axis=1),
                np.concatenate([take(ids), ids], axis=1), np.concatenate([conf, np.zeros_like(tent)], axis=1),
                np.concatenate([np.zeros_like(conf), tent], axis=1), np.concatenate([take(seen), seen], axis=1),
                np.where(users[..., None, None], cov, 0.0))

    def read(self, engine, rows, intent: np.ndarray):
        """The engine of what the car knows at this step (every row's ego; ``rows``' tracks), kept for
        :meth:`current`; returns it with only the confirmed tracks alive (the road users ``obs["intent"]``
        describes, nearest first, for :meth:`BeliefPlanner.read`). Updates the unseen traffic of ``rows``."""
        rows = np.asarray(rows, dtype=int)
        if self.motion is not None and len(rows):
            self._record(engine, rows)
        if self.memory is not None and len(rows):
            self.memory.update(self.perception, rows, ego_pose(engine, rows),
                               engine.ticks[rows] / engine.config["simulation_frequency"])
        obs, conf, tent, ghost = self._observed(engine, rows, np.asarray(intent))
        self.engine, self._ticks, self.tent, self.ghost = obs, engine.ticks.copy(), tent, ghost
        if self.unseen is not None and len(rows):
            self._look(engine, rows)
        shown = copy.copy(obs)
        shown.traffic = copy.copy(obs.traffic)
        shown.traffic.alive = obs.traffic.alive & ~tent
        # a ghost keeps its place among the described tracks (obs["intent"]'s order) but is nobody in the futures
        obs.traffic.alive = obs.traffic.alive & ~ghost
        self._pack()
        return shown

    def _pack(self) -> None:
        """Pack the futures' start's road users into the first slots of every row, their order kept (the ego, the
        confirmed tracks nearest first, the tentative ones, the remembered cars), and its per-slot masks and
        covariances with them. The engine assumes its live slots come first: every step trims the slots past the
        most road users any row holds plus 2 (Traffic.trim) and a spawn (the engine's, the unseen prior's) takes the
        slot after a row's live count, so a road user after a gap (a tentative track after the described block, a
        ghost's hole) left the futures or was overwritten. Packed before any draw, a road user's draws depend on its
        place in this order alone: the batch and a one-row view of an env (EnvTracks) lay it in the same slot."""
        t = self.engine.traffic
        order = np.argsort(~t.alive, axis=1, kind="stable")  # Traffic.compact's order
        t.compact()
        self.tent, self.ghost, self.remembered = (np.take_along_axis(a, order, axis=1)
                                                  for a in (self.tent, self.ghost, self.remembered))
        self.along = np.take_along_axis(self.along, order[..., None, None], axis=1)

    def _observed(self, engine, rows: np.ndarray, intent: np.ndarray) -> tuple:
        """The observed engine (ego in slot 0, then the tracks) and its confirmed / tentative / ghost slot masks."""
        src, B = engine.traffic, engine.B
        pos, ids, conf, tent, seen, cov, kept = self._with_memory(engine, rows, *self._tracks(rows))
        M = pos.shape[1]
        t = Traffic(engine.T, B, N=M + 2)
        t.road_steps[:] = src.road_steps
        e = engine.ego_slot(np.arange(B))
        for name in Traffic.FIELDS:  # the ego knows itself: its whole state
            getattr(t, name)[:, 0] = getattr(src, name)[np.arange(B), e]
        t.vid[:, 0] = 0
        users = conf | tent
        sl = slice(1, M + 1)
        t.alive[rows, sl] = users
        x, y, vx, vy, h = (pos[..., k] for k in range(5))
        speed = np.hypot(vx, vy)
        if self.params.track_heading == "detected":
            # the detector's heading (sd 0.05 rad a frame) for the pose the lane is matched from; the speed along
            # it, negative where the filter's velocity points backwards (a car braking to a halt, backing)
            h = np.where(users, seen[..., 0], h)
            speed = vx * np.cos(h) + vy * np.sin(h)
        # a car backing up is told by the filter's own speed along the heading, before track_lag / track_fit: a
        # car braking hard to a halt (0.8 m/s at -6 m/s², lag 0.2 s: -0.4 m/s) is not backing, it is stopping
        measured = speed
        # the acceleration the intent features measure, for the described tracks (nearest first, as obs["intent"])
        m = min(intent.shape[1], M)
        acc = np.zeros(pos.shape[:2])
        acc[:, :m] = intent[:, :m, 0] * ACC_SCALE
        acc = np.where(conf, acc, 0.0)
        if self.motion is not None:
            # the planner's own line through the detected velocities, where it has one: its speed only (its slope is
            # noisier than the features' acceleration: benchmarks/belief_tracks_motion.py)
            now = engine.ticks[rows] / engine.config["simulation_frequency"]
            v_fit, _, fitted = self.motion.estimate(rows, ids, h, now)
            speed = np.where(fitted & users, v_fit, speed)
        # the constant-velocity filter's speed trails an accelerating car by track_lag s times its acceleration
        # (track_lag_up: only for a car pulling away; a braking car's filter speed is the cautious one)
        speed = speed + float(self.params.track_lag) * (np.maximum(acc, 0.0) if self.params.track_lag_up else acc)
        t.x[rows, sl], t.y[rows, sl], t.h[rows, sl] = x, y, h
        # a car backing up (track_reverse): the engine's IDM brakes a car past 0 into reverse where it stands closer
        # than its desired gap, its speed unclipped; its futures start backing at the speed measured, not standing
        backing = users & (measured < -float(self.params.track_reverse)) if self.params.track_reverse > 0 \
            else np.zeros(users.shape, bool)
        # a backing car starts at its measured speed: lag and fit model a car's forward speed changes
        t.v[rows, sl] = np.where(backing, measured, np.maximum(speed, 0.0))
        t.target[rows, sl] = np.maximum(speed, 0.0)
        lane = engine.T.closest(x, y, h)
        # the tracks carry no crash flag: a road user standing still is taken to stay where it is (a crashed car
        # does; one held at a line is released later than the futures would have it go), with stopped_scope
        # off_approach only off the approach lanes and the crossing lanes' first LINE_ZONE m: one standing there
        # waits at its line, and the futures' regulation and IDM release it as the simulator's would
        standing = users & (speed < float(self.params.stopped)) & ~backing
        if getattr(self.params, "stopped_scope", "anywhere") == "off_approach":
            along, _ = engine.T.local(lane, x, y)
            kind = self.lane_kind[lane]
            standing &= ~((kind == 0) | ((kind == 1) & (along < LINE_ZONE)))
        # ghosts and twins are nobody in the futures (below): neither a road user nor a crash partner
        gone = self._ghosts(ego_pose(engine, rows), pos, users, seen[..., 1]) | twins(
            pos, users, seen[..., 1], float(self.params.merge), float(self.params.merge_far),
            float(self.params.merge_agree), seen[..., 0])
        if float(getattr(self.params, "stopped_alone", 0.0)) > 0:
            standing &= ~alone(pos, users & ~gone, float(self.params.stopped_alone))
        t.crashed[rows, sl] = standing
        t.lane[rows, sl] = t.tlane[rows, sl] = np.where(users, lane, 0)
        t.route[rows, sl, 0] = np.where(users, lane, -1)
        t.vid[rows, sl] = ids + 1
        t.acc[rows, sl] = acc
        full_conf, full_tent, full_ghost = (np.zeros((B, M + 2), bool) for _ in range(3))
        full_conf[rows, sl], full_tent[rows, sl] = conf, tent
        self.remembered = np.zeros((B, M + 2), bool)
        self.remembered[rows, sl] = kept
        full_ghost[rows, sl] = gone
        self.along = np.zeros((B, M + 2, 2, 2))
        self.along[rows, sl] = along_heading(cov, h)
        obs = engine.observed(t, engine.time, engine.ticks, engine.episode_seed)
        return obs, full_conf, full_tent, full_ghost

    def _with_memory(self, engine, rows: np.ndarray, pos, ids, conf, tent, seen, cov) -> tuple:
        """The tracks' arrays (as :meth:`_tracks` gives them) with the remembered cars (``recall``) after the tracks,
        as road users a tentative track is (no readings, not described), and the mask of those remembered slots."""
        kept = np.zeros(conf.shape, bool)
        if self.memory is None:
            return pos, ids, conf, tent, seen, cov, kept
        now = engine.ticks[rows] / engine.config["simulation_frequency"]
        m_pos, m_ids, m_alive, m_seen = self.memory.users(rows, now, self.perception.tracker.fused_at[rows])
        pos, ids = np.concatenate([pos, m_pos], axis=1), np.concatenate([ids, m_ids], axis=1)
        conf, kept = np.concatenate([conf, np.zeros_like(m_alive)], axis=1), np.concatenate([kept, m_alive], axis=1)
        tent = np.concatenate([tent, m_alive], axis=1)
        seen = np.concatenate([seen, m_seen], axis=1)
        cov = np.concatenate([cov, np.zeros(m_pos.shape[:2] + (4, 4))], axis=1)
        return pos, ids, conf, tent, seen, cov, kept

    def _record(self, engine, rows: np.ndarray) -> None:
        """Where the tracker fused a detector frame now in ``rows``: each track it updated gets its detection's
        velocity (:class:`DetectedMotion`)."""
        p = self.perception
        now = engine.ticks[rows] / engine.config["simulation_frequency"]
        fused = np.abs(p.tracker.fused_at[rows] - now) < 1e-9
        if not fused.any():
            return
        r, now = rows[fused], now[fused]
        tracks, _ = p.tracker.tracks(r)
        live = np.arange(tracks.shape[1])[None] < p.tracker.n[r][:, None]
        updated = live & (np.abs(p.tracker.t_update[r][:, : tracks.shape[1]] - now[:, None]) < 1e-9)
        self.motion.record(r, p.tracker.id[r][:, : tracks.shape[1]], updated, tracks[..., :2],
                           p.last_detections[r], now)

    def _ghosts(self, ego: np.ndarray, pos: np.ndarray, users: np.ndarray, missed: np.ndarray) -> np.ndarray:
        """(n, M): the road users of n rows (the ego's poses ``ego`` (n, 3), :func:`ego_pose`) the detector has
        missed in the last ``ghost`` frames although their place is in view now (in range, in the field of view, not
        behind a road user detected in this frame).
        A car there is missed with ``miss_rate`` a frame (0.1: twice in a row 1 %): such a track is what the
        tracker coasts on after its car left the constant-velocity path (a turn: the car's detections start a new
        track), for up to ``max_coast``, straight on into lanes the car never takes."""
        k = int(self.params.ghost)
        if k <= 0 or not len(ego):
            return np.zeros(users.shape, bool)
        det = self.perception.detector.params
        occ = np.concatenate([pos[..., :2], pos[..., 4:7]], axis=-1)
        seen = in_view(pos[..., 0], pos[..., 1], ego, occ, users & (missed == 0), float(det.max_range),
                       float(np.radians(det.fov_deg) / 2), bool(det.occlusion))
        return users & (missed >= k) & seen

    def _look(self, engine, rows: np.ndarray) -> None:
        """Age ``rows``' cohorts to this policy step and, where the tracker fused a detector frame now, count a
        look at every cohort place in view."""
        u, p = self.unseen, self.perception
        u.age(rows, engine.ticks[rows] // u.frames)
        now = engine.ticks[rows] / engine.config["simulation_frequency"]
        fused = np.abs(p.tracker.fused_at[rows] - now) < 1e-9
        if not fused.any():
            return
        r = rows[fused]
        pos, _, conf, _, _, _ = self._tracks(r)
        occ = np.concatenate([pos[..., :2], pos[..., 4:7]], axis=-1)
        u.look(r, u.in_view(ego_pose(engine, r), occ, conf))

    def current(self, engine):
        """The engine :meth:`read` built at this step (the futures' start)."""
        if self.engine is None or not np.array_equal(self._ticks, engine.ticks):
            raise ValueError("TrackBelief: read() the rows at this step before deciding")
        return self.engine

    def fill(self, f, rows: np.ndarray, seed: int, K: int, stream: tuple = ()) -> None:
        """Spread the tracks' start in the future engine ``f`` (:meth:`BeliefPlanner.futures` of ``rows``) by their
        filter's error (``track_spread``) and add the unseen drivers to it."""
        if not len(rows):
            return
        e = self.engine
        if float(self.params.track_spread) > 0:
            self._spread(f, rows, seed, K, stream)
        if float(getattr(self.params, "stopped_release", 0.0)) > 0:
            self._release(f, rows, seed, K, stream)
        alive = f.traffic.alive
        if (alive[:, 1:] > alive[:, :-1]).any():
            # a gap the read's packing did not leave: a tool's edit of the start after the read (the ablation's
            # truth parts, the confirm trace's road user left out) must not leave a road user to the first step's
            # trim or under the unseen drivers, who join at each row's live count
            f.traffic.compact()
        if self.unseen is None:
            return
        gens = [np.random.default_rng(np.random.SeedSequence([int(seed), int(e.episode_seed[r]) % 2**63,
                                                               int(e.ticks[r]), 1, *stream])) for r in rows]
        t = e.traffic
        users = np.stack([t.x[rows], t.y[rows]], axis=-1)
        self.unseen.fill(f, rows, users, t.alive[rows], gens, K)

    def _release(self, f, rows: np.ndarray, seed: int, K: int, stream: tuple = ()) -> None:
        """In ``stopped_release`` of ``rows``' K futures (``f``'s rows, row-major, before the unseen drivers join),
        drawn per future and road user, a track the standing rule holds on a crossing lane is a driver (not
        crashed): the futures' regulation and IDM move it as the simulator's would a car held there and released.
        Draws from ``SeedSequence([seed, episode_seed, tick, RELEASE_STREAM, *stream])``, a fixed width per future
        (``SLOTS``): a road user's draw depends on its slot alone, whatever N."""
        e = self.engine
        t, N, W = e.traffic, e.traffic.N, draw_width(e.traffic.N)
        u = np.stack([np.random.default_rng(np.random.SeedSequence([int(seed), int(e.episode_seed[r]) % 2**63,
                                                                    int(e.ticks[r]), RELEASE_STREAM, *stream]))
                      .random((K, W))[:, :N] for r in rows])  # (n, K, N)
        held = t.alive[rows] & ~t.ego[rows] & t.crashed[rows] & (self.lane_kind[t.lane[rows]] == 1)
        go = np.repeat(held, K, axis=0) & (u.reshape(len(rows) * K, N) < float(self.params.stopped_release))
        f.traffic.crashed[:, :N] &= ~go

    def _spread(self, f, rows: np.ndarray, seed: int, K: int, stream: tuple = ()) -> None:
        """Move each moving road user of ``rows``' K futures (``f``'s rows, row-major, before the unseen drivers
        join) ``track_spread`` times a draw of its filter's error along its heading: place (m) and speed (m/s)
        jointly normal with the covariance :func:`along_heading` gives; a speed is kept at or above 0. Draws from
        ``SeedSequence([seed, episode_seed, tick, 2, *stream])``, a fixed width of them per future (``SLOTS``), so a
        road user's draws depend on its slot alone, not on how many slots the batch holds."""
        e = self.engine
        N = e.traffic.N
        W = draw_width(N)
        z = np.stack([np.random.default_rng(np.random.SeedSequence([int(seed), int(e.episode_seed[r]) % 2**63,
                                                                    int(e.ticks[r]), 2, *stream]))
                      .standard_normal((K, W, 2))[:, :N] for r in rows])  # (n, K, N, 2)
        t = e.traffic
        moving = t.alive[rows] & ~t.ego[rows] & ~t.crashed[rows]  # a standing track stays where it is
        # a Cholesky factor of each 2x2 covariance (a zero one where the slot holds no track)
        S = self.along[rows]
        a = np.sqrt(np.maximum(S[..., 0, 0], 0.0))
        b = np.where(a > 0, S[..., 0, 1] / np.where(a > 0, a, 1.0), 0.0)
        c = np.sqrt(np.maximum(S[..., 1, 1] - b**2, 0.0))
        scale = float(self.params.track_spread) * moving
        ds = (scale * a)[:, None] * z[..., 0]
        dv = scale[:, None] * (b[:, None] * z[..., 0] + c[:, None] * z[..., 1])
        ft = f.traffic
        n = len(rows)
        h = np.repeat(t.h[rows], K, axis=0)
        ft.x[:, :N] += ds.reshape(n * K, N) * np.cos(h)
        ft.y[:, :N] += ds.reshape(n * K, N) * np.sin(h)
        ft.v[:, :N] = np.where(np.repeat(moving, K, axis=0), np.maximum(ft.v[:, :N] + dv.reshape(n * K, N), 0.0),
                               ft.v[:, :N])


TWIN_HEADING = 0.5  # rad: the largest difference of two tracks' detected headings for ``merge_far``'s twins


def alone(pos: np.ndarray, users: np.ndarray, radius: float) -> np.ndarray:
    """(n, M): the road users (``users`` (n, M) of the tracks' rows ``pos`` (n, M, >= 2), x and y in m) with no other
    road user of their row within ``radius`` m, centre to centre. A crash stops both cars in contact (their centres
    3-6 m apart): on train seeds 100-199 (the simulator's crash flag), of the steps a car stood on its crossing
    lane past LINE_ZONE, those with another vehicle within 4 m were crashed in 100 %, those with none within 8 m
    in 3 % (53 % of these drove off within 3 s)."""
    d = np.hypot(pos[..., 0][:, :, None] - pos[..., 0][:, None, :], pos[..., 1][:, :, None] - pos[..., 1][:, None, :])
    other = users[:, None, :] & ~np.eye(users.shape[1], dtype=bool)[None]
    return users & ~(other & (d < radius)).any(axis=-1)


def twins(pos: np.ndarray, users: np.ndarray, missed: np.ndarray, radius: float, far: float = 0.0,
          agree: float = 1.0, heading: np.ndarray | None = None) -> np.ndarray:
    """(n, M): the road users (``users`` (n, M); ``pos`` (n, M, >=4) their x, y in m and vx, vy in m/s) with
    another one closer than ``radius`` (m), or closer than ``far`` (m) with a velocity within ``agree`` (m/s, the
    difference of the vectors) and a heading (``heading`` (n, M) rad, the detected one) within
    :data:`TWIN_HEADING`, that the detector updated more recently (``missed`` (n, M): detector frames since their
    last update), or as recently and earlier in the order (the confirmed tracks come first, nearest first): the
    second track of one car, left out of the futures (one car there, not two that collide with each other)."""
    if radius <= 0:
        return np.zeros(users.shape, bool)
    d = np.hypot(pos[:, :, None, 0] - pos[:, None, :, 0], pos[:, :, None, 1] - pos[:, None, :, 1])
    near = d < radius
    if far > radius:
        # a car's second track moves with it; two real cars this close move differently or collide
        dv = np.hypot(pos[:, :, None, 2] - pos[:, None, :, 2], pos[:, :, None, 3] - pos[:, None, :, 3])
        h = np.arctan2(pos[..., 3], pos[..., 2]) if heading is None else heading
        dh = np.abs((h[:, :, None] - h[:, None, :] + np.pi) % (2 * np.pi) - np.pi)
        near |= (d < far) & (dv <= agree) & (dh <= TWIN_HEADING)
    idx = np.arange(users.shape[1])
    better = (missed[:, None, :] < missed[:, :, None]) | ((missed[:, None, :] == missed[:, :, None])
                                                          & (idx[None, :] < idx[:, None])[None])
    close = users[:, :, None] & users[:, None, :] & near & (idx[:, None] != idx[None, :])[None]
    return (close & better).any(axis=2)


def along_heading(cov: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(..., 2, 2): the covariance ``cov`` (..., 4, 4) of ``[x, y, vx, vy]`` projected on the unit vector of the
    headings ``h`` (rad): of (place along the heading, speed along it), m², m²/s, m²/s²."""
    u = np.stack([np.cos(h), np.sin(h)], axis=-1)[..., :, None]  # (..., 2, 1)
    ut = np.swapaxes(u, -1, -2)
    out = np.empty(cov.shape[:-2] + (2, 2))
    out[..., 0, 0] = (ut @ cov[..., :2, :2] @ u)[..., 0, 0]
    out[..., 1, 1] = (ut @ cov[..., 2:, 2:] @ u)[..., 0, 0]
    out[..., 0, 1] = out[..., 1, 0] = (ut @ cov[..., :2, 2:] @ u)[..., 0, 0]
    return out


class EnvTracks:
    """The per-env stack's detector and tracker (:class:`~av_gym.estimation.object_tracking.ObjectTracker` over
    :class:`~av_gym.estimation.tracker.MultiObjectTracker`) as the arrays :class:`TrackBelief` reads of the batch's
    :class:`~av_gym.batched.perception.BatchedPerception`, for a one-row view of the env
    (:class:`agents.belief.EnvView`); :meth:`update` after every observation."""

    def __init__(self, env) -> None:
        from av_gym.estimation.object_tracking import ObjectTracker
        from av_gym.sensors.base import find_wrapper
        from av_gym.sensors.detector import Detector

        self.wrapper = find_wrapper(env, ObjectTracker)
        self.detector = find_wrapper(env, Detector)
        self.tracker = self  # the batch's tracker arrays, one row
        self.params = self.wrapper.tracker.params
        self.max_tracks = int(self.wrapper.max_tracks)
        self.e = None

    def update(self, engine) -> None:
        """The tracker's state now, for the view ``engine`` of the env (its one row)."""
        mtt = self.wrapper.tracker
        all_tracks = mtt.tracks(include_tentative=True)
        confirmed = np.array([tr.confirmed for tr in mtt._tracks], dtype=bool)
        self.e = engine
        self._tracks, self._shown = all_tracks[None], confirmed[None]
        self.id = mtt.track_ids(include_tentative=True)[None]
        self.n = np.array([len(all_tracks)])
        self.fused_at = np.array([float(mtt._fused_at)])
        self.t_update = np.array([[tr.t_update for tr in mtt._tracks]], dtype=float).reshape(1, -1)
        self.heading = np.array([[tr.heading for tr in mtt._tracks]], dtype=float).reshape(1, -1)
        self.P = np.array([tr.kf.P for tr in mtt._tracks], dtype=float).reshape(1, -1, 4, 4)
        self.last_tracks = self.wrapper._last[None]
        space = self.detector.observation_space[self.detector.key]  # the rows the tracker fused, as the batch has them
        self.last_detections = np.clip(self.detector._rows, space.low, space.high)[None]

    def tracks(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """(1, K, 7) tracks in the tracker's order and which are confirmed (BatchedTracker.tracks' layout)."""
        return self._tracks, self._shown
