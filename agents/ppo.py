"""PPO from stable-baselines3: a factory from plain hyperparameters, and a :class:`Policy` around a trained model."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv

PPO_KEYS = ("learning_rate", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda", "clip_range", "ent_coef",
            "vf_coef", "max_grad_norm")


def make_ppo(env: VecEnv, hyper: dict[str, Any], *, seed: int, tensorboard_log: str | None,
             device: str = "cpu") -> PPO:
    """A fresh SB3 PPO on ``env``. ``hyper`` holds ``policy``, ``net_arch`` (hidden sizes) and :data:`PPO_KEYS`."""
    kwargs = {k: hyper[k] for k in PPO_KEYS if k in hyper}
    policy_kwargs = {"net_arch": list(hyper["net_arch"])} if hyper.get("net_arch") else None
    return PPO(hyper.get("policy", "MultiInputPolicy"), env, seed=seed, tensorboard_log=tensorboard_log,
               policy_kwargs=policy_kwargs, device=device, verbose=0, **kwargs)


class SB3Policy:
    """Deterministic action of a trained SB3 model for one observation."""

    def __init__(self, model: Any) -> None:
        self.model = model

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> "SB3Policy":
        # SB3 zips contain pickled objects: only paths the user gave (or our own checkpoints/ folder) get here.
        return cls(PPO.load(str(path), device=device))

    def reset(self) -> None:
        pass

    def act(self, obs: Any) -> Any:
        action, _ = self.model.predict(obs, deterministic=True)
        return int(action) if np.ndim(action) == 0 else action
