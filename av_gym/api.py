"""What ``gym.make("av_gym/...")`` and ``gymnasium.make_vec`` build: the registered ids' entry points.

``gym.make(id)`` alone gives the bare scenario (its privileged ``state`` observation), as before; the keywords
give the harness's stack in one call, built by the same code ``python -m train`` uses (:mod:`av_gym.make`):

    gym.make("av_gym/UnprotectedLeftTurn-v0", sensors="turn_perceived", shield="aeb",
             env={"spawn_probability": 0.3})                  # a conf/env section's fields (km/h, degrees)
    gym.make("av_gym/UnprotectedLeftTurn-v0", sensors={"name": "turn_perceived", "detector": {"miss_rate": 0.2}})
    gym.make("av_gym/UnprotectedLeftTurn-v0", checkpoint="ppo_turn")  # a shipped agent's env (or a run folder)

- ``config``: highway-env's own config dict (SI units, the env's ``default_config()`` keys), checked before the
  env is built: unknown keys (with the closest known one), types and the bounds of the scenario's ``Params``;
  a partial ``action`` dict is completed from the defaults.
- ``env``: the scenario's ``Params`` fields (conf/env/<scenario>.yaml, edge units), over the shipped defaults.
- ``sensors`` / ``shield``: a preset name of conf/sensors, conf/shield, or a mapping whose ``name`` is one with
  fields to change (deep-merged, as ``sensors.detector.miss_rate=0.2`` on the command line).
- ``checkpoint``: a shipped reference agent's name (:func:`av_gym.reference`) or a run folder (``config.yaml`` +
  ``model.zip``): its env, sensors, shield and the agent-side
  wrappers it was trained with (go/yield actions, action repeat, flat observation), so that SB3's
  ``PPO.load(<folder>/model.zip).predict(obs)`` drives it.

Every stack with sensors, a shield or a checkpoint records :class:`~av_gym.metrics.recorder.EpisodeMetrics`
(``info["episode_metrics"]`` at the end of an episode), as the harness does.

Every ``info`` key has one kind of value at reset and in every step, and none is None, so that
``gymnasium.make_vec(..., vectorization_mode="sync"/"async")`` batches each into a typed array whichever env has
just reset (an array takes the first env's type): "not yet" is a sentinel of the key's own type (the shield's
:data:`~av_gym.shields.aeb.NOT_YET`, :data:`~av_gym.shields.aeb.NO_ACTION`); ``info["truth"]`` is a mapping, not a
dict, batched as an object array of each env's own (tests/test_vector_api.py).
"""

from __future__ import annotations

import copy
import difflib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from av_gym.errors import ConfigError
from av_gym.presets import as_section, compose_group, deep_merge, plain

# ----------------------------------------------------------------------------------------------- entry points
def lane_keeping(**kwargs: Any) -> gym.Env:
    """Entry point of ``av_gym/LaneKeepingLap-v0`` (see the module docstring for the keywords)."""
    return make("lane_keeping", **kwargs)


def left_turn(**kwargs: Any) -> gym.Env:
    """Entry point of ``av_gym/UnprotectedLeftTurn-v0`` (see the module docstring for the keywords)."""
    return make("left_turn", **kwargs)


def left_turn_vector(num_envs: int, *, env: Mapping | None = None, sensors: Any = None, shield: Any = None,
                     config: Mapping | None = None, render_mode: str | None = None, actions: str = "env",
                     action_repeat: int = 1, **make_only: Any) -> gym.vector.VectorEnv:
    """``vector_entry_point`` of ``av_gym/UnprotectedLeftTurn-v0``: the batched engine (all envs in one numpy
    batch, :mod:`av_gym.batched.vec_env`), what ``gymnasium.make_vec(id, n)`` gives when no
    ``vectorization_mode`` is named. It runs the ``turn_truth`` and ``turn_perceived`` sensors, without a shield or
    with ``shield="aeb"`` (:mod:`av_gym.batched.shield`); anything else (``config=``, ``render_mode=``, another
    shield, ``make_only``: a keyword of :func:`make` the batch does not take, ``checkpoint=`` or ``record_metrics=``)
    is refused in one line (``vectorization_mode="sync"`` or ``"async"`` runs every stack)."""
    import numbers

    from av_gym.batched.vec_env import BatchedLeftTurnVectorEnv, check_batchable

    # the batch's rows are allocated at once: 0 or -1 failed deep in numpy, 1e9 asked for 179 GiB, 2.5 passed; the
    # bound is the one agent.n_envs has for the same engine (its speed is flat well before it)
    if isinstance(num_envs, bool) or not isinstance(num_envs, numbers.Integral) or not 1 <= num_envs <= 4096:
        raise ConfigError(f"num_envs must be an integer in [1, 4096] (the batched engine's rows), got {num_envs!r}")
    other = 'use gymnasium.make_vec(..., vectorization_mode="sync" or "async") for it'
    if config is not None:
        raise ConfigError(f"config= is not available with the batched engine (give env={{...}}); {other}")
    if render_mode is not None:
        raise ConfigError(f"render_mode is not available with the batched engine; {other}")
    given = sorted(k for k, v in make_only.items() if v is not None)
    if given:  # make()'s keywords reach here through make_vec: named, with the modes that run them
        raise ConfigError(f"{'=, '.join(given)}= {'is' if len(given) == 1 else 'are'} not available with the batched "
                          f"engine (it takes env=, sensors=, shield=, actions=, action_repeat=); {other}")
    if sensors is None:
        raise ConfigError(f"the batched engine needs sensors=\"turn_truth\" or \"turn_perceived\" (it computes the "
                          f"turn features, not the privileged state); {other}")
    env_cfg = deep_merge(preset("env", "left_turn"), _mapping(env or {}, "env"))
    sensors_cfg, shield_cfg = as_section("sensors", sensors, "truth"), as_section("shield", shield, "none")
    try:
        check_batchable(env_cfg, sensors_cfg, shield_cfg, with_shield=True)
    except ConfigError as exc:
        if "agent.vec_env=batched" not in str(exc):  # a bad value (miss_rate=nan): the other modes refuse it too
            raise
        what = str(exc).split("; use ")[0].replace("agent.vec_env=batched", "the batched engine")
        raise ConfigError(f"{what}; {other}") from None
    return BatchedLeftTurnVectorEnv(env_cfg, sensors_cfg, int(num_envs), shield_cfg, actions=actions,
                                    action_repeat=int(action_repeat))


