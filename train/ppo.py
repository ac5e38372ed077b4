"""PPO training with stable-baselines3, top to bottom: vectorised envs, model, callbacks, learn, save."""

from __future__ import annotations

import functools
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf


def _env_factory(env_cfg: dict, sensors_cfg: dict, shield_cfg: dict):
    from agents.ppo import FlatDictObservation
    from av_gym.make import make_env

    return FlatDictObservation(make_env(env_cfg, sensors_cfg, shield_cfg))


def validate(cfg: DictConfig) -> list[str]:
    """Problems with ``cfg.agent`` for PPO, as one-line messages (empty if none)."""
    agent, problems = cfg.agent, []
    for key in ("total_timesteps", "n_envs", "n_steps", "batch_size"):
        if int(agent[key]) < 1:
            problems.append(f"agent.{key} must be a positive integer, got {agent[key]}")
    if agent.vec_env not in ("subproc", "dummy"):
        problems.append(f"agent.vec_env must be one of ['subproc', 'dummy'], got {agent.vec_env!r}")
    return problems


def train_ppo(cfg: DictConfig, ckpt_dir: Path, run_dir: Path) -> Path:
    """Train PPO as ``cfg.agent`` says; TensorBoard under ``run_dir/tb``; returns the final checkpoint path."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from agents.ppo import make_ppo
    from train.callbacks import AtomicCheckpointCallback, EpisodeMetricsCallback
    from train.checkpoint import save_model_atomic

    agent, t0 = cfg.agent, time.time()
    plain = [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
    vec_cls = SubprocVecEnv if (agent.vec_env == "subproc" and agent.n_envs > 1) else DummyVecEnv
    venv = make_vec_env(functools.partial(_env_factory, *plain), n_envs=int(agent.n_envs), seed=int(cfg.seed),
                        vec_env_cls=vec_cls)
    model = make_ppo(venv, OmegaConf.to_container(agent, resolve=True), seed=int(cfg.seed),
                     tensorboard_log=str(run_dir / "tb"), device=agent.device)
    callbacks = [EpisodeMetricsCallback(cfg.env.name), AtomicCheckpointCallback(ckpt_dir, int(cfg.train.checkpoint_every))]
    try:
        model.learn(total_timesteps=int(agent.total_timesteps), callback=callbacks,
                    progress_bar=bool(cfg.train.progress_bar), tb_log_name=agent.name)
    except KeyboardInterrupt:
        print(f"[train] interrupted at {model.num_timesteps} steps; saving what was learned")
    path = save_model_atomic(model, ckpt_dir / "model.zip")
    venv.close()
    print(f"[train] {model.num_timesteps} env steps in {time.time() - t0:.0f} s")
    return path
