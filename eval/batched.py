"""``python -m eval env=left_turn vec_env=batched n_envs=64 ...``: the left turn's evaluation episodes on the
batched engine (:mod:`av_gym.batched.vec_env`), ``n_envs`` episodes stepped together in this process.

Episode ``seed`` is the episode ``reset(seed=seed)`` of the per-env stack gives (the engine draws it from a
generator seeded with it), the policy decides as it does there (every env step at 10 Hz; a trained go/yield
checkpoint asked every ``action_repeat`` steps, its held choice mapped to a meta-action at every step), and the row
is ``EpisodeMetrics``' row: rows equal to ``vec_env=subproc``'s within the engine's equivalence (tests and
docs/performance.md). Rows come back in seed order. ``workers=N`` plays the seeds in N contiguous parts, each a batch
of ``n_envs`` in its own spawned process, and merges the rows back in seed order: the same rows (a row on the batch
depends on its seed only, not on its row, its batch or the episodes beside it), in about 1/N of the wall-clock time.

What runs: ``env=left_turn`` in either mode (traffic; ``env.mode=ccftap`` with its ``env.ccftap.*`` case) and with
either action type, without a shield or behind ``shield=aeb`` / ``agent+aeb`` (the improved AEB shield in either
mode, :mod:`av_gym.batched.shield`: the per-env shield's decisions on every row), and the agents
``always_proceed`` (it reads no observation; its sensors: :func:`batch_sensors`), ``gap_acceptance``, the
``lookahead`` oracle (its GO futures played for every env that decides, all at once, by
:mod:`agents.batched_oracle`: the per-env oracle's decisions, ~20x its labels per second) and PPO / DAgger
checkpoints on the batch's sensors: ``turn_truth`` (turn features from truth, turn signals, intent) and
``turn_perceived`` / ``turn_perceived_memory`` (the detector, the Kalman tracker and the features on its tracks,
:mod:`av_gym.batched.perception`: the per-env stack's detections and tracks on the same seeds). Anything
else (another shield or variant, the shield's second opinion ``aeb_belief``, the oracle planning with the shield,
``plan_with_shield``) is refused in one line before any episode runs, and runs with ``vec_env=subproc``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm import tqdm

from av_gym.errors import ConfigError

KINDS = ("always_proceed", "gap_acceptance", "lookahead", "belief_lookahead", "ppo", "dagger")
NO_OBS_SENSORS = {"name": "turn_truth", "turn_features": {"source": "truth"}, "observe": ["turn"]}


def batch_sensors(plan, env_cfg: dict) -> dict:
    """The sensors the batch runs ``plan`` with: its own; ``always_proceed``, which reads no observation, on the
    sensors it was given when the batch runs them (``sensors=turn_perceived``: both engines run, and results.md
    records, the preset asked for), else on the batch's own features (:data:`NO_OBS_SENSORS`: the command's default
    preset ``truth`` has no form on the batch)."""
    from av_gym.batched.vec_env import check_batchable

    if plan_kind(plan) != "always_proceed":
        return plan.sensors
    try:
        check_batchable(env_cfg, plan.sensors or {}, None, with_shield=False)
    except ConfigError:
        return NO_OBS_SENSORS
    return plan.sensors


def plan_kind(plan) -> str:
    """The agent kind of an :class:`eval.agents.AgentPlan` (a trained plan's spec is its checkpoint path)."""
    from agents.registry import trained_kinds
    from eval.agents import _checkpoint_file, _is_path, load_agent_config

    spec = str(plan.spec)
    if spec in trained_kinds():
        return spec
    if _is_path(spec):
        from pathlib import Path

        return _checkpoint_file(Path(spec), "left_turn")[0]
    return str(load_agent_config(spec).get("kind"))


def check_batched_plan(plan, env_cfg: dict) -> None:
    """One-line ConfigError for an agent the batched engine cannot evaluate (checked before any folder is made)."""
    from av_gym.batched.shield import shield_kind
    from av_gym.batched.vec_env import check_batchable

    if env_cfg.get("name") != "left_turn":
        raise ConfigError(f"vec_env=batched runs env=left_turn only, got env={env_cfg.get('name')}")
    kind = plan_kind(plan)
    if kind not in KINDS:
        raise ConfigError(f"agent {plan.given!r} (kind {kind}) cannot run with vec_env=batched (it runs: "
                          f"{', '.join(KINDS)}); use vec_env=subproc")
    sensors = batch_sensors(plan, env_cfg)
    if kind == "lookahead" and shield_kind(plan.shield) != "none" and \
            _agent_config(plan).get("plan_with_shield"):
        raise ConfigError(f"agent {plan.given!r}: lookahead with plan_with_shield=true cannot run with "
                          f"vec_env=batched (its futures on the batch are the driver's own, without the shield); "
                          f"use vec_env=subproc")
    try:
        check_batchable(env_cfg, sensors, plan.shield, with_shield=True)
    except ConfigError as exc:
        msg = str(exc).replace("agent.vec_env=batched", "vec_env=batched").replace("agent.vec_env=subproc",
                                                                                    "vec_env=subproc")
        raise ConfigError(f"agent {plan.given!r}: {msg}") from None


def _agent_config(plan) -> dict:
    """The agent config of a rule-based plan (its spec's ``conf/agent`` file; {} for a checkpoint)."""
    from eval.agents import _is_path, load_agent_config

    return {} if _is_path(str(plan.spec)) else dict(load_agent_config(str(plan.spec)))


class _Decider:
    """The agents' decisions for a batch: per env as :class:`agents.Policy.act` would decide for it."""

    def __init__(self, policy, engine, perception=None) -> None:
        from agents import AlwaysProceed
        from agents.belief import BeliefLookahead, BeliefPlanner
        from agents.go_yield import GapAcceptance, Lookahead
        from agents.ppo import SB3Policy
        from av_gym.wrappers import YIELD

        # the batch's engine: its size, its action type, and the envs the lookahead oracle copies
        self.policy, self.engine, self.n = policy, engine, engine.B
        n, continuous = self.n, engine.continuous
        # the env's actions: meta-action ints, or the continuous action's one float (what each agent hands the
        # per-env env, which LongitudinalAction.act reads as its first float)
        self.dtype = float if continuous else int
        if isinstance(policy, SB3Policy):
            self.kind = "ppo"
            self.k = np.zeros(n, dtype=int)  # SB3Policy._k: env steps since the episode started
            self.held = np.zeros(n, dtype=self.dtype)  # SB3Policy._action (its first entry)
        elif isinstance(policy, AlwaysProceed):
            self.kind = "always_proceed"
        elif isinstance(policy, GapAcceptance):
            self.kind = "gap_acceptance"
        elif isinstance(policy, BeliefLookahead):  # its planner for every row: beliefs per row, K futures each
            self.kind = "belief_lookahead"
            self.planner = BeliefPlanner(policy.params, n_rows=n, perception=perception)  # on tracks: the tracker's
            self.k = np.zeros(n, dtype=int)
            self.choice = np.full(n, YIELD)
        elif isinstance(policy, Lookahead):  # its futures without the shield (plan_with_shield is refused)
            self.kind = "lookahead"
            self.k = np.zeros(n, dtype=int)  # Lookahead._t
            self.choice = np.full(n, YIELD)  # Lookahead._choice
        elif hasattr(policy, "act_rows"):  # keeps its own memory per row (agents/recurrent.py: a hidden state)
            self.kind = "rows"
            policy.start_rows(n)
        else:
            raise ConfigError(f"policy {type(policy).__name__} cannot run with vec_env=batched; use vec_env=subproc")

    def reset(self, rows) -> None:
        from av_gym.wrappers import YIELD

        if self.kind == "ppo":
            self.k[rows], self.held[rows] = 0, 0
        elif self.kind == "rows":
            self.policy.reset_rows(rows)
        elif self.kind == "lookahead":
            self.k[rows], self.choice[rows] = 0, YIELD
        elif self.kind == "belief_lookahead":
            self.k[rows], self.choice[rows] = 0, YIELD
            self.planner.reset(rows)

    def act(self, obs: dict, live: np.ndarray) -> np.ndarray:
        """Meta-actions (n,) for the envs ``live`` (the others get IDLE, unused)."""
        from av_gym.wrappers import action_set, meta_actions

        out = np.ones(self.n, dtype=self.dtype)
        rows = np.nonzero(live)[0]
        if self.kind == "always_proceed":
            out[rows] = np.asarray(self.policy.act(None), dtype=self.dtype).reshape(-1)[0]
        elif self.kind == "gap_acceptance":
            for r in rows:
                out[r] = self.policy.act({"turn": obs["turn"][r]})
        elif self.kind == "lookahead":  # Lookahead.act for every row at once: GO is final once its future is safe
            from agents.batched_oracle import oracle_labels
            from av_gym.wrappers import GO

            ask = rows[(self.choice[rows] != GO) & (self.k[rows] % self.policy.repeat == 0)]
            if len(ask):
                self.choice[ask] = oracle_labels(self.engine, ask)[0]
            self.k[rows] += 1
            out[rows] = meta_actions(self.choice[rows], obs["turn"][rows])
        elif self.kind == "rows":
            out[rows] = self.policy.act_rows(obs, rows)
        elif self.kind == "belief_lookahead":  # BeliefLookahead.act for every row: every reading, then the decisions
            self.planner.read(self.engine, rows, obs["intent"][rows])
            self.choice[rows] = self.planner.decide(self.engine, rows, self.choice[rows], self.k[rows])
            self.k[rows] += 1
            out[rows] = self.planner.meta_actions(self.engine, rows, self.choice[rows], obs["turn"][rows])
        else:
            p = self.policy
            ask = rows[self.k[rows] % p.repeat == 0]
            if len(ask):
                from agents.ppo import flatten_obs

                action, _ = p.model.predict(flatten_obs({k: v[ask] for k, v in obs.items()}), deterministic=True)
                self.held[ask] = np.asarray(action).reshape(len(ask), -1)[:, 0]
            self.k[rows] += 1
            # the held choices become the env's actions by the policy's action set, as SB3Policy.act does per env
            out[rows] = action_set(p.actions).act(self.held[rows], {k: v[rows] for k, v in obs.items()})
        return out


def run_episodes_batched(env_cfg: dict, plan, policy, seeds: Sequence[int], n_envs: int, label: str,
                         progress: bool = True, out: list | None = None, workers: int = 1,
                         checkpoints: str = "checkpoints") -> list[dict]:
    """:func:`eval.runner.run_episodes` on the batched engine: one row per seed, ``{"agent", "episode", "seed",
    **episode_metrics}``, in the order of ``seeds`` (each appended to ``out``, if given, once every earlier seed's
    row is in). ``workers`` > 1: :func:`play_batched_workers`, each worker building the plan's agent itself
    (``checkpoints``: where it resolves it; ``policy`` is not used and may be None)."""
    from eval.runner import single_threaded_torch

    check_batched_plan(plan, env_cfg)
    single_threaded_torch()
    sensors = batch_sensors(plan, env_cfg)
    if workers > 1:
        job = BatchedJob(env_cfg, plan, sensors, str(checkpoints), label)
        return play_batched_workers(job, seeds, n_envs, workers, progress, out)
    return play_batched(env_cfg, sensors, plan.shield, policy, seeds, n_envs, label, progress, out)


@dataclass(frozen=True)
class BatchedJob:
    """What a worker process needs to play part of an agent's episodes on its own batch as this process would
    (plain, picklable): the env, the agent's plan (:class:`eval.agents.AgentPlan`: spec, sensors, shield), the
    sensors the batch runs it with, where its checkpoint is found, its label."""

    env: dict
    plan: Any
    sensors: dict
    checkpoints: str
    label: str


_WORKER: dict = {}  # in a worker process: its job, policy and the queue its rows go back on


def _init_batched_worker(job: BatchedJob, rows) -> None:
    """A worker's set-up (:class:`eval.runner.WorkerPool`): the job's agent, built once; its rows go on ``rows``."""
    import contextlib
    import io

    from eval.agents import make_eval_env, resolve_agent
    from eval.runner import single_threaded_torch

    _WORKER.update(job=job, rows=rows)
    env = make_eval_env(job.env, job.plan.sensors, job.plan.shield)
    with contextlib.redirect_stdout(io.StringIO()):  # the parent already said which checkpoint it uses
        _, _WORKER["policy"] = resolve_agent(job.plan.spec, env, job.env["name"], job.checkpoints)
    env.close()
    single_threaded_torch()


class _Sent:
    """``out`` for :func:`play_batched` in a worker: each row, as its episode ends in seed order, onto the queue."""

    def __init__(self, queue) -> None:
        self.queue = queue

    def append(self, row: dict) -> None:
        self.queue.put(row)


def _play_chunk(seeds: Sequence[int], n_envs: int) -> int:
    """A worker's part: ``seeds`` on one batch of ``n_envs``; its rows go back on the queue; returns their count."""
    job = _WORKER["job"]
    return len(play_batched(job.env, job.sensors, job.plan.shield, _WORKER["policy"], seeds, n_envs, job.label,
                            progress=False, out=_Sent(_WORKER["rows"])))


def chunks(seeds: Sequence[int], k: int) -> list[Sequence[int]]:
    """``seeds`` in ``k`` contiguous parts of sizes within one of each other, in order (none empty)."""
    n = len(seeds)
    return [seeds[i * n // k:(i + 1) * n // k] for i in range(k) if (i + 1) * n // k > i * n // k]


def play_batched_workers(job: BatchedJob, seeds: Sequence[int], n_envs: int, workers: int, progress: bool = True,
                         out: list | None = None) -> list[dict]:
    """``seeds`` on the batched engine in ``workers`` spawned processes, each playing one contiguous part of them
    (:func:`chunks`) on its own batch of ``n_envs``; the rows merged back in the order of ``seeds`` (an episode's
    row depends on its seed only, not on its row or batch: docs/performance.md), each appended to ``out`` once
    every earlier seed's row is in. A worker's failure, Ctrl-C or SIGTERM stops every worker at once
    (:func:`eval.runner._stop`) and is raised here; ``out`` keeps the rows of the seeds before the first
    missing one."""
    import multiprocessing

    from eval.runner import WorkerPool

    parts = chunks(seeds, max(1, int(workers)))
    queue = multiprocessing.get_context("spawn").Queue()  # the workers' context (WorkerPool spawns)
    rows: list[dict] = []
    # leaving on Ctrl-C, SIGTERM or a failed worker stops the others now, not after their parts (WorkerPool)
    with WorkerPool(len(parts), _init_batched_worker, (job, queue)) as pool, \
            tqdm(total=len(seeds), desc=f"eval {job.label} (batched, {len(parts)} workers)", unit="ep",
                 disable=not progress, leave=False) as bar:
        futures = [pool.submit(_play_chunk, part, n_envs) for part in parts]
        _merge(queue, futures, seeds, rows, out, bar)
        for future in futures:  # every part played whole
            future.result()
    return rows


def _merge(queue, futures: list, seeds: Sequence[int], rows: list, out: list | None, bar) -> None:
    """The workers' rows off ``queue`` into ``rows`` (and ``out``) in the order of ``seeds``, renumbered; raises a
    worker's exception as soon as its part fails."""
    import queue as queues

    waiting: dict[int, dict] = {}
    quiet = 0.0  # s without a row since every part ended: its last rows are still in the queue's pipe, or lost
    while len(rows) < len(seeds):
        try:
            row = queue.get(timeout=0.5)
        except queues.Empty:
            for future in futures:
                if future.done() and future.exception() is not None:
                    raise future.exception()
            quiet = quiet + 0.5 if all(f.done() for f in futures) else 0.0
            if quiet > 30:
                raise RuntimeError(f"the workers ended without the rows of {len(seeds) - len(rows)} seeds")
            continue
        waiting[row["seed"]] = row
        bar.update()
        while len(rows) < len(seeds) and int(seeds[len(rows)]) in waiting:
            rows.append({**waiting.pop(int(seeds[len(rows)])), "episode": len(rows)})
            if out is not None:
                out.append(rows[-1])


def play_on(env_cfg: dict, sensors: dict, shield: dict, policy, seeds: Iterable[int], n_envs: int, label: str,
            batched: bool, progress: bool = False) -> list[dict]:
    """The episodes ``seeds`` of ``policy`` (a progress bar on stderr if ``progress``): on the batched engine
    (:func:`play_batched`, ``n_envs`` at a time; the caller has checked it can run the stack) or on one per-env env
    (:func:`eval.runner.run_episodes`: a tracker, a shield, the lane keeper). The same episodes either way, the
    batch's cost where it can."""
    if batched:
        return play_batched(env_cfg, sensors, shield, policy, seeds, n_envs, label, progress=progress)
    from eval.agents import make_eval_env
    from eval.runner import run_episodes

    env = make_eval_env(env_cfg, sensors, shield)
    try:
        return run_episodes(env, policy, seeds, label, progress=progress)
    finally:
        env.close()


def play_batched(env_cfg: dict, sensors: dict, shield: dict, policy, seeds: Iterable[int], n_envs: int, label: str,
                 progress: bool = True, out: list | None = None, aeb: dict | None = None) -> list[dict]:
    """The episodes ``seeds`` of ``policy`` on the batched engine (``n_envs`` at a time), rows in seed order; the
    caller has checked that the engine can run this env, sensors, shield and policy (:func:`check_batched_plan`,
    or ``train/ppo.py``'s own check for the stack it trains on). ``aeb``: a dict that gets, per seed, what the
    shield did in that episode (``info["aeb"]``: brake time, stop position, the steps it overrode)."""
    from agents.batched_vec_env import BatchedLeftTurnVecEnv

    total = len(seeds) if hasattr(seeds, "__len__") else None
    B = max(1, min(int(n_envs), total if total is not None else int(n_envs)))
    venv = BatchedLeftTurnVecEnv(env_cfg, sensors, shield, B, action_repeat=1, actions="env", pool=0)
    decide = _Decider(policy, venv.engine, venv.perception)
    order = iter(seeds)
    wanted: list[int] = []  # seeds handed to the engine, in order

    def feed():
        for s in order:
            wanted.append(int(s))
            yield int(s)

    obs = venv.play(feed())
    decide.reset(np.arange(B))
    done: dict[int, dict] = {}
    rows: list[dict] = []
    with tqdm(total=total, desc=f"eval {label} (batched)", unit="ep", disable=not progress, leave=False) as bar:
        while not venv.idle.all():
            live = ~venv.idle
            obs, _, ended, infos = venv.step(decide.act(obs, live))
            restarted = []
            for r in np.nonzero(ended)[0]:
                done[infos[r]["seed"]] = infos[r]["episode_metrics"]
                if aeb is not None and "aeb" in infos[r]:
                    aeb[infos[r]["seed"]] = infos[r]["aeb"]
                restarted.append(r)
            decide.reset(np.array(restarted, dtype=int))
            while len(rows) < len(wanted) and wanted[len(rows)] in done:  # seed order
                seed = wanted[len(rows)]
                rows.append({"agent": label, "episode": len(rows), "seed": seed, **done.pop(seed)})
                if out is not None:
                    out.append(rows[-1])
                bar.update()
    return rows
