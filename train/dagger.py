"""DAgger (Ross et al. 2011) top to bottom: a PPO policy network learns from a teacher on its own states.

Round 0: the teacher drives ``agent.round_episodes`` episodes, labelling every decision; the student is fitted to
the labels. Round k ≥ 1: the student drives, the teacher labels the states the student visits, the labels join
the aggregate, the student is refitted on all of it. Why: a clone fitted once to its teacher's own episodes meets
states its teacher never visited (waiting at the line after a wrong yield, a late GO) and has no label for them.

The student is SB3's PPO policy (``agents.ppo.make_ppo`` with the agent's extractor and net_arch): the actor is
fitted to the labels (cross-entropy for GO/YIELD, Gaussian NLL for steering), the critic to the discounted returns
of the driven episodes, so that ``model.zip`` loads in ``python -m eval`` as any PPO checkpoint and PPO can
fine-tune it. The teacher is any agent of a TEACHERS kind (``agent.teacher``). Two stacks:

- ``agent.vec_env=batched`` (the left turn's sensors the batch runs: ``turn_truth``, and ``turn_perceived`` with
  the detector and tracker over every row, av_gym/batched/perception.py): ``agent.n_envs`` episodes stepped together
  on the batched engine; the look-ahead oracle labels every env's decision at once from the simulator's state
  (:mod:`agents.batched_oracle`), a rule from the observation row by row; the same rounds as the replica below
  (tests/test_dagger_batched_perceived.py) at a fraction of its wall time;
- otherwise (any sensors; any scenario): the per-env training stack (``train/ppo.py``'s
  wrappers). On the left turn with the oracle as teacher, ``agent.n_envs`` of them drive in lockstep with a batched
  replica of their episodes, which the oracle labels all at once (:func:`drive_replica`); else one stack, the
  teacher labelling one state at a time.

On the batch, ``agent.workers=N`` drives and labels each round's seeds in N spawned processes, one contiguous part
each (:func:`drive_parts`), merged into the aggregate one process gives (:func:`merge_parts`).

Per round: a progress line, TensorBoard scalars (``run_dir/tb/<name>``), ``rounds.csv`` (labels, wall-clock, the
seconds spent labelling and refitting, the student's agreement with the teacher on its own states, its
success/collision while driving and on the validation seeds) and an atomic ``latest.zip``; ``best.zip`` holds the
best validation (success - collision); ``model.zip`` the last round.

Resumable at round granularity (a stopped run restarted at round 0 and overwrote its files):
``latest.zip`` is the whole state at the end of the last finished round, in one file replaced at once: the
student with its optimizer, the aggregate of labelled states (member ``av_gym_dagger.npz``), the rounds' rows, the
best validation score and the RNG states. ``train.resume=true`` continues at the next round, so a kill -9 costs at
most the round in progress, and (the rounds' seeds and fits being fixed by the run's seed) the resumed run ends with
the same student as an uninterrupted one.
"""

from __future__ import annotations

import csv
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from conf.commands import TrainCommand, TrainOptions

if TYPE_CHECKING:
    from agents.dagger import DaggerParams

ROUND_FIELDS = ("round", "driver", "episodes", "labels", "wall_s", "label_s", "agreement", "drive_success",
                "drive_collision", "fit_accuracy", "val_success", "val_collision", "fit_s")
STATE_MEMBER = "av_gym_dagger.npz"  # the aggregate's labelled states, inside latest.zip


# ------------------------------------------------------------------------------------------------------ checks
def _teacher_kind(cfg: DictConfig) -> str | None:
    from eval.agents import load_agent_config

    return load_agent_config(str(cfg.agent.teacher)).get("kind")


def labeller_of(cfg: DictConfig) -> str:
    """``batched`` (the oracle on the batched engine), ``rule`` (a teacher of the observation alone, row by row on
    the batch), ``replica`` (the student on the per-env stack, the oracle on a batched replica of its episodes) or
    ``per_env`` (the teacher on the per-env stack, one state at a time)."""
    oracle = _teacher_kind(cfg) == "lookahead"
    if cfg.agent.vec_env == "batched":  # the belief planner plays its futures on the batch too
        return "batched" if oracle or _teacher_kind(cfg) == "belief_lookahead" else "rule"
    if cfg.agent.labeller == "per_env" or not oracle or _replica_refusal(cfg):
        return "per_env"
    return "replica"


def _replica_refusal(cfg: DictConfig) -> str | None:
    """Why the oracle's batched replica cannot play the per-env episodes of ``cfg`` (None: it can)."""
    from av_gym.batched.vec_env import check_batchable
    from av_gym.errors import ConfigError

    try:  # the left turn only, and no shield: its overrides would change the per-env episode, not the replica's
        check_batchable(OmegaConf.to_container(cfg.env, resolve=True), replica_sensors(cfg.sensors),
                        OmegaConf.to_container(cfg.shield, resolve=True))
    except ConfigError as exc:
        return str(exc).split(" is not available")[0].split(" runs ")[0]
    return None


