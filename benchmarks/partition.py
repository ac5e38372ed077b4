"""The oracle's edge over a student split into information and learning, from ``python -m eval`` rows.

    python benchmarks/partition.py docs/results/left_turn_partition/results.csv --oracle lookahead \\
        --planner belief_lookahead --students dagger_turn ppo_turn

The agents played the same seeds, so every difference is paired episode by episode. For success (higher is
better) and collision (lower is better): the oracle's edge over the student, ``edge = oracle - student`` (success;
``student - oracle`` for collisions), its information part ``oracle - planner`` (what a planner that knows only what
the car can know cannot get) and its learning part ``planner - student`` (what the car could know and the student
does not use); each with a 95 % interval from a paired bootstrap over seeds (``--resamples``), and the shares
``information / edge`` and ``learning / edge`` with their bootstrap intervals. Prints a markdown table."""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict

import numpy as np


def load(path: str) -> dict[str, dict[int, dict[str, float]]]:
    out: dict[str, dict[int, dict[str, float]]] = defaultdict(dict)
    for files in path.split(","):
        with open(files) as fh:
            for row in csv.DictReader(fh):
                out[row["agent"]][int(row["seed"])] = {"collision": float(row["collision"]),
                                                      "success": float(row["success"])}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", help="results.csv of python -m eval (several: comma-separated)")
    ap.add_argument("--oracle", default="lookahead")
    ap.add_argument("--planner", default="belief_lookahead")
    ap.add_argument("--students", nargs="+", default=["dagger_turn", "ppo_turn"])
    ap.add_argument("--resamples", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rows = load(args.csv)
    g = np.random.default_rng(args.seed)
    print("| student | metric | oracle | planner | student | edge (oracle over student) | information (oracle - "
          "planner) | learning (planner - student) | information share | learning share |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for student in args.students:
        seeds = sorted(set(rows[args.oracle]) & set(rows[args.planner]) & set(rows[student]))
        if not seeds:
            sys.exit(f"no common seeds for {args.oracle}, {args.planner}, {student}")
        idx = g.integers(len(seeds), size=(args.resamples, len(seeds)))
        for metric, sign in (("success", 1.0), ("collision", -1.0)):
            o, p, s = (np.array([rows[a][k][metric] for k in seeds]) for a in (args.oracle, args.planner, student))
            # oriented so that a positive number is the oracle's (or the planner's) advantage
            edge_e, info_e, learn_e = sign * (o - s), sign * (o - p), sign * (p - s)
            boot = lambda x: x[idx].mean(axis=1)  # noqa: E731
            E, I, L = boot(edge_e), boot(info_e), boot(learn_e)
            ok = np.abs(E) > 1e-12
            share_i, share_l = I[ok] / E[ok], L[ok] / E[ok]

            def ci(a):
                lo, hi = np.percentile(a, [2.5, 97.5])
                return f"[{lo:.3f}, {hi:.3f}]"

            e, i, l_ = edge_e.mean(), info_e.mean(), learn_e.mean()
            si = f"{i / e:.2f} {ci(share_i)}" if abs(e) > 1e-12 else "n/a"
            sl = f"{l_ / e:.2f} {ci(share_l)}" if abs(e) > 1e-12 else "n/a"
            print(f"| {student} | {metric} | {o.mean():.3f} | {p.mean():.3f} | {s.mean():.3f} | {e:.3f} {ci(E)} | "
                  f"{i:.3f} {ci(I)} | {l_:.3f} {ci(L)} | {si} | {sl} |")
    print(f"\n{len(seeds)} common seeds ({seeds[0]}..{seeds[-1]}); intervals: 95 % paired bootstrap over seeds "
          f"({args.resamples} resamples)")


if __name__ == "__main__":
    main()
