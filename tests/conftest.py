from __future__ import annotations

from importlib import resources

import numpy as np
import pytest
import yaml

from av_gym.make import make_env


def conf(group: str, name: str) -> dict:
    """A config section exactly as shipped in conf/ (tests build envs the way the CLI does)."""
    return yaml.safe_load((resources.files("conf") / group / f"{name}.yaml").read_text())


@pytest.fixture
def lane_cfg() -> dict:
    return conf("env", "lane_keeping")


@pytest.fixture
def turn_cfg() -> dict:
    return conf("env", "left_turn")


def ccftap_cfg(ego_kmh: float, target_kmh: float, dt: float, action: str = "discrete") -> dict:
    cfg = conf("env", "left_turn")
    cfg.update(mode="ccftap", action=action)
    cfg["ccftap"] = {"ego_speed_kmh": ego_kmh, "target_speed_kmh": target_kmh, "dt": dt}
    return cfg


def rollout(env, policy, seed: int, max_steps: int = 100_000):
    """Run one episode; returns (list of truth dicts, last info, terminated, truncated)."""
    obs, info = env.reset(seed=seed)
    policy.reset()
    truths = []
    for _ in range(max_steps):
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        truths.append(info["truth"])
        if terminated or truncated:
            return truths, info, terminated, truncated
    raise AssertionError("episode did not end")


class Scripted:
    """A policy from a function of (step, obs)."""

    def __init__(self, fn):
        self.fn, self.k = fn, 0

    def reset(self):
        self.k = 0

    def act(self, obs):
        self.k += 1
        return self.fn(self.k - 1, obs)


@pytest.fixture
def make():
    return make_env


def zeros_action(_k, _obs):
    return np.zeros(1, dtype=np.float32)
