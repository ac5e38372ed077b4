"""What the planner on tracks believed about the car it hit (docs/dagger.md, "What sensing costs"): validation
episodes only.

    python benchmarks/belief_tracks_diagnose.py --seeds 1000003 1000017 --set tentative=road_user

Plays each seed with :class:`agents.belief.BeliefPlanner` on ``sensors=turn_perceived`` (``--set``:
BeliefLookaheadParams fields) as ``eval.batched`` drives it. For a collision after a GO, the last GO decision before
it is taken apart for the car hit (the "culprit"): its track against the simulator's vehicle (position, speed,
acceleration, heading, closest lane, the planner's destination probabilities against the true route, the true
set-point and regulation hold), and GO's collision probability again with one attribute of that track replaced by the
simulator's (position and heading, speed, acceleration, lane): which part of the behaviour model made the planner go.
Prints one JSON line per episode, a collision with its ``cause`` (:func:`cause`), and a last line counting the
causes. The choices are the planner's own (``decide``: ``commit``, ``confirm``, ``recheck`` as set). Each record also
has, for each car hit, the road user or left-out track nearest it at the last GO (``held_by``: its distance, whether
left out as a ghost or twin, tentative, its coast in detector frames, its speed and heading error) and the last GO
started's collision probability against the threshold (``go_started``: with the recheck's and the pooled share);
with ``--paths`` the last GO's own futures traced (``predicted``: where they put each car hit at the time of the hit,
how many of them collided, how many with it)."""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/
from belief_tracks_sweep import traced_batch  # noqa: E402  (this folder is sys.path[0] when run as a script)
from belief_tracks_truth import decision_p, nearest_cars  # noqa: E402

# per attribute, the simulator's hidden set-point with the speed: which part of the behaviour model made the planner
# go (belief_tracks_truth's true state, what a filter could know, leaves the set-point the track's speed)
SWAPS = {"pos": ("x", "y", "h"), "v": ("v", "target"), "acc": ("acc",), "lane": ("lane", "tlane", "route0")}


def _swapped(planner, engine, r: int, j: int, i: int, what: tuple, held: int) -> float:
    """GO's collision probability for row ``r`` (holding ``held`` at the decision: belief_tracks_truth.decision_p)
    with the track slot ``j``'s ``what`` replaced by the simulator's vehicle ``i``'s."""
    saved = planner.tracks.engine
    e = copy.copy(saved)
    e.traffic = saved.traffic.subset(np.arange(saved.B))
    t, s = e.traffic, engine.traffic
    for name in what:
        if name == "route0":
            t.route[r, j, 0] = s.lane[r, i]
        else:
            getattr(t, name)[r, j] = getattr(s, name)[r, i]
    planner.tracks.engine = e
    try:
        return float(decision_p(planner, engine, r, held)[0])
    finally:
        planner.tracks.engine = saved


def nearest_track_per_car(matched: dict[int, tuple[int, float]]) -> dict[int, tuple[int, float, int]]:
    """Simulator slot -> (track slot, distance m, tracks matched to that car) from :func:`nearest_cars`' track slot
    -> (simulator slot, distance m): when two tracks share their nearest car (a twin, a ghost) the nearest of them
    speaks for the car, so the error reported is its own (keyed by car, the last track read overwrote the others:
    seed 1,953,064 reported a 79 m error for a car with a track on it)."""
    out: dict[int, tuple[int, float, int]] = {}
    for j, (i, dist) in matched.items():
        best = out.get(i)
        if best is None or dist < best[1]:
            out[i] = (j, dist, 1 if best is None else best[2] + 1)
        else:
            out[i] = (best[0], best[1], best[2] + 1)
    return out


