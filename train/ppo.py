"""PPO training with stable-baselines3, top to bottom: vectorised envs, model, callbacks, learn, save."""

from __future__ import annotations

import functools
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf


ACTIONS = ("env", "go_yield")  # agent.actions: the env's own action space, or agents/go_yield.py's two choices


def _env_factory(env_cfg: dict, sensors_cfg: dict, shield_cfg: dict, intervention_cost: float = 0.0,
                 action_repeat: int = 1, actions: str = "env", render_mode: str | None = None,
                 timeout_is_terminal: bool = False):
    from agents.go_yield import GoYieldActions
    from agents.ppo import ActionRepeat, FlatDictObservation, InterventionCost, TimeLimitIsTerminal
    from av_gym.make import make_env

    env = make_env(env_cfg, sensors_cfg, shield_cfg, render_mode=render_mode)
    if timeout_is_terminal:
        env = TimeLimitIsTerminal(env)
    if intervention_cost > 0:
        env = InterventionCost(env, intervention_cost)
    if actions == "go_yield":
        env = GoYieldActions(env)
    if action_repeat > 1:
        env = ActionRepeat(env, action_repeat)
    return FlatDictObservation(env)


def pretrain_from_teacher(model, env, teacher, seeds, gamma: float, epochs: int, batch_size: int) -> dict:
    """Behaviour cloning before PPO: the teacher (:class:`agents.go_yield.GapAcceptance`) drives ``env`` (the
    training stack: go/yield actions, action repeat, flat observations) on ``seeds``; the policy is fitted to its
    choices (cross-entropy) and the value head to the discounted returns it earned (MSE), with the model's own
    optimizer. Why both: PPO's first updates on an untrained critic would undo a cloned actor.
    Returns ``{"episodes", "decisions", "accuracy", "teacher_collision", "teacher_success"}``."""
    import numpy as np
    import torch as th

    obs_list, actions, returns, outcomes = [], [], [], []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        rewards, done = [], False
        while not done:
            a = teacher.choice(obs["turn"])
            obs_list.append(obs["turn"].copy())
            actions.append(a)
            obs, r, terminated, truncated, info = env.step(a)
            rewards.append(r)
            done = terminated or truncated
        g, ret = 0.0, []
        for r in reversed(rewards):
            g = r + gamma * g
            ret.append(g)
        returns += ret[::-1]
        m = info["episode_metrics"]
        outcomes.append((m["collision"], m["success"]))
    x = th.as_tensor(np.array(obs_list), dtype=th.float32)
    y = th.as_tensor(np.array(actions), dtype=th.long)
    g = th.as_tensor(np.array(returns), dtype=th.float32)
    policy = model.policy
    policy.set_training_mode(True)
    gen = th.Generator().manual_seed(0)
    for _ in range(epochs):
        for idx in th.randperm(len(y), generator=gen).split(batch_size):
            values, log_prob, _ = policy.evaluate_actions({"turn": x[idx]}, y[idx])
            loss = -log_prob.mean() + th.nn.functional.mse_loss(values.flatten(), g[idx])
            policy.optimizer.zero_grad()
            loss.backward()
            th.nn.utils.clip_grad_norm_(policy.parameters(), 0.5)
            policy.optimizer.step()
    policy.set_training_mode(False)
    with th.no_grad():
        accuracy = float((policy.get_distribution({"turn": x}).distribution.probs.argmax(1) == y).float().mean())
    coll, succ = np.mean(outcomes, axis=0)
    return {"episodes": len(outcomes), "decisions": len(y), "accuracy": accuracy, "teacher_collision": float(coll),
            "teacher_success": float(succ)}


