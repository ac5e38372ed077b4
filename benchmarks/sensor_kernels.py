"""CPU time of one LiDAR scan and one detector frame, with the numba kernels (av_gym/sensors/kernels.py) and with the
numpy reference code they replace.

    python benchmarks/sensor_kernels.py [--steps 200] [--repeats 3]

For each scenario, one seeded drive (PID on the true CTE for the lap, IDLE for the left turn) with a `Lidar` and a
`Detector`; at every step the scan (``Lidar._scan``), its ray cast alone (``_cast`` on the same inputs) and the
detector frame (``Detector._frame``) are timed with the kernels on and off, interleaved on the same states. CPU time
of this process, best of ``--repeats`` drives, so load from other processes inflates it less than wall time. The
roadside world is built before the timing (once per episode; see ``generate_world``). The detector's switch covers
its occlusion test only: both columns draw a detection's noise the same (one call, av_gym/sensors/detector.py).
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse
import time

import gymnasium as gym
import numpy as np

import av_gym  # noqa: F401  (registers the envs)
from agents import PIDSteering
from av_gym.sensors import detector as det
from av_gym.sensors import lidar as lid
from av_gym.sensors.base import ego_pose, others_state
from av_gym.sensors.world import roadside_world

ENV_IDS = {"lane_keeping": "av_gym/LaneKeepingLap-v0", "left_turn": "av_gym/UnprotectedLeftTurn-v0"}


def drive(scenario: str, steps: int) -> dict[str, float]:
    """CPU seconds per call of each timed part, kernels on and off, over one ``steps``-step drive."""
    env = det.Detector(lid.Lidar(gym.make(ENV_IDS[scenario])))
    lidar, detector = env.env, env
    on = {"lidar": set(lid.KERNELS), "detector": set(det.KERNELS)}
    total: dict[str, float] = {}

    def timed(name: str, fn, *args) -> None:
        for kernels in ((True, False) if step % 2 else (False, True)):  # alternate which runs first (cache-cold)
            lid.KERNELS.clear()
            det.KERNELS.clear()
            if kernels:
                lid.KERNELS.update(on["lidar"])
                det.KERNELS.update(on["detector"])
            t0 = time.process_time()
            fn(*args)
            key = f"{name} {'kernels' if kernels else 'numpy'}"
            total[key] = total.get(key, 0.0) + time.process_time() - t0

    try:
        seed, pid = 0, PIDSteering()
        obs, info = env.reset(seed=seed)
        for step in range(steps):
            a = pid.act({"state": np.array([info["truth"]["cte"]])}) if scenario == "lane_keeping" else 1
            obs, _, terminated, truncated, info = env.step(a)
            if terminated or truncated:
                seed += 1
                obs, info = env.reset(seed=seed)
                pid.reset()
            world = roadside_world(env)
            x, y, psi, _ = ego_pose(env)
            others = others_state(env)
            boxes = lid.box_corners(others[:, 0:2], others[:, 4], others[:, 5], others[:, 6])
            angles = psi + np.pi - 2 * np.pi / lidar.beams * np.arange(lidar.beams)
            timed("ray cast", lid._cast, np.array([x, y]), angles, lidar.elevations, lidar.mount_height,
                  world.segments, np.inf, world.circles, np.inf, boxes, np.inf, lidar.max_range)
            timed("LiDAR scan", lidar._scan, 0.0)
            timed("detector frame", detector._frame)
    finally:
        lid.KERNELS.clear()
        lid.KERNELS.update(on["lidar"])
        det.KERNELS.clear()
        det.KERNELS.update(on["detector"])
    return {k: v / steps for k, v in total.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    drive("left_turn", 5)  # load (or compile) the kernels outside the timing
    print(f"\n{'scenario':<14} {'part':<16} {'numpy ms':>9} {'kernels ms':>11} {'speed-up':>9}")
    for scenario in ENV_IDS:
        runs = [drive(scenario, args.steps) for _ in range(args.repeats)]
        best = {k: min(r[k] for r in runs) for k in runs[0]}
        for part in ("ray cast", "LiDAR scan", "detector frame"):
            a, b = best[f"{part} numpy"], best[f"{part} kernels"]
            print(f"{scenario:<14} {part:<16} {1000 * a:>9.3f} {1000 * b:>11.3f} {a / b:>9.2f}")


if __name__ == "__main__":
    main()
