"""Where ``confirm`` costs the planner on tracks its arrivals (docs/dagger.md, "What sensing costs"): validation
episodes only.

    python benchmarks/belief_tracks_confirm.py --seeds 1700003 1700017 --set confirm=2 stopped_scope=off_approach

Plays each seed with :class:`agents.belief.BeliefPlanner` on ``sensors=turn_perceived`` (``--set``:
BeliefLookaheadParams fields) as ``eval.batched`` drives it, and prints one JSON line per episode: its outcome,
every decision (time s, GO's collision probability, the choice) and, at each decision that found GO safe right
after one that did not (a *flip*: where ``confirm`` 2 holds a GO that ``confirm`` 1 takes), what made that earlier
decision unsafe: each road user without which its futures were safer (GO's collision probability without it),
with its distance from the ego (m), its speed (m/s), whether the track was tentative, the kind of its lane
(approach, crossing, exit) and, on an approach, its time to the stop line at its speed (s); and whether the unseen
traffic's prior alone made it unsafe; and each such road user's track against the simulator vehicle within
``--match`` m (default 3) of it (its detections so far, its filter's speed sd, the true speed, the distance to the
nearest vehicle, and GO's collision probability with the track's true state: belief_tracks_truth.py, the state
belief_tracks_state.py plays with, so the set-point is the true speed, not the simulator's hidden one). Only live
decisions are logged (``BeliefPlanner.live``: a row ``commit`` has made final decides nothing). The last line
counts the flips by the blamed road user's kind and by whether its true state would have made GO safe."""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/
from belief_tracks_sweep import traced_batch  # noqa: E402  (this folder is sys.path[0] when run as a script)
from belief_tracks_truth import decision_p, go_with_true_state, nearest_cars  # noqa: E402

LANE_KINDS = ("approach", "crossing", "exit")


def _without(planner, engine, r: int, j: int | None, held: int) -> float:
    """GO's collision probability for row ``r`` (holding ``held``: belief_tracks_truth.decision_p) without road user
    slot ``j`` of the futures' start (None: without the unseen traffic's prior)."""
    saved, unseen = planner.tracks.engine, planner.tracks.unseen
    try:
        if j is None:
            planner.tracks.unseen = None
        else:
            e = copy.copy(saved)
            e.traffic = saved.traffic.subset(np.arange(saved.B))
            e.traffic.alive[r, j] = False
            planner.tracks.engine = e
        return float(decision_p(planner, engine, r, held)[0])
    finally:
        planner.tracks.engine, planner.tracks.unseen = saved, unseen


def blame(planner, engine, r: int, p: float, radius: float, held: int = 0) -> dict:
    """What made GO unsafe for row ``r`` (GO's collision probability ``p`` at a decision of a row holding ``held``,
    default YIELD: belief_tracks_truth.decision_p): the unseen prior's share and each road user whose removal lowers
    it, with its track against the simulator vehicle within ``radius`` m of it."""
    te = planner.tracks.engine
    t = te.traffic
    ex, ey = t.x[r, 0], t.y[r, 0]
    out = {"p": round(p, 3), "p_no_unseen": round(_without(planner, engine, r, None, held), 3), "users": []}
    nearest = nearest_cars(te, engine, r)
    tracker = planner.tracks.perception.tracker
    for j in np.flatnonzero(t.alive[r] & ~t.ego[r]):
        q = _without(planner, engine, r, int(j), held)
        if q >= p:
            continue
        i, dist = nearest.get(int(j), (-1, None))
        i = i if dist is not None and dist <= radius else -1
        p_true = go_with_true_state(planner, engine, r, int(j), i, held) if i >= 0 else None
        k = np.flatnonzero(tracker.id[r, : tracker.n[r]] == t.vid[r, j] - 1)
        kind = int(planner.tracks.lane_kind[t.lane[r, j]])
        v = float(t.v[r, j])
        lane = t.lane[r, j]
        s_now = engine.T.local(np.array([lane]), t.x[r, j:j + 1], t.y[r, j:j + 1])[0][0]
        to_line = float(engine.T.length[lane] - s_now)  # an approach lane ends at its stop line
        out["users"].append({"p_without": round(q, 3), "d_ego_m": round(float(np.hypot(t.x[r, j] - ex,
                                                                                         t.y[r, j] - ey)), 1),
                             "v": round(v, 2), "tentative": bool(planner.tracks.tent[r, j]),
                             "lane": LANE_KINDS[kind],
                             "to_line_s": round(to_line / max(v, 0.1), 1) if kind == 0 else None,
                             # the track against its simulator vehicle: its detections so far, its filter's speed
                             # sd along its heading (m/s), the true speed, the distance to the nearest vehicle (m),
                             # and GO's collision probability with the track's state (belief_tracks_truth: place,
                             # heading, speed, acceleration, lane) that of the vehicle within ``radius``
                             "hits": int(tracker.hits[r, k[0]]) if len(k) else None,
                             "sd_v": round(float(np.sqrt(max(planner.tracks.along[r, j, 1, 1], 0.0))), 2),
                             "v_true": round(float(engine.traffic.v[r, i]), 2) if i >= 0 else None,
                             "err_m": round(dist, 2) if dist is not None else None,
                             "p_true_state": round(p_true, 3) if p_true is not None else None,
                             "safe_true_state": (bool(p_true <= planner.threshold + 1e-12)
                                                 if p_true is not None else None)})
    return out


