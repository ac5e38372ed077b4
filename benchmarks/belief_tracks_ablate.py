"""Where the planner on tracks loses against the planner on truth, part by part (docs/dagger.md, "What sensing costs",
"Where the planner on tracks loses"): validation (screen) episodes only.

    python benchmarks/belief_tracks_ablate.py --seed 1931000 --episodes 500 --truth velocity --out /tmp/v.json
    python benchmarks/belief_tracks_ablate.py --seed 1947000 --truth=all,crash,-velocity --out /tmp/lo.json
    python benchmarks/belief_tracks_ablate.py --table /tmp/none.json /tmp/v.json ...

Plays the episodes with :class:`agents.belief.BeliefPlanner` on ``sensors=turn_perceived`` (``--set``:
BeliefLookaheadParams fields; the preset's options are given there) as ``eval.batched`` drives it, one batch row per
seed, except that after every step's reading and before the decisions the futures' start (``planner.tracks.engine``)
has the sensed quantities named by ``--truth`` replaced by the simulator's (a measurement: it reads the hidden state,
never a policy):

- ``users``: which road users there are. Each simulator vehicle takes the nearest road user the planner has within
  ``--match`` m (confirmed, tentative, or a ghost left out; one track per vehicle, nearest pairs first), kept at its
  tracked state; tracks of no vehicle (twins, ghosts, false ones) are removed; vehicles with no track (unconfirmed,
  missed, out of range, occluded) are added at their true state;
- ``users_missing``, ``users_extra``: each half of ``users`` alone (not in ``all``; ``all,-users,users_missing``):
  the cars without a road user added (a ghost or twin matched to a car brought back), or the road users of no car
  removed;
- ``prior``: the prior over unconfirmed road users (agents/track_prior.py UnseenTraffic) is not added to the futures
  (with ``users`` the truth describes them all; its looks are still counted);
- ``position`` (x, y), ``velocity`` (speed, also as set-point, as a track's), ``heading``, ``acc`` (the measured
  acceleration the behaviour posterior weighs): of each road user matched to a vehicle (as ``users`` matches);
- ``all``: every one of them, and the lane the simulator's.

Besides the sensed parts, two things the planner on truth has that the planner on tracks does not (named on their
own, or with ``all``: ``all,intent,crash`` is everything the truth has):

- ``intent``: the intent filter's indicator readings kept per car, not per track id: each reading the planner takes
  on a described track (``obs["intent"]``) goes to the car that track matches (as ``users`` matches) and, at the
  decision, every matched track (and a car ``users`` added) carries its car's readings, so a re-born track keeps
  them; a track of no car keeps its own;
- ``crash``: each matched road user's (and each added car's) crash flag is the simulator's, instead of the standing
  rule on its speed (a track of no car keeps the rule).

A road user whose pose changed takes the closest lane of its new pose (with position and heading both true, the
simulator's lane); one whose speed or lane changed has the standing rule (``stopped``, ``stopped_scope``) applied
again (with ``crash``: the simulator's flag). Without ``intent`` the intent filter (indicator readings on the
tracks the features describe, by track id) stays the planner's; everything hidden (routes, set-points, IDM draws)
always does. ``none``: the planner as it is (the paired baseline, the same
machinery). Prints and writes (``--out``, a new file) one JSON object: rates, the collided and not-arrived seeds,
and per collision its class: hit waiting (no GO in the episode) or hit after a GO, and the car hit as the planner
had it at the last GO started (or, hit waiting, at the last decision): confirmed / tentative / left out (a ghost or
twin) / unseen (no road user of the futures' start within ``--match`` m). ``--table`` prints the markdown table of
several such files, paired against the first. ``--on-truth``: the planner on the simulator's vehicles (sensors
turn_truth) on the same seeds, the reference the parts add up to. ``--seeds``: these seeds instead (a replay of the
collided ones); ``--why``: per car hit that was not a confirmed road user at that decision, why it was missing
(:class:`SensorHistory`, :func:`why_cause`: never in view, occluded, its tentative track died on a miss, its
confirmed track deleted after coasting, held by the tracker but left out by the planner)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/
from belief_tracks_sweep import fail, planner_point  # noqa: E402  (this folder is sys.path[0] as a script)
from belief_tracks_truth import MATCH_M  # noqa: E402

PARTS = ("users", "prior", "position", "velocity", "heading", "acc")  # the sensed parts (``all``: these and lane)
BESIDES = ("intent", "crash")  # what the truth has besides the sensed parts (not in ``all``; named with it)
HALVES = ("users_missing", "users_extra")  # the two halves of ``users``, each named on its own
ADDED = 100_000  # a car ``users`` adds is road user ADDED + its simulator vid (no track id is that large)


def parts_of(spec: str) -> frozenset:
    """``--truth`` (comma-separated parts of :data:`PARTS` and :data:`BESIDES`, ``all`` or ``none``) as a set of
    parts; ``all`` is every sensed part and the simulator's lane (``all,intent,crash``: everything the truth has).
    A part after a ``-`` is taken out of ``all`` (``all,crash,-velocity``: a leave-one-out; without ``all`` it is
    refused); taking out ``position`` or ``heading`` takes out the simulator's lane too (it is the lane of
    the true pose), ``-lane`` the lane alone."""
    names = [s for s in spec.split(",") if s]
    drop = {s[1:] for s in names if s.startswith("-")}
    names = [s for s in names if not s.startswith("-")]
    bad = [s for s in names if s not in PARTS + BESIDES + HALVES + ("all", "none")]
    bad += [f"-{s}" for s in drop if s not in PARTS + BESIDES + ("lane",)]
    if bad or not names:
        fail(f"--truth takes a comma list of {', '.join(PARTS + BESIDES + HALVES)}, all or none, and -part to "
             f"take one of them out; got {spec!r}")
    out = {n for n in names if n not in ("all", "none")}
    if "all" in names:
        out |= set(PARTS) | {"lane"}
    if drop and "all" not in names:  # a leave-one-out is of all; naming a part and taking it out names nothing
        fail(f"--truth {spec!r}: -part takes a part out of all (e.g. all,crash,-velocity)")
    if drop & {"position", "heading"}:
        drop = drop | {"lane"}
    return frozenset(out - drop)


def match_users(te, engine, r: int, radius: float, left_out: np.ndarray) -> dict[int, int]:
    """Simulator slot -> track slot for row ``r``: each vehicle (ego excluded) the nearest road user of the
    futures' start ``te`` (alive, or left out: ``left_out`` (N,) its ghosts and twins) within ``radius`` m, one
    track per vehicle, nearest pairs first."""
    t, s = te.traffic, engine.traffic
    cars = np.flatnonzero(s.alive[r] & ~s.ego[r])
    users = np.flatnonzero((t.alive[r] | left_out) & ~t.ego[r])
    if not len(cars) or not len(users):
        return {}
    d = np.hypot(s.x[r, cars][:, None] - t.x[r, users][None], s.y[r, cars][:, None] - t.y[r, users][None])
    out: dict[int, int] = {}
    taken: set[int] = set()
    for flat in np.argsort(d, axis=None, kind="stable"):
        a, b = divmod(int(flat), len(users))
        if d[a, b] > radius:
            break
        if int(cars[a]) not in out and int(users[b]) not in taken:
            out[int(cars[a])] = int(users[b])
            taken.add(int(users[b]))
    return out


def standing(params, T, lane_kind: np.ndarray, lane, x, y, v) -> np.ndarray:
    """The planner's standing rule (agents/track_prior.py TrackBelief._observed) for road users at lanes ``lane``,
    places ``x``, ``y`` (m) and speeds ``v`` (m/s): slower than ``stopped``, with ``stopped_scope`` off_approach
    only off the approach lanes and the crossing lanes' first LINE_ZONE m."""
    from agents.track_prior import LINE_ZONE

    out = np.asarray(v) < float(params.stopped)
    if params.stopped_scope == "off_approach":
        along, _ = T.local(lane, x, y)
        kind = lane_kind[lane]
        out &= ~((kind == 0) | ((kind == 1) & (along < LINE_ZONE)))
    return out


