"""PID lane keeping on cross-track error, in paper 001's per-step form (digest 001 §4, §8.4).

    u_k = -(Kp·e_k + Ki·Σ_{j≤k} e_j + Kd·(e_k − e_{k−1}))          (eq. (1) discretised per step, no dt)

e is the CTE in metres (+ = right of centre), u the normalised steering in [-1, 1] (+ = right), so a car right of
centre steers left. The gains of paper 001 (Kp 0.75, Ki 0.0001, Kd 1) only make sense in this per-step form: the
sum stays tiny and Kd multiplies a per-step difference. Anti-windup: the integral is frozen while the output
saturates (conditional integration) and clamped to ``i_max``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from agents.registry import AgentKind, AgentParams
from av_gym.errors import ConfigError
from av_gym.params import param

PRESETS: dict[str, dict[str, float]] = {
    "paper": {"kp": 0.75, "ki": 0.0001, "kd": 1.0},  # digest 001 Table 2, set by hand by the authors
    # `python -m train.pid_search` (grid 120 + Nelder-Mead 60, layout A, training seeds 0-4, gain margin 2):
    # mean |CTE| 0.713 paper units (lane = 100) on those laps vs 4.88 for "paper". The search drops I and D: see
    # train/pid_search.py.
    "tuned": {"kp": 4.88591, "ki": 0.0, "kd": 0.0},
}


@dataclass(frozen=True)
class PIDParams(AgentParams):
    """PID lane keeping on the CTE (conf/agent/pid_*.yaml); the gains default to paper 001's."""

    kind: Literal["pid"] = param("pid")
    name: str = param("pid_paper")
    scenarios: tuple[str, ...] = param(("lane_keeping",))
    kp: float = param(PRESETS["paper"]["kp"], "1/m", doc="proportional gain (paper 001 Table 2, set by hand)")
    ki: float = param(PRESETS["paper"]["ki"], "1/(m step)", doc="integral gain, per-step sum (paper 001)")
    kd: float = param(PRESETS["paper"]["kd"], "step/m", doc="derivative gain, per-step difference (paper 001)")
    i_max: float = param(1000.0, "m step", gt=0, doc="integral clamp (anti-windup)")
    obs_key: str = param("state", doc="the CTE comes from obs[obs_key][cte_index]; state = privileged "
                                      "(sensors=truth), ego_estimate = the localizer's")
    cte_index: int = param(0, ge=0, doc="index of the CTE in obs[obs_key]")
    search: Any = param(None, doc="the record of how the gains were found (documentation, never read)")


class PIDSteering:
    """Per-step PID on CTE → normalised steering. ``cte_index`` picks the CTE from ``obs[obs_key]``; parameters:
    :class:`PIDParams`."""

    def __init__(self, params: PIDParams | None = None, **overrides: Any) -> None:
        p = self.params = PIDParams.build(params, **overrides)
        self.kp, self.ki, self.kd, self.i_max = float(p.kp), float(p.ki), float(p.kd), float(p.i_max)
        self.obs_key, self.cte_index = p.obs_key, int(p.cte_index)
        self.reset()

    def reset(self) -> None:
        self._integral = 0.0
        self._prev: float | None = None

    def act(self, obs: dict) -> np.ndarray:
        e = float(np.asarray(obs[self.obs_key]).reshape(-1)[self.cte_index])
        if not np.isfinite(e):
            raise ValueError(f"PID got a non-finite CTE ({e}) from obs[{self.obs_key!r}][{self.cte_index}]")
        d = 0.0 if self._prev is None else e - self._prev
        self._prev = e
        integral = float(np.clip(self._integral + e, -self.i_max, self.i_max))
        u = -(self.kp * e + self.ki * integral + self.kd * d)
        if abs(u) < 1.0:  # conditional integration: no wind-up while saturated
            self._integral = integral
        return np.array([np.clip(u, -1.0, 1.0)], dtype=np.float32)


class PIDAgent(AgentKind):
    Params = PIDParams

    @classmethod
    def build(cls, params: PIDParams, env: Any, label: str) -> PIDSteering:
        if params.obs_key not in env.observation_space.spaces:
            raise ConfigError(f"agent {label!r} reads its CTE from obs[{params.obs_key!r}], which this sensors preset "
                              f"does not provide (keys: {list(env.observation_space.spaces)}); use sensors=truth")
        return PIDSteering(kp=params.kp, ki=params.ki, kd=params.kd, obs_key=params.obs_key,
                           cte_index=params.cte_index)


def pid_teacher(params: PIDParams, actions: str, scenario: str | None = None, action_repeat: int = 1) -> Callable:
    """Steering from the simulator's CTE in ``info["truth"]`` (a privileged teacher), so that a policy that sees
    only images can start from lane keeping. Needs ``scenario`` lane_keeping (or None: unchecked), continuous
    actions and ``action_repeat`` 1: its gains are tuned for a 10 Hz steering loop on the lane's CTE."""
    if actions != "env" or scenario not in (None, "lane_keeping") or action_repeat != 1:
        raise ConfigError(f"agent.init={params.name} teaches lane-keeping steering: it needs env=lane_keeping, "
                          f"agent.actions=env and agent.action_repeat=1 (got env={scenario}, "
                          f"agent.actions={actions}, agent.action_repeat={action_repeat})")
    pid = PIDSteering(kp=params.kp, ki=params.ki, kd=params.kd, obs_key="cte")

    def steer(env, obs, info):
        if info["truth"]["time"] == 0.0:
            pid.reset()
        return np.asarray(pid.act({"cte": [info["truth"]["cte"]]}), dtype=np.float32).reshape(-1)
    return steer
