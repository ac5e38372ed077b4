"""How well the planner on tracks knows a track's motion (docs/dagger.md, "What sensing costs"): the Kalman
filter's speed and the intent features' acceleration against the planner's own least-squares line through the
detected velocities (``track_fit``, agents/track_prior.py DetectedMotion), each against the simulator's vehicle.
Validation episodes only.

    python benchmarks/belief_tracks_motion.py --episodes 40 --seed 1500000 --fit 1.0

Drives ``--episodes`` episodes with belief_tracks (conf/agent/belief_tracks.yaml's options, ``--set`` to change
them) on the batch and, at every env step, pairs each confirmed track that has a line with the nearest simulator
vehicle (within 2 m): speed along the track's detected heading and acceleration. Prints one JSON line: bias and sd of
each error, over all pairs and over the cars accelerating harder than 2 m/s² (pulling away) or braking harder."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/
from belief_tracks_sweep import fail, planner_point  # noqa: E402  (this folder is sys.path[0] when run as a script)

SHIPPED = ["tentative=road_user", "track_heading=detected", "ghost=2", "merge=2", "recheck=16"]


def pairs(planner, engine, rows: np.ndarray, intent: np.ndarray) -> np.ndarray:
    """(k, 6) per confirmed track of ``rows`` with a line, matched to a vehicle within 2 m: true speed along the
    track's heading, filter's speed, the line's speed, true acceleration, the features', the line's (m/s, m/s²)."""
    from av_gym.estimation.turn_features import ACC_SCALE

    tb = planner.tracks
    pos, ids, conf, _, seen, _ = tb._tracks(rows)
    h = seen[..., 0]
    now = engine.ticks[rows] / engine.config["simulation_frequency"]
    v_fit, a_fit, ok = tb.motion.estimate(rows, ids, h, now)
    filt = pos[..., 2] * np.cos(h) + pos[..., 3] * np.sin(h)
    feat = np.zeros(conf.shape)
    m = min(intent.shape[1], conf.shape[1])
    feat[:, :m] = intent[:, :m, 0] * ACC_SCALE
    t = engine.traffic
    others = t.alive[rows] & ~t.ego[rows]
    d = np.hypot(pos[..., None, 0] - t.x[rows][:, None], pos[..., None, 1] - t.y[rows][:, None])
    d = np.where(others[:, None], d, np.inf)
    j = np.argmin(d, axis=-1)
    near = np.take_along_axis(d, j[..., None], -1)[..., 0] < 2.0
    b, k = np.nonzero(conf & ok & near)
    i = j[b, k]
    r = rows[b]
    true_v = t.v[r, i] * np.cos(t.h[r, i] - h[b, k])
    return np.stack([true_v, filt[b, k], v_fit[b, k], t.acc[r, i], feat[b, k], a_fit[b, k]], axis=1)


def summary(rows: np.ndarray) -> dict:
    """Bias and sd of the filter's and the line's speed errors, the features' and the line's acceleration errors."""
    if not len(rows):
        return {"pairs": 0}
    out = {"pairs": int(len(rows))}
    for name, est, true in (("speed_filter", 1, 0), ("speed_fit", 2, 0), ("acc_features", 4, 3), ("acc_fit", 5, 3)):
        err = rows[:, est] - rows[:, true]
        out[name] = {"bias": round(float(err.mean()), 3), "sd": round(float(err.std()), 3)}
    return out


def main() -> None:
    from agents.belief import BeliefPlanner
    from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
    from av_gym.presets import compose_group
    from av_gym.seeds import SPLITS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--seed", type=int, default=SPLITS["validation"].start)
    ap.add_argument("--fit", type=float, default=1.0, help="track_fit, s (> 0)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    seeds = list(range(args.seed, args.seed + args.episodes))
    if args.episodes < 1 or seeds[0] not in SPLITS["validation"] or seeds[-1] not in SPLITS["validation"]:
        fail(f"--seed/--episodes must stay in the validation split {SPLITS['validation']}")
    if args.fit <= 0:
        fail(f"--fit must be > 0 (s), got {args.fit}")
    point, params = planner_point(SHIPPED + [f"track_fit={args.fit}"] + args.set)
    t0 = time.time()
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, compose_group("sensors", "turn_perceived"), None, len(seeds),
                                pool=0)
    obs = venv.play(iter(seeds))
    planner = BeliefPlanner(params, n_rows=len(seeds), perception=venv.perception)
    planner.reset(np.arange(len(seeds)))
    choice, k, got = np.zeros(len(seeds), dtype=int), np.zeros(len(seeds), dtype=int), []
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        planner.read(venv.engine, rows, obs["intent"][rows])
        got.append(pairs(planner, venv.engine, rows, obs["intent"][rows]))
        choice[rows] = planner.decide(venv.engine, rows, choice[rows], k[rows])
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(venv.engine, rows, choice[rows], obs["turn"][rows])
        obs, _, _, _ = venv.step(act)
    allp = np.concatenate(got)
    print(json.dumps({"point": point, "episodes": len(seeds), "all": summary(allp),
                      "pulling_away": summary(allp[allp[:, 3] > 2.0]), "braking": summary(allp[allp[:, 3] < -2.0]),
                      "wall_s": round(time.time() - t0, 1), "load": os.getloadavg()[0]}))


if __name__ == "__main__":
    main()