def all_pairs(planner, engine, rows: np.ndarray, radius: float) -> dict[int, dict[int, int]]:
    """Per row of ``rows``, :func:`match_users` on the futures' start as the planner read it (before any part is
    given from the truth)."""
    tb = planner.tracks
    te = tb.engine
    out = {}
    for r in rows:
        r = int(r)
        left_out = tb.ghost[r] if tb.ghost is not None else np.zeros(te.traffic.N, bool)
        out[r] = match_users(te, engine, r, radius, left_out)
    return out


def with_truth(planner, engine, rows: np.ndarray, parts: frozenset, radius: float,
               pairs_of: dict[int, dict[int, int]] | None = None) -> None:
    """The futures' start of ``rows`` (``planner.tracks.engine``) with ``parts`` the simulator's, in place
    (``pairs_of``: :func:`all_pairs` of this reading, computed here when not given; ``intent`` is
    :class:`CarReadings`', not this)."""
    tb = planner.tracks
    te = tb.engine
    t, s, T = te.traffic, engine.traffic, engine.T
    state = parts & {"position", "velocity", "heading", "acc", "lane"}
    if pairs_of is None:
        pairs_of = all_pairs(planner, engine, rows, radius)
    for r in rows:
        r = int(r)
        pairs = pairs_of[r]
        left_out = tb.ghost[r] if tb.ghost is not None else np.zeros(t.N, bool)
        changed: list[int] = []
        added: dict[int, int] = {}  # simulator slot -> the slot ``users`` added it in
        missing = bool(parts & {"users", "users_missing"})
        if missing or parts & {"users", "users_extra"}:
            keep = np.zeros(t.N, bool)
            keep[list(pairs.values())] = True
            if missing:  # a ghost or twin matched to a car is that car's road user again
                t.alive[r] |= left_out & keep
            if parts & {"users", "users_extra"}:  # the road users of no car go
                t.alive[r] &= keep | t.ego[r]
        if missing:
            for i in np.flatnonzero(s.alive[r] & ~s.ego[r]):
                if int(i) in pairs:
                    continue
                free = np.flatnonzero(~t.alive[r] & ~t.ego[r])
                if not len(free):
                    t.grow(1)
                    for name in ("tent", "ghost"):
                        setattr(tb, name, np.concatenate([getattr(tb, name), np.zeros((te.B, 1), bool)], 1))
                    # the filter's covariance per slot (track_spread): a car from the truth has no error
                    tb.along = np.concatenate([tb.along, np.zeros((te.B, 1, 2, 2))], 1)
                    free = [t.N - 1]
                j = int(free[0])
                for name in ("x", "y", "h", "v", "acc", "lane", "tlane"):
                    getattr(t, name)[r, j] = getattr(s, name)[r, i]
                t.target[r, j] = max(float(s.v[r, i]), 0.0)
                t.route[r, j] = -1
                t.route[r, j, 0] = s.lane[r, i]
                t.alive[r, j], t.plain[r, j], t.yielding[r, j], t.mdp[r, j] = True, False, False, False
                t.rpos[r, j], t.vid[r, j] = 0, ADDED + int(s.vid[r, i])  # no reading attached (intent: its car's)
                t.delta[r, j] = 4.0
                tb.tent[r, j], tb.ghost[r, j] = False, False
                changed.append(j)
                added[int(i)] = j
        if state:
            for i, j in pairs.items():
                if not t.alive[r, j]:
                    continue
                if "position" in parts:
                    t.x[r, j], t.y[r, j] = s.x[r, i], s.y[r, i]
                if "heading" in parts:
                    t.h[r, j] = s.h[r, i]
                if "velocity" in parts:
                    t.v[r, j], t.target[r, j] = s.v[r, i], max(float(s.v[r, i]), 0.0)
                if "acc" in parts:
                    t.acc[r, j] = s.acc[r, i]
                if "lane" in parts:
                    t.lane[r, j] = t.tlane[r, j] = t.route[r, j, 0] = s.lane[r, i]
                elif parts & {"position", "heading"}:
                    t.lane[r, j] = t.tlane[r, j] = t.route[r, j, 0] = T.closest(
                        np.array([t.x[r, j]]), np.array([t.y[r, j]]), np.array([t.h[r, j]]))[0]
                changed.append(j)
        if changed and (parts - {"acc", "prior", "intent", "crash"}):
            j = np.array(changed)
            t.crashed[r, j] = standing(planner.params, T, tb.lane_kind, t.lane[r, j], t.x[r, j], t.y[r, j], t.v[r, j])
        if "crash" in parts:
            for i, j in list(pairs.items()) + list(added.items()):
                if t.alive[r, j]:
                    t.crashed[r, j] = s.crashed[r, i]


