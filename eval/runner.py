"""Run a policy on seeded episodes and collect one metrics row per episode."""

from __future__ import annotations

from collections.abc import Iterable

import gymnasium as gym
from tqdm import tqdm

from agents import Policy


def run_episodes(env: gym.Env, policy: Policy, seeds: Iterable[int], label: str,
                 progress: bool = True) -> list[dict]:
    """One row per seed: ``{"agent", "episode", "seed", **info["episode_metrics"]}``. ``env`` must be wrapped in
    :class:`av_gym.metrics.recorder.EpisodeMetrics` (as :func:`av_gym.make.make_env` does)."""
    seeds = list(seeds)
    rows = []
    for i, seed in enumerate(tqdm(seeds, desc=f"eval {label}", unit="ep", disable=not progress, leave=False)):
        obs, _ = env.reset(seed=int(seed))
        policy.reset()
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            done = terminated or truncated
        rows.append({"agent": label, "episode": i, "seed": int(seed), **info["episode_metrics"]})
    return rows
