"""PPO training with stable-baselines3, top to bottom: vectorised envs, model, callbacks, learn, save."""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from av_gym.seeds import DEMONSTRATIONS, config_seeds, train_seed


def _env_factory(env_cfg: dict, sensors_cfg: dict, shield_cfg: dict, intervention_cost: float = 0.0,
                 action_repeat: int = 1, actions: str = "env", render_mode: str | None = None,
                 timeout_is_terminal: bool = False):
    from av_gym.make import make_training_env  # the same stack gym.make(id, checkpoint=...) builds

    return make_training_env(env_cfg, sensors_cfg, shield_cfg, intervention_cost, action_repeat, actions,
                             render_mode=render_mode, timeout_is_terminal=timeout_is_terminal)


def make_teacher(name: str, actions: str, scenario: str | None = None, action_repeat: int = 1):
    """The teacher ``agent.init`` names (an agent config, ``conf/agent/<name>.yaml``), as
    ``teacher(env, obs, info) -> action`` in the training env's action space: its kind's entry in
    :data:`agents.registry.TEACHERS` (gap_acceptance and lookahead teach GO/YIELD choices, a pid agent steering
    from the simulator's CTE). The privileged teachers read what the student never sees (``env``'s future,
    ``info``); only their labels reach the student. A teacher refuses, in one line, a training setup it cannot
    label (``actions``, ``scenario``, ``action_repeat``)."""
    from agents.registry import TEACHERS, agent_params
    from av_gym.errors import ConfigError
    from eval.agents import load_agent_config

    cfg = load_agent_config(name)
    kind = cfg.get("kind")
    if kind not in TEACHERS:
        raise ConfigError(f"agent.init must name an agent of kind {' or '.join(TEACHERS.names())}, got {name!r} "
                          f"(kind {kind!r})")
    return TEACHERS.get(kind)(agent_params(cfg, where=name), actions, scenario, action_repeat)


@dataclass
class Demonstrations:
    """Labelled states for cloning, in the order they were visited: the (flat) observations, the teacher's labels
    and each step's discounted return to its episode's end (the critic's regression target)."""

    gamma: float
    observations: list[dict] = field(default_factory=list)
    labels: list = field(default_factory=list)
    returns: list[float] = field(default_factory=list)

    def add_episode(self, observations: list[dict], labels: list, rewards: list[float]) -> None:
        self.observations.extend(observations)
        self.labels.extend(labels)
        g, ret = 0.0, []
        for r in reversed(rewards):
            g = r + self.gamma * g
            ret.append(g)
        self.returns.extend(ret[::-1])

    def __len__(self) -> int:
        return len(self.labels)


def _outcome(info: dict) -> tuple[float, float]:
    """(collision, success) of a finished episode; lane keeping's success is a completed lap."""
    m = info["episode_metrics"]
    return m.get("collision", 0.0), m["success"] if "success" in m else m["lap_completed"]


def _drive(env, model, teacher, seed: int, student: bool, demos: Demonstrations, action_noise: float,
           rng) -> tuple[float, float]:
    """One episode of ``env`` on ``seed``, every state labelled by ``teacher``; the teacher's label is executed
    (``student``: the model's own deterministic action), plus DART noise of std ``action_noise`` on continuous
    actions. Appends the episode to ``demos``; returns its outcome."""
    import numpy as np
    from gymnasium import spaces

    discrete = isinstance(env.action_space, spaces.Discrete)
    obs, info = env.reset(seed=int(seed))
    seen, labels, rewards, done = [], [], [], False
    while not done:
        label = teacher(env, obs, info)
        seen.append({k: np.array(v, copy=True) for k, v in obs.items()})
        labels.append(label)
        executed = model.predict(obs, deterministic=True)[0] if student else label
        if action_noise > 0 and not discrete:
            executed = np.clip(executed + rng.normal(0.0, action_noise, np.shape(executed)),
                               env.action_space.low, env.action_space.high).astype(np.float32)
        obs, r, terminated, truncated, info = env.step(executed)
        rewards.append(r)
        done = terminated or truncated
    demos.add_episode(seen, labels, rewards)
    return _outcome(info)