class CarReadings:
    """``intent``: the planner's indicator readings kept per simulator car rather than per track id. Around each
    :meth:`BeliefPlanner.read`, :meth:`before` and :meth:`after` move what the read added to each described track
    (its readings' counts) to the car the track matches; :meth:`lend` gives the planner, for its decision, counts
    in which every matched track (and every car ``users`` added) carries its car's; :meth:`restore` puts the
    planner's own per-track counts back before the next read."""

    def __init__(self, n_rows: int) -> None:
        self.cars: list[dict[int, np.ndarray]] = [{} for _ in range(n_rows)]  # per row: simulator vid -> counts
        self.own: list[dict[int, np.ndarray]] = [{} for _ in range(n_rows)]  # per row: the planner's own counts
        self._was: dict[int, dict[int, np.ndarray]] = {}

    def before(self, planner, rows: np.ndarray) -> None:
        """Just before the read of ``rows``: what the planner's own counts hold."""
        self._was = {int(r): {v: c.copy() for v, c in planner.counts[r].items()} for r in rows}

    def after(self, planner, engine, rows: np.ndarray, pairs_of: dict[int, dict[int, int]]) -> None:
        """Just after the read, before any part is given from the truth: each track's new readings to its car."""
        te, s = planner.tracks.engine.traffic, engine.traffic
        for r in rows:
            r = int(r)
            self.own[r] = planner.counts[r]
            car_of = {int(te.vid[r, j]): int(s.vid[r, i]) for i, j in pairs_of[r].items()}
            was = self._was.get(r, {})
            for v, c in planner.counts[r].items():
                new = c - was.get(v, 0)
                if v in car_of and new.any():
                    self.cars[r].setdefault(car_of[v], np.zeros(3, dtype=int))[:] += new

    def lend(self, planner, engine, rows: np.ndarray, pairs_of: dict[int, dict[int, int]]) -> None:
        """For the decision of ``rows`` (after the truth's parts): the per-car counts on the road users."""
        te, s = planner.tracks.engine.traffic, engine.traffic
        for r in rows:
            r = int(r)
            counts = dict(self.own[r])
            for i, j in pairs_of[r].items():
                counts.pop(int(te.vid[r, j]), None)
            for i, j in pairs_of[r].items():
                if te.alive[r, j] and int(te.vid[r, j]) < ADDED:
                    car = self.cars[r].get(int(s.vid[r, i]))
                    if car is not None:
                        counts[int(te.vid[r, j])] = car
            for j in np.flatnonzero(te.alive[r] & (te.vid[r] >= ADDED)):
                car = self.cars[r].get(int(te.vid[r, j]) - ADDED)
                if car is not None:
                    counts[int(te.vid[r, j])] = car
            planner.counts[r] = counts

    def restore(self, planner, rows: np.ndarray) -> None:
        """The planner's own per-track counts back (its next read adds to them)."""
        for r in rows:
            planner.counts[int(r)] = self.own[int(r)]


