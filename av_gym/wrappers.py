"""Env wrappers the training stack puts around a scenario (they change its actions, rewards or observation layout,
not what it simulates): flat observations for SB3, an action held for several steps, go/yield choices mapped onto
the left turn's meta-actions, a reward term per second of shield override, and the time limit as a termination.

They live in ``av_gym`` (not ``agents`` or ``train``) because they are env wrappers: the trainers build them
(:func:`train.ppo._env_factory`), the batched engine mirrors them (:mod:`av_gym.batched.vec_env`), and the
evaluation maps a trained policy's actions the same way (:class:`agents.ppo.SB3Policy`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.actions import check_action
from av_gym.errors import ConfigError
from av_gym.estimation.turn_features import EGO_FEATURES, TURN


# ----------------------------------------------------------------------------------------------- flat observations
def flat_space(space: gym.Space) -> gym.Space:
    """SB3's ``MultiInputPolicy`` takes one level of ``Dict``; sensors such as the cameras nest one more
    (``cameras: {left, centre, right}``). Nested keys become ``cameras_left`` etc."""
    if not isinstance(space, spaces.Dict):
        return space
    flat = {}
    for key, sub in space.spaces.items():
        if isinstance(sub, spaces.Dict):
            flat.update({f"{key}_{k}": v for k, v in flat_space(sub).spaces.items()})
        else:
            flat[key] = sub
    return spaces.Dict(flat)


def flatten_obs(obs: Any) -> Any:
    """The observation matching :func:`flat_space`."""
    if not isinstance(obs, dict):
        return obs
    flat = {}
    for key, value in obs.items():
        if isinstance(value, dict):
            flat.update({f"{key}_{k}": v for k, v in flatten_obs(value).items()})
        else:
            flat[key] = value
    return flat


class FlatDictObservation(gym.ObservationWrapper):
    """Applies :func:`flatten_obs` so SB3 can train on nested sensor observations."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = flat_space(env.observation_space)

    def observation(self, observation: Any) -> Any:
        return flatten_obs(observation)


