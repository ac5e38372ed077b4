"""PPO-stage ablation table: each configuration's periodic evaluations at the clone (0 decisions) and after a fixed
PPO budget, on the same 50 validation seeds (100000-100049) every run evaluates on.

    python docs/ppo/v2/ablation_table.py [--at 20480]

Reads ``docs/ppo/v2/eval_ppo_turn_v2b_s*.csv`` (the reference recipe: attention + intent) and
``docs/ppo/v2/ablation/<config>_s*.csv`` (copies of ``runs/abl_<config>_s<seed>/eval.csv``). Per configuration:
each seed's collision / success, the mean over seeds with its 95 % Student-t interval, and the pooled rate over
all seeds' episodes with its Wilson interval (50 episodes per seed and evaluation).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from av_gym.metrics.stats import wilson_ci

HERE = Path(__file__).parent
N_EVAL = 50
CONFIGS = {
    "attention + intent (reference recipe)": sorted(HERE.glob("eval_ppo_turn_v2b_s*.csv")),
    "attention, no intent (`sensors.observe=[turn]`)": sorted((HERE / "ablation").glob("noint_s*.csv")),
    "MLP + intent (`agent.extractor=mlp`)": sorted((HERE / "ablation").glob("mlp_s*.csv")),
}


def fmt_seeds(v: list[float]) -> str:
    a = np.asarray(v)
    if len(a) < 2:
        return f"{a.mean():.3f}"
    h = stats.t.ppf(0.975, len(a) - 1) * a.std(ddof=1) / np.sqrt(len(a))
    return f"{a.mean():.3f} [{max(a.mean() - h, 0):.3f}, {min(a.mean() + h, 1):.3f}]"


def pooled(v: list[float]) -> str:
    k = int(round(sum(v) * N_EVAL))
    p, lo, hi = wilson_ci(k, N_EVAL * len(v))
    return f"{p:.3f} [{lo:.3f}, {hi:.3f}]"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--at", type=int, default=20480, help="decisions of PPO")
    a = ap.parse_args()
    print(f"| configuration | decisions | seeds | per seed (collision / success) | collision, mean of seeds "
          f"[95 % CI] | success, mean of seeds [95 % CI] | collision, pooled [Wilson] | success, pooled [Wilson] |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, files in CONFIGS.items():
        if not files:
            continue
        frames = {f.stem.split("_s")[-1]: pd.read_csv(f) for f in files}
        for at in (0, a.at):
            rows = {s: f[f.steps == at] for s, f in frames.items()}
            rows = {s: r.iloc[0] for s, r in rows.items() if len(r)}
            c = [float(r.collision) for r in rows.values()]
            su = [float(r.success) for r in rows.values()]
            per = ", ".join(f"s{s}: {float(r.collision):.2f} / {float(r.success):.2f}" for s, r in rows.items())
            print(f"| {name} | {at:,} | {len(rows)} | {per} | {fmt_seeds(c)} | {fmt_seeds(su)} | {pooled(c)} | "
                  f"{pooled(su)} |")


if __name__ == "__main__":
    main()