def statuses(planner, engine, rows: np.ndarray, radius: float) -> dict[int, dict[int, str]]:
    """Per row, simulator vid -> how the planner had that car at this decision: the nearest road user within
    ``radius`` m of it confirmed, tentative, remembered (``recall``: agents/track_memory.py), left out (a ghost or
    twin), or none (unseen)."""
    tb = planner.tracks
    t, s = tb.engine.traffic, engine.traffic
    out = {}
    for r in rows:
        r = int(r)
        left_out = tb.ghost[r] if tb.ghost is not None else np.zeros(t.N, bool)
        users = np.flatnonzero((t.alive[r] | left_out) & ~t.ego[r])
        row = {}
        for i in np.flatnonzero(s.alive[r] & ~s.ego[r]):
            d = np.hypot(t.x[r, users] - s.x[r, i], t.y[r, users] - s.y[r, i]) if len(users) else np.zeros(0)
            if not len(d) or d.min() > radius:
                row[int(s.vid[r, i])] = "unseen"
                continue
            j = int(users[np.argmin(d)])
            kept = getattr(tb, "remembered", None)
            row[int(s.vid[r, i])] = ("left out" if left_out[j] and not t.alive[r, j] else
                                     "remembered" if kept is not None and kept[r, j] else
                                     "tentative" if tb.tent[r, j] else "confirmed")
        out[r] = row
    return out


