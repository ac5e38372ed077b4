"""``belief_lookahead`` on the batch: success, collisions and the planner's labels per second for a grid of K
(futures per decision), GO thresholds and commitments, on seeds of one split (the validation split to choose them).

    python benchmarks/belief_planner.py --split validation --episodes 300 --samples 8 16 --thresholds 0.02 0.05 0.1 0.2
    python benchmarks/belief_planner.py --split validation --episodes 300 --samples 16 --commit never stop
    python benchmarks/belief_planner.py --episodes 40 --samples 16 --thresholds 0.05 --paths   # numpy vs compiled

Each (K, threshold, commit) plays the same episodes (``python -m eval``'s batched loop,
:func:`eval.batched.play_batched`); one csv row per point (``--out``, a new file), with 95 % Wilson intervals and
the labels/s of the planner alone (wall-clock of its futures) and of the whole run. ``--paths``: each point on every
engine path (the numpy step, the compiled step with obs["turn"], truth and rewards in numpy, the compiled step:
benchmarks/batched_speed.py's PATHS), one after the other, with the planner's labels per CPU-second."""

from __future__ import annotations

import itertools
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def stacks():
    """The env / sensors / shield configs of ``agent=belief_lookahead`` through Hydra, as ``python -m eval``."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    with initialize_config_module("conf", version_base="1.3"):
        cfg = compose("train", overrides=["agent=ppo_turn"])  # the same env and sensors preset (turn_truth)
    return [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]


def main() -> None:
    from conf.cli import ToolParser, number

    ap = ToolParser(prog="benchmarks/belief_planner.py", description=__doc__.splitlines()[0])
    ap.add_argument("--split", default="validation", choices=["validation", "test"])
    ap.add_argument("--first", type=int, default=None, help="first seed (default: the split's first)")
    ap.add_argument("--episodes", type=number(int, low=1), default=300, help="episodes per point, >= 1")
    ap.add_argument("--samples", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--thresholds", type=float, nargs="+", default=[0.02, 0.05, 0.1, 0.2])
    ap.add_argument("--commit", nargs="+", default=["never"], choices=["never", "stop", "go"],
                    help="when a GO is final (BeliefLookaheadParams.commit; its default: never)")
    ap.add_argument("--n-envs", type=number(int, low=1), default=100, help="episodes stepped together, >= 1")
    ap.add_argument("--out", default=None, help="csv of the points, a new file (rewritten whole after each point)")
    ap.add_argument("--paths", action="store_true", help="each point on every engine path (batched_speed.PATHS)")
    args = ap.parse_args()
    from av_gym.atomic import csv_text, new_paths_or_exit, write_new_or_exit, write_text_atomic

    # before the run: a file there (a user's, an earlier run's points) is never appended to or replaced
    new_paths_or_exit((args.out, "--out"))
    points: list[dict] = []

    import numpy as np

    from agents.belief import BeliefLookahead, BeliefLookaheadParams
    from av_gym.metrics.stats import wilson_ci
    from av_gym.seeds import seeds as split_seeds
    from av_gym.sim import batched as engine
    from batched_speed import PATHS
    from eval.batched import _Decider, play_batched

    env, sensors, shield = stacks()
    seeds = list(split_seeds(args.split, args.episodes, args.first))
    paths = PATHS if args.paths else {"compiled step": PATHS["compiled step"]}
    for K, thr, commit, path in itertools.product(args.samples, args.thresholds, args.commit, paths):
        policy = BeliefLookahead(None, BeliefLookaheadParams(samples=K, threshold=thr, commit=commit))
        made = []
        init = _Decider.__init__

        def spy(self, *args, _init=init, **kwargs):  # keep the decider to read its planner's counters
            _init(self, *args, **kwargs)
            made.append(self)
        _Decider.__init__ = spy
        start, cpu = time.perf_counter(), time.process_time()
        try:
            with engine.using_kernels(paths[path]):
                rows = play_batched(env, sensors, shield, policy, seeds, args.n_envs, "belief_lookahead",
                                    progress=False)
        finally:
            _Decider.__init__ = init
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
        planner = made[0].planner
        n = len(rows)
        col = np.array([r["collision"] for r in rows], float)
        suc = np.array([r["success"] for r in rows], float)
        _, cl, ch = wilson_ci(int(col.sum()), n)
        _, sl, sh = wilson_ci(int(suc.sum()), n)
        point = {"split": args.split, "first_seed": seeds[0], "episodes": n, "samples": K, "threshold": thr,
                 "commit": commit, "engine": path,
                 "collision": round(col.mean(), 4), "collision_lo": round(cl, 4), "collision_hi": round(ch, 4),
                 "success": round(suc.mean(), 4), "success_lo": round(sl, 4), "success_hi": round(sh, 4),
                 "labels": planner.labelled, "planner_labels_per_s": round(planner.labelled / planner.seconds, 1),
                 "planner_labels_per_cpu_s": round(planner.labelled / planner.cpu_seconds, 1),
                 "run_labels_per_s": round(planner.labelled / wall, 1),
                 "run_labels_per_cpu_s": round(planner.labelled / cpu, 1), "wall_s": round(wall, 1),
                 "load": " ".join(f"{x:.2f}" for x in os.getloadavg())}
        print(point, flush=True)
        points.append(point)
        if args.out:  # every point so far, whole: the first write a new file (one appeared meanwhile is kept)
            (write_new_or_exit if len(points) == 1 else write_text_atomic)(args.out, csv_text(points), "--out")


if __name__ == "__main__":
    main()
