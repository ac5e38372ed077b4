"""SB3's ``VecEnv`` over the batched left turn: ``python -m train agent=ppo_turn agent.vec_env=batched``.

All the work is :class:`av_gym.batched.vec_env.BatchedLeftTurnBatch` (the library, which does not import SB3); this
class only adds SB3's base, so that SB3's algorithms and wrappers (``VecNormalize``, ``VecMonitor``) accept it."""

from __future__ import annotations

from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from av_gym.batched.vec_env import BatchedLeftTurnBatch


class BatchedLeftTurnVecEnv(BatchedLeftTurnBatch, VecEnv):
    """:class:`BatchedLeftTurnBatch` as an SB3 ``VecEnv`` (same arguments)."""

    def __init__(self, *args, **kwargs) -> None:
        BatchedLeftTurnBatch.__init__(self, *args, **kwargs)
        seeds = self._seeds
        VecEnv.__init__(self, self.num_envs, self.observation_space, self.action_space)
        self._seeds = seeds  # VecEnv's [None] * n means the same as the batch's None: no seeds queued
