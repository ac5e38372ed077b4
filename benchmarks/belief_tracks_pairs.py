"""The (ego, car) pair as the real regulation and the held GO's futures see it, step by step up to the takeback
(docs/dagger.md, "Where the target stands"): validation episodes only.

    python benchmarks/belief_tracks_pairs.py --seeds 1953999 1963261 --set tentative=road_user ghost=2

Plays each seed as benchmarks/belief_tracks_takeback.py does (the planner's own choices). At every decision that
holds GO it keeps the decision's own K futures and steps them beside the real episode (GO's set-point, as
play_go_fast plays it), env step by env step. At a decision that takes the GO back it prints, for each road user
blamed (benchmarks/belief_tracks_diagnose.py's ``_blame``), its track at the held GO's start (lane, lane kind, how
far along it, speed, whether the standing rule held it: ``crashed``, the nearest other road user of the start) and
per env step since then the real car nearest the track now and the futures' road user of the track's id: speed,
acceleration, lane and its priority, route and its position, set-point, yielding, crashed, the ego's lane and
priority, the regulation's conflict test on the pair at that state (Traffic._predict, the engine's pair test) and
whom respect_priorities would hold, the road's step count (the regulation's phase); the futures' as the share or
mean over the K. Hypotheses it tells apart: the futures place the car on another lane or priority, predict it
otherwise, tick the regulation at another phase, or hold it otherwise. A measurement: it reads the simulator.
Prints one JSON line per takeback, then one per episode."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/
from belief_tracks_diagnose import _blame  # noqa: E402  (this folder is sys.path[0] when run as a script)
from belief_tracks_sweep import decide_due, traced_batch  # noqa: E402
from belief_tracks_takeback import _futures  # noqa: E402
from belief_tracks_truth import nearest_cars  # noqa: E402


def pair_test(t, b: int, ego: int, car: int) -> tuple[bool, str]:
    """The regulation's test on the pair (``ego``, ``car``) of row ``b`` of traffic ``t`` now: whether their
    constant-speed predictions along their routes conflict (Traffic._predict, batched._conflicts) and whom
    respect_priorities would hold (the lower lane priority; at equal priority the one behind): "ego" or "car"."""
    from av_gym.sim import batched

    px, py, ph = t._predict(np.array([b]))
    live = np.zeros((1, t.N), bool)
    live[0, [ego, car]] = True
    i, j = min(ego, car), max(ego, car)
    conflict = bool(batched._conflicts(px, py, ph, live)[0, i, j])
    p1, p2 = t.tables.priority[t.lane[b, i]], t.tables.priority[t.lane[b, j]]
    if p1 != p2:
        held = j if p1 > p2 else i
    else:  # the vehicle behind yields: front_distance_to
        dx, dy = t.x[b, j] - t.x[b, i], t.y[b, j] - t.y[b, i]
        fi = np.cos(t.h[b, i]) * dx + np.sin(t.h[b, i]) * dy
        fj = -(np.cos(t.h[b, j]) * dx + np.sin(t.h[b, j]) * dy)
        held = i if fi > fj else j
    return conflict, "car" if held == car else "ego"


def pair_state(t, b: int, car: int, ego: int) -> dict:
    """Road user ``car`` of row ``b`` of traffic ``t`` beside the ego ``ego``: the fields the regulation reads."""
    conflict, held = pair_test(t, b, ego, car)
    prio = t.tables.priority
    return {"v": round(float(t.v[b, car]), 2), "acc": round(float(t.acc[b, car]), 2), "lane": int(t.lane[b, car]),
            "prio": int(prio[t.lane[b, car]]), "route": [int(k) for k in t.route[b, car]], "rpos": int(t.rpos[b, car]),
            "target": round(float(t.target[b, car]), 2), "yielding": bool(t.yielding[b, car]),
            "crashed": bool(t.crashed[b, car]), "ego_lane": int(t.lane[b, ego]), "ego_prio": int(prio[t.lane[b, ego]]),
            "ego_v": round(float(t.v[b, ego]), 2), "conflict": conflict, "held": held,
            "road_steps": int(t.road_steps[b])}


def _slot(t, b: int, vid: int) -> int | None:
    j = np.flatnonzero(t.alive[b] & (t.vid[b] == vid))
    return int(j[0]) if len(j) else None


def _ego(t, b: int) -> int:
    return int(np.flatnonzero(t.alive[b] & t.ego[b])[0])


def start_state(engine, start, r: int, j: int, kind: np.ndarray) -> dict:
    """Track slot ``j`` of row ``r`` in the held GO's start ``start`` (traffic): its pair state, lane kind, how far
    along its lane (m) and the nearest other road user of the start (m; None: none)."""
    out = pair_state(start, r, j, _ego(start, r))
    along, _ = engine.T.local(start.lane[r, [j]], start.x[r, [j]], start.y[r, [j]])
    others = np.flatnonzero(start.alive[r] & ~start.ego[r] & (np.arange(start.N) != j))
    d = np.hypot(start.x[r, others] - start.x[r, j], start.y[r, others] - start.y[r, j])
    out.update(kind=int(kind[start.lane[r, j]]), along_m=round(float(along[0]), 2),
               nearest_user_m=round(float(d.min()), 2) if len(d) else None)
    return out


def futures_state(ft, vid: int) -> dict | None:
    """The futures' road user ``vid`` over the K rows of ``ft``: the share or mean of each pair field."""
    rows = [(k, _slot(ft, k, vid)) for k in range(ft.B)]
    states = [pair_state(ft, k, a, _ego(ft, k)) for k, a in rows if a is not None]
    if not states:
        return None
    mean = {key: round(float(np.mean([s[key] for s in states])), 3)
            for key in ("v", "acc", "target", "yielding", "crashed", "conflict", "ego_v", "road_steps")}
    mean.update(n=len(states), lanes=sorted({s["lane"] for s in states}), prio=sorted({s["prio"] for s in states}),
                routes=sorted({tuple(s["route"]) for s in states}), rpos=sorted({s["rpos"] for s in states}),
                held_car=round(float(np.mean([s["held"] == "car" for s in states])), 3))
    return mean


