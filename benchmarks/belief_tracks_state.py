"""How much the planner on tracks would gain from exact track states (docs/dagger.md, "What sensing costs"): a bound
for the options that refine a track's state (covariance, a speed prior for young tracks, smoothing), validation
episodes only.

    python benchmarks/belief_tracks_state.py --seeds 1900600 1900601 --set confirm=2 stopped_scope=off_approach

Plays each seed with :class:`agents.belief.BeliefPlanner` on ``sensors=turn_perceived`` (``--set``:
BeliefLookaheadParams fields) as ``eval.batched`` drives it, except that before every step's decisions each road
user the planner has (a confirmed or tentative track) within ``--match`` m (default 3) of a simulator vehicle takes
that vehicle's place, heading, speed (also as its set-point, as a track's), acceleration and lane
(belief_tracks_truth.py, the true state belief_tracks_confirm.py uses too): the tracks as a perfect filter would
give them; which road users there are (confirmation, misses, ghosts, twins), the standing
rule's flag and everything hidden (routes, set-points, IDM draws) stay the planner's. Not a policy (it reads the
simulator): the gap between it and the planner on the same seeds is what any state refinement can buy. Prints one
JSON line as belief_tracks_sweep.py does, plus the road-user states replaced."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/
from belief_tracks_sweep import traced_batch  # noqa: E402  (this folder is sys.path[0] when run as a script)
from belief_tracks_truth import true_states  # noqa: E402


def main() -> None:
    from av_gym.batched.vec_env import meta_actions
    from av_gym.wrappers import YIELD

    t0, c0 = time.time(), time.process_time()
    point, params, venv, obs, planner, args = traced_batch(__doc__.splitlines()[0], match=True)
    radius = args.match
    B, engine = venv.num_envs, venv.engine
    choice, k = np.full(B, YIELD), np.zeros(B, dtype=int)
    rows_out, replaced = [], 0
    while not venv.idle.all():
        rows = np.flatnonzero(~venv.idle)
        planner.read(engine, rows, obs["intent"][rows])
        replaced += true_states(planner.tracks.engine, engine, rows, radius)
        choice[rows] = planner.decide(engine, rows, choice[rows], k[rows])
        k[rows] += 1
        act = meta_actions(choice, obs["turn"])  # the idle rows' (unused)
        act[rows] = planner.meta_actions(engine, rows, choice[rows], obs["turn"][rows])
        obs, _, done, infos = venv.step(act)
        for r in np.flatnonzero(done):
            m = infos[r]["episode_metrics"]
            rows_out.append((infos[r]["seed"], bool(m["collision"]), bool(m["success"])))
    n = len(rows_out)
    print(json.dumps({"point": point, "state": "true", "match_m": radius if np.isfinite(radius) else None,
                      "episodes": n,
                      "collision": sum(c for _, c, _ in rows_out) / n, "success": sum(s for _, _, s in rows_out) / n,
                      "collided": sorted(s for s, c, _ in rows_out if c),
                      "not_arrived": sorted(s for s, _, a in rows_out if not a), "replaced": replaced,
                      "wall_s": round(time.time() - t0, 1), "cpu_s": round(time.process_time() - c0, 1),
                      "load": os.getloadavg()[0]}))


if __name__ == "__main__":
    main()
