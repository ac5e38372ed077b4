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
from av_gym.registry import SCENARIOS
from av_gym.metrics.recorder import EpisodeMetrics

SENSOR_PRESETS = ("truth", "gnss_imu", "gnss_raw", "lidar", "cameras", "detector", "localized", "full",
                  "turn_truth", "turn_perceived", "lane_localized", "camera_centre")


def _shields() -> dict:
    """shield config ``kind`` → builder ``f(env, params: dict) -> gym.Env`` (wraps the sensed env)."""
    from agents.aeb import build_shield  # imported here: av_gym stays importable without agents/

    return {"aeb": build_shield}


def _sensor_classes() -> dict:
    """Sensor config key → wrapper class, in the order they are stacked (imported here, not at module level, so
    building a truth-only env does not load OpenCV)."""
    from av_gym.sensors.detector import Detector
    from av_gym.sensors.gnss import GNSS
    from av_gym.sensors.imu import IMU

    from av_gym.sensors.camera import Cameras
    from av_gym.sensors.lidar import Lidar
    from av_gym.sensors.turn_signal import TurnSignals

    return {"gnss": GNSS, "imu": IMU, "lidar": Lidar, "cameras": Cameras, "detector": Detector,
            "turn_signals": TurnSignals, **_estimators()}


def _estimators() -> dict:
    """Estimator config key → wrapper class. Estimators read sensor keys and add estimated ones beside them
    (e.g. ``ego_estimate``), so they are stacked after every sensor, in this order."""
    from av_gym.estimation.localization import Localizer
    from av_gym.estimation.lane_features import LaneFeatures
    from av_gym.estimation.object_tracking import ObjectTracker
    from av_gym.estimation.turn_features import TurnFeatures, TurnIntent

    return {"localizer": Localizer, "tracker": ObjectTracker, "turn_features": TurnFeatures,
            "turn_intent": TurnIntent, "lane_features": LaneFeatures}


def add_sensors(env: gym.Env, sensors_cfg: Mapping | None) -> gym.Env:
    """Stack the sensor wrappers a ``sensors`` preset asks for; drop the privileged ``state`` unless
    ``keep_state``. Parameter errors name the field (``sensors.gnss.sigma must be >= 0, got -1``)."""
    import inspect

    from gymnasium.wrappers import FilterObservation

    c = _plain(sensors_cfg)
    name = c.get("name", "truth")
    if name not in SENSOR_PRESETS:
        raise ConfigError(f"sensors must be one of {list(SENSOR_PRESETS)}, got {name!r}")
    classes = _sensor_classes()
    known = {"name", "keep_state", "observe", *classes}
    unknown = sorted(set(c) - known)
    if unknown:
        raise ConfigError(f"sensors.{unknown[0]} is not a sensor; allowed: {sorted(classes)}")
    for key, cls in classes.items():
        params = c.get(key)
        if params is None:
            continue
        if getattr(cls, "Params", None) is not None:
            from av_gym.params import ParamError

            try:
                env = cls(env, cls.Params.from_mapping(params, where=f"sensors.{key}",
                                                       what=f"a parameter of {cls.__name__}"))
            except ParamError as exc:
                raise ConfigError(str(exc)) from None
            continue
        signature = inspect.signature(cls.__init__).parameters
        allowed = [p for p in signature if p not in ("self", "env")]
        bad = [] if any(p.kind is p.VAR_KEYWORD for p in signature.values()) else sorted(set(params) - set(allowed))
        if bad:
            raise ConfigError(f"sensors.{key}.{bad[0]} is not a parameter of {cls.__name__}; allowed: {allowed}")
        try:
            env = cls(env, **params)
        except ValueError as exc:
            msg = str(exc)
            raise ConfigError(msg if msg.startswith(f"sensors.{key}") else f"sensors.{key}: {msg}") from None
    if c.get("observe"):  # the keys the agent sees (e.g. only the features an estimator computed)
        missing = sorted(set(c["observe"]) - set(env.observation_space.spaces))
        if missing:
            raise ConfigError(f"sensors.observe lists {missing[0]!r}, which this preset does not provide; "
                              f"allowed: {sorted(env.observation_space.spaces)}")
        return FilterObservation(env, filter_keys=list(c["observe"]))
    if not c.get("keep_state", name == "truth"):
        keys = [k for k in env.observation_space.spaces if k != "state"]
        if not keys:
            raise ConfigError(f"sensors={name} removes the privileged state and adds no sensor")
        env = FilterObservation(env, filter_keys=keys)
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
    """The full stack for one episode stream: scenario → sensors → shield → :class:`EpisodeMetrics`."""
    env_id, config = highway_config(env_cfg)
    try:
        env = gym.make(env_id, config=config, render_mode=render_mode)
    except ValueError as exc:  # the envs validate their own config and name the field
        raise ConfigError(str(exc)) from None
    env = add_sensors(env, sensors_cfg)
    env = add_shield(env, shield_cfg)
    return EpisodeMetrics(env) if record_metrics else env


def add_shield(env: gym.Env, shield_cfg: Mapping | None) -> gym.Env:
    """Wrap ``env`` in the safety shield a ``shield`` config asks for (``kind: none`` leaves it unchanged)."""
    c = _plain(shield_cfg)
    kind = c.get("kind", c.get("name", "none"))
    builders = _shields()
    if kind == "none":
        return env
    if kind not in builders:
        raise ConfigError(f"shield.kind must be one of {['none', *builders]}, got {kind!r}")
    params = {k: v for k, v in c.items() if k not in ("name", "kind")}
    try:
        return builders[kind](env, params)
    except (TypeError, ValueError) as exc:
        msg = str(exc)
        raise ConfigError(msg if msg.startswith("shield.") else f"shield: {msg}") from None