def validate(cfg: DictConfig) -> list[str]:
    """Problems with ``cfg.agent`` for PPO, as one-line messages (empty if none)."""
    agent, problems = cfg.agent, []
    for key in ("total_timesteps", "n_envs", "n_steps", "batch_size"):
        if int(agent[key]) < 1:
            problems.append(f"agent.{key} must be a positive integer, got {agent[key]}")
    if agent.vec_env not in ("subproc", "dummy"):
        problems.append(f"agent.vec_env must be one of ['subproc', 'dummy'], got {agent.vec_env!r}")
    if agent.get("actions", "env") not in ACTIONS:
        problems.append(f"agent.actions must be one of {list(ACTIONS)}, got {agent.actions!r}")
    if int(agent.get("action_repeat", 1)) < 1:
        problems.append(f"agent.action_repeat must be >= 1, got {agent.action_repeat}")
    if float(agent.get("intervention_cost", 0.0)) < 0:
        problems.append(f"agent.intervention_cost must be >= 0, got {agent.intervention_cost}")
    for key in ("eval_every", "eval_n", "video_every"):
        if int(cfg.train[key]) < 0:
            problems.append(f"train.{key} must be >= 0, got {cfg.train[key]}")
    return problems


def _tensorboard_logger(folder: Path, purge_step: int | None):
    """SB3 logger writing TensorBoard events to ``folder``. When resuming, ``purge_step`` makes TensorBoard drop
    what the killed run logged after its last checkpoint, so curves continue with neither a gap nor a duplicate."""
    from stable_baselines3.common.logger import Logger, TensorBoardOutputFormat
    from torch.utils.tensorboard import SummaryWriter

    fmt = TensorBoardOutputFormat(str(folder))
    if purge_step:
        fmt.writer.close()
        fmt.writer = SummaryWriter(log_dir=str(folder), purge_step=purge_step)
    return Logger(folder=str(folder), output_formats=[fmt])