WHY_DET_M = 2.5  # m: a detection within this of a car's true place is that car's (the detector's sd <= 1.1 m)


class SensorHistory:
    """``--why``: per row, per simulator vid, one entry per detector frame the tracker fused: [time s, view (0 out of
    range or field of view, 1 occluded, 2 in view: the detector's own view), detected (a detection within
    :data:`WHY_DET_M`), the tracker's track within ``radius`` m (0 none, 1 tentative, 2 confirmed) and its id, the
    planner's status (:func:`statuses`), range m, lane kind (0 approach, 1 crossing, 2 exit)]. A measurement: it
    reads the simulator, never a policy."""

    def __init__(self, n_rows: int, radius: float) -> None:
        self.log: list[dict[int, list]] = [{} for _ in range(n_rows)]
        self.tracks: list[dict[float, frozenset]] = [{} for _ in range(n_rows)]  # per frame (s): the tracker's ids
        self.radius = radius

    def frame(self, planner, engine, rows: np.ndarray) -> None:
        from av_gym.batched.perception import others_state

        p, tb = planner.tracks.perception, planner.tracks
        now = now_of(engine, rows)
        fused = np.abs(p.tracker.fused_at[rows] - now) < 1e-9
        rows, now = rows[fused], now[fused]
        if not len(rows):
            return
        t = engine.traffic
        slot = engine.ego_slot(rows)
        ego = np.stack([t.x[rows, slot], t.y[rows, slot], t.h[rows, slot]], axis=1)
        others, vids, off = others_state(engine, rows)
        rng, in_view, hidden = p.detector._views(ego, others, off) if len(others) else (np.zeros(0),) * 3
        st = statuses(planner, engine, rows, self.radius)
        tracks, shown = p.tracker.tracks(rows)
        for b, r in enumerate(rows.tolist()):
            live = np.arange(tracks.shape[1]) < p.tracker.n[r]
            det = p.last_detections[r]
            det = det[det[:, 0] > 0]
            t_frame = round(float(now[b]), 2)
            self.tracks[r][t_frame] = frozenset(p.tracker.id[r, : len(live)][live].tolist())
            for i in range(off[b], off[b + 1]):
                v = int(vids[i])
                x, y = others[i, 0], others[i, 1]
                seen = bool(len(det)) and float(np.hypot(det[:, 1] - x, det[:, 2] - y).min()) <= WHY_DET_M
                d = np.where(live, np.hypot(tracks[b, :, 0] - x, tracks[b, :, 1] - y), np.inf)
                k = int(np.argmin(d)) if len(d) else -1
                held = k >= 0 and d[k] <= self.radius
                kind = (2 if shown[b, k] else 1) if held else 0
                lane = engine.T.closest(np.array([x]), np.array([y]), np.array([others[i, 4]]))[0]
                self.log[r].setdefault(v, []).append([
                    t_frame, 0 if not in_view[i] else 1 if hidden[i] else 2, seen, kind,
                    int(p.tracker.id[r, k]) if held else -1, st[r].get(v, "?"), round(float(rng[i]), 1),
                    int(tb.lane_kind[lane])])

    def why(self, r: int, vid: int, t_go: float) -> dict:
        """The cause the car ``vid`` of row ``r`` was not a confirmed road user of the planner at ``t_go`` (s, the
        last GO started or the last decision): its frames up to then, summarised (:func:`why_cause`)."""
        h = [e for e in self.log[r].get(vid, []) if e[0] <= t_go + 1e-9]
        return why_cause(h, self.tracks[r].get(h[-1][0], frozenset()) if h else frozenset())


