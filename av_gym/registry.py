"""One registry per family of kinds (scenarios, sensors, shields here; agent kinds and teachers in
:mod:`agents.registry`): a name → the class that implements it, whose ``Params`` dataclass is its configuration.

A new kind is one class with its ``Params`` plus one ``register`` line; the config checker, ``make_env``, the
trainers and the evaluation find it through the registry and nothing else needs editing (tests/test_registry.py
registers a toy kind of each family to prove it).

Entries may be given as ``"module:Class"`` strings so that a family lists its kinds in one place without
importing them all (a truth-only env does not load OpenCV or kiss-icp); the class is imported on first use.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from typing import Any

from av_gym import SCENARIO_ENTRIES
from av_gym.errors import ConfigError


class Registry:
    """Named kinds of one family, in registration order (for sensors: the order they are stacked)."""

    def __init__(self, family: str, entries: dict[str, Any] | None = None) -> None:
        self.family = family
        self._entries: dict[str, Any] = dict(entries or {})

    def register(self, name: str, target: Any = None, *, replace: bool = False):
        """Register ``target`` (a class, a callable or a ``"module:attr"`` string) under ``name``; without a
        target, a class decorator."""
        if target is None:
            return lambda cls: self.register(name, cls, replace=replace) or cls
        if name in self._entries and not replace:
            raise ValueError(f"{self.family} {name!r} is already registered")
        self._entries[name] = target
        return target

    def unregister(self, name: str) -> None:
        self._entries.pop(name, None)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def names(self) -> list[str]:
        return list(self._entries)

    def get(self, name: str, where: str | None = None) -> Any:
        """The class registered as ``name`` (imported now if it was given as a string); a :class:`ConfigError`
        naming ``where`` (default: the family) and the allowed names otherwise."""
        if name not in self._entries:
            raise ConfigError(f"{where or self.family} must be one of {self.names()}, got {name!r}")
        target = self._entries[name]
        if isinstance(target, str):
            module, _, attr = target.partition(":")
            target = getattr(importlib.import_module(module), attr)
            self._entries[name] = target
        return target

    def items(self) -> Iterator[tuple[str, Any]]:
        for name in list(self._entries):
            yield name, self.get(name)


SCENARIOS = Registry("env.name", {name: entry for name, (_, entry) in SCENARIO_ENTRIES.items()})
"""``env.name`` → the env class; its ``Params`` is the ``env`` config section (edge units); its Gymnasium id is in
:data:`av_gym.SCENARIO_ENTRIES`."""

SENSORS = Registry("sensor", {
    "gnss": "av_gym.sensors.gnss:GNSS",
    "imu": "av_gym.sensors.imu:IMU",
    "lidar": "av_gym.sensors.lidar:Lidar",
    "cameras": "av_gym.sensors.camera:Cameras",
    "detector": "av_gym.sensors.detector:Detector",
    "turn_signals": "av_gym.sensors.turn_signal:TurnSignals",
    # estimators read sensor keys and add estimated ones beside them: stacked after every sensor, in this order
    "localizer": "av_gym.estimation.localization:Localizer",
    "tracker": "av_gym.estimation.object_tracking:ObjectTracker",
    "turn_features": "av_gym.estimation.turn_features:TurnFeatures",
    "turn_intent": "av_gym.estimation.turn_features:TurnIntent",
    "lane_features": "av_gym.estimation.lane_features:LaneFeatures",
})
"""``sensors.<key>`` → the observation wrapper (sensor or estimator), stacked in this order; its ``Params``
is the section's parameters."""

SHIELDS = Registry("shield.kind", {
    "aeb": "av_gym.shields.aeb:AEBShield",
})
"""``shield.kind`` → the safety-shield wrapper; ``none`` (no shield) is not a kind."""
