"""belief_lookahead on tracks on the batch, one parameter point on validation episodes (docs/dagger.md, "What sensing
costs": how belief_tracks' parameters were chosen).

    python benchmarks/belief_tracks_sweep.py --episodes 300 --set tentative=road_user

Plays ``--episodes`` validation seeds from ``--seed`` (default 1,000,000; or the ``--seeds`` listed) with :class:`agents.belief.BeliefLookahead`
on ``sensors=turn_perceived`` (``--set key=value``: BeliefLookaheadParams fields, e.g. ``unseen=2 samples=32``),
``--n-envs`` at a time, and prints one JSON line: the point, the seeds played (``seeds``: a ``--seeds`` list may
scatter them, so ``seed`` .. ``seed + episodes`` is not the run), collision and success rates, the seeds that collided
and those that did not arrive (for paired comparisons of points on the same seeds), wall and CPU seconds and the
load; ``--rows PATH`` writes every episode's row besides (its seed and EpisodeMetrics: outcome, length, ...; CSV,
never over an existing file), to see episode by episode what changed between two points."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's agents/ and eval/


def fail(message: str) -> None:
    """One ``error:`` line on stderr, exit status 2 (bad input)."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def planner_point(pairs: list[str]):
    """``--set KEY=VALUE ...`` as (the point's mapping, its BeliefLookaheadParams); a bad pair is one error line."""
    import yaml

    from agents.belief import BeliefLookaheadParams
    from av_gym.errors import ConfigError

    bad = [kv for kv in pairs if "=" not in kv]
    if bad:
        fail(f"--set takes KEY=VALUE (BeliefLookaheadParams fields), got {bad[0]!r}")
    try:
        point = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in pairs)}
        return point, BeliefLookaheadParams.from_mapping(point, "--set")
    except (ValueError, ConfigError, yaml.YAMLError) as exc:
        fail(str(exc).splitlines()[0])


def traced_batch(description: str, match: bool = False, extra=None):
    """The set-up the tracing tools share (belief_tracks_diagnose, _confirm, _state): ``--seeds`` (validation
    seeds, one batch row each), ``--set`` and, with ``match``, ``--match M`` (m, default
    belief_tracks_truth.MATCH_M: the radius within which a track is a simulator vehicle's) and what ``extra`` (a
    function of the parser) adds; returns (the point's
    mapping, its params, the batch, its first observations, a BeliefPlanner reset on every row, the parsed
    arguments)."""
    import numpy as np

    from agents.belief import BeliefPlanner
    from av_gym.batched.vec_env import BatchedLeftTurnBatch
    from av_gym.presets import compose_group
    from av_gym.seeds import SPLITS
    from conf.cli import ToolParser, number

    ap = ToolParser(description=description)
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    if match:
        from belief_tracks_truth import MATCH_M

        ap.add_argument("--match", type=number(float, low=0.0), default=MATCH_M, metavar="M",
                        help="match radius (m): a track within it of a simulator vehicle is that vehicle's")
    if extra is not None:
        extra(ap)
    args = ap.parse_args()
    if any(s not in SPLITS["validation"] for s in args.seeds):
        fail(f"--seeds must be in the validation split {SPLITS['validation']}")
    point, params = planner_point(args.set)
    B = len(args.seeds)
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, compose_group("sensors", "turn_perceived"), None, B, pool=0)
    obs = venv.play(iter(args.seeds))
    planner = BeliefPlanner(params, n_rows=B, perception=venv.perception)
    planner.reset(np.arange(B))
    return point, params, venv, obs, planner, args


def decide_due(planner, engine, obs, rows, choice, k):
    """One env step of the planner's own decisions on ``rows`` of a traced batch (the tracing tools' shared step):
    read the detections, decide where due (``choice`` updated in place); returns (the rows that decided, their
    choices before)."""
    planner.read(engine, rows, obs["intent"][rows])
    live, _ = planner.live(engine, rows, choice[rows], k[rows])
    due = rows[live]
    before = choice[due].copy()
    if len(due):
        choice[rows] = planner.decide(engine, rows, choice[rows], k[rows])
    return due, before


def main() -> None:
    from agents.belief import BeliefLookahead
    from av_gym.presets import compose_group
    from av_gym.seeds import SPLITS
    from eval.batched import play_batched

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=300)
    ap.add_argument("--seed", type=int, default=SPLITS["validation"].start)
    ap.add_argument("--n-envs", type=int, default=300)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--seeds", type=int, nargs="+", default=None, help="these validation seeds instead of --seed and "
                    "--episodes (e.g. the episodes two points ended differently)")
    ap.add_argument("--rows", default=None, metavar="PATH", help="every episode's row as CSV (a new file)")
    args = ap.parse_args()
    from av_gym.atomic import new_paths_or_exit

    new_paths_or_exit((args.rows, "--rows"))  # before the run: a taken path loses none of it
    seeds = args.seeds or range(args.seed, args.seed + args.episodes)
    if len(seeds) < 1 or any(s not in SPLITS["validation"] for s in (min(seeds), max(seeds))):
        fail(f"--seed/--episodes/--seeds must stay in the validation split {SPLITS['validation']}")
    point, params = planner_point(args.set)
    t0, c0 = time.time(), time.process_time()
    rows = play_batched({"name": "left_turn"}, compose_group("sensors", "turn_perceived"), None,
                        BeliefLookahead(None, params), list(seeds), args.n_envs, "belief_tracks", progress=False)
    n = len(rows)
    print(json.dumps({"point": point, "episodes": n, "seed": seeds[0], "seeds": list(seeds),
                      "collision": sum(r["collision"] for r in rows) / n, "success": sum(r["success"] for r in rows) / n,
                      "collided": [r["seed"] for r in rows if r["collision"]],
                      "not_arrived": [r["seed"] for r in rows if not r["success"]], "wall_s": round(time.time() - t0, 1),
                      "cpu_s": round(time.process_time() - c0, 1), "load": os.getloadavg()[0]}))
    if args.rows:  # after the summary (a refused --rows loses no run); linked in: a file there since the check is kept
        from av_gym.atomic import csv_text, write_new_or_exit

        write_new_or_exit(args.rows, csv_text(rows), "--rows")


if __name__ == "__main__":
    main()
