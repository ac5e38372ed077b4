"""What both scenarios share on top of highway-env's ``AbstractEnv``: a per-tick hook and an episode seed for
everything outside the simulator (sensor noise, the roadside world)."""

from __future__ import annotations

import copy
from collections import UserDict
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

import numpy as np
from gymnasium import error

from av_gym.actions import InvalidAction, check_action  # noqa: F401 - InvalidAction: re-exported
from av_gym.errors import ConfigError
from av_gym.params import RATE_MAX_HZ, Params, field_at, field_problems, param, relation_problems

KMH = 1 / 3.6  # m/s per km/h: scenario configs take km/h at the edge, the envs m/s

TO_SI: dict[str, Callable[[float], float]] = {
    "km/h": lambda v: v * KMH,
    "deg": lambda v: float(np.radians(v)),
}
"""A field's edge unit → SI: how the env config key that comes from a field in km/h or degrees gets its value (every
other unit is SI already)."""
FROM_SI: dict[str, Callable[[float], float]] = {
    "km/h": lambda v: v / KMH,
    "deg": lambda v: float(np.degrees(v)),
}


@dataclass(frozen=True)
class ScenarioParams(Params):
    """What every scenario's ``env`` section holds (edge units: km/h, degrees); :meth:`env_config` gives the
    env's own (highway-env) config in SI units. The registered Gymnasium ids default to these values."""

    name: str = param("", doc="the scenario: a key of av_gym.registry.SCENARIOS")
    policy_frequency: int = param(10, "Hz", ge=10, le=RATE_MAX_HZ, doc="decisions per second; >= 10 so a shield can decide every "
                                                        "0.1 s (digest 003 §9.2)")
    simulation_frequency: int = param(20, "Hz", ge=1, le=RATE_MAX_HZ, doc="simulation ticks per second, a multiple of "
                                                           "policy_frequency")
    fast: bool = param(True, doc="av_gym.sim fast paths, the same trajectories as highway-env's code (false = "
                                 "stock highway-env)")
    compare: tuple[str, ...] = param((), doc="python -m eval with no agents=: the agents compared on this scenario")

    CONFIG_KEYS: ClassVar[dict[str, str]] = {"simulation_frequency": "simulation_frequency",
                                             "policy_frequency": "policy_frequency", "fast": "fast"}
    """The one table of the env config (highway-env's keys, SI units) a scenario's fields give: config key (dotted
    into a nested dict: ``action.type``) → the field it comes from (dotted into a nested section: ``ccftap.dt``),
    converted from the field's unit by :data:`TO_SI`. :meth:`env_config` writes it, :meth:`config_problems` checks
    a config against the fields' types, bounds and relations; a new key is one field and one line here."""

    def relations(self) -> list[str]:
        if self.simulation_frequency % self.policy_frequency:
            return [f"@simulation_frequency ({self.simulation_frequency}) must be a multiple of @policy_frequency "
                    f"({self.policy_frequency})"]
        return []

    def env_config(self) -> dict:
        """The env's config dict (SI units), what ``gym.make(id, config=...)`` takes: :attr:`CONFIG_KEYS`."""
        config: dict = {}
        for key, path in self.CONFIG_KEYS.items():
            value = self
            for name in path.split("."):
                value = getattr(value, name)
            *heads, last = key.split(".")
            inner = config
            for head in heads:
                inner = inner.setdefault(head, {})
            inner[last] = _convert(value, TO_SI.get(field_at(type(self), path)[1].metadata.get("unit", "")))
        return config

    @classmethod
    def config_problems(cls, config: Mapping, where: str = "config") -> list[str]:
        """Every problem of the keys of an env ``config`` (SI units) that come from a field (:attr:`CONFIG_KEYS`),
        one line each naming ``<where>.<key>``: the field's type and bounds (converted to SI); once those hold and
        ``config`` has every top-level field's key, the relations between them. Other keys are not looked at."""
        found, values, present = [], {}, set()
        for key, path in cls.CONFIG_KEYS.items():
            value = config_value(config, key)
            if value is ABSENT:
                continue
            unit = field_at(cls, path)[1].metadata.get("unit", "")
            found += field_problems(cls, path, value, f"{where}.{key}", scale=TO_SI.get(unit))
            present.add(key)
            if "." not in path:  # relations are between top-level fields (a nested section checks its own)
                values[path] = _convert(value, FROM_SI.get(unit))
        if found or not {k for k, f in cls.CONFIG_KEYS.items() if "." not in f} <= present:
            return found
        key_of = {f: k for k, f in cls.CONFIG_KEYS.items()}
        return relation_problems(cls, values, lambda name: f"{where}.{key_of.get(name, name)}")


ABSENT = object()  # config_value's answer for a key a config does not hold


