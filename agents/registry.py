"""Agent kinds (``agent.kind``) and teachers (what ``agent.init`` may name): one registry each, the one list the
config checker, ``python -m train`` and ``python -m eval`` consult.

An agent kind is one :class:`AgentKind` subclass with its ``Params`` (an :class:`AgentParams` dataclass holding
every field of that kind, with its default, unit, bounds and reason) plus one line in :data:`AGENT_KINDS`:

- a rule-based kind implements :meth:`AgentKind.build` (its policy for an env, refusing an env that lacks the
  observation it reads, in one line);
- a trained kind names its ``checkpoint`` file and implements :meth:`AgentKind.load`; its trainer is registered by
  kind on the training side (:data:`train.registry.TRAINERS`), so that agents never name :mod:`train`.

Nothing else needs editing: tests/test_registry.py registers a toy kind and runs ``python -m eval``'s machinery
on it. The defaults of every kind reach Hydra through :func:`register_configs` (group ``agent_kind``), so a file
``conf/agent/<name>.yaml`` holds only what differs from its kind's defaults.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from av_gym.params import Params, check, param
from av_gym.registry import Registry


@dataclass(frozen=True)
class AgentParams(Params):
    """The fields every agent config has. A kind's Params subclasses this and gives ``kind`` its own default."""

    name: str = param("agent", doc="the agent config's name (conf/agent/<name>.yaml): labels, run names, "
                                   "checkpoint lookup")
    kind: str = param("agent", doc="the agent kind (agents/registry.py AGENT_KINDS)")
    scenarios: tuple[str, ...] = param(("lane_keeping", "left_turn"),
                                       doc="the scenarios (env.name) it can drive")
    sensors: str | None = param(None, doc="the sensors preset it is designed for (conf/sensors/<name>.yaml), used "
                                          "by eval and train in place of the command's; null: the command's")

    def relations(self) -> list[str]:
        from av_gym.registry import SCENARIOS

        found = [f"@scenarios[{i}] must be one of {SCENARIOS.names()}, got {s!r}"
                 for i, s in enumerate(self.scenarios) if s not in SCENARIOS]
        return found  # sensors names a preset of conf/sensors/: conf/check.py checks it (the presets are config)


class AgentKind:
    """One agent kind: its ``Params`` and what the harness needs from it (see the module docstring)."""

    Params: type[AgentParams] = AgentParams
    checkpoint: str | None = None
    """Trained kinds: the model file their trainer writes into ``checkpoints/<run>/`` (``None``: rule-based)."""

    @classmethod
    def trained(cls) -> bool:
        return cls.checkpoint is not None

    @classmethod
    def build(cls, params: AgentParams, env: Any, label: str) -> Any:
        """A rule-based kind's :class:`agents.base.Policy` for ``env``; a :class:`ConfigError` naming ``label`` if
        ``env`` lacks what it reads."""
        raise NotImplementedError(f"agent kind {params.kind!r} is trained: load a checkpoint")

    @classmethod
    def load(cls, model_path: Path, env: Any) -> Any:
        """A trained kind's policy from its ``checkpoint`` file, checked against ``env`` (one-line errors)."""
        raise NotImplementedError(f"agent kind {cls.Params().kind!r} is rule-based: nothing to load")


AGENT_KINDS = Registry("agent.kind", {
    "ppo": "agents.ppo:PPOAgent",
    "dagger": "agents.dagger:DaggerAgent",
    "pilotnet": "agents.bc:PilotNetAgent",
    "pid": "agents.pid:PIDAgent",
    "always_proceed": "agents.rules:AlwaysProceedAgent",
    "gap_acceptance": "agents.go_yield:GapAcceptanceAgent",
    "lookahead": "agents.go_yield:LookaheadAgent",
    "belief_lookahead": "agents.belief:BeliefLookaheadAgent",
})
"""``agent.kind`` → its :class:`AgentKind`."""

TEACHERS = Registry("agent.init", {
    "gap_acceptance": "agents.go_yield:gap_acceptance_teacher",
    "lookahead": "agents.go_yield:lookahead_teacher",
    "belief_lookahead": "agents.belief:belief_lookahead_teacher",
    "pid": "agents.pid:pid_teacher",
})
"""Agent kind → ``teacher(params, actions, scenario, action_repeat) -> label(env, obs, info)``: how an agent of that
kind labels the states of a training env for behaviour cloning before PPO (``agent.init`` names the agent config).
The label is an action of the training env; a teacher refuses (:class:`ConfigError`, one line) a training setup it
cannot label."""


OPINIONS = Registry("shield.second_opinion", {
    "belief_lookahead": "agents.belief:PlannerOpinion",
})
"""``shield.second_opinion`` → the class of the :class:`av_gym.shields.Opinion` the harness installs on the AEB
shield (:func:`eval.agents.install_opinion`), built from the agent config of that name (its Params): the library's
shield takes an object and knows none of these names."""


def opinion_problems(name: object, where: str = "shield.second_opinion") -> list[str]:
    """One line if ``name`` (a shield's ``second_opinion``) is neither ``none`` nor one of :data:`OPINIONS`."""
    if name == "none" or (isinstance(name, str) and name in OPINIONS):
        return []
    return [f"{where} must be one of {['none', *OPINIONS.names()]}, got {name!r}"]


def trained_kinds() -> list[str]:
    return [name for name, cls in AGENT_KINDS.items() if cls.trained()]


def agent_problems(value: Any, where: str = "agent") -> list[str]:
    """Every problem of an agent config section (a mapping), one line each naming the field under ``where``."""
    if not isinstance(value, Mapping):
        return [f"{where} must be a mapping, got {value!r}"]
    kind = value.get("kind")
    if not isinstance(kind, str) or kind not in AGENT_KINDS:
        return [f"{where}.kind must be one of {AGENT_KINDS.names()}, got {kind!r}"]
    return check(AGENT_KINDS.get(kind).Params, value, where, what=f"a field of a {kind} agent")


def agent_params(value: Mapping, where: str = "agent") -> AgentParams:
    """The Params of an agent config section (its kind's), or a :class:`ConfigError` naming the first problem."""
    from av_gym.errors import ConfigError

    found = agent_problems(value, where)
    if found:
        raise ConfigError(found[0])
    return AGENT_KINDS.get(value["kind"]).Params.from_mapping(dict(value))


def register_configs(store: Any = None) -> None:
    """Each kind's defaults as a Hydra config ``agent_kind/<kind>`` (``Params().as_dict()``), what
    ``conf/agent/<name>.yaml`` extends with ``defaults: [/agent_kind/<kind>@_here_, _self_]``."""
    if store is None:
        from hydra.core.config_store import ConfigStore

        store = ConfigStore.instance()
    for kind, cls in AGENT_KINDS.items():
        store.store(group="agent_kind", name=kind, node=cls.Params().as_dict())
