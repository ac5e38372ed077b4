"""Distribution check of the batched left turn: the same agents on the same seeds through ``python -m
eval`` on the per-env stack and on the batched engine; collision rate, success rate and mean time to exit (and min
TTC), with the 95 % confidence interval of the difference (normal approximation, unpaired, so it does not lean on
the episodes being the same ones), and how many episodes have the identical row.

    python -m eval agents='[always_proceed,gap_acceptance,checkpoints/reference/ppo_turn]' episodes=2000 \\
        seed=50000 out_dir=DIR_PER_ENV
    python -m eval agents='[...same...]' episodes=2000 seed=50000 vec_env=batched n_envs=256 out_dir=DIR_BATCHED
    python benchmarks/batched_distribution.py DIR_PER_ENV/results.csv DIR_BATCHED/results.csv [more pairs...]
"""

from __future__ import annotations

import argparse
import csv
import math

import numpy as np

METRICS = ("collision", "success", "time_to_exit_s", "min_ttc_s")
OUTCOME = ("collision", "success", "length", "truncated")
NAMES = ("agent", "split")  # the columns of python -m eval's results.csv that are not numbers


def read(path: str) -> dict[str, dict[int, dict]]:
    out: dict[str, dict[int, dict]] = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            vals = {k: float(v) if v not in ("", "nan") else math.nan for k, v in row.items() if k not in NAMES}
            out.setdefault(row["agent"], {})[int(vals["seed"])] = vals
    return out


def diff_ci(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """Mean difference b - a and its 95 % CI (normal approximation, unpaired; NaNs dropped)."""
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    d = b.mean() - a.mean()
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    return d, d - 1.96 * se, d + 1.96 * se


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("csv", nargs="+", help="pairs: per-env results.csv, batched results.csv")
    args = parser.parse_args()
    if len(args.csv) % 2:
        parser.error("give results.csv files in pairs: per-env, batched")
    per_env, batched = {}, {}
    for p, b in zip(args.csv[::2], args.csv[1::2]):
        per_env.update(read(p))
        batched.update(read(b))
    print("| agent | metric | per-env | batched | difference [95 % CI] | within |")
    print("|---|---|---:|---:|---|---|")
    for agent, ref in per_env.items():
        bat = batched.get(agent)
        if bat is None:
            continue
        seeds = sorted(set(ref) & set(bat))
        for m in METRICS:
            a, b = np.array([ref[s][m] for s in seeds]), np.array([bat[s][m] for s in seeds])
            d, lo, hi = diff_ci(a, b)
            print(f"| {agent} | {m} | {np.nanmean(a):.3f} | {np.nanmean(b):.3f} | {d:+.4f} [{lo:+.4f}, {hi:+.4f}] | "
                  f"{'yes' if lo <= 0 <= hi else 'NO'} |")
        same_outcome = sum(all(ref[s][k] == bat[s][k] for k in OUTCOME) for s in seeds)
        same_row = sum(all(ref[s][k] == bat[s][k] or abs(ref[s][k] - bat[s][k]) <= 1e-6
                                or (ref[s][k] != ref[s][k] and bat[s][k] != bat[s][k]) for k in ref[s])
                       for s in seeds)
        print(f"| {agent} | episodes: same outcome / every column within 1e-6 | | "
              f"{same_outcome}/{len(seeds)} / {same_row}/{len(seeds)} | | |")


if __name__ == "__main__":
    main()
