"""Rule-based baselines."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from agents.registry import AgentKind, AgentParams
from av_gym.params import param


class AlwaysProceed:
    """Left-turn baseline: keeps its speed through the intersection whatever the traffic does (the "driver who
    always proceeds" of highway-env's intersection, which collides in a large share of seeded episodes)."""

    def __init__(self, cruise_action: Any) -> None:
        self.cruise_action = cruise_action

    def reset(self) -> None:
        pass

    def act(self, obs: Any) -> Any:
        a = self.cruise_action
        return a.copy() if isinstance(a, np.ndarray) else a


@dataclass(frozen=True)
class AlwaysProceedParams(AgentParams):
    """No parameters of its own: it holds the scenario's cruise action."""

    kind: Literal["always_proceed"] = param("always_proceed")
    name: str = param("always_proceed")
    scenarios: tuple[str, ...] = param(("left_turn",))


class AlwaysProceedAgent(AgentKind):
    Params = AlwaysProceedParams

    @classmethod
    def build(cls, params: AlwaysProceedParams, env: Any, label: str) -> AlwaysProceed:
        return AlwaysProceed(env.unwrapped.cruise_action())
