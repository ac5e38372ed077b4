"""The torch/SB3 pieces that a saved model names by module: SB3 pickles ``policy_kwargs`` (the ego-attention
features extractor class) into every ``model.zip``, and loading it imports that module again. Here, under a name of
its own, ``PPO.load`` of a shipped reference works in any project: under the harness's ``agents`` it imported the
user's own ``agents`` package when there was one. Above the library (it imports torch and SB3, which ``av_gym``
never does), below the harness (``agents`` builds on it).

:class:`BatchedLeftTurnVecEnv` (:mod:`av_gym_sb3.batched`), SB3's ``VecEnv`` over the batched left turn, is here
too: ``from av_gym_sb3 import BatchedLeftTurnVecEnv`` (imported on first use, so that loading a saved model does
not load the batch)."""

from __future__ import annotations

from typing import Any

__all__ = ["BatchedLeftTurnVecEnv"]


def __getattr__(name: str) -> Any:
    if name == "BatchedLeftTurnVecEnv":
        from av_gym_sb3.batched import BatchedLeftTurnVecEnv

        return BatchedLeftTurnVecEnv
    raise AttributeError(f"module 'av_gym_sb3' has no attribute {name!r}")
