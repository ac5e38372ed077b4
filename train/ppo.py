"""PPO training with stable-baselines3, top to bottom: vectorised envs, model, callbacks, learn, save."""

from __future__ import annotations

import functools
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from av_gym.seeds import DEMONSTRATIONS, config_seeds, train_seed


def _env_factory(env_cfg: dict, sensors_cfg: dict, shield_cfg: dict, intervention_cost: float = 0.0,
                 action_repeat: int = 1, actions: str = "env", render_mode: str | None = None,
                 timeout_is_terminal: bool = False):
    from av_gym.make import make_env
    from av_gym.wrappers import ActionRepeat, FlatDictObservation, GoYieldActions, InterventionCost, TimeLimitIsTerminal

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


def pretrain_from_teacher(model, env, teacher, seeds, gamma: float, epochs: int, batch_size: int,
                          action_noise: float = 0.0, dagger_rounds: int = 0, lr: float | None = None,
                          log=print) -> dict:
    """Behaviour cloning before PPO: ``teacher(env, obs, info)`` (:func:`make_teacher`) labels the states of ``env``
    (the training stack: its actions, action repeat, flat observations) on ``seeds``; the policy is fitted to the
    labels (negative log-likelihood: cross-entropy for GO/YIELD, Gaussian for steering) and the value head to the
    discounted returns of the episodes (MSE), with the model's own optimizer. Why both: PPO's first updates on an
    untrained critic would undo a cloned actor.

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
    import torch as th
    from gymnasium import spaces

    discrete = isinstance(env.action_space, spaces.Discrete)
    rng = np.random.default_rng(0)
    policy = model.policy
    obs_list, actions, returns = [], [], []

    def outcome(info):
        m = info["episode_metrics"]
        return m.get("collision", 0.0), m["success"] if "success" in m else m["lap_completed"]

    def discounted(rewards: list[float]) -> list[float]:
        """Each step's discounted return to the episode's end (the critic's regression target)."""
        g, ret = 0.0, []
        for r in reversed(rewards):
            g = r + gamma * g
            ret.append(g)
        return ret[::-1]

    def drive(seed: int, student: bool):
        obs, info = env.reset(seed=int(seed))
        rewards, done = [], False
        while not done:
            label = teacher(env, obs, info)
            obs_list.append({k: np.array(v, copy=True) for k, v in obs.items()})
            actions.append(label)
            executed = model.predict(obs, deterministic=True)[0] if student else label
            if action_noise > 0 and not discrete:
                executed = np.clip(executed + rng.normal(0.0, action_noise, np.shape(executed)),
                                   env.action_space.low, env.action_space.high).astype(np.float32)
            obs, r, terminated, truncated, info = env.step(executed)
            rewards.append(r)
            done = terminated or truncated
        returns.extend(discounted(rewards))
        return outcome(info)

    def batch(x, idx):  # obs_to_tensor transposes images to the policy's channel-first layout, as VecTransposeImage
        return policy.obs_to_tensor({k: v[idx.numpy()] for k, v in x.items()})[0]

    def fit():
        if lr is not None:
            for group in policy.optimizer.param_groups:
                group["lr"] = float(lr)
        x = {k: np.stack([o[k] for o in obs_list]) for k in obs_list[0]}
        y = th.as_tensor(np.array(actions), dtype=th.long if discrete else th.float32)
        g = th.as_tensor(np.array(returns), dtype=th.float32)
        g_var = max(float(g.var()), 1.0) if len(g) > 1 else 1.0
        # Continuous actions: the Gaussian's std stays at agent.log_std_init. Fitted too, the NLL shrinks it to the
        # labels' residual (0.05 of full lock from the camera) and PPO's KL per update grows as 1/std^2: the
        # camera run then drifted off the road after 20k steps (approx KL 0.2-2, measured).
        log_std = getattr(policy, "log_std", None)
        if log_std is not None:
            log_std.requires_grad_(False)
        policy.set_training_mode(True)
        gen = th.Generator().manual_seed(0)
        for _ in range(epochs):
            for idx in th.randperm(len(y), generator=gen).split(batch_size):
                values, log_prob, _ = policy.evaluate_actions(batch(x, idx), y[idx])
                # The value error is scaled by the returns' variance: the actor and critic share the feature
                # extractor (a CNN on images), and raw squared returns (a lap is worth ~50) would drown the actor's
                # gradient (measured: the camera clone reached only 0.82 with them).
                loss = -log_prob.mean() + th.nn.functional.mse_loss(values.flatten(), g[idx]) / g_var
                policy.optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(policy.parameters(), 0.5)
                policy.optimizer.step()
        policy.set_training_mode(False)
        if log_std is not None:
            log_std.requires_grad_(True)
        with th.no_grad():
            scores = []
            for idx in th.arange(len(y)).split(1024):
                dist = policy.get_distribution(batch(x, idx)).distribution
                if discrete:
                    scores.append((dist.probs.argmax(1) == y[idx]).float())
                else:
                    scores.append(1.0 - (dist.mean - y[idx]).abs().mean(1))
            return float(th.cat(scores).mean())

    def drive_batch(seeds) -> list:
        """The teacher's episodes of ``seeds`` on a batched VecEnv (issue 16), all rows stepped together: the same
        (observation, label, return) triples as :func:`drive` gives per env, episode by episode in seed order."""
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
                    finished[int(infos[r]["seed"])] = (open_eps[r], outcome(infos[r]))
                    open_eps[r] = []
        outcomes = []
        for seed in seeds:
            steps, result = finished[int(seed)]
            obs_list.extend(o for o, _, _ in steps)
            actions.extend(int(a) for _, a, _ in steps)
            returns.extend(discounted([r for _, _, r in steps]))
            outcomes.append(result)
        return outcomes

    parts = np.array_split(np.asarray(list(seeds)), 1 + int(dagger_rounds))
    if hasattr(env, "play"):  # the batched engine: teacher-driven episodes only (no DAgger, no action noise)
        from av_gym.errors import ConfigError

        if dagger_rounds or action_noise:
            raise ConfigError("agent.init_dagger_rounds and agent.init_action_noise need the per-env stack: "
                              "agent.vec_env=subproc")
        teacher_outcomes = drive_batch(parts[0])
    else:
        teacher_outcomes = [drive(seed, student=False) for seed in parts[0]]
    accuracy = fit()
    student_outcomes = [(np.nan, np.nan)]
    for k, part in enumerate(parts[1:], start=1):
        student_outcomes = [drive(seed, student=True) for seed in part]
        coll, succ = np.mean(student_outcomes, axis=0)
        log(f"[train] DAgger round {k}/{dagger_rounds}: the student drove {len(part)} episodes (collision "
            f"{coll:.2f}, success {succ:.2f}), {len(actions)} labelled decisions")
        accuracy = fit()
    coll, succ = np.mean(teacher_outcomes, axis=0)
    s_coll, s_succ = np.mean(student_outcomes, axis=0)
    return {"episodes": sum(len(p) for p in parts), "decisions": len(actions), "accuracy": accuracy,
            "teacher_collision": float(coll), "teacher_success": float(succ),
            "student_collision": float(s_coll), "student_success": float(s_succ)}


def validate(cfg: DictConfig) -> list[str]:
    """What PPO's training needs beyond :class:`agents.ppo.PPOParams` (checked by the config checker), as one-line
    messages: with ``agent.vec_env=batched``, an env, sensors and shield the batched engine can run (on the command
    line, before any folder)."""
    if cfg.agent.vec_env != "batched":
        return []
    from av_gym.batched.vec_env import check_batchable
    from av_gym.errors import ConfigError

    try:
        check_batchable(*[OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)])
    except ConfigError as exc:
        # the same rollout on the per-env stack: one env per core, as many decisions per update
        per_env = max(2, int(cfg.agent.n_steps) * int(cfg.agent.n_envs) // 2)
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


def train_ppo(cfg: DictConfig, ckpt_dir: Path, run_dir: Path) -> Path:
    """Train PPO as ``cfg.agent`` says; TensorBoard under ``run_dir/tb``; returns the final checkpoint path.

    ``train.resume=true`` continues ``checkpoints/<run_name>/latest.zip`` (policy, optimizer, step counter, RNG
    states) to the same ``total_timesteps``. SIGINT and SIGTERM save a checkpoint before exiting."""
    import signal

    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from agents.ppo import PPOParams, SB3Policy, make_ppo
    from av_gym.errors import ConfigError
    from train.callbacks import (AtomicCheckpointCallback, EpisodeMetricsCallback, FiniteGuard, HParamsCallback,
                                 PeriodicEval, nonfinite_parameter, raise_if_diverged)
    from agents.checkpoint import check_sb3_zip
    from eval.agents import load_agent_config
    from train.checkpoint import load_rng_state, save_model_atomic

    agent, t0 = cfg.agent, time.time()
    params = PPOParams.from_mapping(OmegaConf.to_container(agent, resolve=True), where="agent")
    latest = ckpt_dir / "latest.zip"
    resume = bool(cfg.train.get("resume", False))
    if resume and not latest.is_file():
        raise ConfigError(f"train.resume=true but {latest} does not exist (resume needs the run_name of a run "
                          f"that wrote a checkpoint)")
    if resume:
        check_sb3_zip(latest)  # empty or corrupt (copied by hand?): one line, not SB3's traceback
    for stale in ckpt_dir.glob(".*.tmp"):  # a save that was killed half-way; the previous file is intact
        stale.unlink()
    plain = [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
    vec_cls = SubprocVecEnv if (agent.vec_env == "subproc" and agent.n_envs > 1) else DummyVecEnv
    done_steps = 0
    if resume:
        done_steps = int(PPO.load(str(latest), device=agent.device).num_timesteps)
    # A resumed run's episodes come from fresh seeds (the env streams of the killed run cannot be restored); every
    # stream's seed is folded into the train split (av_gym/seeds.py), whatever the seed and the steps done.
    stream_seed = train_seed(int(cfg.seed), done_steps)
    cost, repeat, actions = float(params.intervention_cost), int(params.action_repeat), str(params.actions)
    if agent.vec_env == "batched":  # issue 16: all envs in one numpy batch (av_gym/batched/vec_env.py)
        from av_gym.batched.vec_env import BatchedLeftTurnVecEnv

        if cost > 0:
            raise ConfigError("agent.intervention_cost needs a shield: not available with agent.vec_env=batched")
        venv = BatchedLeftTurnVecEnv(*plain, int(agent.n_envs), action_repeat=repeat, actions=actions,
                                     timeout_is_terminal=params.timeout_is_terminal)
        venv.seed(stream_seed)
    else:
        venv = make_vec_env(functools.partial(_env_factory, *plain, cost, repeat, actions,
                                              timeout_is_terminal=params.timeout_is_terminal),
                            n_envs=int(agent.n_envs),
                            seed=stream_seed, vec_env_cls=vec_cls)
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
        if params.init:
            teacher = make_teacher(str(agent.init), actions, str(cfg.env.name), repeat)
            if agent.vec_env == "batched" and load_agent_config(str(agent.init)).get("kind") == "gap_acceptance":
                # a rule of the observation alone: its episodes on the batch too (lookahead simulates its env's copy)
                demo_env = BatchedLeftTurnVecEnv(*plain, int(agent.n_envs), action_repeat=repeat, actions=actions,
                                                 timeout_is_terminal=params.timeout_is_terminal)
            else:
                demo_env = _env_factory(*plain, cost, repeat, actions)
            # Demonstration seeds: train split, 500000+, away from PPO's own streams (seed + steps, from 0).
            t_bc = time.time()
            try:
                stats = pretrain_from_teacher(model, demo_env, teacher,
                                              config_seeds("train", int(agent.init_episodes), DEMONSTRATIONS,
                                                           "agent.init_episodes from seed"),
                                              float(agent.gamma), int(agent.init_epochs), int(agent.batch_size),
                                              float(params.init_action_noise), int(params.init_dagger_rounds),
                                              params.init_lr)
            except (ValueError, RuntimeError) as exc:  # NaN logits refused inside torch: say why, in one line
                lr = ("agent.init_lr", params.init_lr) if params.init_lr else ("agent.learning_rate",
                                                                                params.learning_rate)
                raise_if_diverged(exc, model.policy, "behaviour cloning", lr[0], float(lr[1]))
                raise
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
    guard = FiniteGuard(float(agent.learning_rate), latest,  # first: a diverged update never reaches a checkpoint
                        params.init_lr if params.init and not resume else None)
    callbacks = [guard, EpisodeMetricsCallback(cfg.env.name), checkpoint]
    if not resume:
        callbacks.append(HParamsCallback({**OmegaConf.to_container(agent, resolve=True), "env": cfg.env.name,
                                          "sensors": cfg.sensors.name, "shield": cfg.shield.name,
                                          "seed": int(cfg.seed)}, cfg.env.name))
    if int(cfg.train.eval_n) > 0:
        # they pick best.zip: validation, never test
        eval_seeds = config_seeds("validation", int(cfg.train.eval_n), cfg.train.get("eval_seed"), "train.eval_seed")
        play = None
        if agent.vec_env == "batched":  # the stack it trains on, checked by validate(): validation on the batch too
            from eval.batched import play_batched

            def play(policy, seeds):  # the batch steps at 10 Hz: the policy holds its choice as ActionRepeat does
                held = SB3Policy(policy.model, repeat, actions)
                return play_batched(*plain, held, seeds, int(agent.n_envs), "eval", progress=False)
        callbacks.append(PeriodicEval(lambda mode: _env_factory(*plain, 0.0, repeat, actions, render_mode=mode),
                                      cfg.env.name,
                                      eval_seeds,
                                      int(cfg.train.eval_every), ckpt_dir, run_dir, int(cfg.train.video_every),
                                      play=play))
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM behaves like Ctrl-C
    try:
        remaining = int(agent.total_timesteps) - int(model.num_timesteps)
        # SB3 collects whole rollouts (n_steps x n_envs) until the total is reached: ask for that rounded-up total,
        # which it would train anyway, so that the progress bar ends at its total (not 24,576/24,000).
        rollout = int(agent.n_steps) * int(agent.n_envs)
        rounded = -(-remaining // rollout) * rollout
        if rounded != remaining:
            print(f"[train] agent.total_timesteps={int(agent.total_timesteps)}: PPO trains whole rollouts of "
                  f"n_steps x n_envs = {rollout} steps, so {int(model.num_timesteps) + rounded}")
        remaining = rounded
        if remaining > 0:
            model.learn(total_timesteps=remaining, callback=callbacks, reset_num_timesteps=False,
                        progress_bar=bool(cfg.train.progress_bar))
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
        print(f"[train] interrupted at {model.num_timesteps} env steps; checkpoint {latest} "
              f"(continue with run_name={cfg.run_name} train.resume=true)")
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
        try:
            venv.close()
        except (EOFError, BrokenPipeError, ConnectionResetError):  # workers already gone after a signal
            pass
    guard.check("the last PPO update")  # model.zip only from finite parameters
    path = save_model_atomic(model, ckpt_dir / "model.zip")
    env_steps = f" ({model.num_timesteps * repeat} env steps)" if repeat > 1 else ""
    print(f"[train] {model.num_timesteps} steps{env_steps} in {time.time() - t0:.0f} s")
    return path
