"""Cost of each sensor per policy step, as a ratio to the bare env step measured in the same run.

    python benchmarks/sensor_cost.py [--steps 300] [--repeats 3]

For each scenario, the same seeded episodes are driven with the same actions (PID on the true CTE for the lap,
IDLE for the left turn) by the bare env, the env with one sensor, and the env with the `full` preset. The table
reports milliseconds per policy step, wall and CPU time of this process (best of ``--repeats`` runs, to suppress
scheduler noise), and their ratios to the bare env. Target: env+full / env <= 2.0. On a shared machine
the CPU-time ratio is the steadier one: other processes' load stretches wall time, not this process's CPU time.

A second table times one 66x200 camera frame on one core (OpenCV limited to one thread), for the texture
renderer (the default) and the original raster renderer (``ground="raster"``) on the same poses: CPU time per
frame (best of ``--repeats``), so load from other processes on a shared machine inflates it less than wall time;
plus the whole sensor frame of the default `Cameras` wrapper (texture render + exposure + pixel noise) on the same
poses. Target: <= 0.3 ms per frame.
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse
import time

import numpy as np
from hydra import compose, initialize_config_module

from agents import PIDSteering
from av_gym.make import make_env

PRESETS = ["gnss_imu", "lidar", "cameras", "detector", "full"]


def run(env, steps: int, seed: int = 0) -> tuple[float, float]:
    """Wall and CPU seconds per policy step over ``steps`` steps (resets excluded from the timing)."""
    pid = PIDSteering()
    total, cpu, n = 0.0, 0.0, 0
    obs, info = env.reset(seed=seed)
    while n < steps:
        if env.unwrapped.scenario == "lane_keeping":
            a = pid.act({"state": np.array([info["truth"]["cte"]])})
        else:
            a = 1
        t0, c0 = time.perf_counter(), time.process_time()
        obs, _, terminated, truncated, info = env.step(a)
        total += time.perf_counter() - t0
        cpu += time.process_time() - c0
        n += 1
        if terminated or truncated:
            seed += 1
            obs, info = env.reset(seed=seed)
            pid.reset()
    return total / n, cpu / n


def best_of(make, steps: int, repeats: int) -> tuple[float, float]:
    """Best wall and best CPU time per step over ``repeats`` runs, each on a freshly built env."""
    runs = [run(make(), steps) for _ in range(repeats)]
    return min(r[0] for r in runs), min(r[1] for r in runs)


def frame_cost(scenario: str, steps: int, repeats: int) -> dict[str, float]:
    """CPU seconds per camera frame of each renderer, on the poses of one seeded drive (best of ``repeats``)."""
    import cv2
    import gymnasium as gym

    from av_gym.sensors.camera import Cameras, camera_rig, render_views

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        env_id = {"lane_keeping": "av_gym/LaneKeepingLap-v0", "left_turn": "av_gym/UnprotectedLeftTurn-v0"}[scenario]
        env = gym.make(env_id)
        sensor = Cameras(env)  # the default wrapper, measured on the same poses (it steps nothing itself)
        rig = camera_rig()
        best = {"texture": np.inf, "raster": np.inf, "sensor": np.inf}
        for _ in range(repeats):
            seed, pid = 0, PIDSteering()
            obs, info = sensor.reset(seed=seed)
            for g in ("texture", "raster"):  # per-episode scene and per-layout texture built outside the timing
                render_views(env, rig, ground=g)
            total = {g: 0.0 for g in best}
            for _ in range(steps):
                a = pid.act({"state": np.array([info["truth"]["cte"]])}) if scenario == "lane_keeping" else 1
                obs, _, terminated, truncated, info = env.step(a)
                if terminated or truncated:
                    seed += 1
                    obs, info = sensor.reset(seed=seed)
                    pid.reset()
                    for g in ("texture", "raster"):
                        render_views(env, rig, ground=g)
                for g in best:
                    t0 = time.process_time()
                    if g == "sensor":
                        sensor.measure()
                    else:
                        render_views(env, rig, ground=g)
                    total[g] += time.process_time() - t0
            best = {g: min(best[g], total[g] / (steps * len(rig))) for g in best}
        return best
    finally:
        cv2.setNumThreads(threads)


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
            bare = best_of(lambda: make_env(base_cfg.env, record_metrics=False), args.steps, args.repeats)
            rows.append((scenario, "bare env", bare, bare))
            for preset in available:
                cfg = compose("train", overrides=[f"env={scenario}", f"sensors={preset}"])
                t = best_of(lambda: make_env(cfg.env, cfg.sensors, record_metrics=False), args.steps, args.repeats)
                rows.append((scenario, f"env + {preset}", t, bare))
    print(f"\n{'scenario':<14} {'stack':<20} {'ms/step':>9} {'ratio':>7} {'CPU ms/step':>12} {'CPU ratio':>10}")
    for scenario, stack, (t, c), (t0, c0) in rows:
        print(f"{scenario:<14} {stack:<20} {1000 * t:>9.2f} {t / t0:>7.2f} {1000 * c:>12.2f} {c / c0:>10.2f}")
    print(f"\n{'scenario':<14} {'camera frame (1 core)':<22} {'texture ms':>10} {'raster ms':>10} {'speed-up':>9} "
          f"{'sensor frame ms':>16}")
    for scenario in ("lane_keeping", "left_turn"):
        c = frame_cost(scenario, args.steps, args.repeats)
        print(f"{scenario:<14} {'66x200, CPU time':<22} {1000 * c['texture']:>10.3f} {1000 * c['raster']:>10.3f} "
              f"{c['raster'] / c['texture']:>9.2f} {1000 * c['sensor']:>16.3f}")


def _exists(preset: str) -> bool:
    from importlib import resources

    return (resources.files("conf") / "sensors" / f"{preset}.yaml").is_file()


if __name__ == "__main__":
    main()
