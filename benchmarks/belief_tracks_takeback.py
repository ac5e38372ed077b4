"""What changes between a held GO and the decision that takes it back (docs/dagger.md, "Where the target stands"):
validation episodes only.

    python benchmarks/belief_tracks_takeback.py --seeds 1953712 1953333 --set tentative=road_user ghost=2

Plays each seed as benchmarks/belief_tracks_diagnose.py does (the planner's own choices). At every decision that
holds GO it keeps the decision's own K futures played ``steps`` policy steps on (GO's set-point, as play_go_fast
plays it): each future's state at the next decision. At a decision that takes a held GO back it draws that
decision's own K futures again and asks how many of them collide when, future by future (the k-th new one against
the k-th kept one, the road users matched by vid), a part of the new start is replaced by what the kept future had
there:

- ``ego``: the ego's kinematic state (:data:`KINEMATIC`): (a) the ego's motion in the futures;
- ``hidden``: the blamed road users' driver draws (:data:`HIDDEN`: set-point, yielding for the regulation, IDM
  exponent): (b) the futures counted on the car braking or yielding;
- ``route``: their routes (:data:`ROUTE`);
- ``kin``: their kinematic state as the kept futures had moved it: (c) the tracks moved off the prediction;
- ``all``: all of the above for every road user the two share, besides the ego.

A road user is blamed when leaving it out lowers the takeback's collision share (benchmarks/belief_tracks_diagnose.
py's ``_blame``); ``new`` marks a blamed track the held GO's start did not hold (d). Beside the shares: the real
ego against the kept futures' ego, and per blamed road user its track now, the simulator's car nearest it and the
kept futures' (mean; ``yield``: the share of them where it was held by the regulation or had set-point 0 at any
step up to the next decision; ``idm_brake``: where it braked harder than 1 m/s² besides). A measurement: it reads
the simulator. Prints one JSON line per takeback, then one per episode."""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/
from belief_tracks_diagnose import _blame  # noqa: E402  (this folder is sys.path[0] when run as a script)
from belief_tracks_sweep import decide_due, traced_batch  # noqa: E402
from belief_tracks_truth import decision_p, nearest_cars  # noqa: E402

KINEMATIC = ("x", "y", "h", "v", "acc", "steer", "lane")
HIDDEN = ("target", "yielding", "delta")
ROUTE = ("route", "rpos", "tlane")


def _futures(planner, engine, r: int):
    """The K futures of row ``r``'s decision now, as go_collision draws them (the tracks' fill included)."""
    e = planner.tracks.current(engine)
    f = planner.futures(e, np.array([r]), planner.K)
    planner.tracks.fill(f, np.array([r]), planner.seed, planner.K)
    return f


def _played(f, steps: int) -> tuple:
    """``f`` played ``steps`` policy steps with GO's set-point (play_go_fast's meta-actions); returns it and, per
    future and road user vid, whether it was yielding / at set-point 0, or braking harder than 1 m/s², at any step."""
    from agents.belief import set_point_meta

    top = float(f.speeds[-1])
    live = np.ones(f.B, bool)
    held: dict[int, np.ndarray] = {}
    brake: dict[int, np.ndarray] = {}
    for _ in range(steps):
        _, term, trunc = f.step(set_point_meta(f, top), active=live)
        t = f.traffic
        for k in range(f.B):
            for j in np.flatnonzero(t.alive[k] & ~t.ego[k]):
                v = int(t.vid[k, j])
                held.setdefault(v, np.zeros(f.B, bool))[k] |= bool(t.yielding[k, j] or t.target[k, j] <= 0.0)
                brake.setdefault(v, np.zeros(f.B, bool))[k] |= bool(t.acc[k, j] < -1.0)
        live &= ~(term | trunc)
    return f, held, brake


def _slot(t, k: int, vid: int) -> int | None:
    j = np.flatnonzero(t.alive[k] & (t.vid[k] == vid))
    return int(j[0]) if len(j) else None


def _swapped_share(planner, engine, r: int, kept, vids: list[int], fields: tuple, ego: bool) -> float:
    """The collision share of row ``r``'s decision's K futures (GO played to the end) with, in each, the road users
    ``vids``' ``fields`` (and with ``ego`` the ego's kinematic state) those of the kept future of the same index."""
    from agents.belief import play_go_fast

    f = _futures(planner, engine, r)
    t, s = f.traffic, kept.traffic
    for k in range(f.B):
        pairs = [(_slot(t, k, v), _slot(s, k, v)) for v in vids]
        if ego:
            pairs.append((int(f.ego_slot([k])[0]), int(kept.ego_slot([k])[0])))
            for name in KINEMATIC:
                a, b = pairs[-1]
                getattr(t, name)[k, a] = getattr(s, name)[k, b]
            pairs.pop()
        for a, b in pairs:
            if a is None or b is None:
                continue
            for name in fields:
                getattr(t, name)[k, a] = getattr(s, name)[k, b]
    return float(1.0 - play_go_fast(f).mean())


def _users(planner, r: int) -> set[int]:
    t = planner.tracks.engine.traffic
    return {int(v) for v in t.vid[r][t.alive[r] & ~t.ego[r]]}