def report(planner, engine, r: int, kept: dict, seed: int, kind: np.ndarray) -> dict:
    """The record of a GO of row ``r`` taken back now; ``kept``: the held GO's start, its futures and the real
    traffic at every env step since."""
    blame = _blame(planner, engine, r)
    te = planner.tracks.engine.traffic
    matched = nearest_cars(planner.tracks.engine, engine, r)
    out = {"seed": seed, "t_s": round(float(engine.time[r]), 1), "go_s": round(kept["t0"], 1), "p": blame["p"],
           "blamed": []}
    for j in sorted(int(k[4:]) for k in blame if k.startswith("slot")):
        vid = int(te.vid[r, j])
        i, dist = matched.get(j, (-1, None))
        car_vid = int(engine.traffic.vid[r, i]) if i >= 0 else None
        j0 = _slot(kept["start"], r, vid)
        rec = {"vid": vid, "car_dist_m": None if dist is None else round(dist, 2),
               "start": None if j0 is None else start_state(engine, kept["start"], r, j0, kind), "steps": []}
        for step, (real, ft) in enumerate(zip(kept["real"], kept["futures"])):
            c = None if car_vid is None else _slot(real, r, car_vid)
            rec["steps"].append({"step": step, "real": None if c is None else pair_state(real, r, c, _ego(real, r)),
                                 "futures": futures_state(ft, vid)})
        out["blamed"].append(rec)
    return out


def main() -> None:
    from agents.belief import set_point_meta
    from agents.track_prior import lane_kinds
    from av_gym.batched.vec_env import meta_actions
    from av_gym.wrappers import GO, YIELD

    point, params, venv, obs, planner, args = traced_batch(__doc__.splitlines()[0])
    B, engine = venv.num_envs, venv.engine
    kind = lane_kinds(engine.T)[0]
    choice, k = np.full(B, YIELD), np.zeros(B, dtype=int)
    kept: list = [None] * B
    everyone = np.arange(B)
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        due, before = decide_due(planner, engine, obs, rows, choice, k)
        if len(due):
            for r, b in zip(due, before):
                r = int(r)
                if b == GO and choice[r] != GO and kept[r] is not None:
                    print(json.dumps(report(planner, engine, r, kept[r], int(args.seeds[r]), kind)), flush=True)
                kept[r] = None
                if choice[r] == GO:
                    f = _futures(planner, engine, r)
                    te = planner.tracks.engine.traffic
                    kept[r] = {"t0": float(engine.time[r]), "f": f, "futures": [f.traffic.subset(np.arange(f.B))],
                               "real": [engine.traffic.subset(everyone)], "start": te.subset(np.arange(te.B)),
                               "live": np.ones(f.B, bool)}
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(engine, rows, choice[rows], obs["turn"][rows])
        obs, _, done, infos = venv.step(act)
        for r in np.flatnonzero(~venv.idle & ~done):
            kp = kept[r]
            if kp is None:
                continue
            f = kp["f"]
            _, term, trunc = f.step(set_point_meta(f, float(f.speeds[-1])), active=kp["live"])
            kp["live"] &= ~(term | trunc)
            kp["futures"].append(f.traffic.subset(np.arange(f.B)))
            kp["real"].append(engine.traffic.subset(everyone))
        for r in np.flatnonzero(done):
            m = infos[r]["episode_metrics"]
            print(json.dumps({"seed": infos[r]["seed"], "collision": bool(m["collision"]),
                              "success": bool(m["success"])}), flush=True)
            kept[r] = None


if __name__ == "__main__":
    main()