class SelectKeys(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """Keep only ``keys`` of a ``Dict`` observation (a sensors preset's ``observe``, or dropping the privileged
    ``state``). Gymnasium's ``FilterObservation`` does the same through a lambda, which cannot be pickled: every
    sensor stack then failed to pickle, and async vector envs and multiprocessing with it."""

    def __init__(self, env: gym.Env, keys: list[str]) -> None:
        # recorded so that gymnasium can rebuild the stack from its spec (check_env's determinism check does)
        gym.utils.RecordConstructorArgs.__init__(self, keys=list(keys))
        gym.ObservationWrapper.__init__(self, env)
        self.keys = list(keys)
        self.observation_space = spaces.Dict({k: env.observation_space[k] for k in self.keys})

    def observation(self, observation: dict) -> dict:
        return {k: observation[k] for k in self.keys}


# ----------------------------------------------------------------------------------------------- rewards, time limit
class InterventionCost(gym.Wrapper):
    """Training-time reward term: ``-cost`` per second during which a safety shield overrides the agent
    (``info["shield_override"]``), so a policy trained with the shield in the loop learns not to need it."""

    def __init__(self, env: gym.Env, cost: float) -> None:
        super().__init__(env)
        self.per_step = float(cost) / env.unwrapped.config["policy_frequency"]

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if info.get("shield_override", False):
            reward -= self.per_step
        return obs, reward, terminated, truncated, info


class TimeLimitIsTerminal(gym.Wrapper):
    """Training-time: the episode's time limit ends it as a *termination* (no value bootstrapped after it). Why: SB3
    bootstraps truncated episodes with the critic's value of the last state, as if the episode went on; on the left
    turn, where not arriving in time is a failure and elapsed time is in the observation, that made waiting at the
    line until the limit look as good as turning, and PPO drifted to never turning (measured)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated or truncated, False, info


class ActionRepeat(gym.Wrapper):
    """The agent decides every ``repeat`` env steps; its action is applied ``repeat`` times and the rewards summed
    (the episode ends early if the env does). Why: on the left turn the decision that matters (wait or go) spans
    seconds; at 10 Hz PPO must assign credit over ~150 steps, at 2 Hz over ~30, and learns several times faster
    per simulated second. A safety shield inside still decides every env step (0.1 s)."""

    def __init__(self, env: gym.Env, repeat: int) -> None:
        super().__init__(env)
        if int(repeat) < 1:
            raise ValueError(f"action_repeat must be >= 1, got {repeat}")
        self.repeat = int(repeat)

    def step(self, action):
        total = 0.0
        for _ in range(self.repeat):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            if terminated or truncated:
                break
        return obs, total, terminated, truncated, info


# ----------------------------------------------------------------------------------------------- go / yield
# Go / yield: a two-choice action for learned left-turn policies, on top of highway-env's speed set-points.
#
# Why: with highway-env's meta-actions {SLOWER, IDLE, FASTER} a stop is "SLOWER, wherever the car is", and PPO must
# also learn *where* to brake (measured: after 50k env steps its policy stopped 20-25 m short of the line
# and never set off again, because IDLE holds a zero set-point). A driver's decision at an unprotected left turn is
# "go" or "yield at the stop line"; the stopping itself is routine. So the agent picks one of
#
# - GO (1): cruise at the highest set-point (9 m/s);
# - YIELD (0): approach and stop at the stop line: the highest set-point not above the comfortable approach speed
#   v = sqrt(2 b (d - d0)) (b = DECEL, d = distance of the front bumper to the line, d0 = MARGIN); past the line
#   that is 0, i.e. stop where it is,
#
# and meta_actions turns the choices into the meta-actions that move the set-point towards them. It reads only the
# agent's own observation (obs["turn"]: set-point and distance to the stop line, decoded by
# av_gym.estimation.turn_features.TurnEncoding), so the same code runs in training (per env and batched) and in
# evaluation (agents.ppo.SB3Policy with actions: go_yield).
YIELD, GO = 0, 1
SLOWER, IDLE, FASTER = 0, 1, 2  # highway-env's longitudinal DiscreteMetaAction indices
SET_POINTS = (0.0, 4.5, 9.0)  # m/s, the left turn's traffic-mode set-points (conf/env/left_turn.yaml)
DECEL = 3.0  # m/s², comfortable approach deceleration b
MARGIN = 0.5  # m, d0
_SET_POINTS = np.array(SET_POINTS)


def meta_actions(choice: np.ndarray, turn: np.ndarray, margin: np.ndarray | float = MARGIN) -> np.ndarray:
    """The meta-actions (n,) for GO/YIELD choices (n,) given the turn features ``turn`` (n, F); ``margin`` (m, one
    or (n,)): how far before the stop line YIELD stops (d0), counted from ``turn``'s ``to_stop_line`` (which the
    encoding clips at 30 m)."""
    ego = np.asarray(turn)[..., :len(EGO_FEATURES)].astype(float)  # decoded in doubles
    set_point, d_stop = TURN.decode(ego, "set_point"), TURN.decode(ego, "to_stop_line")
    v_ok = np.sqrt(2.0 * DECEL * np.maximum(d_stop - np.asarray(margin, dtype=float), 0.0))
    # YIELD: the highest set-point not above v_ok (SET_POINTS ascends from 0, so there is one)
    yield_speed = _SET_POINTS[np.searchsorted(_SET_POINTS, v_ok + 1e-6, side="right") - 1]
    wanted = np.where(np.asarray(choice) == GO, _SET_POINTS[-1], yield_speed)
    return IDLE + (wanted > set_point + 1e-3).astype(int) - (wanted < set_point - 1e-3)  # FASTER, IDLE, SLOWER


def meta_action(choice: int, turn: np.ndarray, margin: float = MARGIN) -> int:
    """:func:`meta_actions` for one env: the meta-action for ``choice`` (GO or YIELD) given its ``turn``."""
    return int(meta_actions(np.array([int(choice)]), np.asarray(turn)[None], margin)[0])


# ----------------------------------------------------------------------------------------------- action sets
@dataclass(frozen=True)
class ActionSet:
    """An agent's actions on top of the env's (``agent.actions``): its space, and how its actions become the env's,
    vectorised over envs so that the per-env wrapper (a batch of one), the batched engine and the evaluation of a
    trained policy map them with the same function. A new set is one entry of :data:`ACTION_SETS`."""

    name: str
    doc: str
    choices: int | None = None  # the agent picks one of this many (Discrete); None: the env's own action space
    env_actions: int | None = None  # ... which become the env's Discrete(env_actions) meta-actions (None: any)
    reads: tuple[str, ...] = ()  # observation keys ``to_env`` reads
    to_env: Callable[[np.ndarray, dict], np.ndarray] | None = None  # (actions (n,), obs {key: (n, ...)}) → (n,)

    def space(self, env_space: gym.Space) -> gym.Space:
        """The agent's action space on an env acting in ``env_space``."""
        return env_space if self.choices is None else spaces.Discrete(self.choices)

    def env_space(self, agent_space: gym.Space) -> gym.Space:
        """The env action space an agent acting in ``agent_space`` needs."""
        return agent_space if self.env_actions is None else spaces.Discrete(self.env_actions)

    def problem(self, env_space: gym.Space, obs_keys, got: str | None = None) -> str | None:
        """Why this set cannot drive an env with ``env_space`` and observation keys ``obs_keys`` (None: it can)."""
        missing = [k for k in self.reads if k not in obs_keys]
        if missing:
            return f"agent.actions={self.name} needs obs[{missing[0]!r}] (sensors=turn_truth or turn_perceived)"
        if self.env_actions is not None and env_space != spaces.Discrete(self.env_actions):
            return (f"agent.actions={self.name} needs env.action=discrete (its choices become meta-actions), got "
                    f"{got or env_space}")
        return None

    def act(self, actions: np.ndarray, obs: dict) -> np.ndarray:
        """The env's actions for the agent's ``actions`` (n,) given the observations ``obs`` (each (n, ...))."""
        return actions if self.to_env is None else self.to_env(actions, obs)

    def act_one(self, action: Any, obs: dict) -> Any:
        """:meth:`act` for one env (``obs`` its observation)."""
        if self.to_env is None:
            return action
        return int(self.to_env(np.array([action]), {k: np.asarray(obs[k])[None] for k in self.reads})[0])

    def wrap(self, env: gym.Env) -> gym.Env:
        """``env`` acting in this set (unchanged for the env's own actions)."""
        return env if self.to_env is None else ChosenActions(env, self)