def _drive_batch(env, teacher, seeds, demos: Demonstrations) -> list[tuple[float, float]]:
    """The teacher's episodes of ``seeds`` on a batched VecEnv, all rows stepped together: the same
    (observation, label, return) triples as :func:`_drive` gives per env, episode by episode in seed order."""
    import numpy as np

    obs, B = env.play(iter(seeds)), env.num_envs
    open_eps: list[list] = [[] for _ in range(B)]  # per row: [observation, label, reward] of its episode so far
    finished: dict[int, tuple] = {}
    while not env.idle.all():
        rows = np.nonzero(~env.idle)[0]
        labels = np.zeros(B, dtype=np.int64)
        for r in rows:
            o = {k: v[r].copy() for k, v in obs.items()}
            labels[r] = teacher(None, o, None)
            open_eps[r].append([o, labels[r]])
        obs, rewards, done, infos = env.step(labels)
        for r in rows:
            open_eps[r][-1].append(float(rewards[r]))
            if done[r]:
                finished[int(infos[r]["seed"])] = (open_eps[r], _outcome(infos[r]))
                open_eps[r] = []
    outcomes = []
    for seed in seeds:
        steps, result = finished[int(seed)]
        demos.add_episode([o for o, _, _ in steps], [int(a) for _, a, _ in steps], [r for _, _, r in steps])
        outcomes.append(result)
    return outcomes


def fit_policy(policy, demos: Demonstrations, discrete: bool, epochs: int, batch_size: int,
               lr: float | None = None, seed: int = 0) -> float:
    """Fit ``policy`` (an SB3 ActorCriticPolicy, with its own optimizer) to ``demos``: the actor by negative
    log-likelihood of the labels, the critic by the returns' MSE. Every tensor goes to the policy's device; the
    minibatch order comes from a CPU generator seeded ``seed``, so it is the same on every device (the cloning
    here and DAgger's rounds, train/dagger.py, both fit with it). Returns the accuracy:
    the share of matching choices (``discrete``), or 1 - mean |error| for continuous actions."""
    import numpy as np
    import torch as th

    device = policy.device
    if lr is not None:
        for group in policy.optimizer.param_groups:
            group["lr"] = float(lr)
    x = {k: np.stack([o[k] for o in demos.observations]) for k in demos.observations[0]}
    y = th.as_tensor(np.array(demos.labels), dtype=th.long if discrete else th.float32, device=device)
    g = th.as_tensor(np.array(demos.returns), dtype=th.float32, device=device)
    g_var = max(float(g.var()), 1.0) if len(g) > 1 else 1.0

    def batch(idx):  # obs_to_tensor transposes images to the policy's channel-first layout, as VecTransposeImage
        return policy.obs_to_tensor({k: v[idx.numpy()] for k, v in x.items()})[0]

    # Continuous actions: the Gaussian's std stays at agent.log_std_init. Fitted too, the NLL shrinks it to the
    # labels' residual (0.05 of full lock from the camera) and PPO's KL per update grows as 1/std^2: the camera run
    # then drifted off the road after 20k steps (approx KL 0.2-2, measured).
    log_std = getattr(policy, "log_std", None)
    if log_std is not None:
        log_std.requires_grad_(False)
    policy.set_training_mode(True)
    gen = th.Generator().manual_seed(int(seed))
    for _ in range(epochs):
        for idx in th.randperm(len(y), generator=gen, device="cpu").split(batch_size):
            on = idx.to(device)
            values, log_prob, _ = policy.evaluate_actions(batch(idx), y[on])
            # The value error is scaled by the returns' variance: the actor and critic share the feature extractor
            # (a CNN on images), and raw squared returns (a lap is worth ~50) would drown the actor's gradient
            # (measured: the camera clone reached only 0.82 with them).
            loss = -log_prob.mean() + th.nn.functional.mse_loss(values.flatten(), g[on]) / g_var
            policy.optimizer.zero_grad()
            loss.backward()
            th.nn.utils.clip_grad_norm_(policy.parameters(), 0.5)
            policy.optimizer.step()
    policy.set_training_mode(False)
    if log_std is not None:
        log_std.requires_grad_(True)
    with th.no_grad():
        scores = []
        for idx in th.arange(len(y), device="cpu").split(1024):
            dist = policy.get_distribution(batch(idx)).distribution
            on = idx.to(device)
            if discrete:
                scores.append((dist.probs.argmax(1) == y[on]).float())
            else:
                scores.append(1.0 - (dist.mean - y[on]).abs().mean(1))
        return float(th.cat(scores).mean())


