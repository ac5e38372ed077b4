"""Across-seed table of left-turn evaluation rows: each training seed's rates, and the mean over seeds with its
95 % Student-t interval (the seeds are the sample: n = 3 gives t = 4.30).

    python docs/ppo/v2/seed_table.py runs/eval/headline_v2b/results.csv \
        --group "ppo_turn (batched, 40,960 decisions)=checkpoints/ppo_turn_v2b_s{}" --seeds 1,2,3 [--group ...]

Each ``--group NAME=PATTERN`` names the agent labels ``PATTERN.format(seed)`` of ``results.csv`` (what ``python -m
eval`` writes, one row per episode). Labels not in any group are printed as single rows (Wilson intervals over
episodes). Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import csv

import numpy as np
from scipy import stats

from av_gym.metrics.stats import wilson_ci

METRICS = ("collision", "success")


def rates(rows: list[dict], label: str) -> dict:
    mine = [r for r in rows if r["agent"] == label]
    if not mine:
        raise SystemExit(f"error: no rows for agent {label!r}")
    out = {"n": len(mine)}
    for m in METRICS:
        out[m] = float(np.mean([float(r[m]) for r in mine]))
    t = [float(r["time_to_exit_s"]) for r in mine if r.get("time_to_exit_s") not in (None, "", "nan")]
    t = [x for x in t if np.isfinite(x)]
    out["time_to_exit_s"] = float(np.mean(t)) if t else float("nan")
    return out


def wilson(rate: float, n: int) -> str:
    _, lo, hi = wilson_ci(int(round(rate * n)), n)
    return f"{rate:.3f} [{lo:.3f}, {hi:.3f}]"


def seed_mean(values: list[float]) -> str:
    v = np.asarray(values, float)
    m = v.mean()
    if len(v) < 2:
        return f"{m:.3f}"
    h = stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / np.sqrt(len(v))
    return f"{m:.3f} [{max(m - h, 0.0):.3f}, {min(m + h, 1.0):.3f}]"  # a rate: the interval clipped to [0, 1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", nargs="+")
    p.add_argument("--group", action="append", default=[], help="NAME=PATTERN with {} for the seed")
    p.add_argument("--seeds", default="1,2,3")
    a = p.parse_args()
    rows = []
    for path in a.results:
        with open(path, newline="") as f:
            rows += list(csv.DictReader(f))
    seeds = [s for s in a.seeds.split(",") if s]
    grouped = set()
    print("| agent | n | collision | success | time to exit s |")
    print("| --- | --- | --- | --- | --- |")
    for g in a.group:
        name, pattern = g.split("=", 1)
        per = []
        for s in seeds:
            label = pattern.format(s)
            grouped.add(label)
            r = rates(rows, label)
            per.append(r)
            print(f"| {name}, seed {s} | {r['n']} | {wilson(r['collision'], r['n'])} | "
                  f"{wilson(r['success'], r['n'])} | {r['time_to_exit_s']:.1f} |")
        print(f"| **{name}, mean of {len(per)} seeds** (95 % CI over seeds) | {len(per)} x {per[0]['n']} | "
              f"**{seed_mean([r['collision'] for r in per])}** | **{seed_mean([r['success'] for r in per])}** | "
              f"{np.mean([r['time_to_exit_s'] for r in per]):.1f} |")
    for label in dict.fromkeys(r["agent"] for r in rows):
        if label in grouped:
            continue
        r = rates(rows, label)
        print(f"| {label} | {r['n']} | {wilson(r['collision'], r['n'])} | {wilson(r['success'], r['n'])} | "
              f"{r['time_to_exit_s']:.1f} |")


if __name__ == "__main__":
    main()
