"""Build a scenario env, with its sensor preset, shield and metrics recorder, from a config section.

This is the one place that reads the ``env``/``sensors``/``shield`` config groups (``conf/``), converting their
edge units (km/h, degrees) to the SI units the envs use."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym

from av_gym import ENV_IDS
from av_gym.envs.base import ScenarioParams
from av_gym.errors import ConfigError
from av_gym.metrics.recorder import EpisodeMetrics
from av_gym.registry import SCENARIOS


def add_sensors(env: gym.Env, sensors_cfg: Mapping | None) -> gym.Env:
    """Stack the sensor wrappers a ``sensors`` preset asks for, in :data:`av_gym.registry.SENSORS` order (sensors,
    then the estimators that read them); drop the privileged ``state`` unless ``keep_state``. A bad parameter
    gives one line naming it under ``sensors.<key>``."""
    from av_gym.params import ParamError
    from av_gym.registry import SENSORS
    from av_gym.wrappers import SelectKeys

    c = _plain(sensors_cfg)
    name = c.get("name", "truth")
    unknown = sorted(set(c) - {"name", "keep_state", "observe", *SENSORS})
    if unknown:
        raise ConfigError(f"sensors.{unknown[0]} is not a sensor; allowed: {sorted(SENSORS)}")
    for key in SENSORS:
        if c.get(key) is None:
            continue
        if not isinstance(c[key], Mapping):  # a preset name or a level where the sensor's parameters go
            raise ConfigError(f"sensors.{key} must be a mapping of the {key} sensor's parameters ({{}} for its "
                              f"defaults), got {c[key]!r}")
        cls = SENSORS.get(key)  # imported only when used: a truth-only env does not load OpenCV
        try:
            params = cls.Params.from_mapping(c[key], where=f"sensors.{key}", what=f"a parameter of {cls.__name__}")
            env = cls(env, params)
        except ParamError as exc:
            raise ConfigError(str(exc)) from None
    if c.get("observe"):  # the keys the agent sees (e.g. only the features an estimator computed)
        missing = sorted(set(c["observe"]) - set(env.observation_space.spaces))
        if missing:
            raise ConfigError(f"sensors.observe lists {missing[0]!r}, which this preset does not provide; "
                              f"allowed: {sorted(env.observation_space.spaces)}")
        return SelectKeys(env, list(c["observe"]))
    if not c.get("keep_state", name == "truth"):
        keys = [k for k in env.observation_space.spaces if k != "state"]
        if not keys:  # the agent would observe nothing
            from av_gym.presets import preset_names

            presets = preset_names("sensors")
            if name not in presets:
                raise ConfigError(f"sensors.name={name!r} is not a sensors preset and the section names no sensor; "
                                  f"give a preset ({presets}) or sensor sections ({sorted(SENSORS)})")
            raise ConfigError(f"sensors={name} names no sensor and drops the simulator's state (keep_state: "
                              f"false): the agent would observe nothing; add a sensor ({sorted(SENSORS)}) or "
                              f"keep_state: true")
        env = SelectKeys(env, keys)
    return env


def _plain(cfg: Any) -> dict:
    if cfg is None:
        return {}
    if hasattr(cfg, "_metadata"):  # an OmegaConf node; keep av_gym importable without Hydra
        from omegaconf import OmegaConf

        return OmegaConf.to_container(cfg, resolve=True)
    if isinstance(cfg, Mapping):
        return dict(cfg)
    raise ConfigError(f"expected a mapping for a config section, got {type(cfg).__name__}")


def scenario_params(env_cfg: Mapping | ScenarioParams) -> ScenarioParams:
    """The ``env`` section as its scenario's typed params (``env.name`` picks the scenario in
    :data:`av_gym.registry.SCENARIOS`); one line naming the field on bad input."""
    if isinstance(env_cfg, ScenarioParams):
        return env_cfg
    c = _plain(env_cfg)
    cls = SCENARIOS.get(c.get("name"), where="env.name")
    return cls.Params.from_mapping(c, where="env", what=f"a field of env={c['name']}")


def highway_config(env_cfg: Mapping | ScenarioParams) -> tuple[str, dict]:
    """Gymnasium id and the env's ``config`` dict (SI units) for an ``env`` config section."""
    params = scenario_params(env_cfg)
    return ENV_IDS[params.name], params.env_config()


