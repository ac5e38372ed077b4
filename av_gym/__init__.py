"""av-gym: Gymnasium scenarios, sensor-noise wrappers and metrics for autonomous-driving research.

Example: the bare scenario (its privileged ``state`` observation), or the harness's stack through the same id's
keywords (a sensors preset, a shield, a scenario's fields in their units, km/h and degrees; :mod:`av_gym.api`):

    >>> import gymnasium as gym
    >>> import av_gym
    >>> env = gym.make("av_gym/LaneKeepingLap-v0")
    >>> obs, info = env.reset(seed=0)
    >>> sorted(obs)
    ['state']
    >>> env = gym.make("av_gym/UnprotectedLeftTurn-v0", sensors="turn_perceived", shield="aeb",
    ...                env={"spawn_probability": 0.3})
    >>> obs, info = env.reset(seed=0)
    >>> sorted(obs), env.action_space
    (['intent', 'turn'], Discrete(3))
    >>> obs, reward, terminated, truncated, info = env.step(1)
    >>> "aeb_override" in info
    True
    >>> "turn_perceived" in av_gym.presets.preset_names("sensors"), "ppo_turn" in av_gym.reference_names()
    (True, True)
"""

import importlib
import importlib.util
import os
from types import ModuleType

from gymnasium.envs.registration import register, registry

# highway-env renders (videos, camera frames, plots) through pygame, which initialises SDL's video subsystem. With no
# display SDL first tries X11/Wayland, prints "error: XDG_RUNTIME_DIR is invalid or not set in the environment." to
# stderr, then falls back to its off-screen driver: the same frames, after a line that reads like a failure. Ask for
# the off-screen driver directly when there is no display, unless the user chose a driver. Not "dummy": highway-env
# disables its viewer under that driver, and every rendered frame comes out black.
if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")

__version__ = "0.1.0"

SCENARIO_ENTRIES = {  # env.name → (Gymnasium id, class); av_gym.registry.SCENARIOS is built from this table
    "lane_keeping": ("av_gym/LaneKeepingLap-v0", "av_gym.envs.lane_keeping:LaneKeepingLapEnv"),
    "left_turn": ("av_gym/UnprotectedLeftTurn-v0", "av_gym.envs.left_turn:UnprotectedLeftTurnEnv"),
}
ENV_IDS = {name: gym_id for name, (gym_id, _) in SCENARIO_ENTRIES.items()}

for _name, (_gym_id, _) in SCENARIO_ENTRIES.items():
    if _gym_id not in registry:  # defaults: the task the harness trains and reports (each env's Params)
        # av_gym.api checks config/render_mode and adds the harness's sensors, shield or a checkpoint's wrappers
        register(id=_gym_id, entry_point=f"av_gym.api:{_name}",
                 vector_entry_point="av_gym.api:left_turn_vector" if _name == "left_turn" else None)


def _preload_in_forkserver() -> None:
    """Worker processes started by a forkserver (SB3's ``SubprocVecEnv`` default on Linux) import ``av_gym`` first,
    so the plain ids resolve there too: Gymnasium 1.x loads no plugins, and ``make_vec_env("av_gym/...",
    vec_env_cls=SubprocVecEnv)`` failed in every worker with "Namespace av_gym not found". Added to the
    modules already asked for; ``spawn`` workers still need the id written ``"av_gym:av_gym/..."``."""
    import multiprocessing.forkserver as forkserver

    server = getattr(forkserver, "_forkserver", None)
    modules = list(getattr(server, "_preload_modules", None) or ["__main__"])
    if server is not None and "av_gym" not in modules:
        server.set_forkserver_preload([*modules, "av_gym"])


_preload_in_forkserver()

from av_gym.references import reference, reference_names  # noqa: E402  (the shipped agents by name)


def __getattr__(name: str) -> ModuleType:
    """A submodule named as an attribute (``av_gym.presets.preset_names("sensors")`` right after ``import av_gym``)
    is imported then (PEP 562). Why not imported here: this package sits below every submodule (each imports its
    ids and errors from it), and ``import av_gym`` stays as light as Gymnasium's registration needs."""
    if name.startswith("_") or importlib.util.find_spec(f"{__name__}.{name}") is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return importlib.import_module(f"{__name__}.{name}")