def config_value(config: Mapping, key: str) -> Any:
    """``config[key]`` with ``key`` dotted into nested dicts (``action.type``); :data:`ABSENT` where there is none."""
    value: Any = config
    for name in key.split("."):
        if not isinstance(value, Mapping) or name not in value:
            return ABSENT
        value = value[name]
    return value


def _convert(value: Any, unit: Callable[[float], float] | None) -> Any:
    """A field's value as an env config holds it: tuples as lists, numbers through ``unit`` (None: as they are)."""
    if isinstance(value, (tuple, list)):
        return [_convert(v, unit) for v in value]
    if unit is None or value is None or isinstance(value, bool) or not isinstance(value, (int, float)):
        return value
    return unit(value)


class Truth(UserDict):
    """``info["truth"]``: a mapping of ground-truth fields, deliberately not a ``dict``. Gymnasium's vector envs
    stack a ``dict`` in ``info`` field by field across envs, which fails on fields whose shape or type changes
    from env to env (``others``: one row per vehicle; ``arrived_time``: None until arrival): ``make_vec`` crashed
    at reset. Any other object they keep per env in an object array, so in a vector env
    ``info["truth"][i]`` is env ``i``'s truth, as in a single env."""

    def __eq__(self, other: object) -> bool:  # field by field, arrays whole (Gymnasium's determinism check asks)
        from gymnasium.utils.env_checker import data_equivalence

        if not isinstance(other, (Truth, dict)):
            return NotImplemented
        return data_equivalence(self.data, other.data if isinstance(other, Truth) else other)


class ScenarioMixin:
    """Mix in before ``AbstractEnv``.

    - ``tick_listeners``: callables ``f(env)`` run after every simulation tick (sensors that sample faster than
      the policy, e.g. the IMU, record there; highway-env only exposes the state at policy steps).
    - ``episode_seed``: drawn from the env's own generator at the end of every reset, so all sensor noise and the
      roadside world follow from ``reset(seed=...)`` and are independent of the wrapper order.
    """

    scenario: str = ""
    Params: ClassVar[type[ScenarioParams]]  # the scenario's env section: its defaults, checks and config keys

    def reset(self, *args, **kwargs):
        self._episode_over = False
        return super().reset(*args, **kwargs)

    def step(self, action):
        """highway-env's step, once the action is checked against ``action_space`` and the episode is running:
        after ``terminated`` or ``truncated`` the simulation would go on and pay rewards for an episode that has
        ended, so that is refused until ``reset()``."""
        if getattr(self, "_episode_over", False):
            raise error.ResetNeeded("step() after the episode ended (terminated or truncated): call reset() first")
        check_action(self.action_space, action)
        result = self._step(action)
        self._episode_over = bool(result[2] or result[3])
        return result

    def _step(self, action):
        """The scenario's own step, once the action is checked (highway-env's by default)."""
        return super().step(action)

    def _check_config(self) -> None:
        """The env's config against its scenario's fields (:meth:`ScenarioParams.config_problems`): built directly,
        or reconfigured, an env never saw the checks its Params make; one :class:`ConfigError` line."""
        if self.config == getattr(self, "_checked_config", None):  # asked at every reset: ~0.3 ms of a 2 ms one
            return
        problems = self.Params.config_problems(self.config)
        if problems:
            raise ConfigError(problems[0])
        self._checked_config = copy.deepcopy(self.config)

    def _init_scenario_state(self) -> None:
        if not hasattr(self, "tick_listeners"):
            self.tick_listeners: list[Callable] = []

    def _finish_reset(self) -> None:
        self._init_scenario_state()
        self.episode_seed = int(self.np_random.integers(2**63 - 1))

    def _simulate(self, action=None) -> None:
        self._init_scenario_state()
        frames = int(self.config["simulation_frequency"] // self.config["policy_frequency"])
        for frame in range(frames):
            if action is not None and frame == 0 and not self.config["manual_control"]:
                self.action_type.act(action)
            self.road.act()
            self.road.step(1 / self.config["simulation_frequency"])
            self.steps += 1
            self._on_tick()
            for listener in self.tick_listeners:
                listener(self)
            if frame < frames - 1:
                self._automatic_rendering()
        self.enable_auto_render = False

    def _on_tick(self) -> None:
        """Scenario bookkeeping after each tick (lap progress, arrival time)."""

    def _info(self, obs, action=None) -> dict:
        info = super()._info(obs, action)
        if isinstance(action, np.ndarray):  # highway-env stores the caller's array itself: a user re-using one action
            info["action"] = action.copy()  # array (or a buffer of infos) would see every step's record change with it
        info["truth"] = truth = Truth()
        truth.data = self.truth()  # the dict itself, not copied key by key
        return info