def pretrain_from_teacher(model, env, teacher, seeds, gamma: float, epochs: int, batch_size: int,
                          action_noise: float = 0.0, dagger_rounds: int = 0, lr: float | None = None,
                          log=print) -> dict:
    """Behaviour cloning before PPO: ``teacher(env, obs, info)`` (:func:`make_teacher`) labels the states of ``env``
    (the training stack: its actions, action repeat, flat observations) on ``seeds``; the policy is fitted to the
    labels (negative log-likelihood: cross-entropy for GO/YIELD, Gaussian for steering) and the value head to the
    discounted returns of the episodes (MSE), with the model's own optimizer (:func:`fit_policy`). Why both: PPO's
    first updates on an untrained critic would undo a cloned actor.

    ``action_noise`` (std, continuous actions only) perturbs the executed action but not the label (DART), so the
    demonstrations include recoveries. ``dagger_rounds`` > 0 (DAgger, Ross et al. 2011): the seeds are split into
    1 + rounds parts; the teacher drives the first, the student's own deterministic policy the others, the teacher
    labels every state visited and the student is refitted on everything so far. Why: a cloned GO/YIELD policy
    meets states its teacher never visited (waiting at the line after a wrong yield) and has no label for them.
    ``lr``: the optimizer's learning rate while cloning (``None``: PPO's own); PPO resets it at its first update.
    Returns ``{"episodes", "decisions", "accuracy" (share of matching choices, or 1 - mean |error| for continuous
    actions), "teacher_collision", "teacher_success" (arrived, or lap completed; teacher-driven episodes),
    "student_collision", "student_success" (the last DAgger round; NaN without DAgger)}``."""
    import numpy as np
    from gymnasium import spaces

    discrete = isinstance(env.action_space, spaces.Discrete)
    rng = np.random.default_rng(0)  # DART's perturbations
    demos = Demonstrations(float(gamma))
    parts = np.array_split(np.asarray(list(seeds)), 1 + int(dagger_rounds))
    if hasattr(env, "play"):  # the batched engine: teacher-driven episodes only (no DAgger, no action noise)
        from av_gym.errors import ConfigError

        if dagger_rounds or action_noise:
            raise ConfigError("agent.init_dagger_rounds and agent.init_action_noise need the per-env stack: "
                              "agent.vec_env=subproc")
        teacher_outcomes = _drive_batch(env, teacher, parts[0], demos)
    else:
        teacher_outcomes = [_drive(env, model, teacher, seed, False, demos, action_noise, rng) for seed in parts[0]]
    accuracy = fit_policy(model.policy, demos, discrete, epochs, batch_size, lr)
    student_outcomes = [(np.nan, np.nan)]
    for k, part in enumerate(parts[1:], start=1):
        student_outcomes = [_drive(env, model, teacher, seed, True, demos, action_noise, rng) for seed in part]
        coll, succ = np.mean(student_outcomes, axis=0)
        log(f"[train] DAgger round {k}/{dagger_rounds}: the student drove {len(part)} episodes (collision "
            f"{coll:.2f}, success {succ:.2f}), {len(demos)} labelled decisions")
        accuracy = fit_policy(model.policy, demos, discrete, epochs, batch_size, lr)
    coll, succ = np.mean(teacher_outcomes, axis=0)
    s_coll, s_succ = np.mean(student_outcomes, axis=0)
    return {"episodes": sum(len(p) for p in parts), "decisions": len(demos), "accuracy": accuracy,
            "teacher_collision": float(coll), "teacher_success": float(succ),
            "student_collision": float(s_coll), "student_success": float(s_succ)}


