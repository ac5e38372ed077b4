"""Go / yield: a two-choice action for learned left-turn policies, on top of highway-env's speed set-points.

Why: with highway-env's meta-actions {SLOWER, IDLE, FASTER} a stop is "SLOWER, wherever the car is", and PPO must
also learn *where* to brake (measured, issue 7: after 50k env steps its policy stopped 20-25 m short of the line
and never set off again, because IDLE holds a zero set-point). A driver's decision at an unprotected left turn is
"go" or "yield at the stop line"; the stopping itself is routine. So the agent picks one of

- ``GO`` (1): cruise at the highest set-point (9 m/s);
- ``YIELD`` (0): approach and stop at the stop line: the highest set-point not above the comfortable approach
  speed ``v = sqrt(2 b (d - d0))`` (``b`` = 3 m/s², ``d`` = distance of the front bumper to the line, ``d0`` =
  0.5 m margin); past the line that is 0, i.e. stop where it is,

and this module turns the choice into the meta-action that moves the set-point towards it. It reads only the
agent's own observation (``obs["turn"]``: speed, set-point, distance to the stop line; see
:mod:`av_gym.estimation.turn_features`), so the same code runs in training (:class:`GoYieldActions`) and in
evaluation (:class:`agents.ppo.SB3Policy` with ``actions: go_yield``).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

YIELD, GO = 0, 1
SLOWER, IDLE, FASTER = 0, 1, 2  # highway-env's longitudinal DiscreteMetaAction indices
SET_POINTS = (0.0, 4.5, 9.0)  # m/s, the left turn's traffic-mode set-points (conf/env/left_turn.yaml)
DECEL = 3.0  # m/s², comfortable approach deceleration b
MARGIN = 0.5  # m, d0


def meta_action(choice: int, turn: np.ndarray) -> int:
    """The meta-action for ``choice`` (GO or YIELD) given the turn features ``turn`` (speed / 10 at [0],
    set-point / 10 at [1], distance to the stop line / 30 at [2])."""
    set_point, d_stop = 10.0 * float(turn[1]), 30.0 * float(turn[2])
    if int(choice) == GO:
        wanted = SET_POINTS[-1]
    else:
        v_ok = np.sqrt(2.0 * DECEL * max(d_stop - MARGIN, 0.0))
        wanted = max(v for v in SET_POINTS if v <= v_ok + 1e-6)
    if wanted > set_point + 1e-3:
        return FASTER
    if wanted < set_point - 1e-3:
        return SLOWER
    return IDLE


class GoYieldActions(gym.Wrapper):
    """``Discrete(2)`` {YIELD, GO} in place of the left turn's meta-actions; needs ``obs["turn"]`` (the
    ``turn_truth`` / ``turn_perceived`` sensors presets) and ``env.action=discrete``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        if "turn" not in getattr(env.observation_space, "spaces", {}):
            raise ValueError("agent.actions=go_yield needs obs['turn'] (sensors=turn_truth or turn_perceived)")
        if env.action_space != spaces.Discrete(3):
            raise ValueError(f"agent.actions=go_yield needs env.action=discrete, got {env.action_space}")
        self.action_space = spaces.Discrete(2)
        self._turn = None

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._turn = obs["turn"]
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(meta_action(int(action), self._turn))
        self._turn = obs["turn"]
        return obs, reward, terminated, truncated, info


class GapAcceptance:
    """Rule-based left-turn driver on the turn features: YIELD (stop at the line, wait) while any object will pass
    within ``miss`` metres of the ego's path within ``t_gap`` seconds (constant-velocity closest approach, the
    features' ``t_star`` and ``miss``); otherwise GO. Once past the stop line it commits and goes (stopping inside
    the intersection puts the car in the crossing traffic's way). A gap-acceptance baseline, and the teacher PPO
    can start from (``agent.init: gap_acceptance``).

    ``act(obs)`` returns the env's meta-action (as any agent); :meth:`choice` the GO/YIELD decision."""

    def __init__(self, t_gap: float = 4.0, miss: float = 3.0) -> None:
        if not t_gap > 0 or not miss > 0:
            raise ValueError(f"gap acceptance needs t_gap > 0 and miss > 0, got {t_gap}, {miss}")
        from av_gym.estimation.turn_features import OBJECT_FEATURES, T_MAX

        self.t_gap, self.miss = float(t_gap), float(miss)
        self._n = len(OBJECT_FEATURES)
        self._cols = (OBJECT_FEATURES.index("present"), OBJECT_FEATURES.index("t_star"),
                      OBJECT_FEATURES.index("miss"))
        self._t_max = T_MAX

    def reset(self) -> None:
        pass

    def choice(self, turn: np.ndarray) -> int:
        objs = np.asarray(turn[5:]).reshape(-1, self._n)
        present, t_star, miss = objs[:, self._cols[0]] > 0, objs[:, self._cols[1]] * self._t_max, \
            objs[:, self._cols[2]] * 10.0
        threat = present & (t_star > 0) & (t_star < self.t_gap) & (miss < self.miss)
        past_line = 30.0 * float(turn[2]) < -1.0  # front bumper over 1 m past the stop line
        return YIELD if threat.any() and not past_line else GO

    def act(self, obs) -> int:
        return meta_action(self.choice(obs["turn"]), obs["turn"])


def go_is_safe(env: gym.Env, obs: Any, go: Callable[[Any], Any], visited: dict | None = None) -> bool:
    """Whether going now and never yielding again ends the episode without a collision: the rest of the episode is
    played on a deep copy of ``env``, random generators included, with ``go(obs)`` as the action at every step
    (``obs``: the current observation of ``env``). ``visited``, if given, receives ``time → (x, y, speed)`` of the
    ego along the simulated future.
    The copy's future is the real future under GO (the other drivers react to the ego as they would), which is what
    makes :class:`Lookahead` an oracle. Cost: one simulated episode tail (~0.1 s on the left turn)."""
    future = copy.deepcopy(env)
    while True:
        obs, _, terminated, truncated, info = future.step(go(obs))
        if visited is not None:
            t = info["truth"]
            visited[t["time"]] = (t["x"], t["y"], t["speed"])
        if terminated or truncated:
            return not info["episode_metrics"].get("collision")


class Lookahead:
    """Privileged oracle for the left turn: YIELD until going now would get through without a collision (checked by
    simulating the future, :func:`go_is_safe`), then GO to the end. It sees what no sensor can (the other drivers'
    future decisions and the traffic still to spawn), so it is an upper bound for policies on the turn features and
    a teacher to clone (``agent.init: lookahead``), not a driver. Decides every ``repeat`` env steps like the PPO
    policies (``python -m eval agents=[lookahead]``); needs the env it drives (:func:`eval.agents.resolve_agent`
    passes it) and ``obs["turn"]``."""

    def __init__(self, env: gym.Env, repeat: int = 5) -> None:
        self.env, self.repeat = env, int(repeat)
        self.reset()

    def reset(self) -> None:
        self._t, self._choice = 0, YIELD

    def act(self, obs) -> int:
        if self._choice != GO and self._t % self.repeat == 0:
            # GO is final: once its future is collision-free it stays so (same copy, same draws)
            self._choice = GO if go_is_safe(self.env, obs, lambda o: meta_action(GO, o["turn"])) else YIELD
        self._t += 1
        return meta_action(self._choice, obs["turn"])

