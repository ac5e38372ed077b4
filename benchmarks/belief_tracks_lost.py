"""Why the planner on tracks loses arrivals the planner on truth makes (docs/dagger.md, "What sensing costs"):
validation episodes only, a diagnostic (it reads the simulator), not a policy.

    python benchmarks/belief_tracks_lost.py --seeds 1910003 1910017 --set confirm=2 stopped_scope=off_approach

Plays each seed twice on the batch: with ``belief_lookahead`` on ``sensors=turn_truth`` (the kind's defaults), which
gives the time of its first GO, and with :class:`agents.belief.BeliefPlanner` on ``sensors=turn_perceived``
(``--set``: BeliefLookaheadParams fields) as ``eval.batched`` drives it. Both egos stand alike until one of them
goes and the traffic is the simulator's own, so at the truth planner's first GO the planner on tracks decides on
the same road (``same_ego``: the egos within 1 cm). Each decision of the planner on tracks from then on while it
yields (at most ``--window`` s) gets one cause, the first of these that makes GO safe (:func:`cause`):

- ``caution``: GO was safe at this decision; ``confirm`` / ``recheck`` held it back;
- ``phantom track``: without the road users that have no simulator vehicle within ``--match`` m;
- ``tentative track``: without the tentative tracks;
- ``unseen prior``: without the unseen-traffic prior;
- ``readings lost at a re-birth``: each track's indicator readings joined with those of the earlier tracks of the
  same car (the car its track was matched to at every step: the readings a track born again starts afresh);
- ``track states``: every road user given its car's true state (belief_tracks_truth.py);
- ``acceleration's error``: that, and the behaviour posterior weighing the (true) acceleration with the model's
  spread alone, as on truth (``track_acc_sigma`` 0);
- ``real road users``: none of these.

Prints one JSON line per episode (its outcome, the truth planner's first GO, every cause) and a last line that
counts, over the episodes that arrive on truth and not on tracks, the cause of the decision at the truth planner's
first GO, and the re-births seen on the approach lanes (a car's track replaced by a new one)."""

from __future__ import annotations

import copy
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/
from belief_tracks_sweep import traced_batch  # noqa: E402  (this folder is sys.path[0] when run as a script)
from belief_tracks_truth import decision_p, nearest_cars, true_states  # noqa: E402

SAME_EGO_M = 0.01  # m: the two egos stand at the same place


def truth_first_go(seeds: list[int]) -> dict[int, tuple]:
    """seed -> (time s of the truth planner's first GO or None, its ego's x, y then (m), arrived)."""
    from agents.belief import BeliefLookaheadParams, BeliefPlanner
    from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
    from av_gym.presets import compose_group
    from av_gym.wrappers import GO, YIELD

    B = len(seeds)
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, compose_group("sensors", "turn_truth"), None, B, pool=0)
    obs = venv.play(iter(seeds))
    planner = BeliefPlanner(BeliefLookaheadParams(), n_rows=B)
    planner.reset(np.arange(B))
    e = venv.engine
    choice, k, first, out = np.full(B, YIELD), np.zeros(B, dtype=int), [None] * B, {}
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        planner.read(e, rows, obs["intent"][rows])
        choice[rows] = planner.decide(e, rows, choice[rows], k[rows])
        for r in rows[(choice[rows] == GO)]:
            if first[r] is None:
                s = e.ego_slot(np.array([r]))[0]
                first[r] = (round(float(e.time[r]), 1), float(e.traffic.x[r, s]), float(e.traffic.y[r, s]))
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(e, rows, choice[rows], obs["turn"][rows])
        obs, _, done, infos = venv.step(act)
        for r in np.flatnonzero(done):
            out[int(infos[r]["seed"])] = (first[r], bool(infos[r]["episode_metrics"]["success"]))
    return out


def _p(planner, engine, r: int, held: int, traffic=None, unseen: bool = True, counts: dict | None = None) -> float:
    """GO's collision probability for row ``r`` (holding ``held`` at the decision: belief_tracks_truth.decision_p)
    with the futures' start's traffic ``traffic`` (default the planner's), with or without the unseen prior, with
    the indicator readings ``counts`` (default the planner's)."""
    tb = planner.tracks
    saved, saved_unseen, saved_counts = tb.engine, tb.unseen, planner.counts[r]
    try:
        if traffic is not None:
            tb.engine = copy.copy(saved)
            tb.engine.traffic = traffic
        tb.unseen = tb.unseen if unseen else None
        planner.counts[r] = saved_counts if counts is None else counts
        return float(decision_p(planner, engine, r, held)[0])
    finally:
        tb.engine, tb.unseen, planner.counts[r] = saved, saved_unseen, saved_counts


def _without(planner, r: int, drop: np.ndarray):
    """The futures' start's traffic with the slots ``drop`` of row ``r`` left out."""
    t = planner.tracks.engine.traffic.subset(np.arange(planner.tracks.engine.B))
    t.alive[r, drop] = False
    return t


def carried_counts(planner, r: int, car_of: dict) -> dict:
    """Row ``r``'s indicator readings with each track's joined with those of every track of the same car
    (``car_of``: track vid -> the simulator vid it was last matched to)."""
    by_car: dict[int, np.ndarray] = {}
    for v, c in planner.counts[r].items():
        if v in car_of:
            by_car[car_of[v]] = by_car.get(car_of[v], np.zeros(3, dtype=int)) + c
    return {v: (by_car[car_of[v]].copy() if v in car_of else c) for v, c in planner.counts[r].items()}


