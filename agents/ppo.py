"""PPO from stable-baselines3: a factory from plain hyperparameters, and a :class:`Policy` around a trained model."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv

PPO_KEYS = ("learning_rate", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda", "clip_range", "ent_coef",
            "vf_coef", "max_grad_norm", "target_kl")


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


def sb3_space(space: gym.Space) -> gym.Space:
    """The observation space an SB3 model trained on ``space`` reports: flattened, images channel-first (SB3
    wraps image envs in ``VecTransposeImage``). Used to check that a checkpoint fits an env."""
    from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
    from stable_baselines3.common.vec_env import VecTransposeImage

    space = flat_space(space)
    if not isinstance(space, spaces.Dict):
        return space
    return spaces.Dict({k: VecTransposeImage.transpose_space(v, k) if is_image_space(v)
                        and not is_image_space_channels_first(v) else v for k, v in space.spaces.items()})


class FlatDictObservation(gym.ObservationWrapper):
    """Applies :func:`flatten_obs` so SB3 can train on nested sensor observations."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = flat_space(env.observation_space)

    def observation(self, observation: Any) -> Any:
        return flatten_obs(observation)


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


def make_ppo(env: VecEnv, hyper: dict[str, Any], *, seed: int, tensorboard_log: str | None,
             device: str = "cpu") -> PPO:
    """A fresh SB3 PPO on ``env``. ``hyper`` holds ``policy``, ``net_arch`` (hidden sizes), optionally
    ``log_std_init`` (continuous actions: initial log std of the Gaussian), ``cnn_output_dim`` (image inputs: width of
    the NatureCNN's output layer, SB3's default 256), ``extractor`` (``mlp``: SB3's concatenation of the inputs;
    ``attention``: :class:`agents.attention.EgoAttention` over the left turn's road users, ``attention_dim`` wide
    with ``attention_heads`` heads) and :data:`PPO_KEYS`."""
    kwargs = {k: hyper[k] for k in PPO_KEYS if k in hyper}
    policy_kwargs = {"net_arch": list(hyper["net_arch"])} if hyper.get("net_arch") else {}
    if hyper.get("log_std_init") is not None:
        policy_kwargs["log_std_init"] = float(hyper["log_std_init"])
    if hyper.get("cnn_output_dim") is not None:
        # MultiInputPolicy's CombinedExtractor names the CNN's width cnn_output_dim; CnnPolicy's NatureCNN features_dim
        key = "features_dim" if hyper.get("policy") == "CnnPolicy" else "cnn_output_dim"
        policy_kwargs["features_extractor_kwargs"] = {key: int(hyper["cnn_output_dim"])}
    if hyper.get("extractor", "mlp") == "attention":  # the left turn's road users through ego-attention
        from agents.attention import EgoAttention

        policy_kwargs["features_extractor_class"] = EgoAttention
        policy_kwargs["features_extractor_kwargs"] = {"embed_dim": int(hyper.get("attention_dim", 64)),
                                                      "heads": int(hyper.get("attention_heads", 2))}
    return PPO(hyper.get("policy", "MultiInputPolicy"), env, seed=seed, tensorboard_log=tensorboard_log,
               policy_kwargs=policy_kwargs or None, device=device, verbose=0, **kwargs)


class ActionRepeat(gym.Wrapper):
    """The agent decides every ``repeat`` env steps; its action is applied ``repeat`` times and the rewards summed
    (the episode ends early if the env does). Why: on the left turn the decision that matters (wait or go) spans
    seconds; at 10 Hz PPO must assign credit over ~150 steps, at 2 Hz over ~30, and learns several times faster
    per simulated second. A safety shield inside still decides every env step (0.1 s)."""

    def __init__(self, env: gym.Env, repeat: int) -> None:
        super().__init__(env)
        if int(repeat) < 1:
            raise ValueError(f"agent.action_repeat must be >= 1, got {repeat}")
        self.repeat = int(repeat)

    def step(self, action):
        total = 0.0
        for _ in range(self.repeat):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            if terminated or truncated:
                break
        return obs, total, terminated, truncated, info


class TimeLimitIsTerminal(gym.Wrapper):
    """Training-time: the episode's time limit ends it as a *termination* (no value bootstrapped after it). Why: SB3
    bootstraps truncated episodes with the critic's value of the last state, as if the episode went on; on the left
    turn, where not arriving in time is a failure and elapsed time is in the observation, that made waiting at the
    line until the limit look as good as turning, and PPO drifted to never turning (measured, issue 7)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated or truncated, False, info


class SB3Policy:
    """Deterministic action of a trained SB3 model for one observation. With ``repeat`` > 1 (a model trained with
    :class:`ActionRepeat`) the model is asked every ``repeat`` calls and its action held in between."""

    def __init__(self, model: Any, repeat: int = 1, actions: str = "env") -> None:
        self.model, self.repeat, self.actions = model, int(repeat), actions
        self._k, self._action = 0, None

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> "SB3Policy":
        # SB3 zips contain pickled objects: only paths the user gave (or our own checkpoints/ folder) get here.
        return cls(PPO.load(str(path), device=device))

    def reset(self) -> None:
        self._k, self._action = 0, None

    def act(self, obs: Any) -> Any:
        if self._k % self.repeat == 0:
            action, _ = self.model.predict(flatten_obs(obs), deterministic=True)
            self._action = int(action) if np.ndim(action) == 0 else action
        self._k += 1
        if self.actions == "go_yield":  # the held choice becomes a meta-action at every env step, as in training
            from agents.go_yield import meta_action

            return meta_action(self._action, obs["turn"])
        return self._action