def now_of(engine, rows):
    """The clock (s) of row ``rows`` (an int) or of each of ``rows`` (an array)."""
    return engine.ticks[rows] / engine.config["simulation_frequency"]


def why_cause(h: list, track_ids: frozenset = frozenset()) -> dict:
    """One cause from a car's frames ``h`` (SensorHistory entries up to the decision): ``never in view`` (out of
    range or field of view at every frame; ``occluded`` where it was at some), else at the decision's frame ``not in
    view now`` with the track it last had (``confirmed deleted`` / ``confirmed drifted off`` / ``tentative died`` /
    ``tentative drifted off`` / ``never tracked``) or, in view, ``tentative died`` (its last tracker track tentative
    and gone: deleted on a miss, its next detection a new track), ``tentative drifted off`` (that tentative track's
    id still among ``track_ids``, more than the match radius off the car), ``confirmed deleted`` (its last confirmed
    track's id not among ``track_ids``, the tracker's at the last frame of ``h``), ``confirmed drifted off`` (that
    track still held, more than the match radius off the car), ``held, not a road user`` (a track within the match
    radius of it at that frame, in view or not now, and the planner has it as nobody: ghost, twin, off by more than
    the match radius), ``never tracked``; with the frames since it was last in view, detected, held by a track, and
    its range and lane kind at the decision."""
    if not h:
        return {"cause": "not on the map"}
    last = h[-1]
    ever_view = [e for e in h if e[1] == 2]
    tracked = [e for e in h if e[3] > 0]
    conf = [e for e in h if e[3] == 2]
    out = {"status": last[5], "range_m": last[6], "lane_kind": last[7], "frames": len(h),
           "in_view_frames": len(ever_view), "detected_frames": sum(bool(e[2]) for e in h),
           "tracked_frames": len(tracked), "confirmed_frames": len(conf),
           "since_in_view_s": round(last[0] - ever_view[-1][0], 1) if ever_view else None,
           "since_tracked_s": round(last[0] - tracked[-1][0], 1) if tracked else None}
    # the car's last track of the kind it reached: gone from the tracker at the decision's frame (deleted; a
    # tentative one on its first miss: died), or still held there, more than the match radius off the car
    had = ("confirmed drifted off" if conf[-1][4] in track_ids else "confirmed deleted") if conf else \
        ("tentative drifted off" if tracked[-1][4] in track_ids else "tentative died") if tracked else \
        "never tracked"
    if not ever_view:
        cause = "never in view: occluded" if any(e[1] == 1 for e in h) else "never in view: out of range/fov"
    elif last[3] > 0:  # a track within the match radius of the car at the decision's frame, in view or not
        now = "" if last[1] == 2 else f"not in view now ({'occluded' if last[1] == 1 else 'out of range/fov'}), "
        cause = f"{now}held by the tracker, not a road user of the planner"
    elif last[1] != 2:
        cause = f"not in view now ({'occluded' if last[1] == 1 else 'out of range/fov'}), {had}"
    else:
        cause = f"in view, {had}"
    out["cause"] = cause
    return out


def collision_record(engine, r: int, seed: int, went: bool, known: dict, history, t_at: float) -> dict:
    """The collision of row ``r`` (episode ``seed``): its class (hit after a GO, or waiting), each car hit as the
    planner had it (``known``: at the last GO started, or at the last decision) and, with ``history`` (``--why``),
    why each car hit that was not a confirmed road user was missing at ``t_at`` (s)."""
    tr = engine.traffic
    hit = [int(tr.vid[r, j]) for j in np.flatnonzero(tr.alive[r] & tr.crashed[r] & ~tr.ego[r])]
    record = {"seed": seed, "class": "after GO" if went else "waiting",
              "hit": {v: known.get(v, "not on the map") for v in hit}}
    if history is not None:
        record["why"] = {v: history.why(r, v, t_at) for v in hit if known.get(v) != "confirmed"}
        record["t_decision"] = round(t_at, 2)
    return record


