"""Go / yield drivers for the left turn: the gap-acceptance rule and the privileged look-ahead oracle, as agent
kinds (``gap_acceptance``, ``lookahead``) and as teachers PPO can clone (``agent.init``).

The two-choice action itself (``GO``/``YIELD`` and the meta-action that moves the set-point towards it) is an env
wrapper, :mod:`av_gym.wrappers` (:class:`~av_gym.wrappers.GoYieldActions`, :func:`~av_gym.wrappers.meta_action`).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import gymnasium as gym
import numpy as np

from agents.registry import AgentKind, AgentParams
from av_gym.errors import ConfigError
from av_gym.estimation.turn_features import TURN
from av_gym.params import param
from av_gym.wrappers import GO, YIELD, meta_action

__all__ = ["GO", "YIELD", "GapAcceptance", "GapAcceptanceAgent", "Lookahead", "LookaheadAgent", "go_is_safe",
           "meta_action"]


@dataclass(frozen=True)
class GapAcceptanceParams(AgentParams):
    """The gap-acceptance rule (conf/agent/gap_acceptance.yaml)."""

    kind: Literal["gap_acceptance"] = param("gap_acceptance")
    name: str = param("gap_acceptance")
    scenarios: tuple[str, ...] = param(("left_turn",))
    t_gap: float = param(4.0, "s", gt=0, doc="yield while an object's closest approach is within this time "
                                             "(measured on seeds 1000-1059: 4 s -> 0.20 collisions / 0.65 success; "
                                             "6 s -> 0.07 / 0.28)")
    miss: float = param(3.0, "m", gt=0, doc="... and within this distance of the ego's path")


class GapAcceptance:
    """Rule-based left-turn driver on the turn features: YIELD (stop at the line, wait) while any object will pass
    within ``miss`` metres of the ego's path within ``t_gap`` seconds (constant-velocity closest approach, the
    features' ``t_star`` and ``miss``); otherwise GO. Once past the stop line it commits and goes (stopping inside
    the intersection puts the car in the crossing traffic's way). A gap-acceptance baseline, and the teacher PPO
    can start from (``agent.init: gap_acceptance``).

    ``act(obs)`` returns the env's meta-action (as any agent); :meth:`choice` the GO/YIELD decision."""

    def __init__(self, params: GapAcceptanceParams | None = None, **overrides: Any) -> None:
        p = self.params = GapAcceptanceParams.build(params, **overrides)
        self.t_gap, self.miss = float(p.t_gap), float(p.miss)

    def reset(self) -> None:
        pass

    def choice(self, turn: np.ndarray) -> int:
        turn = np.asarray(turn)
        present, t_star, miss = TURN.decode(turn, "present") > 0, TURN.decode(turn, "t_star"), \
            TURN.decode(turn, "miss")
        threat = present & (t_star > 0) & (t_star < self.t_gap) & (miss < self.miss)
        past_line = TURN.decode(turn.astype(float), "to_stop_line") < -1.0  # front bumper over 1 m past the line
        return YIELD if threat.any() and not past_line else GO

    def act(self, obs) -> int:
        return meta_action(self.choice(obs["turn"]), obs["turn"])


def go_is_safe(env: gym.Env, obs: Any, go: Callable[[Any], Any], visited: dict | None = None,
               shield_off: bool = False) -> bool:
    """Whether going now and never yielding again ends the episode without a collision: the rest of the episode is
    played on a deep copy of ``env``, random generators included, with ``go(obs)`` as the action at every step
    (``obs``: the current observation of ``env``). ``visited``, if given, receives ``time → (x, y, speed)`` of the
    ego along the simulated future; ``shield_off``: a safety shield in ``env`` is bypassed in the copy (the future
    of the driver alone).
    The copy's future is the real future under GO (the other drivers react to the ego as they would), which is what
    makes :class:`Lookahead` an oracle. Cost: one simulated episode tail (~0.1 s on the left turn)."""
    future = copy.deepcopy(env)
    if shield_off:
        from av_gym.shields.aeb import find_shield

        shield = find_shield(future)
        if shield is not None:
            shield.switch_off()
    while True:
        obs, _, terminated, truncated, info = future.step(go(obs))
        if visited is not None:
            t = info["truth"]
            visited[t["time"]] = (t["x"], t["y"], t["speed"])
        if terminated or truncated:
            return not info["episode_metrics"].get("collision")


