"""SB3's ``VecEnv`` over the batched left turn: B intersections stepped together as numpy arrays
(:mod:`av_gym.batched`), for SB3's algorithms and wrappers (``VecNormalize``, ``VecMonitor``)::

    from stable_baselines3 import PPO
    from av_gym_sb3 import BatchedLeftTurnVecEnv

    venv = BatchedLeftTurnVecEnv({"name": "left_turn"}, {"turn_features": {}}, None, 64)
    venv.seed(0)  # env i plays the episodes reset(seed=i) gives on the per-env stack, then goes on unseeded
    PPO("MultiInputPolicy", venv, n_steps=8).learn(4096)

``python -m train agent=ppo_turn agent.vec_env=batched`` trains on it. All the work is
:class:`av_gym.batched.vec_env.BatchedLeftTurnBatch` (the library, which imports neither SB3 nor torch: it is also
Gymnasium's ``make_vec`` of ``av_gym/UnprotectedLeftTurn-v0``); this class only adds SB3's base class. Its
arguments: the env config (``env=left_turn``, either mode, discrete or continuous actions), the sensors (those of
the ``turn_truth`` preset), the shield (None: the batch runs none), the number of envs, and the agent's options
``action_repeat``, ``actions``, ``timeout_is_terminal``; what the batch cannot run is refused in one
:class:`~av_gym.errors.ConfigError` line. Actions outside the action space, a wrong shape, a step before the first
reset and a malformed seed are refused in one line, as on the per-env stack (docs/performance.md, "Batched
simulation")."""

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
