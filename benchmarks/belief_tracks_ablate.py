"""Where the planner on tracks loses against the planner on truth, part by part (docs/dagger.md, "What sensing costs",
"Where the planner on tracks loses"): validation (screen) episodes only.

    python benchmarks/belief_tracks_ablate.py --seed 1931000 --episodes 500 --truth velocity --out /tmp/v.json
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
- ``prior``: the prior over unconfirmed road users (agents/track_prior.py UnseenTraffic) is not added to the futures
  (with ``users`` the truth describes them all; its looks are still counted);
- ``position`` (x, y), ``velocity`` (speed, also as set-point, as a track's), ``heading``, ``acc`` (the measured
  acceleration the behaviour posterior weighs): of each road user matched to a vehicle (as ``users`` matches);
- ``all``: every one of them, and the lane the simulator's.

A road user whose pose changed takes the closest lane of its new pose (with position and heading both true, the
simulator's lane); one whose speed or lane changed has the standing rule (``stopped``, ``stopped_scope``) applied
again. The intent filter (indicator readings on the tracks the features describe) and everything hidden (routes,
set-points, IDM draws) stay the planner's. ``none``: the planner as it is (the paired baseline, the same
machinery). Prints and writes (``--out``, a new file) one JSON object: rates, the collided and not-arrived seeds,
and per collision its class: hit waiting (no GO in the episode) or hit after a GO, and the car hit as the planner
had it at the last GO started (or, hit waiting, at the last decision): confirmed / tentative / left out (a ghost or
twin) / unseen (no road user of the futures' start within ``--match`` m). ``--table`` prints the markdown table of
several such files, paired against the first. ``--on-truth``: the planner on the simulator's vehicles (sensors
turn_truth) on the same seeds, the reference the parts add up to."""

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

PARTS = ("users", "prior", "position", "velocity", "heading", "acc")


def parts_of(spec: str) -> frozenset:
    """``--truth`` (comma-separated parts of :data:`PARTS`, ``all`` or ``none``) as a set of parts; ``all`` adds
    the simulator's lane."""
    names = [s for s in spec.split(",") if s]
    bad = [s for s in names if s not in PARTS + ("all", "none")]
    if bad or not names:
        fail(f"--truth takes a comma list of {', '.join(PARTS)}, all or none; got {spec!r}")
    if "all" in names:
        return frozenset(PARTS + ("lane",))
    return frozenset(n for n in names if n != "none")


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


def with_truth(planner, engine, rows: np.ndarray, parts: frozenset, radius: float) -> None:
    """The futures' start of ``rows`` (``planner.tracks.engine``) with ``parts`` the simulator's, in place."""
    tb = planner.tracks
    te = tb.engine
    t, s, T = te.traffic, engine.traffic, engine.T
    state = parts & {"position", "velocity", "heading", "acc", "lane"}
    for r in rows:
        r = int(r)
        left_out = tb.ghost[r] if tb.ghost is not None else np.zeros(t.N, bool)
        pairs = match_users(te, engine, r, radius, left_out)
        changed: list[int] = []
        if "users" in parts:
            keep = np.zeros(t.N, bool)
            keep[list(pairs.values())] = True
            t.alive[r] = (t.alive[r] | left_out) & (keep | t.ego[r])
            for i in np.flatnonzero(s.alive[r] & ~s.ego[r]):
                if int(i) in pairs:
                    continue
                free = np.flatnonzero(~t.alive[r] & ~t.ego[r])
                if not len(free):
                    t.grow(1)
                    for name in ("tent", "ghost"):
                        setattr(tb, name, np.concatenate([getattr(tb, name), np.zeros((te.B, 1), bool)], 1))
                    free = [t.N - 1]
                j = int(free[0])
                for name in ("x", "y", "h", "v", "acc", "lane", "tlane"):
                    getattr(t, name)[r, j] = getattr(s, name)[r, i]
                t.target[r, j] = max(float(s.v[r, i]), 0.0)
                t.route[r, j] = -1
                t.route[r, j, 0] = s.lane[r, i]
                t.alive[r, j], t.plain[r, j], t.yielding[r, j], t.mdp[r, j] = True, False, False, False
                t.rpos[r, j], t.vid[r, j] = 0, 100_000 + int(s.vid[r, i])  # no indicator reading attached
                t.delta[r, j] = 4.0
                tb.tent[r, j], tb.ghost[r, j] = False, False
                changed.append(j)
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
        if changed and (parts - {"acc", "prior"}):
            j = np.array(changed)
            t.crashed[r, j] = standing(planner.params, T, tb.lane_kind, t.lane[r, j], t.x[r, j], t.y[r, j], t.v[r, j])