@dataclass(frozen=True)
class LookaheadParams(AgentParams):
    """The look-ahead oracle (conf/agent/lookahead.yaml)."""

    kind: Literal["lookahead"] = param("lookahead")
    name: str = param("lookahead")
    scenarios: tuple[str, ...] = param(("left_turn",))
    repeat: int = param(5, "env steps", ge=1, doc="env steps between decisions (2 Hz, as the PPO policies); "
                                                  "~0.1 s of simulation each")
    plan_with_shield: bool = param(False, doc="agent+aeb: simulate the futures with the shield in them (the oracle "
                                              "then goes whenever the shield would save it, i.e. defers to the "
                                              "shield: 0.89 success, as always_proceed+aeb) | false: the driver's "
                                              "own futures, the shield a backup (what the shield costs a "
                                              "perfect driver)")


class Lookahead:
    """Privileged oracle for the left turn: YIELD until going now would get through without a collision (checked by
    simulating the future, :func:`go_is_safe`), then GO to the end. It sees what no sensor can (the other drivers'
    future decisions and the traffic still to spawn), so it is an upper bound for policies on the turn features and
    a teacher to clone (``agent.init: lookahead``), not a driver. Decides every ``repeat`` env steps like the PPO
    policies (``python -m eval agents=[lookahead]``); needs the env it drives (:func:`eval.agents.resolve_agent`
    passes it) and ``obs["turn"]``."""

    def __init__(self, env: gym.Env, params: LookaheadParams | None = None, **overrides: Any) -> None:
        p = self.params = LookaheadParams.build(params, **overrides)
        self.env, self.repeat, self.plan_with_shield = env, int(p.repeat), bool(p.plan_with_shield)
        self.reset()

    def reset(self) -> None:
        self._t, self._choice = 0, YIELD

    def act(self, obs) -> int:
        if self._choice != GO and self._t % self.repeat == 0:
            # GO is final: once its future is collision-free it stays so (same copy, same draws)
            safe = go_is_safe(self.env, obs, lambda o: meta_action(GO, o["turn"]), shield_off=not self.plan_with_shield)
            self._choice = GO if safe else YIELD
        self._t += 1
        return meta_action(self._choice, obs["turn"])



# ----------------------------------------------------------------------------------------------- kinds and teachers
def _needs_turn(env: gym.Env, label: str) -> None:
    if "turn" not in env.observation_space.spaces:
        raise ConfigError(f"agent {label!r} reads obs['turn']; use sensors=turn_truth or turn_perceived")


class GapAcceptanceAgent(AgentKind):
    Params = GapAcceptanceParams

    @classmethod
    def build(cls, params: GapAcceptanceParams, env: gym.Env, label: str) -> GapAcceptance:
        _needs_turn(env, label)
        return GapAcceptance(t_gap=params.t_gap, miss=params.miss)


class LookaheadAgent(AgentKind):
    Params = LookaheadParams

    @classmethod
    def build(cls, params: LookaheadParams, env: gym.Env, label: str) -> Lookahead:
        _needs_turn(env, label)
        return Lookahead(env, params)


def _go_yield_only(params: AgentParams, actions: str) -> None:
    if actions != "go_yield":
        raise ConfigError(f"agent.init={params.name} teaches go/yield choices: it needs agent.actions=go_yield")


def gap_acceptance_teacher(params: GapAcceptanceParams, actions: str, scenario: str | None = None,
                           action_repeat: int = 1) -> Callable:
    """GO/YIELD from ``obs["turn"]`` by the rule (see :data:`agents.registry.TEACHERS`)."""
    _go_yield_only(params, actions)
    rule = GapAcceptance(t_gap=params.t_gap, miss=params.miss)
    return lambda env, obs, info: rule.choice(obs["turn"])


def lookahead_teacher(params: LookaheadParams, actions: str, scenario: str | None = None,
                      action_repeat: int = 1) -> Callable:
    """A privileged oracle that simulates the future (:func:`go_is_safe`): GO when going now is collision-free."""
    _go_yield_only(params, actions)
    safe_path: dict[float, tuple] = {}  # time → ego pose on the last collision-free GO future

    def oracle(env, obs, info):
        # Once GO was found safe, GO stays safe as long as the ego is still on that future (the simulation
        # is deterministic): an exact shortcut that skips most of the simulated futures of an episode.
        pose = (info["truth"]["x"], info["truth"]["y"], info["truth"]["speed"])
        if safe_path.get(info["truth"]["time"]) == pose:
            return GO
        safe_path.clear()
        if go_is_safe(env, obs, lambda o: GO, visited=safe_path):
            return GO
        safe_path.clear()
        return YIELD
    return oracle
