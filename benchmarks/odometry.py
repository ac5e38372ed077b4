"""Runtime per LiDAR scan of the localization stages, on recorded scans of a lap and a left turn.

    python benchmarks/odometry.py [--repeats 3] [--scans 300]

Scans are recorded once (the LiDAR's defaults, LidarParams: 720 beams, planar, 100 m), then each stage is timed
on the same scans: kiss-icp ``register_frame`` alone (plain and with a motion prior, and with deskew on scans cast
with ``deskew_poses``), the scan-to-map matcher, the EKF steps, and a whole ``fused``+map localizer step. Times are
the best of ``--repeats`` passes (per-scan mean, to suppress scheduler noise on shared cores) with the median and
95th percentile of that pass; Hz = 1 / mean. kiss-icp runs single-threaded (``max_threads=1``), as the localizer
does.
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse
import time
from importlib import resources

import numpy as np
import yaml

from agents import PIDSteering
from av_gym.estimation.ekf import EKFNoise, LocalizationEKF
from av_gym.estimation.lidar_odometry import LidarOdometry, MapMatcher, sensor_delta
from av_gym.estimation.localization import LocalizationPipeline, find_wrapper
from av_gym.make import make_env
from av_gym.metrics.localization import runtime_stats
from av_gym.metrics.stats import markdown_table
from av_gym.sensors.world import roadside_world


def _conf(group: str, name: str) -> dict:
    path = resources.files("conf") / group / f"{name}.yaml"
    if group == "sensor" and not path.is_file():  # its defaults are its Params (conf/__init__.py)
        from av_gym.registry import SENSORS

        return SENSORS.get(name).Params().as_dict()
    if group == "env":  # conf/env/*.yaml are defaults lists over the scenario Params: composed by Hydra
        from conf.presets import compose_group

        return compose_group("env", name)
    return yaml.safe_load(path.read_text())


def record(scenario: str, scans: int, deskew: bool = False, seed: int = 0) -> dict:
    lidar = {**_conf("sensor", "lidar"), "deskew_poses": deskew}
    env = make_env(_conf("env", scenario), {"name": "full", "keep_state": True, "gnss": _conf("sensor", "gnss"),
                                            "imu": _conf("sensor", "imu"), "lidar": lidar}, record_metrics=False)
    obs, info = env.reset(seed=seed)
    lid = find_wrapper(env, "lidar")
    pid = PIDSteering()
    out = {"points": [], "times": [], "pose": [], "obs": [], "env": env}
    for _ in range(scans):
        pts, t = lid.points()
        out["points"].append(pts)
        out["times"].append(t)
        out["pose"].append(lid.scan_pose())
        action = pid.act({"state": np.array([info["truth"]["cte"]])}) if scenario == "lane_keeping" \
            else env.unwrapped.cruise_action()
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    out["world"] = roadside_world(env)
    return out


def _prior(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b[:2] - a[:2]
    c, s = np.cos(a[2]), np.sin(a[2])
    return sensor_delta(c * d[0] + s * d[1], -s * d[0] + c * d[1], b[2] - a[2])


def time_odometry(rec: dict, prior: bool, deskew: bool = False) -> list[float]:
    odo = LidarOdometry(deskew=deskew)
    for k, (pts, t) in enumerate(zip(rec["points"], rec["times"])):
        odo.register(pts, t if deskew else None, prior=_prior(rec["pose"][k - 1], rec["pose"][k]) if prior and k
                     else None)
    return odo.runtimes


def time_map(rec: dict) -> list[float]:
    w = rec["world"]
    matcher = MapMatcher(w.segments, w.circles)
    rng = np.random.default_rng(0)
    out = []
    for pts, pose in zip(rec["points"], rec["pose"]):
        guess = pose + [*rng.normal(0, 0.05, 2), rng.normal(0, 0.002)]  # a converged filter's guess
        t0 = time.perf_counter()
        matcher.match(MapMatcher.scan_to_body(pts), guess)
        out.append(time.perf_counter() - t0)
    return out


def time_ekf(n: int = 2000) -> tuple[list[float], list[float], list[float]]:
    ekf = LocalizationEKF(EKFNoise())
    ekf.initialize([0.0, 0.0], 0.0, 10.0)
    pred, gnss, rel = [], [], []
    for k in range(n):
        t0 = time.perf_counter()
        ekf.predict(0.0, 0.01, 0.05)
        pred.append(time.perf_counter() - t0)
        if k % 2:
            t0 = time.perf_counter()
            ekf.update_gnss_position(ekf.x[:2] + 0.1)
            gnss.append(time.perf_counter() - t0)
        if k % 20 == 19:
            t0 = time.perf_counter()
            ekf.update_relative_pose([10.0, 0.0, 0.0])
            ekf.clone()
            rel.append(time.perf_counter() - t0)
    return pred, gnss, rel


def time_pipeline(scenario: str, scans: int, map_matching: bool) -> list[float]:
    env = make_env(_conf("env", scenario), {"name": "full", "keep_state": True, "gnss": _conf("sensor", "gnss"),
                                            "imu": _conf("sensor", "imu"), "lidar": _conf("sensor", "lidar")},
                   record_metrics=False)
    obs, info = env.reset(seed=0)
    pipe = LocalizationPipeline(mode="fused", map_matching=map_matching)
    pipe.reset(env, obs, np.random.default_rng(0))
    pid = PIDSteering()
    for _ in range(scans):
        action = pid.act({"state": np.array([info["truth"]["cte"]])}) if scenario == "lane_keeping" \
            else env.unwrapped.cruise_action()
        obs, _, terminated, truncated, info = env.step(action)
        pipe.step(obs)
        if terminated or truncated:
            break
    return pipe.runtimes["step"]


def best(fn, repeats: int) -> dict:
    runs = [runtime_stats(fn()) for _ in range(repeats)]
    return min(runs, key=lambda r: r["ms_mean"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scans", type=int, default=300)
    args = parser.parse_args()
    rows = []
    for scenario in ("lane_keeping", "left_turn"):
        rec = record(scenario, args.scans)
        skewed = record(scenario, args.scans, deskew=True)
        n_pts = float(np.mean([len(p) for p in rec["points"]]))
        stages = [
            ("kiss-icp register_frame, no prior", lambda: time_odometry(rec, prior=False)),
            ("kiss-icp register_frame, motion prior", lambda: time_odometry(rec, prior=True)),
            ("kiss-icp register_frame, deskew on", lambda: time_odometry(skewed, prior=True, deskew=True)),
            ("scan-to-map matching (MapMatcher.match)", lambda: time_map(rec)),
            ("localizer step, fused (odometry)", lambda: time_pipeline(scenario, args.scans, False)),
            ("localizer step, fused + map", lambda: time_pipeline(scenario, args.scans, True)),
        ]
        for name, fn in stages:
            rows.append({"scenario": scenario, "stage": name, "scans": len(rec["points"]), "points/scan": n_pts,
                         **best(fn, args.repeats)})
    pred, gnss, rel = time_ekf()
    for name, s in (("EKF predict (one IMU sample)", pred), ("EKF GNSS position update", gnss),
                    ("EKF relative-pose update + clone", rel)):
        rows.append({"scenario": "-", "stage": name, "scans": len(s), "points/scan": float("nan"),
                     **runtime_stats(s)})
    print(markdown_table(rows, ["scenario", "stage", "scans", "points/scan", "ms_mean", "ms_p50", "ms_p95", "hz"]))


if __name__ == "__main__":
    main()
