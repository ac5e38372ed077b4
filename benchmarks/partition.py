"""The oracle's edge over a student split into information and learning, from ``python -m eval`` rows.

    python benchmarks/partition.py docs/results/left_turn_partition/results.csv --oracle lookahead \\
        --planner belief_lookahead --students dagger_turn ppo_turn

The agents played the same seeds, so every difference is paired episode by episode. For success (higher is
better) and collision (lower is better): the oracle's edge over the student, ``edge = oracle - student`` (success;
``student - oracle`` for collisions), its information part ``oracle - planner`` (what a planner that knows only what
the car can know cannot get) and its learning part ``planner - student`` (what the car could know and the student
does not use); each with a 95 % interval from a paired bootstrap over seeds (``--resamples``), and the shares
``information / edge`` and ``learning / edge`` with their bootstrap intervals. Prints a markdown table.

    python benchmarks/partition.py docs/results/left_turn_partition/results.csv \\
        docs/results/left_turn_sensing_partition/results.csv --chain lookahead belief_lookahead belief_tracks \\
        dagger_turn_perceived

``--chain A B C ...`` splits the edge of the first agent over the last into the steps between neighbours (the
sensing partition, docs/dagger.md "What sensing costs": information no sensor has = oracle - planner on truth, what
the sensors lose = planner on truth - planner on tracks, learning still to do = planner on tracks - student), each
step and its share of the edge with the same paired bootstrap (the same resampled seeds for every step). The same
chain with the shield: ``--chain lookahead+aeb belief_lookahead+aeb belief_tracks+aeb dagger_turn_perceived+aeb``
(each agent's label as ``python -m eval`` wrote it). An agent without rows in the files is one line, exit 2."""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict

import numpy as np


def load(paths: list[str]) -> dict[str, dict[int, dict[str, float]]]:
    """Each agent's rows by seed from ``python -m eval`` results.csv files (each may be a comma-separated list)."""
    out: dict[str, dict[int, dict[str, float]]] = defaultdict(dict)
    for files in ",".join(paths).split(","):
        with open(files) as fh:
            for row in csv.DictReader(fh):
                out[row["agent"]][int(row["seed"])] = {"collision": float(row["collision"]),
                                                      "success": float(row["success"])}
    return out


def ci(a: np.ndarray) -> str:
    """The 95 % percentile interval of bootstrap values ``a``."""
    lo, hi = np.percentile(a, [2.5, 97.5])
    return f"[{lo:.3f}, {hi:.3f}]"


def missing(rows: dict, agents: list[str], paths: list[str]) -> str | None:
    """The one-line error for agents without rows in the files (a misspelt label, a ``+aeb`` row not measured yet),
    naming the agents the files hold; None when every agent has rows."""
    absent = [a for a in agents if not rows.get(a)]
    if not absent:
        return None
    return (f"error: no rows for {', '.join(absent)} in {', '.join(paths)}; the files hold: "
            f"{', '.join(sorted(a for a in rows if rows[a]))}")


def chain(rows: dict, agents: list[str], resamples: int, g: np.random.Generator) -> None:
    """Print the steps of ``agents`` (best first) on their common seeds: per metric, each agent's rate, each step
    between neighbours and its share of the first agent's edge over the last, with paired bootstrap intervals."""
    seeds = sorted(set.intersection(*(set(rows[a]) for a in agents)))
    if not seeds:
        sys.exit(f"no common seeds for {', '.join(agents)}")
    idx = g.integers(len(seeds), size=(resamples, len(seeds)))
    steps = [f"{a} - {b}" for a, b in zip(agents, agents[1:])]
    print("| metric | " + " | ".join(agents) + " | edge (first - last) | " + " | ".join(steps) + " | "
          + " | ".join(f"share: {s}" for s in steps) + " |")
    print("|---" * (3 * len(agents)) + "|")
    for metric, sign in (("success", 1.0), ("collision", -1.0)):
        v = [np.array([rows[a][k][metric] for k in seeds]) for a in agents]
        # oriented so that a positive step is the better agent's advantage
        diffs = [sign * (a - b) for a, b in zip(v, v[1:])]
        edge = sign * (v[0] - v[-1])
        E = edge[idx].mean(axis=1)
        ok = np.abs(E) > 1e-12
        cells = [f"{x.mean():.3f}" for x in v] + [f"{edge.mean():.3f} {ci(E)}"]
        cells += [f"{d.mean():.3f} {ci(d[idx].mean(axis=1))}" for d in diffs]
        cells += [f"{d.mean() / edge.mean():.2f} {ci(d[idx].mean(axis=1)[ok] / E[ok])}" if abs(edge.mean()) > 1e-12
                  else "n/a" for d in diffs]
        print(f"| {metric} | " + " | ".join(cells) + " |")
    print(f"\n{len(seeds)} common seeds ({seeds[0]}..{seeds[-1]}); intervals: 95 % paired bootstrap over seeds "
          f"({resamples} resamples)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", nargs="+", help="results.csv of python -m eval (several: one after the other)")
    ap.add_argument("--oracle", default="lookahead")
    ap.add_argument("--planner", default="belief_lookahead")
    ap.add_argument("--students", nargs="+", default=["dagger_turn", "ppo_turn"])
    ap.add_argument("--chain", nargs="+", default=None, help="agents best first: the steps between neighbours")
    ap.add_argument("--resamples", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.chain is not None and len(args.chain) < 2:
        print("error: --chain needs at least two agents (best first)", file=sys.stderr)
        sys.exit(2)
    rows = load(args.csv)
    problem = missing(rows, args.chain or [args.oracle, args.planner, *args.students], args.csv)
    if problem:
        print(problem, file=sys.stderr)
        sys.exit(2)
    g = np.random.default_rng(args.seed)
    if args.chain:
        chain(rows, args.chain, args.resamples, g)
        return
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
            e, i, l_ = edge_e.mean(), info_e.mean(), learn_e.mean()
            si = f"{i / e:.2f} {ci(share_i)}" if abs(e) > 1e-12 else "n/a"
            sl = f"{l_ / e:.2f} {ci(share_l)}" if abs(e) > 1e-12 else "n/a"
            print(f"| {student} | {metric} | {o.mean():.3f} | {p.mean():.3f} | {s.mean():.3f} | {e:.3f} {ci(E)} | "
                  f"{i:.3f} {ci(I)} | {l_:.3f} {ci(L)} | {si} | {sl} |")
    print(f"\n{len(seeds)} common seeds ({seeds[0]}..{seeds[-1]}); intervals: 95 % paired bootstrap over seeds "
          f"({args.resamples} resamples)")


if __name__ == "__main__":
    main()