def takeback(planner, engine, r: int, kept: dict) -> dict:
    """The record of a GO of row ``r`` taken back now; ``kept``: the held GO's (time s, played futures, yield and
    brake marks, road user vids at its start)."""
    from av_gym.wrappers import GO

    t0, f5, held, brake, users0 = kept
    blame = _blame(planner, engine, r)
    te = planner.tracks.engine.traffic
    slots = [int(k[4:]) for k in blame if k.startswith("slot")]
    vids = [int(te.vid[r, j]) for j in slots]
    s = engine.traffic
    e_real = int(engine.ego_slot([r])[0])
    e5 = f5.ego_slot(np.arange(f5.B))
    k5 = np.arange(f5.B)
    out = {"t_s": round(float(engine.time[r]), 1), "go_s": round(t0, 1),
           "p": round(float(decision_p(planner, engine, [r], [GO])[0]), 3),
           "ego_real": {"x": round(float(s.x[r, e_real]), 2), "y": round(float(s.y[r, e_real]), 2),
                        "v": round(float(s.v[r, e_real]), 2), "target": float(s.target[r, e_real])},
           "ego_kept": {"x": round(float(f5.traffic.x[k5, e5].mean()), 2),
                        "y": round(float(f5.traffic.y[k5, e5].mean()), 2),
                        "v": round(float(f5.traffic.v[k5, e5].mean()), 2),
                        "target": float(f5.traffic.target[k5, e5].mean())},
           "blamed": {}}
    matched = nearest_cars(planner.tracks.engine, engine, r)
    for j, v in zip(slots, vids):
        i, dist = matched.get(j, (-1, None))
        rows = [(k, _slot(f5.traffic, k, v)) for k in range(f5.B)]
        rows = [(k, a) for k, a in rows if a is not None]
        ft = f5.traffic
        pick = lambda name: [float(getattr(ft, name)[k, a]) for k, a in rows]  # noqa: E731
        out["blamed"][v] = {
            "new": v not in users0, "p_without": blame[f"slot{j}"]["p_without"],
            "track": {"x": round(float(te.x[r, j]), 2), "y": round(float(te.y[r, j]), 2),
                      "v": round(float(te.v[r, j]), 2), "acc": round(float(te.acc[r, j]), 2),
                      "lane": int(te.lane[r, j])},
            "car": None if i < 0 else {"dist_m": round(dist, 2), "v": round(float(s.v[r, i]), 2),
                                       "acc": round(float(s.acc[r, i]), 2), "target": round(float(s.target[r, i]), 2),
                                       "yielding": bool(s.yielding[r, i]), "lane": int(s.lane[r, i])},
            "kept": None if not rows else {
                "n": len(rows), "x": round(float(np.mean(pick("x"))), 2), "y": round(float(np.mean(pick("y"))), 2),
                "v": round(float(np.mean(pick("v"))), 2), "acc": round(float(np.mean(pick("acc"))), 2),
                "target": round(float(np.mean(pick("target"))), 2),
                "yield": round(float(held.get(v, np.zeros(1)).mean()), 3),
                "idm_brake": round(float(brake.get(v, np.zeros(1)).mean()), 3)}}
    common = sorted(_users(planner, r) & users0)
    out["p_swapped"] = {
        "ego": _swapped_share(planner, engine, r, f5, [], (), True),
        "hidden": _swapped_share(planner, engine, r, f5, vids, HIDDEN, False),
        "route": _swapped_share(planner, engine, r, f5, vids, ROUTE, False),
        "kin": _swapped_share(planner, engine, r, f5, vids, KINEMATIC, False),
        "blamed_all": _swapped_share(planner, engine, r, f5, vids, KINEMATIC + HIDDEN + ROUTE, False),
        "all": _swapped_share(planner, engine, r, f5, common, KINEMATIC + HIDDEN + ROUTE, True)}
    return out


def main() -> None:
    from av_gym.batched.vec_env import meta_actions
    from av_gym.wrappers import GO, YIELD

    point, params, venv, obs, planner, args = traced_batch(__doc__.splitlines()[0])
    B, engine = venv.num_envs, venv.engine
    choice, k = np.full(B, YIELD), np.zeros(B, dtype=int)
    kept: list = [None] * B
    records: list[list] = [[] for _ in range(B)]
    repeat = int(params.repeat)
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        due, before = decide_due(planner, engine, obs, rows, choice, k)
        if len(due):
            for r, b in zip(due, before):
                if b == GO and choice[r] != GO and kept[r] is not None:
                    rec = takeback(planner, engine, int(r), kept[r])
                    records[r].append(rec)
                    print(json.dumps({"seed": int(args.seeds[r]), **rec}), flush=True)
                kept[r] = None
                if choice[r] == GO:
                    # to the next decision: the next multiple of repeat (a GO confirmed early decides sooner)
                    f5, held, brake = _played(_futures(planner, engine, int(r)), repeat - int(k[r]) % repeat)
                    kept[r] = (float(engine.time[r]), f5, held, brake, _users(planner, int(r)))
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(engine, rows, choice[rows], obs["turn"][rows])
        obs, _, done, infos = venv.step(act)
        for r in np.flatnonzero(done):
            m = infos[r]["episode_metrics"]
            print(json.dumps({"seed": infos[r]["seed"], "collision": bool(m["collision"]),
                              "success": bool(m["success"]), "takebacks": len(records[r])}), flush=True)
            kept[r] = None


if __name__ == "__main__":
    main()