def play(args, parts: frozenset) -> dict:
    """The episodes of ``args`` with ``parts`` the simulator's (:func:`with_truth`): the JSON object."""
    from agents.belief import BeliefPlanner
    from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
    from av_gym.presets import compose_group
    from av_gym.wrappers import GO, YIELD

    point, params = planner_point(args.set)
    seeds = list(args.seeds) if getattr(args, "seeds", None) else list(range(args.seed, args.seed + args.episodes))
    t0, c0 = time.time(), time.process_time()
    B = len(seeds)
    sensors = "turn_truth" if args.on_truth else "turn_perceived"
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, compose_group("sensors", sensors), None, B, pool=0)
    obs = venv.play(iter(seeds))
    planner = BeliefPlanner(params, n_rows=B, perception=None if args.on_truth else venv.perception)
    planner.reset(np.arange(B))
    engine = venv.engine
    choice, k = np.full(B, YIELD), np.zeros(B, dtype=int)
    went = np.zeros(B, bool)
    at_go: list[dict] = [{} for _ in range(B)]  # the cars as the planner had them at the last GO started
    at_last: list[dict] = [{} for _ in range(B)]  # ... at the last decision
    episodes, collisions = [], []
    readings = CarReadings(B) if "intent" in parts else None
    history = SensorHistory(B, args.match) if getattr(args, "why", False) else None
    t_at = np.zeros(B)  # s: the last GO started (or, without one, the last decision)
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        if readings is not None:
            readings.before(planner, rows)
        planner.read(engine, rows, obs["intent"][rows])
        if history is not None:
            history.frame(planner, engine, rows)
        if parts:
            pairs_of = all_pairs(planner, engine, rows, args.match)
            if readings is not None:
                readings.after(planner, engine, rows, pairs_of)
            with_truth(planner, engine, rows, parts, args.match, pairs_of)
            if readings is not None:
                readings.lend(planner, engine, rows, pairs_of)
        due = rows[planner.live(engine, rows, choice[rows], k[rows])[0]]
        before = choice.copy()
        unseen = planner.tracks.unseen if planner.tracks is not None else None
        if "prior" in parts:
            planner.tracks.unseen = None  # its looks go on at read(); only the futures go without it
        try:
            choice[rows] = planner.decide(engine, rows, choice[rows], k[rows])
        finally:
            if planner.tracks is not None:
                planner.tracks.unseen = unseen
            if readings is not None:
                readings.restore(planner, rows)
        if len(due):
            st = statuses(planner, engine, due, args.match) if planner.tracks is not None else {}
            for r in due:
                at_last[r] = st.get(int(r), {})
                if not went[r]:
                    t_at[r] = now_of(engine, r)
                if choice[r] == GO and before[r] != GO:
                    at_go[r], went[r] = at_last[r], True
                    t_at[r] = now_of(engine, r)
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(engine, rows, choice[rows], obs["turn"][rows])
        obs, _, done, infos = venv.step(act)
        for r in np.flatnonzero(done):
            m = infos[r]["episode_metrics"]
            episodes.append((int(infos[r]["seed"]), bool(m["collision"]), bool(m["success"])))
            if m["collision"]:
                known = at_go[r] if went[r] else at_last[r]
                collisions.append(collision_record(engine, int(r), int(infos[r]["seed"]), bool(went[r]), known,
                                                   history, float(t_at[r])))
    n = len(episodes)
    return {"point": point, "truth": ["planner on truth"] if args.on_truth else sorted(parts), "match_m": args.match,
            "episodes": n, "seed": args.seed, "seeds": seeds, "collision": sum(c for _, c, _ in episodes) / n,
            "success": sum(s for _, _, s in episodes) / n,
            "collided": sorted(s for s, c, _ in episodes if c),
            "not_arrived": sorted(s for s, _, a in episodes if not a), "collisions": collisions,
            "wall_s": round(time.time() - t0, 1), "cpu_s": round(time.process_time() - c0, 1),
            "load": os.getloadavg()[0]}


