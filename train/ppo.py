"""PPO training with stable-baselines3, top to bottom: vectorised envs, model, callbacks, learn, save."""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from av_gym.seeds import DEMONSTRATIONS, config_seeds, train_seed
from conf.commands import TrainCommand
from train.imitation import load_weights, make_teacher, pretrain_from_teacher


def _env_factory(env_cfg: dict, sensors_cfg: dict, shield_cfg: dict, intervention_cost: float = 0.0,
                 action_repeat: int = 1, actions: str = "env", render_mode: str | None = None,
                 timeout_is_terminal: bool = False):
    from av_gym.make import make_training_env  # the same stack gym.make(id, checkpoint=...) builds

    return make_training_env(env_cfg, sensors_cfg, shield_cfg, intervention_cost, action_repeat, actions,
                             render_mode=render_mode, timeout_is_terminal=timeout_is_terminal)


def validate(cfg: DictConfig) -> list[str]:
    """What PPO's training needs beyond :class:`agents.ppo.PPOParams` (checked by the config checker), as one-line
    messages: a device torch can use here (``agent.device=cuda`` needs a GPU); with ``agent.vec_env=batched``, an
    env, sensors and shield the batched engine can run (its AEB shield: ``shield=aeb``), and
    ``agent.intervention_cost`` only with a shield whose overrides it is paid on (on the command line, before any
    folder)."""
    from agents.ppo import PPOParams
    from train.device import device_problems

    params = PPOParams.from_mapping(OmegaConf.to_container(cfg.agent, resolve=True), where="agent")
    problems = device_problems(params.device)
    if problems or params.vec_env != "batched":
        return problems
    from av_gym.batched.shield import shield_kind
    from av_gym.batched.vec_env import check_batchable, intervention_cost_problem
    from av_gym.errors import ConfigError

    env, sensors, shield = [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
    problem = intervention_cost_problem(float(params.intervention_cost), shield_kind(shield) != "none",
                                        "agent.intervention_cost")
    if problem:  # the batch would pay it on nothing
        return [problem]
    try:
        check_batchable(env, sensors, shield, with_shield=True)  # the training batch runs the batch's AEB shield
    except ConfigError as exc:
        # the same rollout on the per-env stack: one env per core, as many decisions per update
        per_env = max(2, params.n_steps * params.n_envs // 2)
        msg = str(exc).replace("use agent.vec_env=subproc", f"use agent.vec_env=subproc agent.n_envs=2 "
                                                             f"agent.n_steps={per_env}")
        return [msg]
    return []


def _tensorboard_logger(folder: Path, purge_step: int | None):
    """SB3 logger writing TensorBoard events to ``folder``. When resuming, what the killed run logged at steps >=
    ``purge_step`` (after its last checkpoint) is cut out of its event files (:func:`train.tb_events.truncate_events`:
    every reader, raw ones too, sees each step once), and the new writer's ``purge_step`` marks the restart as
    TensorBoard expects; a folder it cannot write is one line (:func:`train.tb_events.resumed_writer`)."""
    from stable_baselines3.common.logger import Logger, TensorBoardOutputFormat

    from train.tb_events import resumed_writer

    # SB3's format on the harness's writer: its own __init__ opens a SummaryWriter whose OSError (a full disk under
    # paths.runs) is a traceback, and which a resumed run would have to replace (leaving a file of one record)
    fmt = TensorBoardOutputFormat.__new__(TensorBoardOutputFormat)
    fmt.writer, fmt._is_closed = resumed_writer(folder, purge_step), False
    return Logger(folder=str(folder), output_formats=[fmt])


@dataclass(frozen=True)
class _Stack:
    """What every env of a PPO run is built from: the plain ``env``/``sensors``/``shield`` configs and the agent's
    wrappers (:class:`agents.ppo.PPOParams`: intervention cost, action repeat, actions, time limit)."""

    env: dict
    sensors: dict
    shield: dict
    params: Any  # agents.ppo.PPOParams

    @property
    def plain(self) -> tuple[dict, dict, dict]:
        return self.env, self.sensors, self.shield

    def one(self, intervention_cost: float | None = None, render_mode: str | None = None,
            timeout_is_terminal: bool | None = None):
        """One per-env training stack (:func:`_env_factory`); the arguments replace the agent's own settings."""
        p = self.params
        return _env_factory(*self.plain, p.intervention_cost if intervention_cost is None else intervention_cost,
                            p.action_repeat, p.actions, render_mode=render_mode,
                            timeout_is_terminal=p.timeout_is_terminal if timeout_is_terminal is None
                            else timeout_is_terminal)

    def batched(self):
        """The left turn's batched engine with the agent's action repeat, actions, time limit and, behind its AEB
        shield (``shield=aeb``), intervention cost."""
        from agents.batched_vec_env import BatchedLeftTurnVecEnv

        p = self.params
        return BatchedLeftTurnVecEnv(*self.plain, p.n_envs, action_repeat=p.action_repeat, actions=p.actions,
                                     timeout_is_terminal=p.timeout_is_terminal,
                                     intervention_cost=float(p.intervention_cost))


def build_envs(stack: _Stack, seed: int):
    """The training VecEnv: ``agent.n_envs`` envs on the batched engine, in subprocesses or in this process, their
    episode seeds drawn from ``seed``."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    p = stack.params
    if p.vec_env == "batched":  # all envs in one numpy batch (av_gym/batched/vec_env.py), shield and cost included
        venv = stack.batched()
        venv.seed(seed)
        return venv
    vec_cls = SubprocVecEnv if (p.vec_env == "subproc" and p.n_envs > 1) else DummyVecEnv
    factory = functools.partial(_env_factory, *stack.plain, float(p.intervention_cost), int(p.action_repeat),
                                str(p.actions), timeout_is_terminal=p.timeout_is_terminal)
    if vec_cls is SubprocVecEnv:  # its workers end with this process and leave Ctrl-C to it
        factory = functools.partial(_in_worker, factory)
    return make_vec_env(factory, n_envs=p.n_envs, seed=seed, vec_env_cls=vec_cls)


def _in_worker(factory, **kwargs):
    """``factory(**kwargs)`` in a SubprocVecEnv worker, after :func:`eval.runner.guard_worker`."""
    from eval.runner import guard_worker

    guard_worker()
    return factory(**kwargs)


def _check_resume(ckpt_dir: Path, resume: bool) -> Path:
    """``ckpt_dir/latest.zip``, checked when resuming (one line if missing or corrupt); removes the temporary files
    of a save that was killed half-way (the previous file is intact)."""
    from agents.checkpoint import check_sb3_zip
    from av_gym.errors import ConfigError

    latest = ckpt_dir / "latest.zip"
    if resume and not latest.is_file():
        raise ConfigError(f"train.resume=true but {latest} does not exist (resume needs the run_name of a run "
                          f"that wrote a checkpoint)")
    if resume:
        check_sb3_zip(latest)  # empty or corrupt (copied by hand?): one line, not SB3's traceback
    for stale in ckpt_dir.glob(".*.tmp"):
        stale.unlink()
    return latest


def resume_model(latest: Path, venv, params) -> tuple[Any, dict]:
    """The killed run's model on ``venv`` (policy, optimizer, step counter) and its saved RNG/logger state."""
    from stable_baselines3 import PPO

    from av_gym.errors import ConfigError
    from train.checkpoint import load_rng_state

    try:
        model = PPO.load(str(latest), env=venv, device=params.device)
    except ValueError as exc:  # SB3's check that the spaces match the env
        raise ConfigError(f"checkpoint {latest} does not fit this env/sensors config: {exc}") from None
    saved = load_rng_state(latest)  # inside the zip (older runs: latest.rng beside it)
    from train.callbacks import steps_text

    print(f"[train] resuming {latest} at {steps_text(model.num_timesteps, params.action_repeat)} of "
          f"agent.total_timesteps={params.total_timesteps}")
    return model, saved


def clone_teacher(model, stack: _Stack, scenario: str, progress: bool = True) -> None:
    """``agent.init``: behaviour-clone its teacher into ``model`` (:func:`pretrain_from_teacher`) on demonstration
    seeds of the train split, 500000+, away from PPO's own streams (seed + steps, from 0); one line if it diverges.
    A line as each phase starts, and with ``progress`` a bar within it (cloning takes 20-30 s before PPO)."""
    from eval.agents import load_agent_config
    from train.callbacks import raise_if_diverged

    p = stack.params
    teacher = make_teacher(p.init, p.actions, scenario, p.action_repeat)
    if p.vec_env == "batched" and load_agent_config(p.init).get("kind") == "gap_acceptance":
        # a rule of the observation alone: its episodes on the batch too (lookahead simulates its env's copy)
        demo_env = stack.batched()
    else:
        demo_env = stack.one(timeout_is_terminal=False)
    seeds = config_seeds("train", p.init_episodes, DEMONSTRATIONS, "agent.init_episodes from seed")
    t_bc = time.time()
    try:
        stats = pretrain_from_teacher(model, demo_env, teacher, seeds,
                                      float(p.gamma), p.init_epochs, p.batch_size, float(p.init_action_noise),
                                      p.init_dagger_rounds, p.init_lr, print, progress)
    except (ValueError, RuntimeError) as exc:  # NaN logits refused inside torch: say why, in one line
        lr = ("agent.init_lr", p.init_lr) if p.init_lr else ("agent.learning_rate", p.learning_rate)
        raise_if_diverged(exc, model.policy, "behaviour cloning", lr[0], float(lr[1]))
        raise
    except KeyboardInterrupt:  # say what is kept, rather than exit 130 without a word
        import sys

        print(f"[train] interrupted while cloning {p.init} ({time.time() - t_bc:.0f} s in): nothing was kept; the "
              f"clone lives in memory until PPO's first checkpoint (train.checkpoint_every), so there is no "
              f"latest.zip to resume; start the run again (train.overwrite=true to reuse its run_name)",
              file=sys.stderr)
        raise
    finally:
        demo_env.close()
    print(f"[train] cloned {p.init} from {stats['episodes']} episodes ({stats['decisions']} decisions, "
          f"teacher collision {stats['teacher_collision']:.2f}, success {stats['teacher_success']:.2f}): "
          f"accuracy {stats['accuracy']:.3f} in {time.time() - t_bc:.0f} s")


def initialise_model(venv, stack: _Stack, seed: int, scenario: str, progress: bool = True):
    """A fresh PPO on ``venv`` seeded ``seed``, cloned from ``agent.init``'s teacher when it names one (with
    progress bars: ``progress``)."""
    from agents.ppo import make_ppo

    p = stack.params
    model = make_ppo(venv, p.as_dict(), seed=seed, tensorboard_log=None, device=p.device)
    if p.init:
        clone_teacher(model, stack, scenario, progress)
    if p.init_from:
        load_weights(model, p.init_from, scenario)
    return model


def _callbacks(cfg: DictConfig, command: TrainCommand, stack: _Stack, ckpt_dir: Path, run_dir: Path):
    """The guard against divergence (first: a diverged update never reaches a checkpoint), episode metrics,
    checkpoints, the hyperparameters (fresh runs) and the periodic evaluation on fixed seeds."""
    from agents.ppo import SB3Policy
    from train.callbacks import (AtomicCheckpointCallback, EpisodeMetricsCallback, FiniteGuard, HParamsCallback,
                                 PeriodicEval)

    p, scenario, options = stack.params, str(cfg.env.name), command.train
    resume = options.resume
    checkpoint = AtomicCheckpointCallback(ckpt_dir, options.checkpoint_every, p.action_repeat)  # in env steps
    guard = FiniteGuard(float(p.learning_rate), ckpt_dir / "latest.zip",
                        p.init_lr if p.init and not resume else None)
    callbacks = [guard, EpisodeMetricsCallback(scenario), checkpoint]
    if not resume:
        first = config_seeds("validation", max(1, options.eval_n), options.eval_seed, "train.eval_seed").start
        # the run says which split its evaluations (and so best.zip) came from (av_gym/seeds.py)
        callbacks.append(HParamsCallback({**p.as_dict(), "env": scenario, "sensors": cfg.sensors.name,
                                          "shield": cfg.shield.name, "seed": command.seed,
                                          "eval_split": "validation", "eval_seed": first}, scenario))
    if options.eval_n > 0:
        # they pick best.zip: validation, never test
        eval_seeds = config_seeds("validation", options.eval_n, options.eval_seed, "train.eval_seed")
        play = None
        if p.vec_env == "batched":  # the stack it trains on, checked by validate(): validation on the batch too
            from eval.batched import play_batched

            def play(policy, seeds):  # the batch steps at 10 Hz: the policy holds its choice as ActionRepeat does
                held = SB3Policy(policy.model, p.action_repeat, p.actions)
                return play_batched(*stack.plain, held, seeds, p.n_envs, "eval", progress=False)
        callbacks.append(PeriodicEval(lambda mode: stack.one(0.0, render_mode=mode, timeout_is_terminal=False),
                                      scenario, eval_seeds, options.eval_every, ckpt_dir, run_dir,
                                      options.video_every, play=play))
    return callbacks, guard, checkpoint


def learn(model, venv, params, callbacks: list, guard, checkpoint, progress_bar: bool, run_name: str) -> None:
    """PPO up to ``agent.total_timesteps`` (rounded up to whole rollouts). A NaN inside an update is said in one
    line; SIGINT and SIGTERM save a checkpoint of a rollout boundary before exiting (one during an update stops at
    the next boundary: :meth:`train.callbacks.AtomicCheckpointCallback.interrupt`) and say which step it holds."""
    import signal

    from av_gym.errors import ConfigError
    from train.callbacks import nonfinite_parameter, steps_text

    # SIGTERM behaves like Ctrl-C; neither stops an update half-way (its half-updated state is no boundary)
    previous = {s: signal.signal(s, checkpoint.interrupt) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        remaining = params.total_timesteps - int(model.num_timesteps)
        # SB3 collects whole rollouts (n_steps x n_envs) until the total is reached: ask for that rounded-up total,
        # which it would train anyway, so that the progress bar ends at its total (not 24,576/24,000).
        rollout = params.n_steps * params.n_envs
        rounded = -(-remaining // rollout) * rollout
        if rounded != remaining:
            print(f"[train] agent.total_timesteps={params.total_timesteps}: PPO trains whole rollouts of "
                  f"n_steps x n_envs = {rollout} decisions, so {int(model.num_timesteps) + rounded}")
        # rounded == 0 (a resume of a run stopped at its last boundary: a signal during the last update) still goes
        # through learn(): no rollout, but the callbacks' end of training, i.e. the final evaluation it missed
        model.learn(total_timesteps=max(rounded, 0), callback=callbacks, reset_num_timesteps=False,
                    progress_bar=progress_bar and rounded > 0)
    except (ValueError, RuntimeError) as exc:
        # a NaN in the middle of an update fails inside torch (a distribution's argument check) before the guard
        # sees it: with non-finite parameters, that is the divergence, said in one line
        found = None if isinstance(exc, ConfigError) else nonfinite_parameter(model.policy)
        if found:
            raise guard.diverged(found, f"an update ({type(exc).__name__} in torch)") from None
        raise
    except KeyboardInterrupt:
        if checkpoint.model is not None:  # learning had started
            checkpoint.save()
        latest = checkpoint.folder / "latest.zip"
        if latest.is_file() and checkpoint.saved_at is not None:  # name only what exists, at the step it holds
            at, held = (steps_text(n, params.action_repeat) for n in (model.num_timesteps, checkpoint.saved_at))
            print(f"[train] interrupted at {at}; checkpoint {latest} holds {held} (continue from there with "
                  f"run_name={run_name} train.resume=true)")
        else:
            print(f"[train] interrupted at {steps_text(model.num_timesteps, params.action_repeat)}, before any "
                  f"checkpoint: nothing was kept (no latest.zip); start the run again (train.overwrite=true to reuse "
                  f"run_name={run_name})")
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        try:
            venv.close()
        except (EOFError, BrokenPipeError, ConnectionResetError):  # workers already gone after a signal
            pass


def train_ppo(cfg: DictConfig, ckpt_dir: Path, run_dir: Path, command: TrainCommand | None = None) -> Path:
    """Train PPO as ``cfg.agent`` (:class:`agents.ppo.PPOParams`) says: build the envs, resume or initialise the
    model (cloning ``agent.init``'s teacher), learn; TensorBoard under ``run_dir/tb``; returns the final checkpoint.

    ``train.resume=true`` continues ``checkpoints/<run_name>/latest.zip`` (policy, optimizer, step counter, RNG
    states) to the same ``total_timesteps``. SIGINT and SIGTERM save a checkpoint before exiting. ``command``: the
    run's settings (default: read from ``cfg``)."""
    from stable_baselines3 import PPO

    from agents.ppo import PPOParams
    from train.callbacks import steps_text
    from train.checkpoint import save_model_atomic

    t0 = time.time()
    command = command or TrainCommand.of(cfg)
    params = PPOParams.from_mapping(OmegaConf.to_container(cfg.agent, resolve=True), where="agent")
    stack = _Stack(*[OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)], params)
    resume = command.train.resume
    latest = _check_resume(ckpt_dir, resume)
    # A resumed run's episodes come from fresh seeds (the env streams of the killed run cannot be restored); every
    # stream's seed is folded into the train split (av_gym/seeds.py), whatever the seed and the steps done.
    done_steps = int(PPO.load(str(latest), device=params.device).num_timesteps) if resume else 0
    print(f"[train] {command.run_name}: starting {params.n_envs} training envs (agent.vec_env={params.vec_env})",
          flush=True)
    venv = build_envs(stack, train_seed(command.seed, done_steps))
    if resume:
        model, saved = resume_model(latest, venv, params)
    else:
        model = initialise_model(venv, stack, command.seed, str(cfg.env.name), command.train.progress_bar)
    # The checkpoint's own dump (at its step) is complete, so TensorBoard keeps it and drops only what came after.
    model.set_logger(_tensorboard_logger(run_dir / "tb" / params.name, model.num_timesteps + 1 if resume else None))
    if resume:  # values recorded by the last update but not yet written when the run was killed
        for key, store in saved.get("logger", {}).items():
            getattr(model.logger, key).update(store)
    callbacks, guard, checkpoint = _callbacks(cfg, command, stack, ckpt_dir, run_dir)
    learn(model, venv, params, callbacks, guard, checkpoint, command.train.progress_bar, command.run_name)
    guard.check("the last PPO update")  # model.zip only from finite parameters
    path = save_model_atomic(model, ckpt_dir / "model.zip")
    print(f"[train] {steps_text(model.num_timesteps, params.action_repeat)} in {time.time() - t0:.0f} s")
    return path