def _snapshot(planner, engine, r: int, held: int) -> dict:
    """Every simulator vehicle of row ``r`` with a road user nearest to it at a GO decision (``held``: the choice it
    held before it): its nearest track against it (``tracks_on_car``: how many tracks it is the nearest car of), and
    GO's collision probability with each attribute swapped for the truth."""
    te = planner.tracks.engine
    t, s = te.traffic, engine.traffic
    out = {}
    for i, (j, dist, shared) in nearest_track_per_car(nearest_cars(te, engine, r)).items():
        probs = planner.turn_probabilities([r], t.vid[[r]])[0, j]
        origin = planner._origin[t.lane[r, j]]
        cand = ((origin + np.array([-1, 2, 1])) % 4).tolist()
        true_dest = int(planner._dest[s.route[r, i, 2]]) if s.route[r, i, 2] >= 0 else -1
        swaps = {k: _swapped(planner, engine, r, j, i, v, held) for k, v in SWAPS.items()}
        swaps["all"] = _swapped(planner, engine, r, j, i, sum(SWAPS.values(), ()), held)
        out[int(s.vid[r, i])] = {
            "track_slot": int(j), "tracks_on_car": shared,
            "pos_err_m": round(dist, 2), "h_err_rad": round(float(np.angle(np.exp(1j * (t.h[r, j] - s.h[r, i])))), 3),
            "v_track": round(float(t.v[r, j]), 2), "v_true": round(float(s.v[r, i]), 2),
            "acc_track": round(float(t.acc[r, j]), 2), "acc_true": round(float(s.acc[r, i]), 2),
            "lane_track": int(t.lane[r, j]), "lane_true": int(s.lane[r, i]), "crashed_track": bool(t.crashed[r, j]),
            "tentative_track": bool(planner.tracks.tent[r, j]),
            "p_dest": {int(c): round(float(p), 2) for c, p in zip(cand, probs)}, "true_dest": true_dest,
            "target_true": round(float(s.target[r, i]), 2), "yielding_true": bool(s.yielding[r, i]),
            "p_swapped": {k: round(v, 3) for k, v in swaps.items()}}
    return out


def _untracked(planner, engine, r: int, radius: float = 4.0) -> dict:
    """The simulator's cars of row ``r`` that no road user of the futures' start is within ``radius`` m of, at a GO:
    where each is (range m and bearing rad from the ego's heading; the kind of its lane, 0 approach, 1 crossing, 2
    exit; its speed), whether a track left out of the futures (a ghost or a twin) is within ``radius`` of it, and
    whether the detector's view of the places as the car knows them (range, field of view, occlusion by the
    confirmed tracks) sees it now (the unseen prior's test)."""
    from agents.track_prior import in_view, lane_kinds

    te, s = planner.tracks.engine, engine.traffic
    t = te.traffic
    users = np.flatnonzero(t.alive[r] & ~t.ego[r])
    left_out = np.flatnonzero(planner.tracks.ghost[r]) if planner.tracks.ghost is not None else np.zeros(0, int)
    e = int(engine.ego_slot([r])[0])
    ex, ey, eh = s.x[r, e], s.y[r, e], s.h[r, e]
    kinds = lane_kinds(engine.T)[0]
    det = planner.tracks.perception.detector.params
    ego = np.array([[t.x[r, 0], t.y[r, 0], t.h[r, 0]]])
    occ = np.stack([t.x[r], t.y[r], t.h[r], np.full(t.N, 5.0), np.full(t.N, 2.0)], axis=-1)[None]
    out = {}
    for i in np.flatnonzero(s.alive[r] & ~s.ego[r]):
        near = lambda slots: bool(len(slots)) and bool(  # noqa: E731
            (np.hypot(t.x[r, slots] - s.x[r, i], t.y[r, slots] - s.y[r, i]) <= radius).any())
        if near(users):
            continue
        seen = in_view(np.array([[s.x[r, i]]]), np.array([[s.y[r, i]]]), ego, occ, (t.alive[r] & ~t.ego[r])[None],
                       float(det.max_range), float(np.radians(det.fov_deg) / 2), bool(det.occlusion))
        out[int(s.vid[r, i])] = {
            "range_m": round(float(np.hypot(s.x[r, i] - ex, s.y[r, i] - ey)), 1),
            "bearing_rad": round(float(np.angle(np.exp(1j * (np.arctan2(s.y[r, i] - ey, s.x[r, i] - ex) - eh)))), 2),
            "lane_kind": int(kinds[s.lane[r, i]]), "v": round(float(s.v[r, i]), 2), "left_out_track": near(left_out),
            "in_view": bool(seen[0, 0])}
    return out