def make(scenario: str, config: Mapping | None = None, *, env: Mapping | None = None, sensors: Any = None,
         shield: Any = None, checkpoint: str | Path | None = None, render_mode: str | None = None,
         record_metrics: bool | None = None) -> gym.Env:
    """The scenario env (``config``: SI, ``env``: edge units), with ``sensors``, ``shield`` and a ``checkpoint``'s
    agent wrappers; one :class:`ConfigError` line naming the field on bad input, before anything is built.

    Example: a shipped agent's env (its sensors and agent-side wrappers: GO/YIELD), and a mistyped field:

        >>> import gymnasium as gym
        >>> import av_gym
        >>> env = gym.make("av_gym/UnprotectedLeftTurn-v0", checkpoint="ppo_turn")
        >>> obs, info = env.reset(seed=0)
        >>> env.action_space
        Discrete(2)
        >>> gym.make("av_gym/UnprotectedLeftTurn-v0", env={"spawn_probabilty": 0.3})
        Traceback (most recent call last):
        ...
        av_gym.params.ParamError: env.spawn_probabilty is not a field of ...; did you mean 'spawn_probability'?
    """
    from av_gym.make import scenario_params, wrap_env
    from av_gym.registry import SCENARIOS

    cls = SCENARIOS.get(scenario, where="env.name")
    check_render_mode(cls, render_mode)
    if checkpoint is not None:
        if any(x is not None for x in (config, env, sensors, shield)):
            raise ConfigError("checkpoint= builds the env the checkpoint was trained on; give no config, env, "
                              "sensors or shield with it")
        return checkpoint_env(scenario, checkpoint, render_mode)
    if config is not None and env is not None:
        raise ConfigError("give the scenario's settings as env={...} (conf/env fields: km/h, degrees) or "
                          "config={...} (highway-env's keys, SI units), not both")
    if env is not None:
        section = deep_merge(preset("env", scenario), _mapping(env, "env"))
        section["name"] = scenario
        config = scenario_params(section).env_config()
    full = checked_config(scenario, config)
    try:
        base = cls(config=full, render_mode=render_mode)
    except ValueError as exc:  # the envs check their relations (frequencies, ranges) and name the field
        raise ConfigError(str(exc)) from None
    if sensors is None and shield is None and env is None:
        return base if not record_metrics else wrap_env(base, None, None)
    sensors_cfg = as_section("sensors", sensors, default="truth")
    shield_cfg = as_section("shield", shield, default="none")
    return wrap_env(base, sensors_cfg, shield_cfg, record_metrics=record_metrics is not False)


def check_render_mode(cls: type, render_mode: Any) -> None:
    allowed = list(cls.metadata.get("render_modes", []))
    if render_mode is not None and render_mode not in allowed:
        raise ConfigError(f"render_mode must be one of {allowed} or None, got {render_mode!r}")


def checkpoint_env(scenario: str, folder: str | Path, render_mode: str | None = None) -> gym.Env:
    """The env a trained run (``folder``/config.yaml) was trained on, with its agent-side wrappers (what the
    harness's validation drives it in: no time-limit-as-termination, no intervention cost)."""
    import yaml

    from av_gym.make import make_training_env

    folder = checkpoint_folder(folder)
    path = folder / "config.yaml"
    if not path.is_file():
        raise ConfigError(f"checkpoint={folder}: no config.yaml there (a run folder under checkpoints/ has one)")
    cfg = yaml.safe_load(path.read_text()) or {}
    if (cfg.get("env") or {}).get("name") != scenario:
        raise ConfigError(f"checkpoint={folder} was trained on env={(cfg.get('env') or {}).get('name')}, not "
                          f"{scenario}")
    agent = cfg.get("agent") or {}
    return make_training_env(cfg["env"], cfg.get("sensors"), cfg.get("shield"), 0.0,
                             int(agent.get("action_repeat", 1)), str(agent.get("actions", "env")),
                             render_mode=render_mode)