def validate(cfg: DictConfig) -> list[str]:
    """What DAgger needs beyond :class:`agents.dagger.DaggerParams`, one line each (before any folder)."""
    from av_gym.errors import ConfigError
    from train.imitation import make_teacher

    agent = cfg.agent
    try:
        make_teacher(str(agent.teacher), str(agent.actions), str(cfg.env.name), int(agent.action_repeat))
    except ConfigError as exc:
        return [str(exc).replace("agent.init", "agent.teacher")]
    batched = agent.vec_env == "batched"
    if int(agent.get("workers", 1)) > 1 and not batched:
        return [f"agent.workers={agent.workers} needs agent.vec_env=batched (each labelling process drives its part "
                f"of a round on a batch of its own); got agent.vec_env={agent.vec_env}: use agent.workers=1"]
    if agent.labeller == "batched" and not batched:
        return ["agent.labeller=batched needs agent.vec_env=batched (the oracle runs on the batched engine)"]
    if agent.labeller == "per_env" and batched:
        return ["agent.labeller=per_env needs agent.vec_env=subproc or dummy (the per-env stack)"]
    refusal = _replica_refusal(cfg) if agent.labeller == "replica" else None
    if agent.labeller == "replica" and (batched or _teacher_kind(cfg) != "lookahead" or refusal):
        return [f"agent.labeller=replica needs agent.vec_env=subproc or dummy, env=left_turn, shield=none and "
                f"agent.teacher of kind lookahead (the oracle on a batched replica of the per-env episodes); got "
                f"agent.vec_env={agent.vec_env}, agent.teacher={agent.teacher}" + (f", {refusal}" if refusal else "")]
    if batched:
        kind = _teacher_kind(cfg)
        if kind not in ("lookahead", "belief_lookahead", "gap_acceptance"):
            return [f"agent.teacher={agent.teacher} (kind {kind}) cannot label on agent.vec_env=batched (lookahead, "
                    f"belief_lookahead or gap_acceptance can); use agent.vec_env=subproc"]
        from av_gym.batched.perception import perceived
        from av_gym.batched.vec_env import check_batchable

        try:
            check_batchable(*[OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)])
        except ConfigError as exc:
            return [str(exc)]
        if kind == "belief_lookahead" and perceived(OmegaConf.to_container(cfg.sensors, resolve=True)):
            return [f"agent.teacher={agent.teacher} (kind belief_lookahead) cannot label sensors.turn_features."
                    f"source=tracks on agent.vec_env=batched (its batched planner reads the described objects as the "
                    f"simulator's vehicles); use agent.vec_env=subproc"]
    if agent.targets == "go_safe" and (not batched or _teacher_kind(cfg) != "belief_lookahead"):
        return [f"agent.targets=go_safe needs agent.teacher of kind belief_lookahead on agent.vec_env=batched (the "
                f"share of its GO futures without a collision); got agent.teacher={agent.teacher} (kind "
                f"{_teacher_kind(cfg)}), agent.vec_env={agent.vec_env}"]
    if float(agent.label_margin) > 0 and (labeller_of(cfg) not in ("batched", "replica")
                                          or _teacher_kind(cfg) != "lookahead"):
        return ["agent.label_margin > 0 needs the batched oracle (agent.teacher of kind lookahead on env=left_turn, "
                "agent.labeller auto, batched or replica): the per-env teachers give no margin"]
    if float(agent.get("disagree_weight", 1.0)) != 1.0 and agent.actions != "go_yield" \
            and cfg.env.get("action") != "discrete":
        return [f"agent.disagree_weight={agent.disagree_weight} needs discrete choices to disagree on "
                f"(agent.actions=go_yield or env.action=discrete); got agent.actions={agent.actions} on "
                f"env={cfg.env.name}"]
    return []


def replica_sensors(sensors: DictConfig) -> dict:
    """The sensors of the replica that the oracle labels: the student's turn signals and intent (their draws come
    from the episode's own generators, so they are kept), the features from the simulator's vehicles, no detector
    or tracker (the student's per-env stack has them; the oracle reads the truth)."""
    s = OmegaConf.to_container(sensors, resolve=True)
    out = {k: s[k] for k in ("turn_signals", "turn_intent") if k in s}
    out["turn_features"] = {**(s.get("turn_features") or {}), "source": "truth"}
    return {"name": f"{s.get('name', 'sensors')}_replica", **out, "observe": ["turn"]}


# ------------------------------------------------------------------------------------------------------ one round
@dataclass
class Round:
    """What one round drove and labelled."""

    obs: list = field(default_factory=list)  # one dict of arrays per decision
    labels: list = field(default_factory=list)
    returns: list = field(default_factory=list)
    agree: list = field(default_factory=list)  # the student's own choice equals the label (or 1 - |error|)
    targets: list = field(default_factory=list)  # agent.targets=go_safe: the P(GO) fitted, per decision (else empty)
    outcomes: list = field(default_factory=list)  # (collision, success) per episode
    seeds: list = field(default_factory=list)  # per episode on the batch: its seed (in the order of outcomes)
    lengths: list = field(default_factory=list)  # per episode on the batch: its decisions
    label_s: float = 0.0  # seconds spent labelling (summed over the labelling processes, agent.workers)

    def close(self, steps: list[list], info: dict, gamma: float, targets: list | None = None,
              seed: int | None = None) -> None:
        """Add one finished episode: ``steps`` as [obs, label, agree, reward] per decision, ``info`` its last,
        ``targets`` the P(GO) to fit at each decision (agent.targets=go_safe), ``seed`` its episode seed."""
        if seed is not None:
            self.seeds.append(int(seed))
            self.lengths.append(len(steps))
        self.obs += [s[0] for s in steps]
        self.targets += targets or []
        self.labels += [s[1] for s in steps]
        self.agree += [s[2] for s in steps]
        self.returns += discounted([s[3] for s in steps], gamma)
        self.outcomes.append(outcome(info))


def discounted(rewards: list[float], gamma: float) -> list[float]:
    """Each decision's discounted return to its episode's end (the critic's target)."""
    g, out = 0.0, []
    for r in reversed(rewards):
        g = r + gamma * g
        out.append(g)
    return out[::-1]


def outcome(info: dict) -> tuple[float, float]:
    m = info["episode_metrics"]
    return float(m.get("collision", 0.0)), float(m["success"] if "success" in m else m["lap_completed"])


