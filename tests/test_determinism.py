"""Same config and seed, same evaluation metrics to the last bit: across two runs, and across ``n_envs`` = 1 (in
this process) and 2 (episodes spread over worker processes and put back in seed order)."""

from __future__ import annotations

import pytest

from av_gym.make import make_env
from eval.agents import plan_agent, resolve_agent
from eval.runner import EpisodeJob, run_episodes, run_episodes_parallel
from conftest import conf

SEEDS = range(1000, 1003)
# Sensor noise in the agent's observation and a perceived-mode shield (its own noisy detector and tracker), so
# that every random stream of an episode is exercised.
SENSORS = {"name": "gnss_imu", "gnss": conf("sensor", "gnss"), "imu": conf("sensor", "imu")}


def plan():
    p = plan_agent("always_proceed+aeb", "left_turn", SENSORS, {"name": "none", "kind": "none"}, "checkpoints")
    p.shield["mode"] = "perceived"
    return p


def in_process(p) -> list[dict]:
    env = make_env(conf("env", "left_turn"), p.sensors, p.shield)
    _, policy = resolve_agent(p.spec, env, "left_turn", "checkpoints")
    try:
        return run_episodes(env, policy, SEEDS, p.label, progress=False)
    finally:
        env.close()


def same_bits(a: list[dict], b: list[dict]) -> bool:
    """Equal rows, floats compared by their bits (NaN == NaN, 0.0 != -0.0)."""
    def key(v):
        return ("f", float(v).hex()) if isinstance(v, float) else v
    return [{k: key(v) for k, v in r.items()} for r in a] == [{k: key(v) for k, v in r.items()} for r in b]


@pytest.mark.slow  # 15-35 CPU-s (trains or runs whole evaluations): over the README test budget
def test_eval_rows_are_bit_identical_across_runs_and_n_envs():
    p = plan()
    one = in_process(p)
    again = in_process(p)
    job = EpisodeJob(conf("env", "left_turn"), p.sensors, p.shield, p.spec, "left_turn", "checkpoints", p.label)
    two = run_episodes_parallel(job, SEEDS, n_envs=2, progress=False)
    assert [r["seed"] for r in two] == list(SEEDS) and [r["episode"] for r in two] == [0, 1, 2]
    assert same_bits(one, again)
    assert same_bits(one, two), [(r["seed"], r.get("collision"), r.get("min_ttc_s")) for r in one + two]
    # the episodes differ from one another (the check would be empty otherwise)
    assert len({tuple(sorted((k, repr(v)) for k, v in r.items() if k not in ("episode", "seed"))) for r in one}) > 1