def checkpoint_folder(checkpoint: str | Path) -> Path:
    """A ``checkpoint=`` value as a folder: the name of a shipped reference agent (``"ppo_turn"``, see
    :func:`av_gym.reference`) or a path to a run folder. A bare name means the shipped agent even where the working
    folder holds a folder of that name: a path says ``./ppo_turn``."""
    from av_gym.references import reference, reference_names

    if isinstance(checkpoint, str) and "/" not in checkpoint and "\\" not in checkpoint:
        if checkpoint in reference_names():
            return reference(checkpoint)
        if not Path(checkpoint).is_dir():
            raise ConfigError(f"checkpoint must be a run folder or one of the shipped agents {reference_names()}, "
                              f"got {checkpoint!r}")
    if not isinstance(checkpoint, (str, Path)):
        raise ConfigError(f"checkpoint must be a run folder (str or Path) or a shipped agent's name, got "
                          f"{checkpoint!r}")
    return Path(checkpoint)


# ----------------------------------------------------------------------------------------------- config checks
def checked_config(scenario: str, config: Mapping | None) -> dict:
    """``config`` over the scenario's defaults, refused in one line (``config.<key> ...``): an unknown key (with the
    closest known one); a key that comes from a scenario field (the one table,
    :attr:`~av_gym.envs.base.ScenarioParams.CONFIG_KEYS`) against that field's type, bounds (in SI) and relations;
    any other key against the type of its default. Nested dicts (``action``) are merged, so
    ``{"action": {"type": "continuous"}}`` keeps the default acceleration range."""
    from av_gym.envs.base import config_value
    from av_gym.registry import SCENARIOS

    cls = SCENARIOS.get(scenario, where="env.name")
    defaults = cls.default_config()
    if config is None:
        return defaults
    merged = copy.deepcopy(defaults)
    for key, value in _mapping(config, "config").items():
        for sub, v in _known_keys(scenario, defaults, key, value):
            if sub not in cls.Params.CONFIG_KEYS:
                _check_like_default(sub, v, config_value(defaults, sub))
        merged[key] = {**defaults[key], **value} if _nested(defaults, key) else value
    problems = cls.Params.config_problems(merged)
    if problems:
        raise ConfigError(problems[0])
    return merged


def _nested(defaults: Mapping, key: str) -> bool:
    """Whether ``key`` is a dict of settings merged key by key (``action``); ``observation`` is given whole."""
    return isinstance(defaults[key], dict) and key != "observation"


def _known_keys(scenario: str, defaults: Mapping, key: Any, value: Any) -> list[tuple[str, Any]]:
    """``[(dotted key, value)]`` of one entry of a config (a nested dict's entries each), or a :class:`ConfigError`
    for a key the scenario does not have."""
    if key not in defaults:
        close = difflib.get_close_matches(str(key), list(defaults), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else f"; allowed: {sorted(defaults)}"
        raise ConfigError(f"config.{key} is not a setting of {scenario}{hint}")
    if not _nested(defaults, key):
        return [(key, value)]
    if not isinstance(value, Mapping):
        raise ConfigError(f"config.{key} must be a mapping, got {value!r}")
    for sub in value:
        if sub not in defaults[key]:
            raise ConfigError(f"config.{key}.{sub} is not a setting of {scenario}; allowed: {sorted(defaults[key])}")
    return [(f"{key}.{sub}", v) for sub, v in value.items()]


def _check_like_default(key: str, value: Any, default: Any) -> None:
    """A key no scenario field gives (``ttc_horizon``, highway-env's own): the type of its default."""
    if isinstance(default, bool):
        ok, what = isinstance(value, bool), "true or false"
    elif isinstance(default, (int, float)):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and bool(np.isfinite(value))
        what = "a finite number"
    elif isinstance(default, str):
        ok, what = isinstance(value, str), "a string"
    else:
        return
    if not ok:
        raise ConfigError(f"config.{key} must be {what}, got {value!r}")


# ----------------------------------------------------------------------------------------------- presets
def preset(group: str, name: str) -> dict:
    """A shipped preset of conf/<group>/, composed as the command line composes it (:mod:`av_gym.presets`)."""
    return compose_group(group, name)


def _mapping(value: Any, what: str) -> dict:
    value = plain(value)
    if not isinstance(value, Mapping):
        raise ConfigError(f"{what} must be a mapping or a preset name, got {value!r}")
    return dict(value)
