"""Why the ego is hit while it waits (docs/dagger.md, "Where the target stands": a third of the planner on tracks'
collisions, most of the planner on truth's, are the ego hit with no GO at all): validation episodes only.

    python benchmarks/belief_tracks_waiting.py --seeds 1959022 1959254 --set tentative=road_user

Plays each seed (one batch row each) with :class:`agents.belief.BeliefPlanner` as ``eval.batched`` drives it, on
``sensors=turn_perceived`` (``--on-truth``: turn_truth, the planner on the simulator's vehicles), ``--set``:
BeliefLookaheadParams fields. Prints one JSON line per collision: whether the ego ever held GO (``waiting``: it never
did), the ego at the hit (speed, set-point, acceleration, how far its front is past the stop line, how long it had
stood), and per car crashed then: its lane and route (highway-env node names), its box's gap to the ego's, where it
stands in the ego's frame (m ahead, m left), heading difference, speed (its lowest over the last 3 s: a car backing
up, and what stood ahead of it when it began), regulation hold, its lane's priority against the ego's, when it
crashed (before the ego: a wreck), and how it met the ego (:func:`relation`). With ``--shares S`` (default 1) the
collided seeds are played again and their decisions in the last S seconds also get, on the decision's own K futures,
the collision shares of GO, of YIELD (stop at the line, :func:`play_yield_fast`), of stopping now (set-point 0) and of
YIELD :data:`BACK` m before the line: whether another waiting plan would have been safer. A last line counts the
touching cars' relations, waiting and after a GO."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/
from belief_tracks_sweep import fail, planner_point  # noqa: E402
from belief_tracks_truth import decision_p  # noqa: E402

HISTORY = 30  # env steps of state kept per row (3 s at 10 Hz)
BACK = 4.0  # m: the other waiting place whose futures are played besides (YIELD this far before the usual place)


def yield_meta(f, back: float = 0.0) -> np.ndarray:
    """The meta-actions of YIELD for every row of the engine ``f`` (av_gym.wrappers.meta_actions on the truth's
    set-point and distance to the stop line: the highest set-point from which the ego still stops 0.5 m before the
    line at 3 m/s²; ``back``: m farther back than that)."""
    from av_gym.wrappers import DECEL, MARGIN
    from av_gym.sim.batched import FASTER, IDLE, SLOWER

    tr = f.truth()
    d_stop = -tr["stop_line_offset"]
    v_ok = np.sqrt(2.0 * DECEL * np.maximum(d_stop - MARGIN - back, 0.0))
    speeds = np.asarray(f.speeds, dtype=float)
    wanted = speeds[np.searchsorted(speeds, v_ok + 1e-6, side="right") - 1]
    sp = tr["set_point"]
    return np.where(wanted > sp + 1e-3, FASTER, np.where(wanted < sp - 1e-3, SLOWER, IDLE))


def play_yield_fast(f, back: float = 0.0) -> np.ndarray:
    """Whether each row of the future engine ``f`` ends without a collision when the ego yields (YIELD at every env
    step to the episode's end: stopped at its line, or ``back`` m before it, never going)."""
    safe = np.ones(f.B, bool)
    live = np.ones(f.B, bool)
    while live.any():
        _, terminated, truncated = f.step(yield_meta(f, back), active=live)
        ended = (terminated | truncated) & live
        if ended.any():
            e = np.flatnonzero(ended)
            safe[e] = ~f.traffic.crashed[e, f.ego_slot(e)]
            live &= ~ended
    return safe


def relation(ahead: float, left: float, dh: float, v: float, wreck: bool) -> str:
    """How a car that touched the ego met it, from its centre in the ego's frame (``ahead``, ``left``: m), the
    difference of their headings (``dh``, rad in [-pi, pi]), its speed along its own heading (``v``, m/s; below 0:
    driving backwards) and whether it had crashed into another car before (``wreck``). "In front" is the ego's own
    path: centre ahead of the ego's and within 1 m of its axis (a box there meets the ego's front, not its side)."""
    along = abs(dh) < 0.5
    if ahead > 0 and abs(left) < 1.0:
        if wreck:
            return "in front: a wreck"
        if along:
            return "in front: backing into the ego" if v < -0.05 else "in front: the ego ran into it"
        return "in front: across or head-on"
    if wreck:
        return "from the side: a wreck"
    if along and ahead < 0:
        return "from behind"
    if abs(abs(dh) - np.pi) < 0.5:
        return "opposite heading"
    return "crossing or turning across"


def _name(T, k: int) -> str:
    a, b, _ = T.index[int(k)]
    return f"{a}->{b}"


def snapshot(engine, r: int) -> dict:
    """Row ``r``'s ego and vehicles now: what :func:`describe` needs from the steps before a hit."""
    t = engine.traffic
    alive = np.flatnonzero(t.alive[r])
    return {"t": round(float(engine.time[r]), 2),
            **{k: t.__dict__[k][r, alive].copy() for k in ("vid", "ego", "x", "y", "h", "v", "target", "acc",
                                                             "lane", "yielding", "crashed")},
            "route": t.route[r, alive].copy(), "rpos": t.rpos[r, alive].copy()}


def describe(engine, r: int, hist: list, decisions: list, played: list) -> dict:
    """The collision record of row ``r`` (its state history ``hist`` of :func:`snapshot` dicts, the last one at
    the hit; ``decisions``: (t, choice, GO's p) per decision; ``played``: :func:`plan_shares` per decision asked).
    Every car crashed at the hit is listed; ``hitter`` marks those whose box is nearest the ego's (within 0.3 m of
    the least gap: the contact pushes boxes apart), the others crashed among themselves."""
    from av_gym.geometry import box_corners
    from av_gym.sim.batched import LENGTH, WIDTH
    from av_gym.wrappers import GO

    T = engine.T
    last = hist[-1]
    e = int(np.flatnonzero(last["ego"])[0])
    ex, ey, eh = last["x"][e], last["y"][e], last["h"][e]
    tr = engine.truth(np.array([r]))
    ego = {"v": round(float(last["v"][e]), 2), "set_point": round(float(last["target"][e]), 2),
           "acc": round(float(last["acc"][e]), 2), "past_line_m": round(float(tr["stop_line_offset"][0]), 2),
           "x": round(float(ex), 2), "y": round(float(ey), 2), "lane": _name(T, last["lane"][e]),
           "stopped_s": _stopped_for(hist, e)}
    cars = {}
    for j in np.flatnonzero(last["crashed"] & ~last["ego"]):
        vid = int(last["vid"][j])
        dx, dy = last["x"][j] - ex, last["y"][j] - ey
        ahead = float(np.cos(eh) * dx + np.sin(eh) * dy)
        left = float(-np.sin(eh) * dx + np.cos(eh) * dy)
        dh = float((last["h"][j] - eh + np.pi) % (2 * np.pi) - np.pi)
        first = next((s["t"] for s in hist if vid in s["vid"] and s["crashed"][list(s["vid"]).index(vid)]), None)
        past = [s for s in hist if vid in s["vid"]]
        held = [s["yielding"][list(s["vid"]).index(vid)] for s in past]
        route = [_name(T, k) for k in last["route"][j] if k >= 0]
        gap = box_gap(box_corners(np.array([ex, ey]), eh, LENGTH, WIDTH),
                      box_corners(np.array([last["x"][j], last["y"][j]]), last["h"][j], LENGTH, WIDTH))
        cars[vid] = {"gap_m": round(gap, 2), "lane": _name(T, last["lane"][j]), "route": route,
                     "ahead_m": round(ahead, 2), "left_m": round(left, 2), "dist_m": round(float(np.hypot(dx, dy)), 2),
                     "v": round(float(last["v"][j]), 2), "set_point": round(float(last["target"][j]), 2),
                     "acc": round(float(last["acc"][j]), 2), "held_now": bool(last["yielding"][j]),
                     "held_steps": int(np.sum(held)), "v_3s_ago": round(float(past[0]["v"][list(past[0]["vid"]).index(
                         vid)]), 2), "crashed_at_s": first,
                     "priority_vs_ego": int(T.priority[last["lane"][j]]) - int(T.priority[last["lane"][e]]),
                     "dh_rad": round(dh, 2), "front": _front(last, j), **_backing(past, vid),
                     "relation": relation(ahead, left, dh, float(last["v"][j]),
                                          first is not None and first < last["t"] - 0.05)}
    least = min((c["gap_m"] for c in cars.values()), default=0.0)
    for c in cars.values():  # the car(s) the ego touched: the least box gap (a crash's impact pushes boxes apart)
        c["hitter"] = c["gap_m"] <= least + 0.3
    return {"waiting": all(c != GO for _, c, _ in decisions), "end_s": last["t"], "ego": ego, "hit": cars,
            "decisions": decisions[-4:], "shares": played}


def box_gap(a: np.ndarray, b: np.ndarray) -> float:
    """The distance (m) between two boxes given by their corners (4, 2) each (av_gym.geometry.box_corners): 0 where
    they overlap, else the least corner-to-edge distance either way."""
    from av_gym.geometry import boxes_overlap

    if bool(boxes_overlap(a[None], b[None])[0]):
        return 0.0
    best = np.inf
    for p, q in ((a, b), (b, a)):
        for k in range(4):
            s0, s1 = q[k], q[(k + 1) % 4]
            d = s1 - s0
            t = np.clip(((p - s0) @ d) / (d @ d), 0.0, 1.0)
            best = min(best, float(np.hypot(*(p - (s0 + t[:, None] * d)).T).min()))
    return best


def _front(snap: dict, j: int) -> dict | None:
    """The nearest vehicle ahead of vehicle ``j`` of a :func:`snapshot` (centre within 0.6 rad of its heading, 30 m):
    distance (m), speed (m/s), crashed, held, whether it is the ego."""
    dx, dy = snap["x"] - snap["x"][j], snap["y"] - snap["y"][j]
    d = np.hypot(dx, dy)
    bearing = np.arctan2(dy, dx) - snap["h"][j]
    cone = (np.abs((bearing + np.pi) % (2 * np.pi) - np.pi) < 0.6) & (d < 30.0) & (np.arange(len(d)) != j)
    if not cone.any():
        return None
    i = int(np.flatnonzero(cone)[np.argmin(d[cone])])
    return {"dist_m": round(float(d[i]), 2), "v": round(float(snap["v"][i]), 2), "crashed": bool(snap["crashed"][i]),
            "held": bool(snap["yielding"][i]), "ego": bool(snap["ego"][i])}


def _backing(past: list, vid: int) -> dict:
    """Vehicle ``vid``'s lowest speed over the snapshots ``past`` (m/s), and where it first drove backwards: the
    time (s) and what stood ahead of it then (:func:`_front`)."""
    v = [s["v"][list(s["vid"]).index(vid)] for s in past]
    first = next((k for k, x in enumerate(v) if x < -0.05), None)
    out = {"v_min": round(float(min(v)), 2)}
    if first is not None:
        s = past[max(first - 1, 0)]
        out["backing_from_s"] = s["t"]
        out["front_then"] = _front(s, list(s["vid"]).index(vid))
    return out


def _stopped_for(hist: list, e: int) -> float:
    """How long (s) the ego had stood (below 0.1 m/s) before the last snapshot, within the history."""
    n = 0
    for s in reversed(hist):
        k = np.flatnonzero(s["ego"])
        if len(k) == 0 or s["v"][k[0]] >= 0.1:
            break
        n += 1
    return round(0.1 * n, 1)


def plan_shares(planner, engine, r: int, held: int) -> dict:
    """GO's, YIELD's and stopping's collision shares for row ``r`` on the decision's own K futures (the same
    draws: each play forks the futures afresh from the decision's seed sequence)."""
    from agents.belief import play_stop_fast

    rows = np.array([r])
    return {"go": round(float(decision_p(planner, engine, rows, np.array([held]))[0]), 3),
            "yield": round(float(planner._plan_collision(engine, rows, None, (), play_yield_fast)[0]), 3),
            "stop": round(float(planner._plan_collision(engine, rows, None, (), play_stop_fast)[0]), 3),
            f"yield_back{BACK:g}": round(float(planner._plan_collision(
                engine, rows, None, (), lambda f: play_yield_fast(f, BACK))[0]), 3)}


def replay(args, params, seeds: list[int], shares_from: dict | None = None) -> list[dict]:
    """The collision records of ``seeds`` (one batch row each); ``shares_from``: seed -> time (s) from which its
    decisions also get :func:`plan_shares` (each plays 3 x K futures to the episode's end: asked only near a hit
    a first replay found), None: none."""
    from agents.belief import BeliefPlanner
    from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
    from av_gym.presets import compose_group
    from av_gym.wrappers import YIELD

    B = len(seeds)
    sensors = compose_group("sensors", "turn_truth" if args.on_truth else "turn_perceived")
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, sensors, None, B, pool=0)
    obs = venv.play(iter(seeds))
    planner = BeliefPlanner(params, n_rows=B, perception=venv.perception)
    planner.reset(np.arange(B))
    engine = venv.engine
    choice, k = np.full(B, YIELD), np.zeros(B, dtype=int)
    hist: list[list] = [[] for _ in range(B)]
    decisions: list[list] = [[] for _ in range(B)]
    played: list[list] = [[] for _ in range(B)]
    start = [float("inf") if shares_from is None else shares_from.get(s, float("inf")) for s in seeds]
    out = []
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        planner.read(engine, rows, obs["intent"][rows])
        live, _ = planner.live(engine, rows, choice[rows], k[rows])
        due = rows[live]
        before = choice.copy()
        ps = {int(r): decision_p(planner, engine, np.array([r]), before[[r]])[0] for r in due}
        shares = {int(r): plan_shares(planner, engine, int(r), int(before[r])) for r in due
                  if engine.time[r] >= start[r] - 1e-9}
        choice[rows] = planner.decide(engine, rows, choice[rows], k[rows])
        for r in due:
            decisions[r].append((round(float(engine.time[r]), 1), int(choice[r]), round(float(ps[int(r)]), 3)))
            if int(r) in shares:
                played[r].append({"t": round(float(engine.time[r]), 1), **shares[int(r)]})
        for r in rows:
            hist[r] = (hist[r] + [snapshot(engine, int(r))])[-HISTORY:]
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(engine, rows, choice[rows], obs["turn"][rows])
        obs, _, done, infos = venv.step(act)
        for r in np.flatnonzero(done):
            if infos[r]["episode_metrics"]["collision"]:
                out.append({"seed": infos[r]["seed"], "on_truth": bool(args.on_truth),
                            **describe(engine, int(r), hist[r] + [snapshot(engine, int(r))], decisions[r],
                                       played[r])})
    return out