def statuses(planner, engine, rows: np.ndarray, radius: float) -> dict[int, dict[int, str]]:
    """Per row, simulator vid -> how the planner had that car at this decision: the nearest road user within
    ``radius`` m of it confirmed, tentative, left out (a ghost or twin), or none (unseen)."""
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
            row[int(s.vid[r, i])] = ("left out" if left_out[j] and not t.alive[r, j] else
                                     "tentative" if tb.tent[r, j] else "confirmed")
        out[r] = row
    return out


def play(args, parts: frozenset) -> dict:
    """The episodes of ``args`` with ``parts`` the simulator's (:func:`with_truth`): the JSON object."""
    from agents.belief import BeliefPlanner
    from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
    from av_gym.presets import compose_group
    from av_gym.wrappers import GO, YIELD

    point, params = planner_point(args.set)
    seeds = list(range(args.seed, args.seed + args.episodes))
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
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        planner.read(engine, rows, obs["intent"][rows])
        if parts:
            with_truth(planner, engine, rows, parts, args.match)
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
        if len(due):
            st = statuses(planner, engine, due, args.match) if planner.tracks is not None else {}
            for r in due:
                at_last[r] = st.get(int(r), {})
                if choice[r] == GO and before[r] != GO:
                    at_go[r], went[r] = at_last[r], True
        k[rows] += 1
        obs, _, done, infos = venv.step(meta_actions(choice, obs["turn"]))
        for r in np.flatnonzero(done):
            m = infos[r]["episode_metrics"]
            episodes.append((int(infos[r]["seed"]), bool(m["collision"]), bool(m["success"])))
            if m["collision"]:
                tr = engine.traffic
                hit = [int(tr.vid[r, j]) for j in np.flatnonzero(tr.alive[r] & tr.crashed[r] & ~tr.ego[r])]
                known = at_go[r] if went[r] else at_last[r]
                collisions.append({"seed": int(infos[r]["seed"]), "class": "after GO" if went[r] else "waiting",
                                   "hit": {v: known.get(v, "not on the map") for v in hit}})
    n = len(episodes)
    return {"point": point, "truth": ["planner on truth"] if args.on_truth else sorted(parts), "match_m": args.match,
            "episodes": n, "seed": args.seed, "collision": sum(c for _, c, _ in episodes) / n,
            "success": sum(s for _, _, s in episodes) / n,
            "collided": sorted(s for s, c, _ in episodes if c),
            "not_arrived": sorted(s for s, _, a in episodes if not a), "collisions": collisions,
            "wall_s": round(time.time() - t0, 1), "cpu_s": round(time.process_time() - c0, 1),
            "load": os.getloadavg()[0]}


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
        a = set(range(run["seed"], run["seed"] + run["episodes"])) - set(run["not_arrived"])
        a0 = set(range(base["seed"], base["seed"] + base["episodes"])) - set(base["not_arrived"])
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
    ap.add_argument("--truth", default="none", help=f"comma list of {', '.join(PARTS)}, all or none")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--on-truth", action="store_true", help="the planner on the simulator's vehicles (sensors "
                    "turn_truth; --truth none): the reference, on the same seeds")
    ap.add_argument("--match", type=float, default=MATCH_M, metavar="M", help="match radius (m), > 0")
    ap.add_argument("--out", default=None, metavar="PATH", help="the JSON object besides (a new file)")
    ap.add_argument("--table", nargs="+", default=None, metavar="PATH", help="print the table of these results")
    args = ap.parse_args()
    if args.table:
        print(table(args.table))
        return
    if args.out and Path(args.out).exists():
        fail(f"--out {args.out} exists: choose another file (results are never overwritten)")
    if args.episodes < 1 or not (args.match > 0):
        fail("--episodes must be >= 1 and --match > 0 (m)")
    if args.seed not in SPLITS["validation"] or args.seed + args.episodes - 1 not in SPLITS["validation"]:
        fail(f"--seed/--episodes must stay in the validation split {SPLITS['validation']}")
    parts = parts_of(args.truth)
    if args.on_truth and parts:
        fail("--on-truth takes --truth none (its road users are the simulator's)")
    result = play(args, parts)
    text = json.dumps(result)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
