"""Distribution check of the batched left turn (issue 16): the same policies on the same seeds, batched vs the
per-env fast stack; collision rate, success rate and mean time to exit, with the 95 % confidence interval of the
difference (normal approximation; unpaired, so it does not lean on the episodes being the same ones).

    python benchmarks/batched_distribution.py [--episodes 2000] [--seed 50000]

Policies: ``always_proceed`` (IDLE every step: the cruise set-point) and ``gap_acceptance``
(agents/go_yield.py's rule on obs["turn"], every 0.1 s), both at 10 Hz as ``python -m eval`` runs them.
"""

from __future__ import annotations

import argparse
import os
import time

import gymnasium as gym
import numpy as np
from omegaconf import OmegaConf

from agents.go_yield import GapAcceptance
from av_gym.envs.batched_vec import meta_actions
from av_gym.envs.left_turn_batched import BatchedLeftTurn
from av_gym.estimation.turn_features import OBJECT_FEATURES, T_MAX, TurnFeatures
from av_gym.make import highway_config

POLICIES = ("always_proceed", "gap_acceptance")


def gap_choices(turn: np.ndarray, rule: GapAcceptance) -> np.ndarray:
    """GapAcceptance.choice for a batch of turn features (B, F)."""
    n = len(OBJECT_FEATURES)
    objs = turn[:, 5:].reshape(len(turn), -1, n)
    present = objs[..., OBJECT_FEATURES.index("present")] > 0
    t_star = objs[..., OBJECT_FEATURES.index("t_star")] * T_MAX
    miss = objs[..., OBJECT_FEATURES.index("miss")] * 10.0
    threat = (present & (t_star > 0) & (t_star < rule.t_gap) & (miss < rule.miss)).any(axis=1)
    past_line = 30.0 * turn[:, 2].astype(float) < -1.0
    return np.where(threat & ~past_line, 0, 1)


def run_batched(config: dict, policy: str, seeds: list[int], chunk: int = 500) -> np.ndarray:
    """(n, 3) collision, success, time to exit (NaN if none) per episode."""
    out = []
    rule = GapAcceptance()
    for k in range(0, len(seeds), chunk):
        part = seeds[k:k + chunk]
        bt = BatchedLeftTurn(len(part), config)
        obs = bt.reset(part)
        active = np.ones(len(part), bool)
        while active.any():
            a = np.ones(len(part), int) if policy == "always_proceed" else meta_actions(gap_choices(obs, rule), obs)
            _, term, trunc = bt.step(a, active)
            obs = bt.observe()
            active &= ~(term | trunc)
        tr = bt.truth()
        out.append(np.stack([tr["collision"], tr["arrived"] & ~tr["collision"],
                             np.where(tr["arrived"] & ~tr["collision"], tr["arrived_time"], np.nan)], axis=1))
    return np.concatenate(out).astype(float)


def run_per_env(config: dict, policy: str, seeds: list[int]) -> np.ndarray:
    env_id, _ = highway_config({"name": "left_turn"})
    env = TurnFeatures(gym.make(env_id, config=config))
    rule = GapAcceptance()
    rows = []
    for s in seeds:
        obs, _ = env.reset(seed=s)
        while True:
            a = 1 if policy == "always_proceed" else rule.act(obs)
            obs, _, term, trunc, info = env.step(a)
            if term or trunc:
                break
        t = info["truth"]
        ok = t["arrived"] and not t["collision"]
        rows.append((t["collision"], ok, t["arrived_time"] if ok else np.nan))
    return np.array(rows, dtype=float)


def diff_ci(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """Mean difference b - a and its 95 % CI (normal approximation, unpaired; NaNs dropped)."""
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    d = b.mean() - a.mean()
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    return d, d - 1.96 * se, d + 1.96 * se


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--episodes", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=50000)
    args = parser.parse_args()
    _, config = highway_config({"name": "left_turn"})
    seeds = list(range(args.seed, args.seed + args.episodes))
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print("| policy | metric | per-env | batched | difference [95 % CI] | within |")
    print("|---|---|---:|---:|---|---|")
    for policy in POLICIES:
        t0 = time.process_time()
        ref = run_per_env(config, policy, seeds)
        t1 = time.process_time()
        bat = run_batched(config, policy, seeds)
        t2 = time.process_time()
        same = np.mean(np.all((ref == bat) | (np.isnan(ref) & np.isnan(bat)), axis=1))
        for j, name in enumerate(("collision", "success", "time_to_exit_s")):
            d, lo, hi = diff_ci(ref[:, j], bat[:, j])
            print(f"| {policy} | {name} | {np.nanmean(ref[:, j]):.3f} | {np.nanmean(bat[:, j]):.3f} | "
                  f"{d:+.4f} [{lo:+.4f}, {hi:+.4f}] | {'yes' if lo <= 0 <= hi else 'NO'} |")
        print(f"|  {policy} | episodes with identical outcome | | {same:.1%} | CPU s per-env {t1 - t0:.0f}, "
              f"batched {t2 - t1:.0f} | |")


if __name__ == "__main__":
    main()