def _held_by(planner, engine, r: int) -> dict:
    """Per simulator car of row ``r`` (its vid) at a decision: the nearest road user of the futures' start or track
    left out of them (a ghost or twin, ``planner.tracks.ghost``) that the planner read, as the planner had it: its
    distance from the car (m), the nearest road user's of the futures (m; a twin kept for the car), the futures' vid
    (the tracker's id + 1), whether it was left out or tentative, its coast (detector frames since a detection last
    updated that track: 0 updated in this frame) and its speed and heading error against the car's (m/s, rad). A
    measurement: it reads the simulator."""
    tb = planner.tracks
    te, s = tb.engine.traffic, engine.traffic
    left_out = tb.ghost[r] if tb.ghost is not None else np.zeros(te.N, bool)
    users = np.flatnonzero((te.alive[r] | left_out) & ~te.ego[r])
    p = tb.perception
    tracker_ids = p.tracker.id[r, : int(p.tracker.n[r])]
    rate = float(p.detector.params.rate_hz)
    out = {}
    for i in np.flatnonzero(s.alive[r] & ~s.ego[r]):
        if not len(users):
            out[int(s.vid[r, i])] = None
            continue
        d = np.hypot(te.x[r, users] - s.x[r, i], te.y[r, users] - s.y[r, i])
        j = int(users[np.argmin(d)])
        k = np.flatnonzero(tracker_ids == int(te.vid[r, j]) - 1)
        coast = int(np.rint((p.tracker.fused_at[r] - p.tracker.t_update[r, k[0]]) * rate)) if len(k) else None
        alive = te.alive[r, users]
        near = float(d[alive].min()) if alive.any() else None  # the nearest road user in the futures (a kept twin)
        out[int(s.vid[r, i])] = {
            "dist_m": round(float(d.min()), 2), "track_vid": int(te.vid[r, j]), "left_out": bool(left_out[j]),
            "road_user_m": None if near is None else round(near, 2),
            "tentative": bool(tb.tent[r, j]), "coast_frames": coast,
            "v_err": round(float(te.v[r, j] - s.v[r, i]), 2),
            "h_err_rad": round(float(np.angle(np.exp(1j * (te.h[r, j] - s.h[r, i])))), 3)}
    return out


def _future_paths(planner, engine, r: int) -> dict:
    """The decision's own K futures of row ``r`` (:meth:`~agents.belief.BeliefPlanner.go_collision`'s: the same
    seeds, the tracks' fill) with GO played to their end as ``play_go_fast`` plays it, traced: the time (s since the
    decision), per policy step each road user's place (vid -> (K, steps, 2) m, NaN where it is gone), and per
    future whether the ego collided and which road users' vids crashed with it."""
    from agents.belief import set_point_meta

    e = planner.tracks.current(engine)
    K = planner.K
    f = planner.futures(e, np.array([r]), K)
    planner.tracks.fill(f, np.array([r]), planner.seed, K)
    top = float(f.speeds[-1])
    live = np.ones(f.B, bool)
    places: dict[int, list] = {}
    steps = 0
    while live.any() and steps < 400:
        _, terminated, truncated = f.step(set_point_meta(f, top), active=live)
        live &= ~(terminated | truncated)
        steps += 1
        t = f.traffic
        for k in range(f.B):
            for j in np.flatnonzero(t.alive[k] & ~t.ego[k]):
                places.setdefault(int(t.vid[k, j]), {}).setdefault(k, {})[steps] = (float(t.x[k, j]),
                                                                                     float(t.y[k, j]))
    t = f.traffic
    ego = f.ego_slot()
    crashed = t.crashed[np.arange(f.B), ego]
    with_ = [sorted(int(v) for v in t.vid[k][t.crashed[k] & t.alive[k] & ~t.ego[k]]) if crashed[k] else []
             for k in range(f.B)]
    dt = 1.0 / float(f.config["policy_frequency"])
    return {"dt": dt, "places": places, "collided": crashed.tolist(), "with": with_}


def _predicted(paths: dict, track_vid: int, elapsed: float, true_xy: tuple) -> dict:
    """Where the futures (``paths``, :func:`_future_paths` at the last GO) put the road user ``track_vid``
    ``elapsed`` s after that GO, against the car's true place ``true_xy`` (m) then: how many futures still hold it
    there, the nearest and median distance (m) of their places from the true one, and in how many futures the ego
    collided, with that road user among those crashed."""
    step = int(round(elapsed / paths["dt"]))
    per = paths["places"].get(int(track_vid), {})
    at = [xy[step] for xy in per.values() if step in xy]
    d = [float(np.hypot(x - true_xy[0], y - true_xy[1])) for x, y in at]
    return {"elapsed_s": round(elapsed, 1), "futures_holding": len(at),
            "nearest_m": round(min(d), 1) if d else None, "median_m": round(float(np.median(d)), 1) if d else None,
            "futures_collided": int(sum(paths["collided"])),
            "futures_hit_by_it": sum(int(track_vid) in w for w in paths["with"])}