def main() -> None:
    from av_gym.seeds import SPLITS
    from conf.cli import ToolParser

    ap = ToolParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--on-truth", action="store_true", help="the planner on the simulator's vehicles (turn_truth)")
    ap.add_argument("--shares", type=float, default=1.0, metavar="S",
                    help="replay the collided seeds again with GO's, YIELD's, stopping's and YIELD further back's "
                         "collision shares at their decisions in the last S seconds before the hit (0: no second "
                         "replay)")
    args = ap.parse_args()
    if any(s not in SPLITS["validation"] for s in args.seeds):
        fail(f"--seeds must be in the validation split {SPLITS['validation']}")
    if args.shares < 0:
        fail(f"--shares must be >= 0 (s), got {args.shares:g}")
    point, params = planner_point(args.set)
    records = replay(args, params, list(args.seeds))
    if args.shares > 0 and records:
        again = replay(args, params, [r["seed"] for r in records],
                       {r["seed"]: r["end_s"] - args.shares for r in records})
        shared = {r["seed"]: r["shares"] for r in again}
        for r in records:
            r["shares"] = shared.get(r["seed"], [])
    counts: dict[str, int] = {}
    for record in records:
        for car in record["hit"].values():
            if not car["hitter"]:
                continue
            key = ("waiting: " if record["waiting"] else "after a GO: ") + car["relation"]
            counts[key] = counts.get(key, 0) + 1
        print(json.dumps(record), flush=True)
    print(json.dumps({"point": point, "on_truth": bool(args.on_truth), "seeds": len(args.seeds),
                      "collisions": len(records), "relations": counts}), flush=True)


if __name__ == "__main__":
    main()