class BatchedLabels:
    """Labels for the live rows of a :class:`~av_gym.batched.vec_env.BatchedLeftTurnVecEnv`: the look-ahead
    oracle's futures for all of them at once, or a rule of the observation row by row. Exact shortcut (as the
    per-env teacher's): a row labelled GO that then went GO is on its GO future, which stays collision-free (the
    engine is deterministic, the future used the row's own generator), so it keeps its label without a new future."""

    def __init__(self, venv, teacher, oracle: bool, margin: float) -> None:
        self.venv, self.teacher, self.oracle, self.margin = venv, teacher, oracle, float(margin)
        self.go_safe = None  # belief_lookahead: the share of GO futures without a collision, per row of the last call
        self.on_go_future = np.zeros(venv.num_envs, bool)
        self.belief = None  # belief_lookahead: its planner over the batch, the episode each row's belief is of
        if getattr(teacher, "belief", None) is not None:
            from agents.belief import BeliefPlanner

            self.belief = BeliefPlanner(teacher.belief, n_rows=venv.num_envs)
            self.episode = np.full(venv.num_envs, -1, dtype=np.int64)

    def __call__(self, rows: np.ndarray, obs: dict) -> np.ndarray:
        from agents.batched_oracle import oracle_labels
        from av_gym.wrappers import GO

        if self.belief is not None:  # its futures are samples, not the row's own: no GO-future shortcut
            engine = self.venv.engine
            new = rows[engine.episode_seed[rows] != self.episode[rows]]
            self.belief.reset(new)
            self.episode[new] = engine.episode_seed[new]
            self.belief.read(engine, rows, obs["intent"][rows])
            p = self.belief.go_collision(engine, rows)
            self.go_safe = 1.0 - p
            return self.belief.label_of(p)
        labels = np.zeros(len(rows), dtype=np.int64)
        if not self.oracle:
            for n, r in enumerate(rows):
                labels[n] = self.teacher(None, {k: v[r] for k, v in obs.items()}, None)
            return labels
        known = self.on_go_future[rows]
        labels[known] = GO
        ask = rows[~known]
        if len(ask):
            labels[~known] = oracle_labels(self.venv.engine, ask, self.margin)[0]
        return labels

    def executed(self, rows: np.ndarray, labels: np.ndarray, actions: np.ndarray, done: np.ndarray) -> None:
        from av_gym.wrappers import GO

        self.on_go_future[rows] = (labels == GO) & (actions[rows] == GO) & ~done[rows]


def drive_batched(venv, model, labeller: BatchedLabels, seeds, teacher_drives: bool, gamma: float,
                  soft: bool = False) -> Round:
    """The episodes ``seeds`` on the batch, the teacher's labels at every decision, driven by the teacher (its
    labels executed) or by the student (its deterministic choice); ``soft``: the belief planner's share of safe GO
    futures kept beside each label (agent.targets=go_safe)."""
    out, B = Round(), venv.num_envs
    obs = venv.play(iter(seeds))
    labeller.on_go_future[:] = False
    episode: list[list] = [[] for _ in range(B)]  # per row: [obs, label, agree, reward] of the open episode
    targets: list[list] = [[] for _ in range(B)]  # per row: the P(GO) targets of the open episode (soft)
    while not venv.idle.all():
        rows = np.nonzero(~venv.idle)[0]
        t0 = time.perf_counter()
        labels = labeller(rows, obs)
        out.label_s += time.perf_counter() - t0
        student = np.asarray(model.predict(obs, deterministic=True)[0]).reshape(B)
        actions = student.copy()
        if teacher_drives:
            actions[rows] = labels
        for n, r in enumerate(rows):
            episode[r].append([{k: v[r].copy() for k, v in obs.items()}, int(labels[n]),
                               float(student[r] == labels[n])])
            if soft:
                targets[r].append(float(labeller.go_safe[n]))
        obs, rewards, done, infos = venv.step(actions)
        labeller.executed(rows, labels, actions, done)
        for r in rows:
            episode[r][-1].append(float(rewards[r]))
            if done[r]:
                out.close(episode[r], infos[r], gamma, targets[r] if soft else None, infos[r]["seed"])
                episode[r], targets[r] = [], []
    return out