def _started(planner, engine, r: int, p: float, now: float) -> dict:
    """A GO started in row ``r`` at ``now`` s, its GO collision probability ``p`` on the decision's K futures: with
    ``recheck`` the recheck's own R futures' (``p_recheck``) and, with ``recheck_pool``, the pooled share decide()
    held against ``threshold``."""
    from agents.belief import RECHECK_STREAM

    K, R = planner.K, int(planner.params.recheck)
    out = {"t_s": round(now, 1), "p": round(p, 4), "threshold": planner.threshold}
    if R > 0:
        p2 = float(planner.go_collision(engine, [r], R, (RECHECK_STREAM,))[0])
        out["p_recheck"] = round(p2, 4)
        out["pooled"] = round((K * p + R * p2) / (K + R), 4) if planner.params.recheck_pool else None
    return out


def _blame(planner, engine, r: int) -> dict:
    """At a GO taken back: GO's collision probability for row ``r`` (judged as a held GO: belief_tracks_truth.
    decision_p) without each road user the planner has (and without the unseen traffic), for those whose removal
    lowers it: which road user made the futures collide."""
    from av_gym.wrappers import GO

    saved, unseen = planner.tracks.engine, planner.tracks.unseen
    base = float(decision_p(planner, engine, r, GO)[0])
    s = engine.traffic
    out = {"p": round(base, 3)}
    planner.tracks.unseen = None
    try:
        out["no_unseen"] = round(float(decision_p(planner, engine, r, GO)[0]), 3)
    finally:
        planner.tracks.unseen = unseen
    matched = nearest_cars(saved, engine, r)
    tent = planner.tracks.tent
    for j in np.flatnonzero(saved.traffic.alive[r] & ~saved.traffic.ego[r]):
        e = copy.copy(saved)
        e.traffic = saved.traffic.subset(np.arange(saved.B))
        e.traffic.alive[r, j] = False
        planner.tracks.engine = e
        try:
            p = float(decision_p(planner, engine, r, GO)[0])
        finally:
            planner.tracks.engine = saved
        if p < base:
            t = saved.traffic
            i, dist = matched.get(int(j), (-1, None))  # None: no simulator vehicle in the row at all
            out[f"slot{int(j)}"] = {"p_without": round(p, 3), "tentative": bool(tent[r, j]),
                                   "true_dist_m": None if dist is None else round(dist, 2),
                                   "v_track": round(float(t.v[r, j]), 2),
                                   "v_true": round(float(s.v[r, i]), 2) if i >= 0 else None,
                                   "acc_track": round(float(t.acc[r, j]), 2), "lane": int(t.lane[r, j]),
                                   "lane_true": int(s.lane[r, i]) if i >= 0 else None,
                                   "stands": bool(t.crashed[r, j]), "true_vid": int(s.vid[r, i]) if i >= 0 else None}
    ghosts = np.flatnonzero(planner.tracks.ghost[r]) if planner.tracks.ghost is not None else []
    out["ghosts"] = len(ghosts)  # tracks left out of the futures (track_prior.TrackBelief._ghosts)
    return out


def _flip(decisions: list, go_s: float) -> bool:
    """Whether the GO decided at ``go_s`` s came right after a decision that found GO unsafe (or was the first)."""
    times = [d[0] for d in decisions]
    k = times.index(round(go_s, 1)) if round(go_s, 1) in times else -1
    return (k == 0 and go_s == 0.0) or (k > 0 and decisions[k - 1][1] != decisions[k][1])


def _blamed(blame: dict) -> str | None:
    """What made GO unsafe at a GO taken back (:func:`_blame`): twin tracks of one car, a track off its car's place
    or lane (the tracker's ghost), a standing track, or real cars (None)."""
    slots = [v for k, v in blame.items() if k.startswith("slot")]
    vids = [v["true_vid"] for v in slots if v["true_vid"] is not None]
    if len(vids) != len(set(vids)):
        return "twin tracks of one car"
    if any(v["true_dist_m"] is None or v["true_dist_m"] > 1.5 or v["lane"] != v["lane_true"] for v in slots):
        return "a track off its car's place or lane"
    if any(v["stands"] for v in slots):
        return "a standing track"
    return None


def cause(record: dict) -> str:
    """One cause per collision, from what the planner believed: hit waiting (no GO), a car without a track at the
    last GO, a track whose true state would have made GO unsafe, what the futures blamed at the GO taken back
    (twins, ghost, standing), a GO right after an unsafe decision taken back, or real cars on good tracks."""
    if record["last_go_s"] is None:
        return "hit waiting (no GO)"
    culprit = record["culprit"] or {}
    if any(v is None for v in culprit.values()):
        return "hit car without a track at the last GO"
    if any(v["p_swapped"]["all"] > 0.05 for v in culprit.values()):
        return "hit car's track off its true state at the last GO"
    after = [b for t, b in record["taken_back"] if t > record["last_go_s"]]
    blamed = _blamed(after[-1]) if after else None
    if blamed:
        return f"GO taken back for {blamed}"
    if after and _flip(record["decisions"], record["last_go_s"]):
        return "GO after an unsafe decision, taken back"
    return "GO taken back for real cars on good tracks" if after else "GO kept"