def _go_yield(choice: np.ndarray, obs: dict) -> np.ndarray:  # a module function: wrapped envs pickle
    return meta_actions(choice, obs["turn"])


ACTION_SETS = {
    "env": ActionSet("env", "the env's own action space"),
    "go_yield": ActionSet("go_yield", "two choices, GO or YIELD at the stop line (av_gym/wrappers.py), mapped onto "
                          "the left turn's meta-actions every env step", choices=2, env_actions=3, reads=("turn",),
                          to_env=_go_yield),
}
ACTION_SET_NAMES = tuple(ACTION_SETS)


def action_set(name: str) -> ActionSet:
    """The action set ``agent.actions=name``; a ConfigError line naming the others for an unknown one."""
    if name not in ACTION_SETS:
        raise ConfigError(f"agent.actions must be one of {list(ACTION_SETS)}, got {name!r}")
    return ACTION_SETS[name]


class ChosenActions(gym.Wrapper):
    """The env acting in an :class:`ActionSet` (its ``choices`` in place of the env's actions, mapped at every
    step from the latest observation)."""

    def __init__(self, env: gym.Env, actions: ActionSet | str) -> None:
        super().__init__(env)
        self.action_set = action_set(actions) if isinstance(actions, str) else actions
        problem = self.action_set.problem(env.action_space, getattr(env.observation_space, "spaces", {}))
        if problem:
            raise ValueError(problem)
        self.action_space = self.action_set.space(env.action_space)
        self._obs = None

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._obs = obs
        return obs, info

    def step(self, action):
        check_action(self.action_space, action)  # int(nan) would be a bare "cannot convert float NaN"
        obs, reward, terminated, truncated, info = self.env.step(self.action_set.act_one(int(action), self._obs))
        self._obs = obs
        return obs, reward, terminated, truncated, info


class GoYieldActions(ChosenActions):
    """``Discrete(2)`` {YIELD, GO} in place of the left turn's meta-actions; needs ``obs["turn"]`` (the
    ``turn_truth`` / ``turn_perceived`` sensors presets) and ``env.action=discrete``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env, "go_yield")
