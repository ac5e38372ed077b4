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
