"""Example frames of the three windshield cameras (left | centre | right), for both scenarios.

    python docs/make_camera_frames.py [--each] [--out docs/cameras]

writes ``contact_sheet.png`` into ``--out`` (default: docs/cameras/, which docs/sensors.md shows): one row per
scene, each a montage of the left, centre and right 66×200 images, upscaled ×2 with nearest-neighbour so the pixels
the network sees stay visible, with a caption strip. Scenes: the lap's straight, the approach to layout A's left
hairpin and layout B's right hairpin, inside the left hairpin, the intersection with oncoming traffic and the CCFtap
target, the camera noise at its defaults and heavy, fog and night. ``--each`` also writes each scene's montage (×3)
and ``centre_hires.png`` (the centre camera at 264×800, for detail) beside it.
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import gymnasium as gym
import numpy as np

import av_gym  # noqa: F401  (registers the envs)
from av_gym.atomic import atomic_path
from av_gym.sensors.camera import CAMERA_NAMES, Cameras, CameraSpec, Weather, camera_rig, render_view, render_views
from conf.cli import ToolParser

OUT = Path(__file__).resolve().parent / "cameras"
SCALE = 3  # nearest-neighbour upscale of the 66×200 frames
LANE_ID, TURN_ID = "av_gym/LaneKeepingLap-v0", "av_gym/UnprotectedLeftTurn-v0"


def montage(frames: dict[str, np.ndarray], caption: str, scale: int = SCALE) -> np.ndarray:
    """Left | centre | right, upscaled ×scale, white separators, caption strip on top (RGB uint8)."""
    tiles = []
    for name in CAMERA_NAMES:
        tile = cv2.resize(frames[name], None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        cv2.putText(tile, name, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(np.pad(tile, ((0, 0), (3, 3), (0, 0)), constant_values=255))
    row = np.concatenate(tiles, 1)
    strip = np.full((26, row.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, caption, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([strip, row], 0)


def save(out: Path, name: str, image: np.ndarray) -> None:
    """``<out>/<name>.png`` from an RGB uint8 image, atomically (a failed write leaves the previous file whole)."""
    ok, png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise RuntimeError(f"OpenCV could not encode {name}.png")
    with atomic_path(out / f"{name}.png", "--out") as tmp:
        tmp.write_bytes(png.tobytes())
    print("wrote", out / f"{name}.png")


def lap(track: str, start_s: float) -> gym.Env:
    env = gym.make(LANE_ID, config={"track": track, "start_s": start_s, "initial_lateral_std": 0.0,
                                    "initial_heading_std": 0.0})
    env.reset(seed=0)
    return env


def turn_with_oncoming_cars(seed: int = 2, steps: int = 40) -> gym.Env:
    """Traffic mode, ego creeping to the line; stop at the step whose centre view shows the most car pixels."""
    env = gym.make(TURN_ID)
    env.reset(seed=seed)
    best, best_k = -1, 0
    for k in range(steps):
        img = render_view(env)
        n = int(((img[..., 0].astype(int) > img[..., 1].astype(int) + 60)).sum())
        if n > best:
            best, best_k = n, k
        env.step(1)
    env.reset(seed=seed)
    for _ in range(best_k):
        env.step(1)
    return env


def ccftap(seconds: float) -> gym.Env:
    env = gym.make(TURN_ID, config={"mode": "ccftap"})
    env.reset(seed=0)
    for _ in range(int(round(seconds * env.unwrapped.config["policy_frequency"]))):
        env.step(1)
    return env


def main(out: Path = OUT, each: bool = False) -> None:
    out.mkdir(parents=True, exist_ok=True)
    rig = camera_rig()
    shots: list[tuple[str, str, dict[str, np.ndarray]]] = []

    def shot(name: str, caption: str, frames: dict[str, np.ndarray]) -> None:
        shots.append((name, caption, frames))
        if each:
            save(out, name, montage(frames, caption))

    shot("lane_keeping_A_straight", "lane keeping, layout A: start of the 120 m straight",
         render_views(lap("A", 0.0), rig))
    shot("lane_keeping_A_before_left_hairpin", "layout A: 10 m before the 25 m-radius LEFT hairpin",
         render_views(lap("A", 110.0), rig))
    shot("lane_keeping_A_in_left_hairpin", "layout A: inside the left hairpin",
         render_views(lap("A", 135.0), rig))
    shot("lane_keeping_B_before_right_hairpin", "layout B: 10 m before the 22 m-radius RIGHT hairpin",
         render_views(lap("B", 90.0), rig))
    env = turn_with_oncoming_cars()
    shot("left_turn_oncoming_traffic", "left turn (traffic): approaching the intersection, crossing and oncoming cars",
         render_views(env, rig))
    shot("left_turn_ccftap", "left turn (CCFtap 15/45 km/h): turning, the oncoming target 32 m away",
         render_views(ccftap(6.5), rig))

    noisy = Cameras(gym.make(LANE_ID, config={"start_s": 110.0}))
    shot("noisy_default", "sensor noise at defaults (exposure, gain, pixel sigma 3)",
         noisy.reset(seed=1)[0]["cameras"])
    heavy = Cameras(gym.make(TURN_ID), noise={"pixel_std": 8.0, "blur_sigma": 0.8, "brightness": 25.0})
    shot("noisy_heavy", "heavy noise: pixel sigma 8, blur 0.8 px, brightness +-25",
         heavy.reset(seed=2)[0]["cameras"])
    shot("fog_left_turn", "fog, visibility 120 m (Koschmieder transmission from depth)",
         render_views(env, rig, weather=Weather(fog_visibility=120.0)))
    shot("fog_lane_keeping", "fog, visibility 80 m, layout A before the left hairpin",
         render_views(lap("A", 110.0), rig, weather=Weather(fog_visibility=80.0)))
    night = Cameras(gym.make(TURN_ID), night=True)
    shot("night_left_turn", "night: ambient x0.4, gamma 1.8, headlights, pixel sigma 12",
         night.reset(seed=2)[0]["cameras"])
    shot("night_lane_keeping", "night (clean), layout A before the left hairpin",
         render_views(lap("A", 110.0), rig, weather=Weather(night=True)))

    save(out, "contact_sheet", np.concatenate([montage(f, c, scale=2) for _, c, f in shots], 0))
    if each:
        hires = CameraSpec(height=264, width=800)
        save(out, "centre_hires", np.concatenate([render_view(lap("A", 110.0), hires), render_view(env, hires)], 0))


if __name__ == "__main__":
    parser = ToolParser(prog="docs/make_camera_frames.py", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT, help="folder for the images (default: docs/cameras/)")
    parser.add_argument("--each", action="store_true", help="also each scene's montage and centre_hires.png")
    args = parser.parse_args()
    main(args.out, args.each)
