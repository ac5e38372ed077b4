"""av-gym: Gymnasium scenarios, sensor-noise wrappers and metrics for autonomous-driving research."""

import os

from gymnasium.envs.registration import register, registry

# highway-env renders (videos, camera frames, plots) through pygame, which initialises SDL's video subsystem. With no
# display SDL first tries X11/Wayland, prints "error: XDG_RUNTIME_DIR is invalid or not set in the environment." to
# stderr, then falls back to its off-screen driver: the same frames, after a line that reads like a failure. Ask for
# the off-screen driver directly when there is no display, unless the user chose a driver. Not "dummy": highway-env
# disables its viewer under that driver, and every rendered frame comes out black.
if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")

__version__ = "0.1.0"

ENV_IDS = {
    "lane_keeping": "av_gym/LaneKeepingLap-v0",
    "left_turn": "av_gym/UnprotectedLeftTurn-v0",
}

if ENV_IDS["lane_keeping"] not in registry:
    register(id=ENV_IDS["lane_keeping"], entry_point="av_gym.envs.lane_keeping:LaneKeepingLapEnv")
if ENV_IDS["left_turn"] not in registry:
    register(id=ENV_IDS["left_turn"], entry_point="av_gym.envs.left_turn:UnprotectedLeftTurnEnv")
