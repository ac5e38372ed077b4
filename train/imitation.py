"""Imitation: a teacher's labelled episodes and a policy fitted to them, for PPO's warm start
(:func:`pretrain_from_teacher`, ``agent.init``) and for DAgger (train/dagger.py), and a checkpoint's network copied
into a fresh model (``agent.init_from``). The teachers themselves are agents (:data:`agents.registry.TEACHERS`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

if TYPE_CHECKING:
    import numpy as np
    import torch as th


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
    targets: list[float] = field(default_factory=list)  # P(GO) to fit instead of the labels (GO/YIELD students)

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


def _drive_batch(env, teacher, seeds, demos: Demonstrations, bar=None) -> list[tuple[float, float]]:
    """The teacher's episodes of ``seeds`` on a batched VecEnv, all rows stepped together: the same
    (observation, label, return) triples as :func:`_drive` gives per env, episode by episode in seed order.
    ``bar``: a tqdm bar, advanced by each finished episode."""
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
                if bar is not None:
                    bar.update()
    outcomes = []
    for seed in seeds:
        steps, result = finished[int(seed)]
        demos.add_episode([o for o, _, _ in steps], [int(a) for _, a, _ in steps], [r for _, _, r in steps])
        outcomes.append(result)
    return outcomes


def fit_policy(policy, demos: Demonstrations, discrete: bool, epochs: int, batch_size: int,
               lr: float | None = None, seed: int = 0, desc: str | None = None,
               weights: np.ndarray | None = None) -> float:
    """Fit ``policy`` (an SB3 ActorCriticPolicy, with its own optimizer) to ``demos``: the actor by negative
    log-likelihood of the labels, the critic by the returns' MSE. Every tensor goes to the policy's device; the
    minibatch order comes from a CPU generator seeded ``seed``, so it is the same on every device (the cloning
    here and DAgger's rounds, train/dagger.py, both fit with it). Returns the accuracy:
    the share of matching choices (``discrete``), or 1 - mean |error| for continuous actions.

    With ``demos.targets`` (a GO/YIELD student, DAgger's agent.targets=go_safe) the actor is fitted by the
    cross-entropy to those probabilities of GO, -[q log π(GO) + (1 - q) log π(YIELD)], instead of the labels' NLL;
    the accuracy is still against the labels. ``desc``: a progress bar of the epochs with that title. ``weights``
    (one per label, > 0): the actor's loss is the weighted mean over each minibatch (DAgger's
    agent.disagree_weight); None: the plain mean."""
    import numpy as np
    import torch as th

    device = policy.device
    if lr is not None:
        for group in policy.optimizer.param_groups:
            group["lr"] = float(lr)
    x = {k: np.stack([o[k] for o in demos.observations]) for k in demos.observations[0]}
    y = th.as_tensor(np.array(demos.labels), dtype=th.long if discrete else th.float32, device=device)
    g = th.as_tensor(np.array(demos.returns), dtype=th.float32, device=device)
    q = th.as_tensor(np.array(demos.targets), dtype=th.float32, device=device) if demos.targets else None
    if q is not None and (not discrete or len(q) != len(y)):
        raise ValueError(f"targets: {len(q)} P(GO) values for {len(y)} labels of a "
                         f"{'discrete' if discrete else 'continuous'} policy; one per label of a GO/YIELD student")
    w = th.as_tensor(np.asarray(weights), dtype=th.float32, device=device) if weights is not None else None
    g_var = max(float(g.var()), 1.0) if len(g) > 1 else 1.0
    if q is not None:
        from av_gym.wrappers import GO

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
    for _ in tqdm(range(epochs), desc=desc, unit="epoch", disable=desc is None, leave=False):
        for idx in th.randperm(len(y), generator=gen, device="cpu").split(batch_size):
            on = idx.to(device)
            if q is None:
                values, log_prob, _ = policy.evaluate_actions(batch(idx), y[on])
                actor = -_mean(log_prob, w, on)
            else:  # log π(GO) from one pass; log π(YIELD) = log(1 - π(GO)) (two actions)
                values, log_go, _ = policy.evaluate_actions(batch(idx), th.full_like(y[on], GO))
                log_other = th.log1p(-log_go.exp().clamp(max=1.0 - 1e-6))
                actor = -_mean(q[on] * log_go + (1.0 - q[on]) * log_other, w, on)
            # The value error is scaled by the returns' variance: the actor and critic share the feature extractor
            # (a CNN on images), and raw squared returns (a lap is worth ~50) would drown the actor's gradient
            # (measured: the camera clone reached only 0.82 with them).
            loss = actor + th.nn.functional.mse_loss(values.flatten(), g[on]) / g_var
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


def _mean(x: th.Tensor, w: th.Tensor | None, on: th.Tensor) -> th.Tensor:
    """The mean of ``x`` over a minibatch, weighted by ``w[on]`` (None: unweighted)."""
    return x.mean() if w is None else (w[on] * x).sum() / w[on].sum()


def pretrain_from_teacher(model, env, teacher, seeds, gamma: float, epochs: int, batch_size: int,
                          action_noise: float = 0.0, dagger_rounds: int = 0, lr: float | None = None,
                          log=print, progress: bool = False) -> dict:
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
    ``log`` gets a line as each phase starts (the teacher's episodes, each fit: seconds to a minute each);
    ``progress``: a bar within each.
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
    log(f"[train] cloning: the teacher drives {len(parts[0])} demonstration episodes")
    teacher_outcomes = _teacher_episodes(env, model, teacher, parts[0], demos, action_noise, rng, progress)
    accuracy = _fit(model, demos, discrete, epochs, batch_size, lr, log, progress)
    student_outcomes = [(np.nan, np.nan)]
    for k, part in enumerate(parts[1:], start=1):
        student_outcomes = [_drive(env, model, teacher, seed, True, demos, action_noise, rng) for seed in part]
        coll, succ = np.mean(student_outcomes, axis=0)
        log(f"[train] DAgger round {k}/{dagger_rounds}: the student drove {len(part)} episodes (collision "
            f"{coll:.2f}, success {succ:.2f}), {len(demos)} labelled decisions")
        accuracy = _fit(model, demos, discrete, epochs, batch_size, lr, log, progress)
    coll, succ = np.mean(teacher_outcomes, axis=0)
    s_coll, s_succ = np.mean(student_outcomes, axis=0)
    return {"episodes": sum(len(p) for p in parts), "decisions": len(demos), "accuracy": accuracy,
            "teacher_collision": float(coll), "teacher_success": float(succ),
            "student_collision": float(s_coll), "student_success": float(s_succ)}


def _teacher_episodes(env, model, teacher, seeds, demos: Demonstrations, action_noise: float, rng,
                      progress: bool) -> list[tuple[float, float]]:
    """The teacher's episodes of ``seeds`` into ``demos`` (on the batch, or one by one), with a bar of them
    (``progress``); their outcomes."""
    with tqdm(total=len(seeds), desc="teacher episodes", unit="ep", disable=not progress, leave=False) as bar:
        if hasattr(env, "play"):
            return _drive_batch(env, teacher, seeds, demos, bar)
        outcomes = []
        for seed in seeds:
            outcomes.append(_drive(env, model, teacher, seed, False, demos, action_noise, rng))
            bar.update()
        return outcomes


def _fit(model, demos: Demonstrations, discrete: bool, epochs: int, batch_size: int, lr: float | None, log,
         progress: bool) -> float:
    """:func:`fit_policy` of the model's policy, announced by a line (and a bar of its epochs with ``progress``)."""
    log(f"[train] cloning: fitting the policy to {len(demos)} labelled decisions ({epochs} epochs)")
    return fit_policy(model.policy, demos, discrete, epochs, batch_size, lr, desc="fitting" if progress else None)


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