def validate(cfg: DictConfig) -> list[str]:
    """What PPO's training needs beyond :class:`agents.ppo.PPOParams` (checked by the config checker), as one-line
    messages: a device torch can use here (``agent.device=cuda`` needs a GPU); with ``agent.vec_env=batched``, an
    env, sensors and shield the batched engine can run (on the command line, before any folder)."""
    from agents.ppo import PPOParams
    from train.device import device_problems

    params = PPOParams.from_mapping(OmegaConf.to_container(cfg.agent, resolve=True), where="agent")
    problems = device_problems(params.device)
    if problems or params.vec_env != "batched":
        return problems
    from av_gym.batched.vec_env import check_batchable
    from av_gym.errors import ConfigError

    try:
        check_batchable(*[OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)])
    except ConfigError as exc:
        # the same rollout on the per-env stack: one env per core, as many decisions per update
        per_env = max(2, params.n_steps * params.n_envs // 2)
        msg = str(exc).replace("use agent.vec_env=subproc", f"use agent.vec_env=subproc agent.n_envs=2 "
                                                             f"agent.n_steps={per_env}")
        return [msg]
    return []


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
        """The left turn's batched engine with the agent's action repeat, actions and time limit."""
        from agents.batched_vec_env import BatchedLeftTurnVecEnv

        p = self.params
        return BatchedLeftTurnVecEnv(*self.plain, p.n_envs, action_repeat=p.action_repeat, actions=p.actions,
                                     timeout_is_terminal=p.timeout_is_terminal)


def build_envs(stack: _Stack, seed: int):
    """The training VecEnv: ``agent.n_envs`` envs on the batched engine, in subprocesses or in this process, their
    episode seeds drawn from ``seed``."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from av_gym.errors import ConfigError

    p = stack.params
    if p.vec_env == "batched":  # all envs in one numpy batch (av_gym/batched/vec_env.py)
        if p.intervention_cost > 0:
            raise ConfigError("agent.intervention_cost needs a shield: not available with agent.vec_env=batched")
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
    print(f"[train] resuming {latest} at {model.num_timesteps} of {params.total_timesteps} env steps")
    return model, saved


def clone_teacher(model, stack: _Stack, scenario: str) -> None:
    """``agent.init``: behaviour-clone its teacher into ``model`` (:func:`pretrain_from_teacher`) on demonstration
    seeds of the train split, 500000+, away from PPO's own streams (seed + steps, from 0); one line if it diverges."""
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
                                      p.init_dagger_rounds, p.init_lr)
    except (ValueError, RuntimeError) as exc:  # NaN logits refused inside torch: say why, in one line
        lr = ("agent.init_lr", p.init_lr) if p.init_lr else ("agent.learning_rate", p.learning_rate)
        raise_if_diverged(exc, model.policy, "behaviour cloning", lr[0], float(lr[1]))
        raise
    except KeyboardInterrupt:  # it used to exit 130 without a word
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


def initialise_model(venv, stack: _Stack, seed: int, scenario: str):
    """A fresh PPO on ``venv`` seeded ``seed``, cloned from ``agent.init``'s teacher when it names one."""
    from agents.ppo import make_ppo

    p = stack.params
    model = make_ppo(venv, p.as_dict(), seed=seed, tensorboard_log=None, device=p.device)
    if p.init:
        clone_teacher(model, stack, scenario)
    if p.init_from:
        load_weights(model, p.init_from, scenario)
    return model


