"""SB3's ``VecEnv`` over the batched left turn, under the harness's name: it lives in
:mod:`av_gym_sb3.batched` (importable from an installed wheel); this path keeps older imports working."""

from __future__ import annotations

from av_gym_sb3.batched import BatchedLeftTurnVecEnv

__all__ = ["BatchedLeftTurnVecEnv"]