def played(run: dict) -> set[int]:
    """The seeds a :func:`play` result ran: its ``seeds`` (``--seeds`` may scatter them), or, in a file written
    before that field, ``seed`` .. ``seed + episodes - 1``."""
    if "seeds" in run:
        return set(run["seeds"])
    return set(range(run["seed"], run["seed"] + run["episodes"]))


def table(paths: list[str]) -> str:
    """The markdown table of ablation results ``paths`` (JSON objects of :func:`play`), paired against the first:
    collisions, success, the collisions only there / only in the first, and the collided episodes' classes."""
    runs = [json.loads(Path(p).read_text()) for p in paths]
    base = runs[0]
    lines = ["| truth | collision | success | collided only here / only at the first | arrived only here / only "
             "there | hit waiting / after a GO | car hit at the decision (conf / tent / left out / unseen) |",
             "|---|---|---|---|---|---|---|"]
    for run in runs:
        c, c0 = set(run["collided"]), set(base["collided"])
        a, a0 = played(run) - set(run["not_arrived"]), played(base) - set(base["not_arrived"])
        cls = [x["class"] for x in run["collisions"]]
        hit = [v for x in run["collisions"] for v in x["hit"].values()]
        kinds = "/".join(str(hit.count(k)) for k in ("confirmed", "tentative", "left out", "unseen"))
        lines.append(f"| {','.join(run['truth']) or 'none'} | {run['collision']:.3f} | {run['success']:.3f} | "
                     f"{len(c - c0)} / {len(c0 - c)} | {len(a - a0)} / {len(a0 - a)} | "
                     f"{cls.count('waiting')} / {cls.count('after GO')} | {kinds} |")
    return "\n".join(lines)


def main() -> None:
    from av_gym.seeds import SPLITS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1_931_000)
    ap.add_argument("--episodes", type=int, default=500)
    ap.add_argument("--truth", default="none",
                    help=f"comma list of {', '.join(PARTS + BESIDES + HALVES)}, all or none; -part takes one out")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--on-truth", action="store_true", help="the planner on the simulator's vehicles (sensors "
                    "turn_truth; --truth none): the reference, on the same seeds")
    ap.add_argument("--match", type=float, default=MATCH_M, metavar="M", help="match radius (m), > 0")
    ap.add_argument("--out", default=None, metavar="PATH", help="the JSON object besides (a new file)")
    ap.add_argument("--table", nargs="+", default=None, metavar="PATH", help="print the table of these results")
    ap.add_argument("--seeds", nargs="+", type=int, default=None, help="these validation seeds instead of --seed / "
                    "--episodes (a replay of collided ones)")
    ap.add_argument("--why", action="store_true", help="per collision with a car that was not a confirmed road user "
                    "of the planner, why it was missing (SensorHistory: the car's frames in view, detected, tracked)")
    args = ap.parse_args()
    if args.table:
        print(table(args.table))
        return
    from av_gym.atomic import new_paths_or_exit

    new_paths_or_exit((args.out, "--out"))  # before the run: a taken path loses none of it
    if args.episodes < 1 or not (args.match > 0):
        fail("--episodes must be >= 1 and --match > 0 (m)")
    if args.seeds:
        if any(x not in SPLITS["validation"] for x in args.seeds) or len(set(args.seeds)) != len(args.seeds):
            fail(f"--seeds must be distinct seeds of the validation split {SPLITS['validation']}")
        args.seed, args.episodes = min(args.seeds), len(args.seeds)
    elif args.seed not in SPLITS["validation"] or args.seed + args.episodes - 1 not in SPLITS["validation"]:
        fail(f"--seed/--episodes must stay in the validation split {SPLITS['validation']}")
    parts = parts_of(args.truth)
    if args.on_truth and parts:
        fail("--on-truth takes --truth none (its road users are the simulator's)")
    result = play(args, parts)
    text = json.dumps(result)
    print(text)  # first: a refused --out below loses no run
    if args.out:  # linked into place: a file that appeared at --out since the check above is kept, not replaced
        from av_gym.atomic import write_new_or_exit

        write_new_or_exit(args.out, text + "\n", "--out")


if __name__ == "__main__":
    main()
