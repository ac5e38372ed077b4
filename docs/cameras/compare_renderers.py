"""The texture camera renderer against the original raster renderer on the same poses (issue 18).

    .venv/bin/python docs/cameras/compare_renderers.py [--steps 150]

Drives each scenario (the lap on layouts A and B with PID on the true CTE, the left turn in traffic with IDLE),
renders the three windshield cameras at every step with both renderers (``render_views(..., ground="texture")``,
the default, and ``ground="raster"``, the original code kept for this comparison), by day, in fog (80 m) and at
night (clean frames: noise off, so only the renderers differ), and writes ``docs/cameras/renderer_comparison.md``
(per-pixel |difference| statistics: mean, share of pixels whose largest channel difference is above 10 and 30
of 255) and ``renderer_side_by_side.png`` (texture | raster | |difference| ×4 for a few of the poses).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np

import av_gym  # noqa: F401  (registers the envs)
from agents import PIDSteering
from av_gym.sensors.camera import CAMERA_NAMES, Weather, camera_rig, render_views

OUT = Path(__file__).resolve().parent
LANE_ID, TURN_ID = "av_gym/LaneKeepingLap-v0", "av_gym/UnprotectedLeftTurn-v0"
SCENARIOS = {"lap A": (LANE_ID, {"track": "A"}), "lap B": (LANE_ID, {"track": "B"}), "left turn": (TURN_ID, {})}
WEATHERS = {"day": Weather(), "fog 80 m": Weather(fog_visibility=80.0), "night": Weather(night=True)}


def poses(env_id: str, config: dict, steps: int, seed: int = 0):
    """Drive ``steps`` policy steps and yield the env after each (PID on the true CTE on the lap, IDLE on the
    turn), resetting with the next seed when an episode ends."""
    env = gym.make(env_id, config=config)
    _, info = env.reset(seed=seed)
    pid = PIDSteering()
    for _ in range(steps):
        a = pid.act({"state": np.array([info["truth"]["cte"]])}) if env_id == LANE_ID else 1
        _, _, term, trunc, info = env.step(a)
        if term or trunc:
            seed += 1
            _, info = env.reset(seed=seed)
            pid.reset()
        yield env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=150)
    args = parser.parse_args()
    rig = camera_rig()
    rows, tiles = [], []
    for scenario, (env_id, config) in SCENARIOS.items():
        for wname, weather in WEATHERS.items():
            diffs = []
            for k, env in enumerate(poses(env_id, config, args.steps)):
                new = render_views(env, rig, weather=weather)
                old = render_views(env, rig, weather=weather, ground="raster")
                diffs += [np.abs(new[c].astype(np.int16) - old[c]).max(-1) for c in CAMERA_NAMES]
                if k == args.steps // 3 and wname != "fog 80 m":
                    d = np.abs(new["centre"].astype(np.int16) - old["centre"]).clip(0, 63).astype(np.uint8) * 4
                    tiles.append((f"{scenario}, {wname}, step {k}", new["centre"], old["centre"], d))
            d = np.stack(diffs)
            rows.append((scenario, wname, len(diffs), d.mean(), (d > 10).mean(), (d > 30).mean(),
                         np.percentile(d, 99)))
            print(rows[-1])
    lines = ["# Texture renderer vs the original raster renderer", "",
             f"Same poses, clean frames (noise off), three cameras per pose, `python docs/cameras/compare_renderers.py"
             f" --steps {args.steps}`. Difference per pixel = the largest of its three channel differences (0-255).",
             "", "| scenario | conditions | frames | mean abs diff | pixels > 10 | pixels > 30 | 99th percentile |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {s} | {w} | {n} | {m:.2f} | {a:.2%} | {b:.2%} | {p:.0f} |" for s, w, n, m, a, b, p in rows]
    (OUT / "renderer_comparison.md").write_text("\n".join(lines) + "\n")
    print("wrote", OUT / "renderer_comparison.md")

    scale = 3
    strips = []
    for caption, new, old, diff in tiles:
        row = [cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST) for im in (new, old, diff)]
        row = np.concatenate([np.pad(t, ((0, 0), (2, 2), (0, 0)), constant_values=255) for t in row], 1)
        strip = np.full((24, row.shape[1], 3), 255, np.uint8)
        cv2.putText(strip, f"{caption}: texture | raster | |diff| x4", (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (0, 0, 0), 1, cv2.LINE_AA)
        strips += [strip, row]
    image = np.concatenate(strips, 0)
    cv2.imwrite(str(OUT / "renderer_side_by_side.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print("wrote", OUT / "renderer_side_by_side.png")


if __name__ == "__main__":
    main()