def load_weights(model, spec: str, scenario: str) -> None:
    """``agent.init_from``: copy a checkpoint's policy (actor, critic and extractor) into the fresh ``model``; the
    optimiser and PPO's counters start fresh, as after cloning. One line if the networks do not fit."""
    from stable_baselines3 import PPO

    from av_gym.errors import ConfigError
    from eval.agents import _checkpoint_file

    try:
        kind, path = _checkpoint_file(Path(spec), scenario)
    except ConfigError as exc:
        raise ConfigError(f"agent.init_from={spec!r}: {exc}") from None
    if kind not in ("ppo", "dagger"):
        raise ConfigError(f"agent.init_from={spec!r} holds agent kind {kind!r}; a PPO or DAgger checkpoint is needed")
    source = PPO.load(str(path), device=model.device)
    if source.observation_space != model.observation_space or source.action_space != model.action_space:
        raise ConfigError(f"agent.init_from={spec!r} was trained on other observation/action spaces than this "
                          f"run's sensors and agent.actions ({source.observation_space} vs {model.observation_space})")
    try:
        model.policy.load_state_dict(source.policy.state_dict())
    except RuntimeError as exc:  # torch lists every mismatched tensor; the first line says enough
        raise ConfigError(f"agent.init_from={spec!r}: its network does not fit agent.net_arch/extractor of this run "
                          f"({str(exc).splitlines()[0]})") from None
    print(f"[train] starting from {path}'s network")


def _callbacks(cfg: DictConfig, stack: _Stack, ckpt_dir: Path, run_dir: Path, resume: bool):
    """The guard against divergence (first: a diverged update never reaches a checkpoint), episode metrics,
    checkpoints, the hyperparameters (fresh runs) and the periodic evaluation on fixed seeds."""
    from agents.ppo import SB3Policy
    from train.callbacks import (AtomicCheckpointCallback, EpisodeMetricsCallback, FiniteGuard, HParamsCallback,
                                 PeriodicEval)

    p, scenario = stack.params, str(cfg.env.name)
    checkpoint = AtomicCheckpointCallback(ckpt_dir, int(cfg.train.checkpoint_every))
    guard = FiniteGuard(float(p.learning_rate), ckpt_dir / "latest.zip",
                        p.init_lr if p.init and not resume else None)
    callbacks = [guard, EpisodeMetricsCallback(scenario), checkpoint]
    if not resume:
        first = config_seeds("validation", max(1, int(cfg.train.eval_n)), cfg.train.get("eval_seed"),
                             "train.eval_seed").start
        # the run says which split its evaluations (and so best.zip) came from (av_gym/seeds.py)
        callbacks.append(HParamsCallback({**p.as_dict(), "env": scenario, "sensors": cfg.sensors.name,
                                          "shield": cfg.shield.name, "seed": int(cfg.seed),
                                          "eval_split": "validation", "eval_seed": first}, scenario))
    if int(cfg.train.eval_n) > 0:
        # they pick best.zip: validation, never test
        eval_seeds = config_seeds("validation", int(cfg.train.eval_n), cfg.train.get("eval_seed"), "train.eval_seed")
        play = None
        if p.vec_env == "batched":  # the stack it trains on, checked by validate(): validation on the batch too
            from eval.batched import play_batched

            def play(policy, seeds):  # the batch steps at 10 Hz: the policy holds its choice as ActionRepeat does
                held = SB3Policy(policy.model, p.action_repeat, p.actions)
                return play_batched(*stack.plain, held, seeds, p.n_envs, "eval", progress=False)
        callbacks.append(PeriodicEval(lambda mode: stack.one(0.0, render_mode=mode, timeout_is_terminal=False),
                                      scenario, eval_seeds, int(cfg.train.eval_every), ckpt_dir, run_dir,
                                      int(cfg.train.video_every), play=play))
    return callbacks, guard, checkpoint