# --------------------------------------------------------------------------------------------- labelling on the batch
@dataclass(frozen=True)
class LabelJob:
    """What drives and labels a round's episodes on the batch, as plain picklable values (a labelling process
    gets it from the parent; :func:`_build` builds every labeller's student, stacks and validation from it): the env,
    sensors and shield, the agent's config (the student's network, the teacher, the batch), the run's seed, the
    labeller (:func:`labeller_of`) and torch's intra-op threads."""

    env: dict
    sensors: dict
    shield: dict
    agent: dict
    seed: int
    how: str
    torch_threads: int

    @classmethod
    def of(cls, cfg: DictConfig, command: TrainCommand, how: str) -> LabelJob:
        """The job of the run ``cfg`` / ``command`` with the labeller ``how``."""
        plain = [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
        return cls(*plain, OmegaConf.to_container(cfg.agent, resolve=True), command.seed, how,
                   command.train.torch_threads)

    def batch(self, rows: int) -> Any:
        """A :class:`~agents.batched_vec_env.BatchedLeftTurnVecEnv` of ``rows`` rows with the agent's actions."""
        from agents.batched_vec_env import BatchedLeftTurnVecEnv

        a = self.agent
        return BatchedLeftTurnVecEnv(self.env, self.sensors, self.shield, rows, action_repeat=int(a["action_repeat"]),
                                     actions=str(a["actions"]), timeout_is_terminal=bool(a["timeout_is_terminal"]),
                                     pool=0)

    def student(self, venv: Any) -> Any:
        """A fresh student of the run's network and seed on ``venv``'s spaces (:func:`student_model`)."""
        return student_model(venv, self.agent, self.seed, str(self.agent["device"]))

    def teacher(self) -> Any:
        """The run's teacher (agent.teacher) at the agent's actions and action repeat
        (:func:`train.imitation.make_teacher`)."""
        from train.imitation import make_teacher

        a = self.agent
        return make_teacher(str(a["teacher"]), str(a["actions"]), str(self.env["name"]), int(a["action_repeat"]))


def student_model(venv: Any, agent: dict, seed: int, device: str) -> Any:
    """A fresh SB3 PPO of ``agent``'s network and ``seed`` on ``venv``'s spaces (:func:`agents.ppo.make_ppo`), a
    whole PPO: ``learn`` on it collects ``n_steps`` x ``n_envs`` steps. Its rollout buffer, which DAgger never
    fills, is not shrunk: its zeros are never written, so they cost address space, not memory (measured at
    turn_truth / turn_perceived, 512 steps x 64 rows: +8 to +12 kB resident against a 2-step buffer)."""
    from agents.ppo import make_ppo

    return make_ppo(venv, agent, seed=seed, tensorboard_log=None, device=device)


@dataclass
class BatchLabelling:
    """What drives and labels a round's episodes in one process (:func:`drive_batched`): the batch of
    ``agent.n_envs`` rows, the student on it and the teacher's labeller; the parent's with ``agent.workers=1``,
    each labelling process's otherwise (:func:`batch_labelling` builds both)."""

    venv: Any
    model: Any
    labels: BatchedLabels
    gamma: float
    soft: bool  # agent.targets=go_safe: the planner's share of safe GO futures kept beside each label

    def drive(self, seeds: list[int], teacher_drives: bool) -> Round:
        """The episodes ``seeds``, labelled, driven by the teacher or by the student as it is now."""
        return drive_batched(self.venv, self.model, self.labels, seeds, teacher_drives, self.gamma, self.soft)


def batch_labelling(job: LabelJob) -> BatchLabelling:
    """The batch, the teacher's labeller and a fresh student of the run's network and seed, for ``job``."""
    a = job.agent
    venv = job.batch(int(a["n_envs"]))
    teacher = job.teacher()
    return BatchLabelling(venv, job.student(venv), BatchedLabels(venv, teacher, job.how == "batched",
                                                                 float(a["label_margin"])),
                          float(a["gamma"]), a["targets"] == "go_safe")


_PART: dict = {}  # in a labelling process: its BatchLabelling


def _set_up_labeller(job: LabelJob) -> None:
    """A labelling process's set-up (:class:`eval.runner.WorkerPool`): its :func:`batch_labelling`, whose student
    gets the parent's weights with each part."""
    import torch

    torch.set_num_threads(job.torch_threads)  # as the parent: a batch's matmul sums alike
    _PART["labelling"] = batch_labelling(job)


def _drive_part(seeds: list[int], teacher_drives: bool, weights: dict) -> Round:
    """A labelling process's part of a round: ``seeds`` driven and labelled on its batch (:func:`drive_batched`),
    by the teacher or by the student of ``weights`` (the parent's policy's state dict)."""
    labelling = _PART["labelling"]
    labelling.model.policy.load_state_dict(weights)
    return labelling.drive(seeds, teacher_drives)


def labelling_pool(job: LabelJob, workers: int) -> Any:
    """``workers`` labelling processes for :func:`drive_parts` (:class:`eval.runner.WorkerPool`), each set up
    once for the run."""
    from eval.runner import WorkerPool

    return WorkerPool(workers, _set_up_labeller, (job,))


def drive_parts(pool, model, seeds: list[int], teacher_drives: bool, width: int) -> Round:
    """The round's ``seeds`` in ``pool.n`` contiguous parts (:func:`eval.batched.chunks`), each driven and
    labelled in its own labelling process by the student ``model`` as it is now (or the teacher), merged
    (:func:`merge_parts`) into the round that one batch of ``width`` rows gives."""
    from eval.batched import chunks

    weights = {k: v.detach().cpu().clone() for k, v in model.policy.state_dict().items()}
    parts = pool.parts(_drive_part, chunks(seeds, pool.n), teacher_drives, weights)
    return merge_parts(parts, seeds, width)


def merge_parts(parts: list[Round], seeds: list[int], width: int) -> Round:
    """The parts' episodes as one :class:`Round`, in the order in which one batch of ``width`` rows playing
    ``seeds`` ends them (:func:`batch_order`): the aggregate, its order and the round's metrics those of one
    process, since an episode on the batch depends on its seed only (not on its row, its batch or the episodes
    beside it); ``label_s`` summed over the parts. A seed no part played, or played twice, is a RuntimeError."""
    where: dict[int, tuple] = {}  # seed -> (part, first decision, decisions, episode)
    for part in parts:
        starts = np.concatenate([[0], np.cumsum(part.lengths, dtype=np.int64)])
        for n, seed in enumerate(part.seeds):
            where[seed] = (part, int(starts[n]), int(part.lengths[n]), n)
    missing = [int(s) for s in seeds if int(s) not in where]
    if missing or len(where) != len(seeds) or sum(len(p.seeds) for p in parts) != len(seeds):
        raise RuntimeError(f"the labelling processes played {sum(len(p.seeds) for p in parts)} episodes for the "
                           f"round's {len(seeds)} seeds ({len(missing)} missing, first {missing[:3]})")
    out = Round(label_s=sum(p.label_s for p in parts))
    for i in batch_order([where[int(s)][2] for s in seeds], width):
        part, a, length, n = where[int(seeds[i])]
        for name in ("obs", "labels", "agree", "returns", "targets"):  # targets: empty unless agent.targets=go_safe
            getattr(out, name).extend(getattr(part, name)[a:a + length])
        out.outcomes.append(part.outcomes[n])
        out.seeds.append(int(seeds[i]))
        out.lengths.append(length)
    return out


def batch_order(lengths: list[int], width: int) -> list[int]:
    """The order in which one batch of ``width`` rows ends episodes of ``lengths`` decisions handed to it in order
    as rows come free (``BatchedLeftTurnVecEnv.play``: the first ``width`` to rows 0, 1, ...; then each row whose
    episode ended, lowest row first, the next one): their indices by the decision at which each ends, lower rows
    first within a decision, as :func:`drive_batched` closes them."""
    import heapq

    heap = [(lengths[i], i, i) for i in range(min(width, len(lengths)))]  # (decision it ends at, row, episode)
    heapq.heapify(heap)
    order, following = [], len(heap)
    while heap:
        end, row, i = heapq.heappop(heap)
        order.append(i)
        if following < len(lengths):  # the row's next episode, from the decision after this one's last
            heapq.heappush(heap, (end + lengths[following], row, following))
            following += 1
    return order


def drive_per_env(env, model, teacher, seeds, teacher_drives: bool, gamma: float) -> Round:
    """The episodes ``seeds`` on one per-env training stack, ``teacher(env, obs, info)`` labelling each state."""
    from gymnasium import spaces

    out = Round()
    discrete = isinstance(env.action_space, spaces.Discrete)
    for seed in seeds:
        obs, info = env.reset(seed=int(seed))
        rewards, done = [], False
        while not done:
            t0 = time.perf_counter()
            label = teacher(env, obs, info)
            out.label_s += time.perf_counter() - t0
            student = model.predict(obs, deterministic=True)[0]
            out.obs.append({k: np.array(v, copy=True) for k, v in obs.items()})
            out.labels.append(label)
            out.agree.append(float(int(student) == int(label)) if discrete else
                             1.0 - float(np.mean(np.abs(np.asarray(student) - np.asarray(label)))))
            obs, r, terminated, truncated, info = env.step(label if teacher_drives else student)
            rewards.append(float(r))
            done = terminated or truncated
        out.returns += discounted(rewards, gamma)
        out.outcomes.append(outcome(info))
    return out


def drive_replica(envs: list, replica, model, labeller: BatchedLabels, seeds, teacher_drives: bool,
                  gamma: float) -> Round:
    """The episodes ``seeds`` on the per-env stacks ``envs`` (what the student sees: any sensors, e.g. the detector
    and tracker of ``turn_perceived``), labelled by the batched oracle on ``replica``: a batched engine of
    ``len(envs)`` rows playing the same episodes in lockstep (the same seed per row, the same choices). Why a
    replica: the per-env oracle deep-copies the env and simulates one future per decision (~3 labels/s with the
    tracker); the replica's rows are the same traffic as the per-env episodes (the batched engine draws exactly as
    the per-env env, and the sensors draw from their own generators), so all rows' futures roll out at once. A
    replica that leaves its per-env episode (an episode ending on one and not the other, or another outcome) is a
    RuntimeError, never a silently wrong label."""
    from av_gym.wrappers import GO

    out, B = Round(), len(envs)
    replica.play(iter(seeds))
    labeller.on_go_future[:] = False
    obs: list = [None] * B
    for r in np.nonzero(~replica.idle)[0]:
        obs[r] = envs[r].reset(seed=int(replica.row_seed[r]))[0]
    episode: list[list] = [[] for _ in range(B)]  # per row: [obs, label, agree, reward] of the open episode
    while not replica.idle.all():
        rows = np.nonzero(~replica.idle)[0]
        t0 = time.perf_counter()
        labels = labeller(rows, None)  # the oracle reads the replica's state, not an observation
        out.label_s += time.perf_counter() - t0
        batch = {k: np.stack([obs[r][k] for r in rows]) for k in obs[rows[0]]}
        student = np.asarray(model.predict(batch, deterministic=True)[0]).reshape(len(rows))
        actions = np.full(B, GO)
        actions[rows] = labels if teacher_drives else student
        for n, r in enumerate(rows):
            episode[r].append([obs[r], int(labels[n]), float(student[n] == labels[n])])
        _, _, done, infos = replica.step(actions)
        labeller.executed(rows, labels, actions, done)
        for r in rows:
            obs[r], reward, terminated, truncated, info = envs[r].step(int(actions[r]))
            episode[r][-1].append(float(reward))
            ended = terminated or truncated
            if ended != bool(done[r]) or (ended and outcome(info) != outcome(infos[r])):
                raise RuntimeError(f"the oracle's replica left the per-env episode of seed {replica.row_seed[r]} "
                                   f"(ended {ended} vs {bool(done[r])}): the batched engine no longer draws as the "
                                   f"per-env env; use agent.labeller=per_env")
            if ended:
                out.close(episode[r], info, gamma)
                episode[r] = []
                if not replica.idle[r]:
                    obs[r] = envs[r].reset(seed=int(replica.row_seed[r]))[0]
    return out


# ------------------------------------------------------------------------------------------------------ the fit
def fit(model, data: Round, epochs: int, batch_size: int, lr: float, seed: int,
        disagree_weight: float = 1.0) -> float:
    """Actor to the labels (negative log-likelihood), critic to the returns (MSE scaled by their variance, so the
    shared extractor is not driven by the returns' scale), Adam at ``lr``, every tensor on the policy's device
    (agent.device): train/imitation.py's :func:`~train.imitation.fit_policy`, the fit its cloning step uses. Returns the
    accuracy on all labels. ``disagree_weight`` (agent.disagree_weight) > 1: the actor's loss weighs the states where
    the student as it is before this fit chooses otherwise than the label that many times
    (:func:`disagreement_weights`)."""
    from gymnasium import spaces

    from train.imitation import Demonstrations, fit_policy

    demos = Demonstrations(0.0, data.obs, data.labels, data.returns,  # returns already discounted per round
                           targets=data.targets)
    weights = disagreement_weights(model, data, disagree_weight) if disagree_weight != 1.0 else None
    return fit_policy(model.policy, demos, isinstance(model.action_space, spaces.Discrete), epochs, batch_size,
                      lr, seed=seed, weights=weights)


def disagreement_weights(model, data: Round, weight: float, chunk: int = 4096) -> np.ndarray:
    """One weight per aggregated state: ``weight`` where the student ``model`` (its most likely choice, the one it
    drives with) differs from the teacher's label, 1 where they agree. Why: after a few rounds the student agrees
    with the teacher on ~90 % of its own states, and a plain mean spends nine tenths of each step on states it
    already gets right; the rest carry the collisions (docs/dagger.md, "Learning curve")."""
    from gymnasium import spaces

    from av_gym.errors import ConfigError

    if not isinstance(model.action_space, spaces.Discrete):
        raise ConfigError(f"agent.disagree_weight={weight:g} needs discrete choices to disagree on; the student's "
                          f"actions are {model.action_space}")
    return np.where(student_choices(model, data, chunk) != np.asarray(data.labels), float(weight), 1.0)


def student_choices(model, data: Round, chunk: int = 4096) -> np.ndarray:
    """The discrete student ``model``'s most likely choice (the one it drives with) on each of ``data``'s states,
    ``chunk`` states per forward pass."""
    import torch as th

    x = {k: np.stack([o[k] for o in data.obs]) for k in data.obs[0]}
    choices = []
    with th.no_grad():
        for i in range(0, len(data.labels), chunk):
            obs = model.policy.obs_to_tensor({k: v[i:i + chunk] for k, v in x.items()})[0]
            choices.append(model.policy.get_distribution(obs).distribution.probs.argmax(1).cpu().numpy())
    return np.concatenate(choices)


def aggregate(total: Round, new: Round) -> None:
    total.obs += new.obs
    total.labels += new.labels
    total.returns += new.returns
    total.targets += new.targets


# ------------------------------------------------------------------------------------------------------ the run
def pack_rounds(data: Round) -> bytes:
    """The aggregate's labelled states (observations per key, labels, discounted returns) as an ``.npz``."""
    import io

    arrays = {f"obs:{k}": np.stack([o[k] for o in data.obs]) for k in (data.obs[0] if data.obs else {})}
    arrays["labels"], arrays["returns"] = np.asarray(data.labels), np.asarray(data.returns, dtype=np.float64)
    if data.targets:
        arrays["targets"] = np.asarray(data.targets, dtype=np.float64)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def unpack_rounds(raw: bytes) -> Round:
    import io

    npz = np.load(io.BytesIO(raw))
    keys = [k[len("obs:"):] for k in npz.files if k.startswith("obs:")]
    stacked = {k: npz[f"obs:{k}"] for k in keys}
    labels = npz["labels"]
    return Round(obs=[{k: stacked[k][i] for k in keys} for i in range(len(labels))], labels=list(labels),
                 returns=list(npz["returns"]), targets=list(npz["targets"]) if "targets" in npz.files else [])


def save_round(model, path: Path, data: Round, state: dict) -> Path:
    """``latest.zip``: the student at its operating point (and optimizer), the aggregate and ``state`` (rows, best,
    the next round) with the RNG states, one file replaced at once."""
    from train.checkpoint import save_model_atomic

    return save_model_atomic(model, path, rng_extra={"dagger": state}, members={STATE_MEMBER: pack_rounds(data)})


def read_aggregate(latest: Path, unpack):
    """The labelled states :func:`save_round` wrote into ``latest`` (a DAgger run's latest.zip), as ``unpack`` reads
    their raw ``.npz`` bytes (:func:`unpack_rounds`: a :class:`Round`); one line if it holds none."""
    import zipfile

    from av_gym.errors import ConfigError

    if not latest.is_file():
        raise ConfigError(f"{latest} does not exist: run_dir must be a DAgger run's checkpoint folder")
    with zipfile.ZipFile(latest) as z:
        if STATE_MEMBER not in z.namelist():
            raise ConfigError(f"{latest} holds no DAgger aggregate ({STATE_MEMBER}): not a DAgger run's latest.zip")
        return unpack(z.read(STATE_MEMBER))


def load_round(model, path: Path) -> tuple[Round, dict]:
    """The state :func:`save_round` wrote into ``path``, loaded into ``model`` (its policy and optimizer, and the
    global RNG states); one line for a checkpoint that is damaged or was written before DAgger saved its rounds."""
    import zipfile

    from agents.checkpoint import check_sb3_zip
    from av_gym.errors import ConfigError
    from train.checkpoint import load_rng_state

    check_sb3_zip(path)
    with zipfile.ZipFile(path) as z:
        if STATE_MEMBER not in z.namelist():
            raise ConfigError(f"train.resume=true: {path} holds no DAgger rounds (written before DAgger saved its "
                              f"labels with the student): it cannot be resumed; start a new run_name with "
                              f"agent.init_from={path} to go on from its student")
        raw = z.read(STATE_MEMBER)
    try:
        model.set_parameters(str(path), exact_match=True, device=model.device)
    except (ValueError, RuntimeError, KeyError) as exc:  # another network than this config builds
        raise ConfigError(f"train.resume=true: {path} does not fit this run's student "
                          f"({' '.join(str(exc).split())[:200]})") from None
    state = load_rng_state(path).get("dagger")
    if not isinstance(state, dict):
        raise ConfigError(f"train.resume=true: {path} holds no DAgger round state; start a new run_name")
    return unpack_rounds(raw), state


@dataclass
class _Run:
    """What a DAgger run drives with: the student, its stacks, and how one round's episodes are driven."""

    model: Any
    stacks: list
    drive: Callable[[list, bool], Round]  # (seeds, teacher drives) → the round's labelled states
    how: str  # the labeller (labeller_of)
    validation: Callable | None  # model → (collision, success) on the validation seeds; None without
    pool: Any = None  # agent.workers > 1: the labelling processes (eval.runner.WorkerPool)

    def close(self, failed: bool) -> None:
        """Close the stacks and end the labelling processes (``failed``: at once, a part in progress included)."""
        for e in self.stacks:
            e.close()
        if self.pool is not None:
            self.pool.close(failed)


def train_dagger(cfg: DictConfig, ckpt_dir: Path, run_dir: Path, command: TrainCommand | None = None) -> Path:
    """Train the student as ``cfg.agent`` says; returns ``ckpt_dir/model.zip``. Every finished round is saved in
    ``latest.zip`` (:func:`save_round`), which ``train.resume=true`` continues from the next round; SIGINT /
    SIGTERM end the round in progress. ``command``: the run's settings (default: read from ``cfg``)."""
    import signal

    from tqdm import tqdm

    from agents.dagger import DaggerParams
    from train.checkpoint import save_model_atomic, write_text_atomic
    from train.tb_events import resumed_writer

    command = command or TrainCommand.of(cfg)
    t_start, latest = time.time(), ckpt_dir / "latest.zip"
    resume = command.train.resume
    params = DaggerParams.from_mapping(OmegaConf.to_container(cfg.agent, resolve=True), where="agent")
    for stale in ckpt_dir.glob(".*.tmp"):  # a save killed half-way; the previous file is intact
        stale.unlink()
    run = _build(cfg, command, params, resume)
    shift = _operating_point(params)
    rows: list[dict] = []
    data, best, start = Round(), -np.inf, 0
    if resume:  # the state at the end of the last finished round: go on with the next
        data, rows, best, start = _resume(run.model, latest, ckpt_dir, params, shift)
        t_start -= float(rows[-1]["wall_s"]) if rows else 0.0  # wall-clock of the run, not of this process
    # resumed: what the cut-short round logged after the saved state goes (steps are label counts)
    writer = resumed_writer(run_dir / "tb" / str(params.name), int(rows[-1]["labels"]) + 1 if resume and rows else None)
    # each training seed drives its own episodes, train_seed + 50,000 x seed + the round's offset, all in the
    # train split (av_gym/seeds.py: folded into it)
    first = int(params.train_seed) + 50_000 * command.seed
    grown = (f" (x {params.round_growth:g} a round: {sum(params.round_sizes())} in all)"
             if params.round_growth > 1 else "")
    print(f"[train] DAgger: {params.rounds} rounds x {params.round_episodes} episodes{grown}, teacher {params.teacher} "
          f"({run.how} labels), student {params.extractor} on {cfg.sensors.name}"
          f"{' from ' + str(params.init_from) if params.init_from else ''}; episode seeds {first}+")
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM behaves like Ctrl-C
    bar = tqdm(range(start, int(params.rounds)), desc="DAgger rounds", initial=start, total=int(params.rounds),
               disable=not command.train.progress_bar)
    done = start  # rounds saved in latest.zip
    try:
        for k in bar:
            row, new = _round(run, params, data, k, first, command.seed, t_start, shift)
            rows.append(row)
            score = row["val_success"] - row["val_collision"]
            if run.validation is not None and score > best:
                best = score
                save_model_atomic(run.model, ckpt_dir / "best.zip")
            _log(writer, row, len(new.labels) / max(new.label_s, 1e-9))
            write_text_atomic(ckpt_dir / "rounds.csv", _csv(rows))
            # last: the round counts as done once latest.zip holds it (a kill before redoes it, with the same
            # seeds, fit and so the same best.zip and rows)
            save_round(run.model, latest, data, {"next_round": k + 1, "rows": rows, "best": best})
            done = k + 1
            shift(run.model, False)
            _print_round(row, new, run.validation is not None)
    except BaseException as exc:  # Ctrl-C, SIGTERM, an error: the labelling processes end now
        run.close(failed=True)
        if isinstance(exc, KeyboardInterrupt):
            _say_interrupted(done, latest, command.run_name)
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
        writer.close()
    run.close(failed=False)
    write_text_atomic(run_dir / "rounds.csv", _csv(rows))
    shift(run.model, True)
    path = save_model_atomic(run.model, ckpt_dir / "model.zip")
    print(f"[train] DAgger: {len(data.labels)} labels in {time.time() - t_start:.0f} s")
    return path


def _build(cfg: DictConfig, command: TrainCommand, params: DaggerParams, resume: bool) -> _Run:
    """The student, what drives and labels its rounds (:func:`labeller_of`: on the batch, :func:`_on_the_batch`;
    else one per-env stack, or ``n_envs`` of them beside a batched replica), the student from ``agent.init_from``
    on a fresh run, and the validation, all from the run's one :class:`LabelJob`."""
    job = LabelJob.of(cfg, command, labeller_of(cfg))
    if job.how in ("batched", "rule"):
        model, stacks, drive, pool = _on_the_batch(job, int(params.workers))
    else:
        (model, stacks, drive), pool = _per_env(job, cfg, params), None
    if params.init_from and not resume:  # a student to go on from (a DAgger run or a PPO policy of the same spaces)
        from train.imitation import load_weights

        load_weights(model, params.init_from, str(cfg.env.name))
        if params.drive_at_threshold:  # an absolute P(GO) from round 0: the init back at its fit's own boundary
            from train.operating_point import at_fit_boundary

            at_fit_boundary(model, saved_config(params.init_from, str(cfg.env.name)))
    validation = _validation(command.train, [job.env, job.sensors, job.shield], int(params.action_repeat),
                             str(params.actions), job.how in ("batched", "rule"))
    return _Run(model, stacks, drive, job.how, validation, pool)


def _on_the_batch(job: LabelJob, workers: int) -> tuple[Any, list, Callable[[list, bool], Round], Any]:
    """The student, the stacks to close, the round's driver and the labelling processes (None: none) on the batch:
    with ``workers`` = 1 this process's :func:`batch_labelling`; else the labelling processes drive and label
    (:func:`drive_parts`) and this process only fits and validates the student, built on a batch of one row for the
    spaces SB3 builds a policy from (never stepped, closed with the run: no batch of ``n_envs``, no teacher)."""
    if workers > 1:
        one_row, width = job.batch(1), int(job.agent["n_envs"])
        model, pool = job.student(one_row), labelling_pool(job, workers)
        return model, [one_row], lambda seeds, by_teacher: drive_parts(pool, model, seeds, by_teacher, width), pool
    labelling = batch_labelling(job)
    return labelling.model, [labelling.venv], labelling.drive, None


def _per_env(job: LabelJob, cfg: DictConfig, params: DaggerParams) -> tuple[Any, list, Callable]:
    """The student, its per-env stacks and the round's driver for the labellers off the batch (``job.how``):
    ``replica`` (the student on ``n_envs`` per-env stacks, the oracle on a batched replica of their episodes, with
    the sensors of :func:`replica_sensors`) or ``per_env`` (the teacher on one stack, one state at a time)."""
    from av_gym.make import make_training_env

    teacher = job.teacher()
    gamma, n_envs = float(params.gamma), int(params.n_envs)
    stacks = [make_training_env(job.env, job.sensors, job.shield, 0.0, int(params.action_repeat), str(params.actions),
                                timeout_is_terminal=params.timeout_is_terminal)
              for _ in range(n_envs if job.how == "replica" else 1)]
    env = stacks[0]
    model = job.student(env)
    if job.how == "per_env":
        return model, stacks, lambda seeds, by_teacher: drive_per_env(env, model, teacher, seeds, by_teacher, gamma)
    replica = replace(job, sensors=replica_sensors(cfg.sensors)).batch(n_envs)
    labels = BatchedLabels(replica, teacher, True, params.label_margin)
    return model, stacks, lambda seeds, by_teacher: drive_replica(stacks, replica, model, labels, seeds, by_teacher,
                                                                  gamma)


def saved_config(spec: str, scenario: str) -> dict:
    """The config.yaml beside the student of ``spec`` (agent.init_from: a checkpoint folder or its model file)."""
    from agents.checkpoint import read_config_yaml
    from eval.agents import _checkpoint_file

    _, path = _checkpoint_file(Path(spec), scenario)
    return read_config_yaml(path.parent / "config.yaml")


def _operating_point(params) -> Callable[[Any, bool], None]:
    """``shift(model, on)``: move the GO boundary to go_threshold (on) or back to the fit's 0.5 (off); go/yield
    students only (the others: nothing to move)."""
    tau = float(params.go_threshold)

    def shift(m, on: bool) -> None:
        if tau != 0.5 and str(params.actions) == "go_yield":
            from train.operating_point import shift_go

            shift_go(m, tau if on else 1.0 - tau)
    return shift


def _resume(model, latest: Path, ckpt_dir: Path, params, shift) -> tuple[Round, list[dict], float, int]:
    """The aggregate, rows, best score and next round saved in ``latest.zip``; the student as it was then."""
    from train.checkpoint import write_text_atomic

    data, state = load_round(model, latest)
    rows, best, start = list(state["rows"]), float(state["best"]), int(state["next_round"])
    shift(model, False)  # saved at the operating point; back as the uninterrupted run shifts it, bit for bit
    write_text_atomic(ckpt_dir / "rounds.csv", _csv(rows))  # without a row of the round that was cut short
    print(f"[train] resuming {latest}: rounds 0..{start - 1} done, {len(data.labels)} labels; next round {start} "
          f"of {params.rounds}")
    return data, rows, best, start


def _round(run: _Run, params, data: Round, k: int, first: int, seed: int, t_start: float, shift) -> tuple[dict, Round]:
    """Round ``k``: its episodes driven (by the teacher in round 0 of a fresh student) and labelled, the aggregate
    grown, the student refitted, shifted to its operating point and validated; returns its row and new labels."""
    seeds = round_seeds(params, first, k)
    by_teacher = k == 0 and not params.init_from  # a student to go on from drives from the start
    # A student fitted to probabilities (targets go_safe) drives at its operating point: its argmax (P(GO) 0.5)
    # would go where at most half the planner's futures collide, states the student at go_threshold never meets.
    # agent.drive_at_threshold: a label student likewise, so its labels are of the states it meets when used.
    at_tau = (params.targets == "go_safe" or params.drive_at_threshold) and not by_teacher
    if at_tau:
        shift(run.model, True)
    new = run.drive(seeds, by_teacher)
    if at_tau:
        shift(run.model, False)
    aggregate(data, new)
    t_fit = time.perf_counter()
    accuracy = fit(run.model, data, int(params.fit_epochs), int(params.fit_batch), float(params.fit_lr),
                   seed * 1000 + k, float(params.disagree_weight))
    fit_s = time.perf_counter() - t_fit
    coll, succ = np.mean(new.outcomes, axis=0)
    row = {"round": k, "driver": "teacher" if by_teacher else "student", "episodes": len(new.outcomes),
           "labels": len(data.labels), "wall_s": round(time.time() - t_start, 1),
           "label_s": round(new.label_s, 1), "agreement": float(np.mean(new.agree)),
           "drive_success": float(succ), "drive_collision": float(coll), "fit_accuracy": accuracy,
           "val_success": np.nan, "val_collision": np.nan, "fit_s": round(fit_s, 1)}
    shift(run.model, True)  # validated and saved at the operating point
    if run.validation is not None:
        row["val_collision"], row["val_success"] = run.validation(run.model)
    return row, new


def round_seeds(params, first: int, k: int) -> list[int]:
    """Round ``k``'s episode seeds in the train split: the rounds' episodes follow each other from ``first``, so
    no two rounds (of any sizes, :meth:`agents.dagger.DaggerParams.round_sizes`) drive the same episode."""
    from av_gym.seeds import train_seed

    sizes = params.round_sizes()
    return [train_seed(first, sum(sizes[:k]) + i) for i in range(sizes[k])]


def _print_round(row: dict, new: Round, validated: bool) -> None:
    """The round's line, above the rounds' bar (``tqdm.write``: a plain print would split the bar in two)."""
    from tqdm import tqdm

    tqdm.write(f"[train] round {row['round']}: {row['driver']} drove {row['episodes']} episodes (success "
               f"{row['drive_success']:.3f}, collision {row['drive_collision']:.3f}); the student agreed with the "
               f"teacher on {row['agreement']:.3f} of its states; {row['labels']} labels "
               f"({len(new.labels) / max(new.label_s, 1e-9):.0f}/s), fit accuracy {row['fit_accuracy']:.3f}"
               + (f"; validation success {row['val_success']:.3f}, collision {row['val_collision']:.3f}" if validated
                  else "") + f" [{row['wall_s']:.0f} s]")


def _say_interrupted(done: int, latest: Path, run_name: str) -> None:
    """What an interrupted run kept, naming only what exists (no latest.zip before the first round has ended);
    written past the rounds' bar, which is still open."""
    from tqdm import tqdm

    if done > 0 and latest.is_file():
        tqdm.write(f"[train] interrupted in round {done}: rounds 0..{done - 1} are kept in {latest} (student, "
                   f"labels, rounds.csv); continue with run_name={run_name} train.resume=true", file=sys.stderr)
    else:
        tqdm.write(f"[train] interrupted in round 0, before any round finished: nothing was kept (no latest.zip); "
                   f"start the run again (train.overwrite=true to reuse run_name={run_name})", file=sys.stderr)


def _validation(options: TrainOptions, plain: list, repeat: int, actions: str, batched: bool,
                policy_of: Callable[[Any], Any] | None = None):
    """``model -> (collision, success)`` on ``train.eval_n`` episodes of the validation split from
    ``train.eval_seed`` (None if 0); ``policy_of(model)``: the policy that drives them (default: the SB3 model's,
    every ``repeat`` steps)."""
    from av_gym.seeds import config_seeds

    n = options.eval_n
    if n <= 0:
        return None
    seeds = config_seeds("validation", n, options.eval_seed, "train.eval_seed")

    def run(model):
        from agents.ppo import SB3Policy

        from eval.batched import play_on

        policy = policy_of(model) if policy_of is not None else SB3Policy(model, repeat, actions)
        rows = play_on(*plain, policy, seeds, min(n, 128), "val", batched)
        return (float(np.mean([r["collision"] for r in rows])),
                float(np.mean([r["success"] if "success" in r else r["lap_completed"] for r in rows])))
    return run


def _log(writer, row: dict, label_rate: float) -> None:
    step = int(row["labels"])
    for key in ("agreement", "drive_success", "drive_collision", "fit_accuracy", "val_success", "val_collision"):
        if row[key] == row[key]:  # not NaN
            writer.add_scalar(f"dagger/{key}", row[key], step)
    writer.add_scalar("dagger/wall_s", row["wall_s"], step)
    writer.add_scalar("dagger/labels_per_s", label_rate, step)
    writer.flush()


def _csv(rows: list[dict]) -> str:
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=ROUND_FIELDS)
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()