def main() -> None:
    from av_gym.batched.vec_env import meta_actions
    from av_gym.wrappers import GO, YIELD

    point, params, venv, obs, planner, args = traced_batch(__doc__.splitlines()[0], extra=lambda ap: ap.add_argument(
        "--paths", action="store_true", help="trace the last GO's own futures: where they put each car hit at the "
        "time of the hit, and how many of them collided with it (_future_paths; 16 futures played per GO)"))
    B = venv.num_envs
    engine = venv.engine
    choice, k = np.full(B, YIELD), np.zeros(B, dtype=int)
    history = [[] for _ in range(B)]  # (time s, choice, p) per decision
    last_go = [None] * B
    takeback = [[] for _ in range(B)]  # (time s, _blame) at each GO taken back
    started: list[dict | None] = [None] * B  # the last GO started (_started)
    causes: dict[str, int] = {}
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        planner.read(engine, rows, obs["intent"][rows])
        live, _ = planner.live(engine, rows, choice[rows], k[rows])
        due = rows[live]  # the rows that decide now (confirm_after's early ones too; not those commit made final)
        if len(due):
            before = choice[due].copy()
            p = decision_p(planner, engine, due, before)  # the decision's own draws again: the same p decide() sees
            choice[rows] = planner.decide(engine, rows, choice[rows], k[rows])
            for r, pr, b in zip(due, p, before):
                history[r].append((round(float(engine.time[r]), 1), int(choice[r]), round(float(pr), 3)))
                if choice[r] == GO:
                    last_go[r] = (float(engine.time[r]), _snapshot(planner, engine, int(r), int(b)),
                                  _untracked(planner, engine, int(r)), _held_by(planner, engine, int(r)),
                                  _future_paths(planner, engine, int(r)) if args.paths else None)
                    if b != GO:  # a GO started: its p on the K futures and, asked, the recheck's pooled with it
                        started[r] = _started(planner, engine, int(r), float(pr), float(engine.time[r]))
                        started[r]["held_by"] = last_go[r][3]
            for r, b in zip(due, before):
                if b == GO and choice[r] != GO:
                    takeback[r].append((round(float(engine.time[r]), 1), _blame(planner, engine, int(r))))
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(engine, rows, choice[rows], obs["turn"][rows])
        obs, _, done, infos = venv.step(act)
        for r in np.flatnonzero(done):
            m = infos[r]["episode_metrics"]
            t = engine.traffic
            hit = [int(t.vid[r, j]) for j in np.flatnonzero(t.alive[r] & t.crashed[r] & ~t.ego[r])]
            go = last_go[r]
            record = {"seed": infos[r]["seed"], "collision": bool(m["collision"]), "success": bool(m["success"]),
                      "end_s": round(float(engine.time[r]), 1), "hit": hit,
                      "last_go_s": None if go is None else round(go[0], 1),
                      "culprit": None if go is None else {v: go[1].get(v) for v in hit},
                      "untracked": None if go is None else {v: go[2][v] for v in hit if v in go[2]},
                      "decisions": history[r][-8:], "taken_back": takeback[r][-2:],
                      "go_started": None if started[r] is None else {
                          **started[r], "held_by": {v: started[r]["held_by"].get(v) for v in hit}},
                      "held_by": None if go is None else {v: go[3].get(v) for v in hit}}
            if go is not None and go[4] is not None and m["collision"]:
                record["predicted"] = {
                    v: _predicted(go[4], go[3][v]["track_vid"], float(engine.time[r]) - go[0],
                                  (float(t.x[r, j]), float(t.y[r, j])))
                    for v, j in zip(hit, np.flatnonzero(t.alive[r] & t.crashed[r] & ~t.ego[r]))
                    if go[3].get(v) is not None}
            if record["collision"]:
                record["cause"] = cause(record)
                causes[record["cause"]] = causes.get(record["cause"], 0) + 1
            print(json.dumps(record), flush=True)
    print(json.dumps({"causes": dict(sorted(causes.items(), key=lambda kv: -kv[1]))}), flush=True)


if __name__ == "__main__":
    main()