def blamed_kind(b: dict) -> str:
    """One word for a flip's earlier unsafe decision: the road user whose removal lowers GO's collision probability
    most (its lane kind, tentative or not, near or far on its approach), or the unseen prior."""
    if not b["users"]:
        return "unseen prior" if b["p_no_unseen"] < b["p"] else "nobody alone"
    u = min(b["users"], key=lambda x: x["p_without"])
    near = "" if u["lane"] != "approach" else (" < 3 s" if (u["to_line_s"] or 0) < 3 else " >= 3 s")
    return f"{'tentative' if u['tentative'] else 'confirmed'} on {u['lane']}{near}"


def state_kind(b: dict) -> str:
    """Whether the road user most to blame for a flip's earlier unsafe decision was unsafe by its track's error:
    with its track's state the simulator's, GO was safe there (a track off its car), or still unsafe (the car
    itself); young: a track of at most 4 detections."""
    if not b["users"]:
        return "no road user"
    u = min(b["users"], key=lambda x: x["p_without"])
    if u["safe_true_state"] is None:
        return "no car matched"
    age = "young" if (u["hits"] or 0) <= 4 else "older"
    return f"{age} track, {'safe' if u['safe_true_state'] else 'unsafe'} with its true state"


def main() -> None:
    from av_gym.batched.vec_env import meta_actions
    from av_gym.wrappers import GO, YIELD

    point, params, venv, obs, planner, args = traced_batch(__doc__.splitlines()[0], match=True)
    B = venv.num_envs
    engine = venv.engine
    choice, k = np.full(B, YIELD), np.zeros(B, dtype=int)
    history = [[] for _ in range(B)]  # (time s, p, choice) per decision
    pending: list = [None] * B  # the blame of each row's last decision, when it found GO unsafe
    flips = [[] for _ in range(B)]
    kinds: dict[str, int] = {}
    states: dict[str, int] = {}
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        planner.read(engine, rows, obs["intent"][rows])
        live, _ = planner.live(engine, rows, choice[rows], k[rows])
        due = rows[live]  # the rows that decide now (a row ``commit`` has made final does not)
        held = choice[due].copy()
        p = decision_p(planner, engine, due, held) if len(due) else np.zeros(0)  # the decision's own draws and p
        choice[rows] = planner.decide(engine, rows, choice[rows], k[rows])
        for r, pr, h in zip(due, p, held):
            history[r].append((round(float(engine.time[r]), 1), round(float(pr), 3), int(choice[r])))
            if pr > planner.threshold and h != GO:
                pending[r] = blame(planner, engine, int(r), float(pr), args.match, int(h))
            elif pending[r] is not None and h != GO:
                flips[r].append({"t": round(float(engine.time[r]), 1), "before": pending[r]})
                name = blamed_kind(pending[r])
                kinds[name] = kinds.get(name, 0) + 1
                name = state_kind(pending[r])
                states[name] = states.get(name, 0) + 1
                pending[r] = None
            else:
                pending[r] = None
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(engine, rows, choice[rows], obs["turn"][rows])
        obs, _, done, infos = venv.step(act)
        for r in np.flatnonzero(done):
            m = infos[r]["episode_metrics"]
            print(json.dumps({"seed": infos[r]["seed"], "collision": bool(m["collision"]),
                              "success": bool(m["success"]), "end_s": round(float(engine.time[r]), 1),
                              "decisions": history[r], "flips": flips[r]}), flush=True)
    print(json.dumps({"point": point, "flips_by_blamed": dict(sorted(kinds.items(), key=lambda kv: -kv[1])),
                      "flips_by_state": dict(sorted(states.items(), key=lambda kv: -kv[1]))}), flush=True)


if __name__ == "__main__":
    main()