def make_env(env_cfg: Mapping, sensors_cfg: Mapping | None = None, shield_cfg: Mapping | None = None, *,
             render_mode: str | None = None, record_metrics: bool = True) -> gym.Env:
    """The full stack for one episode stream: scenario → sensors → shield → :class:`EpisodeMetrics`, from config
    sections as ``python -m train`` composes them (``env_cfg`` names the scenario, its fields in conf/env units).

    Example: the lap's layout B with GNSS and IMU (the ``gnss_imu`` preset, composed by :mod:`av_gym.presets`):

        >>> from av_gym.make import make_env
        >>> from av_gym.presets import compose_group
        >>> env = make_env({"name": "lane_keeping", "track": "B"}, compose_group("sensors", "gnss_imu"))
        >>> obs, info = env.reset(seed=0)
        >>> sorted(obs)
        ['gnss', 'imu']
    """
    env_id, config = highway_config(env_cfg)
    try:
        env = gym.make(env_id, config=config, render_mode=render_mode)
    except ValueError as exc:  # the envs validate their own config and name the field
        raise ConfigError(str(exc)) from None
    return wrap_env(env, sensors_cfg, shield_cfg, record_metrics=record_metrics)


def wrap_env(env: gym.Env, sensors_cfg: Mapping | None = None, shield_cfg: Mapping | None = None, *,
             record_metrics: bool = True) -> gym.Env:
    """Sensors → shield → :class:`EpisodeMetrics` around a scenario env (what :func:`make_env` and the registered
    ids' keywords, :mod:`av_gym.api`, both build)."""
    env = add_sensors(env, sensors_cfg)
    env = add_shield(env, shield_cfg)
    return EpisodeMetrics(env) if record_metrics else env


def make_training_env(env_cfg: Mapping, sensors_cfg: Mapping | None, shield_cfg: Mapping | None,
                      intervention_cost: float = 0.0, action_repeat: int = 1, actions: str = "env",
                      render_mode: str | None = None, timeout_is_terminal: bool = False) -> gym.Env:
    """The stack a PPO agent trains and is validated on: :func:`make_env`, then the agent-side wrappers its
    ``agent`` config asks for (time limit as termination, intervention cost, go/yield actions, action repeat) and
    the flat observation SB3 takes. ``python -m train`` and ``gym.make(id, checkpoint=...)`` both build it here."""
    from av_gym.wrappers import ActionRepeat, FlatDictObservation, InterventionCost, TimeLimitIsTerminal, action_set

    env = make_env(env_cfg, sensors_cfg, shield_cfg, render_mode=render_mode)
    if timeout_is_terminal:
        env = TimeLimitIsTerminal(env)
    if intervention_cost > 0:
        env = InterventionCost(env, intervention_cost)
    env = action_set(actions).wrap(env)
    if action_repeat > 1:
        env = ActionRepeat(env, action_repeat)
    return FlatDictObservation(env)


def add_shield(env: gym.Env, shield_cfg: Mapping | None) -> gym.Env:
    """Wrap ``env`` in the safety shield a ``shield`` config asks for (``kind: none`` leaves it unchanged)."""
    from av_gym.params import ParamError
    from av_gym.registry import SHIELDS

    c = _plain(shield_cfg)
    kind = c.get("kind", c.get("name", "none"))
    if kind == "none":
        return env
    if kind not in SHIELDS:
        raise ConfigError(f"shield.kind must be one of {['none', *SHIELDS]}, got {kind!r}")
    try:  # the shield class reads its own fields (name and kind aside) and names them under `shield`
        return SHIELDS.get(kind).from_config(env, c, where="shield")
    except ParamError as exc:
        raise ConfigError(str(exc)) from None
    except (TypeError, ValueError) as exc:
        msg = str(exc)
        raise ConfigError(msg if msg.startswith("shield.") else f"shield: {msg}") from None
