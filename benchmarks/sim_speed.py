"""Stock highway-env code vs av-gym's fast paths: same seeds, same actions, in one run.

    python benchmarks/sim_speed.py [--steps 400] [--repeats 3]

Prints simulation ticks/s and policy steps/s for ``fast=False`` (highway-env's own lane search and pandas
observation) and ``fast=True`` (the default), their ratio, for the unprotected left turn (traffic and CCFtap) and
the lap, bare and with the ``full`` sensor preset. Best of ``--repeats`` runs per row, to suppress scheduler noise.
The trajectories are identical (tests/test_fast_sim.py).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from hydra import compose, initialize_config_module

from av_gym.make import make_env

SCENARIOS = [("left_turn", []), ("left_turn", ["env.mode=ccftap"]), ("lane_keeping", [])]


def steps_per_second(env, steps: int) -> float:
    actions = np.random.default_rng(0)
    seed, n, busy = 0, 0, 0.0
    env.reset(seed=seed)
    while n < steps:
        a = np.array([actions.uniform(-0.1, 0.1)], np.float32) if env.unwrapped.scenario == "lane_keeping" else 1
        t0 = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(a)
        busy += time.perf_counter() - t0
        n += 1
        if terminated or truncated:
            seed += 1
            env.reset(seed=seed)
    return n / busy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rows = []
    with initialize_config_module("conf", version_base="1.3"):
        for scenario, extra in SCENARIOS:
            for sensors in ("truth", "full"):
                cfg = compose("train", overrides=[f"env={scenario}", f"sensors={sensors}", *extra])
                rates = {}
                for fast in (False, True):
                    env_cfg = {**dict(cfg.env), "fast": fast}
                    env = make_env(env_cfg, cfg.sensors, record_metrics=False)
                    rates[fast] = max(steps_per_second(env, args.steps) for _ in range(args.repeats))
                ticks = cfg.env.simulation_frequency // cfg.env.policy_frequency
                label = f"{scenario}{' ccftap' if extra else ''}"
                rows.append((label, sensors, rates[False], rates[True], ticks))
    print(f"\n{'scenario':<18} {'sensors':<7} {'stock steps/s':>13} {'fast steps/s':>12} {'stock ticks/s':>13} "
          f"{'fast ticks/s':>12} {'ratio':>6}")
    for label, sensors, slow, fast, ticks in rows:
        print(f"{label:<18} {sensors:<7} {slow:>13.0f} {fast:>12.0f} {slow * ticks:>13.0f} {fast * ticks:>12.0f} "
              f"{fast / slow:>6.2f}")


if __name__ == "__main__":
    main()