def train_ppo(cfg: DictConfig, ckpt_dir: Path, run_dir: Path) -> Path:
    """Train PPO as ``cfg.agent`` says; TensorBoard under ``run_dir/tb``; returns the final checkpoint path.

    ``train.resume=true`` continues ``checkpoints/<run_name>/latest.zip`` (policy, optimizer, step counter, RNG
    states) to the same ``total_timesteps``. SIGINT and SIGTERM save a checkpoint before exiting."""
    import signal

    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from agents.ppo import make_ppo
    from av_gym.errors import ConfigError
    from train.callbacks import AtomicCheckpointCallback, EpisodeMetricsCallback, HParamsCallback, PeriodicEval
    from train.checkpoint import load_rng_state, save_model_atomic

    agent, t0 = cfg.agent, time.time()
    latest = ckpt_dir / "latest.zip"
    resume = bool(cfg.train.get("resume", False))
    if resume and not latest.is_file():
        raise ConfigError(f"train.resume=true but {latest} does not exist (resume needs the run_name of a run "
                          f"that wrote a checkpoint)")
    for stale in ckpt_dir.glob(".*.tmp"):  # a save that was killed half-way; the previous file is intact
        stale.unlink()
    plain = [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
    vec_cls = SubprocVecEnv if (agent.vec_env == "subproc" and agent.n_envs > 1) else DummyVecEnv
    done_steps = 0
    if resume:
        done_steps = int(PPO.load(str(latest), device=agent.device).num_timesteps)
    # A resumed run's episodes come from fresh seeds (the env streams of the killed run cannot be restored).
    cost, repeat = float(agent.get("intervention_cost", 0.0)), int(agent.get("action_repeat", 1))
    actions = str(agent.get("actions", "env"))
    venv = make_vec_env(functools.partial(_env_factory, *plain, cost, repeat, actions,
                                          timeout_is_terminal=bool(agent.get("timeout_is_terminal", False))),
                        n_envs=int(agent.n_envs),
                        seed=int(cfg.seed) + done_steps, vec_env_cls=vec_cls)
    if resume:
        try:
            model = PPO.load(str(latest), env=venv, device=agent.device)
        except ValueError as exc:  # SB3's check that the spaces match the env
            raise ConfigError(f"checkpoint {latest} does not fit this env/sensors config: {exc}") from None
        saved = load_rng_state(ckpt_dir / "latest.rng")
        print(f"[train] resuming {latest} at {model.num_timesteps} of {agent.total_timesteps} env steps")
    else:
        model = make_ppo(venv, OmegaConf.to_container(agent, resolve=True), seed=int(cfg.seed),
                         tensorboard_log=None, device=agent.device)
        if agent.get("init"):
            from agents.go_yield import GapAcceptance
            from eval.agents import load_agent_config

            if actions != "go_yield":
                raise ConfigError(f"agent.init={agent.init} teaches go/yield choices: it needs agent.actions=go_yield")
            teacher_cfg = load_agent_config(str(agent.init))
            teacher = GapAcceptance(t_gap=teacher_cfg["t_gap"], miss=teacher_cfg["miss"])
            demo_env = _env_factory(*plain, cost, repeat, actions)
            # Demonstration seeds 500000+: disjoint from evaluation (1000+, 100000+) and from PPO's own episodes.
            t_bc = time.time()
            stats = pretrain_from_teacher(model, demo_env, teacher, range(500000, 500000 + int(agent.init_episodes)),
                                          float(agent.gamma), int(agent.init_epochs), int(agent.batch_size))
            demo_env.close()
            print(f"[train] cloned {agent.init} from {stats['episodes']} episodes ({stats['decisions']} decisions, "
                  f"teacher collision {stats['teacher_collision']:.2f}, success {stats['teacher_success']:.2f}): "
                  f"accuracy {stats['accuracy']:.3f} in {time.time() - t_bc:.0f} s")
    # The checkpoint's own dump (at its step) is complete, so TensorBoard keeps it and drops only what came after.
    model.set_logger(_tensorboard_logger(run_dir / "tb" / str(agent.name),
                                         model.num_timesteps + 1 if resume else None))
    if resume:  # values recorded by the last update but not yet written when the run was killed
        for key, store in saved.get("logger", {}).items():
            getattr(model.logger, key).update(store)
    checkpoint = AtomicCheckpointCallback(ckpt_dir, int(cfg.train.checkpoint_every))
    callbacks = [EpisodeMetricsCallback(cfg.env.name), checkpoint]
    if not resume:
        callbacks.append(HParamsCallback({**OmegaConf.to_container(agent, resolve=True), "env": cfg.env.name,
                                          "sensors": cfg.sensors.name, "shield": cfg.shield.name,
                                          "seed": int(cfg.seed)}, cfg.env.name))
    if int(cfg.train.eval_n) > 0:
        eval_seeds = range(int(cfg.train.eval_seed), int(cfg.train.eval_seed) + int(cfg.train.eval_n))
        callbacks.append(PeriodicEval(lambda mode: _env_factory(*plain, 0.0, repeat, actions, render_mode=mode),
                                      cfg.env.name,
                                      eval_seeds,
                                      int(cfg.train.eval_every), ckpt_dir, run_dir, int(cfg.train.video_every)))
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM behaves like Ctrl-C
    try:
        remaining = int(agent.total_timesteps) - int(model.num_timesteps)
        if remaining > 0:
            model.learn(total_timesteps=remaining, callback=callbacks, reset_num_timesteps=False,
                        progress_bar=bool(cfg.train.progress_bar))
    except KeyboardInterrupt:
        if checkpoint.model is not None:  # learning had started
            checkpoint.save()
        print(f"[train] interrupted at {model.num_timesteps} env steps; checkpoint {latest} "
              f"(continue with run_name={cfg.run_name} train.resume=true)")
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
        try:
            venv.close()
        except (EOFError, BrokenPipeError, ConnectionResetError):  # workers already gone after a signal
            pass
    path = save_model_atomic(model, ckpt_dir / "model.zip")
    env_steps = f" ({model.num_timesteps * repeat} env steps)" if repeat > 1 else ""
    print(f"[train] {model.num_timesteps} steps{env_steps} in {time.time() - t0:.0f} s")
    return path
