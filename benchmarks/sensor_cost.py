"""Cost of each sensor per policy step, as a ratio to the bare env step measured in the same run.

    python benchmarks/sensor_cost.py [--steps 300] [--repeats 3]

For each scenario, the same seeded episodes are driven with the same actions (PID on the true CTE for the lap,
IDLE for the left turn) by the bare env, the env with one sensor, and the env with the `full` preset. The table
reports milliseconds per policy step (best of ``--repeats`` runs, to suppress scheduler noise) and the ratio to
the bare env. Target (issue 3): env+full / env <= 2.0.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from hydra import compose, initialize_config_module

from agents import PIDSteering
from av_gym.make import make_env

PRESETS = ["gnss_imu", "lidar", "cameras", "detector", "full"]


def run(env, steps: int, seed: int = 0) -> float:
    """Seconds per policy step over ``steps`` steps (resets excluded from the timing)."""
    pid = PIDSteering()
    total, n = 0.0, 0
    obs, info = env.reset(seed=seed)
    while n < steps:
        if env.unwrapped.scenario == "lane_keeping":
            a = pid.act({"state": np.array([info["truth"]["cte"]])})
        else:
            a = 1
        t0 = time.perf_counter()
        obs, _, terminated, truncated, info = env.step(a)
        total += time.perf_counter() - t0
        n += 1
        if terminated or truncated:
            seed += 1
            obs, info = env.reset(seed=seed)
            pid.reset()
    return total / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with initialize_config_module("conf", version_base="1.3"):
        available = [p for p in PRESETS if _exists(p)]
        rows = []
        for scenario in ("lane_keeping", "left_turn"):
            base_cfg = compose("train", overrides=[f"env={scenario}"])
            bare = min(run(make_env(base_cfg.env, record_metrics=False), args.steps) for _ in range(args.repeats))
            rows.append((scenario, "bare env", bare, 1.0))
            for preset in available:
                cfg = compose("train", overrides=[f"env={scenario}", f"sensors={preset}"])
                t = min(run(make_env(cfg.env, cfg.sensors, record_metrics=False), args.steps)
                        for _ in range(args.repeats))
                rows.append((scenario, f"env + {preset}", t, t / bare))
    print(f"\n{'scenario':<14} {'stack':<20} {'ms/step':>9} {'ratio':>7}")
    for scenario, stack, t, ratio in rows:
        print(f"{scenario:<14} {stack:<20} {1000 * t:>9.2f} {ratio:>7.2f}")


def _exists(preset: str) -> bool:
    from importlib import resources

    return (resources.files("conf") / "sensors" / f"{preset}.yaml").is_file()


if __name__ == "__main__":
    main()