def learn(model, venv, params, callbacks: list, guard, checkpoint, progress_bar: bool, run_name: str) -> None:
    """PPO up to ``agent.total_timesteps`` (rounded up to whole rollouts). A NaN inside an update is said in one
    line; SIGINT and SIGTERM save a checkpoint before exiting."""
    import signal

    from av_gym.errors import ConfigError
    from train.callbacks import nonfinite_parameter

    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM behaves like Ctrl-C
    try:
        remaining = params.total_timesteps - int(model.num_timesteps)
        # SB3 collects whole rollouts (n_steps x n_envs) until the total is reached: ask for that rounded-up total,
        # which it would train anyway, so that the progress bar ends at its total (not 24,576/24,000).
        rollout = params.n_steps * params.n_envs
        rounded = -(-remaining // rollout) * rollout
        if rounded != remaining:
            print(f"[train] agent.total_timesteps={params.total_timesteps}: PPO trains whole rollouts of "
                  f"n_steps x n_envs = {rollout} steps, so {int(model.num_timesteps) + rounded}")
        if rounded > 0:
            model.learn(total_timesteps=rounded, callback=callbacks, reset_num_timesteps=False,
                        progress_bar=progress_bar)
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
        if latest.is_file():  # name only what exists
            print(f"[train] interrupted at {model.num_timesteps} env steps; checkpoint {latest} (continue with "
                  f"run_name={run_name} train.resume=true)")
        else:
            print(f"[train] interrupted before PPO's first rollout: nothing was kept (no latest.zip); start the run "
                  f"again (train.overwrite=true to reuse run_name={run_name})")
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
        try:
            venv.close()
        except (EOFError, BrokenPipeError, ConnectionResetError):  # workers already gone after a signal
            pass


def train_ppo(cfg: DictConfig, ckpt_dir: Path, run_dir: Path) -> Path:
    """Train PPO as ``cfg.agent`` (:class:`agents.ppo.PPOParams`) says: build the envs, resume or initialise the
    model (cloning ``agent.init``'s teacher), learn; TensorBoard under ``run_dir/tb``; returns the final checkpoint.

    ``train.resume=true`` continues ``checkpoints/<run_name>/latest.zip`` (policy, optimizer, step counter, RNG
    states) to the same ``total_timesteps``. SIGINT and SIGTERM save a checkpoint before exiting."""
    from stable_baselines3 import PPO

    from agents.ppo import PPOParams
    from train.checkpoint import save_model_atomic

    t0 = time.time()
    params = PPOParams.from_mapping(OmegaConf.to_container(cfg.agent, resolve=True), where="agent")
    stack = _Stack(*[OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)], params)
    resume = bool(cfg.train.get("resume", False))
    latest = _check_resume(ckpt_dir, resume)
    # A resumed run's episodes come from fresh seeds (the env streams of the killed run cannot be restored); every
    # stream's seed is folded into the train split (av_gym/seeds.py), whatever the seed and the steps done.
    done_steps = int(PPO.load(str(latest), device=params.device).num_timesteps) if resume else 0
    venv = build_envs(stack, train_seed(int(cfg.seed), done_steps))
    if resume:
        model, saved = resume_model(latest, venv, params)
    else:
        model = initialise_model(venv, stack, int(cfg.seed), str(cfg.env.name))
    # The checkpoint's own dump (at its step) is complete, so TensorBoard keeps it and drops only what came after.
    model.set_logger(_tensorboard_logger(run_dir / "tb" / params.name, model.num_timesteps + 1 if resume else None))
    if resume:  # values recorded by the last update but not yet written when the run was killed
        for key, store in saved.get("logger", {}).items():
            getattr(model.logger, key).update(store)
    callbacks, guard, checkpoint = _callbacks(cfg, stack, ckpt_dir, run_dir, resume)
    learn(model, venv, params, callbacks, guard, checkpoint, bool(cfg.train.progress_bar), str(cfg.run_name))
    guard.check("the last PPO update")  # model.zip only from finite parameters
    path = save_model_atomic(model, ckpt_dir / "model.zip")
    env_steps = f" ({model.num_timesteps * params.action_repeat} env steps)" if params.action_repeat > 1 else ""
    print(f"[train] {model.num_timesteps} steps{env_steps} in {time.time() - t0:.0f} s")
    return path