def cause(planner, engine, r: int, p: float, car_of: dict, radius: float, held: int) -> str:
    """The first counterfactual (module docstring) under which GO is safe at row ``r``'s decision (GO's collision
    probability ``p``, the row holding ``held`` before it)."""
    thr = planner.threshold + 1e-12
    if p <= thr:
        return "caution"
    t = planner.tracks.engine.traffic
    users = np.flatnonzero(t.alive[r] & ~t.ego[r])
    matched = nearest_cars(planner.tracks.engine, engine, r, radius)
    phantom = np.array([j for j in users if int(j) not in matched], dtype=int)
    if len(phantom) and _p(planner, engine, r, held, _without(planner, r, phantom)) <= thr:
        return "phantom track"
    tent = np.flatnonzero(planner.tracks.tent[r] & t.alive[r])
    if len(tent) and _p(planner, engine, r, held, _without(planner, r, tent)) <= thr:
        return "tentative track"
    if planner.tracks.unseen is not None and _p(planner, engine, r, held, unseen=False) <= thr:
        return "unseen prior"
    if _p(planner, engine, r, held, counts=carried_counts(planner, r, car_of)) <= thr:
        return "readings lost at a re-birth"
    exact = t.subset(np.arange(planner.tracks.engine.B))
    e = copy.copy(planner.tracks.engine)
    e.traffic = exact
    true_states(e, engine, [r], radius)
    if _p(planner, engine, r, held, exact) <= thr:
        return "track states"
    saved = planner.params
    planner.params = dataclasses.replace(saved, track_acc_sigma=0.0)
    try:
        if _p(planner, engine, r, held, exact) <= thr:
            return "acceleration's error"
    finally:
        planner.params = saved
    return "real road users"


def match_cars(planner, engine, rows: np.ndarray, car_of: list, radius: float, rebirths: list) -> None:
    """Record each road user's car (its nearest simulator vehicle within ``radius`` m) per row; a car on an approach
    lane whose track vid changed is a re-birth (counted per row in ``rebirths``)."""
    t = planner.tracks.engine.traffic
    for r in rows:
        for j, (i, _) in nearest_cars(planner.tracks.engine, engine, int(r), radius).items():
            v, car = int(t.vid[r, j]), int(engine.traffic.vid[r, i])
            if v not in car_of[r]:
                earlier = [w for w, c in car_of[r].items() if c == car]
                if earlier and planner.tracks.lane_kind[t.lane[r, j]] == 0:
                    rebirths[r] += 1
                car_of[r][v] = car


def _window(ap) -> None:
    from conf.cli import number

    ap.add_argument("--window", type=number(float, low=0.0), default=2.0, metavar="S",
                    help="s after the truth planner's first GO over which the planner on tracks' yields get causes")


def main() -> None:
    from av_gym.batched.vec_env import meta_actions
    from av_gym.wrappers import GO, YIELD

    point, params, venv, obs, planner, args = traced_batch(__doc__.splitlines()[0], match=True, extra=_window)
    truth = truth_first_go(list(args.seeds))
    B, engine = venv.num_envs, venv.engine
    seed_of = list(args.seeds)
    choice, k = np.full(B, YIELD), np.zeros(B, dtype=int)
    car_of, rebirths, causes = [{} for _ in range(B)], [0] * B, [[] for _ in range(B)]
    first_cause, counts = [None] * B, {}
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        planner.read(engine, rows, obs["intent"][rows])
        match_cars(planner, engine, rows, car_of, args.match, rebirths)
        live, _ = planner.live(engine, rows, choice[rows], k[rows])
        due = rows[live]
        held = choice[due].copy()
        p = decision_p(planner, engine, due, held) if len(due) else np.zeros(0)  # decide()'s own p
        choice[rows] = planner.decide(engine, rows, choice[rows], k[rows])
        for r, pr, h in zip(due, p, held):
            go = truth[seed_of[r]][0]
            now = round(float(engine.time[r]), 1)
            if go is None or choice[r] == GO or not go[0] <= now <= go[0] + args.window:
                continue
            c = cause(planner, engine, int(r), float(pr), car_of[r], args.match, int(h))
            causes[r].append((now, round(float(pr), 3), c))
            if now == go[0]:
                s = engine.ego_slot(np.array([r]))[0]
                same = np.hypot(engine.traffic.x[r, s] - go[1], engine.traffic.y[r, s] - go[2]) < SAME_EGO_M
                first_cause[r] = c if same else "egos apart"
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(engine, rows, choice[rows], obs["turn"][rows])
        obs, _, done, infos = venv.step(act)
        for r in np.flatnonzero(done):
            m, seed = infos[r]["episode_metrics"], int(infos[r]["seed"])
            lost = truth[seed][1] and not m["success"]
            if lost:
                name = first_cause[r] or "tracks went first"
                counts[name] = counts.get(name, 0) + 1
            print(json.dumps({"seed": seed, "collision": bool(m["collision"]), "success": bool(m["success"]),
                              "truth_arrived": truth[seed][1], "truth_first_go_s": (truth[seed][0] or [None])[0],
                              "lost": lost, "rebirths_on_approach": rebirths[r], "causes": causes[r]}), flush=True)
    print(json.dumps({"point": point, "lost_by_cause_at_truths_go": dict(sorted(counts.items(), key=lambda kv: -kv[1])),
                      "rebirths_on_approach": sum(rebirths)}), flush=True)


if __name__ == "__main__":
    main()
