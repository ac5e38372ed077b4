"""Run a policy on seeded episodes and collect one metrics row per episode, in this process or spread over worker
processes (``n_envs``).

Determinism: an episode depends on its seed only (the env, every sensor and the shield reseed from it on reset;
policies reset), so which process runs it, and after which other episode, does not change its row. The rows are
put back in seed order, and the result is bit-identical for any ``n_envs`` (tests/test_determinism.py)."""

from __future__ import annotations

import contextlib
import io
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import gymnasium as gym
from tqdm import tqdm

from agents import Policy


def _single_threaded_torch() -> None:
    # A multi-threaded matmul may sum in a different order from one run to the next (and from one process to
    # another), which changes a network's action in the last bit; one thread makes it the same everywhere.
    # Evaluation networks are small, so nothing is lost.
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def run_episodes(env: gym.Env, policy: Policy, seeds: Iterable[int], label: str,
                 progress: bool = True, out: list | None = None) -> list[dict]:
    """One row per seed: ``{"agent", "episode", "seed", **info["episode_metrics"]}``. ``env`` must be wrapped in
    :class:`av_gym.metrics.recorder.EpisodeMetrics` (as :func:`av_gym.make.make_env` does). Each row is also
    appended to ``out`` (if given) as its episode ends, so that a caller interrupted half-way keeps them."""
    _single_threaded_torch()
    # Seeds are drawn one by one, never listed: episodes=10**12 is a long run, not a MemoryError before the first.
    total = len(seeds) if hasattr(seeds, "__len__") else None
    rows = []
    with tqdm(total=total, desc=f"eval {label}", unit="ep", disable=not progress, leave=False) as bar:
        on_step = _step_counter(bar) if progress else None
        for i, seed in enumerate(seeds):
            rows.append({"agent": label, "episode": i, "seed": int(seed),
                         **play_episode(env, policy, int(seed), on_step)})
            bar.update()
            if out is not None:
                out.append(rows[-1])
    return rows


def _step_counter(bar, every_s: float = 1.0) -> Callable[[int], None]:
    """``on_step(k)`` for :func:`play_episode`: the episode's step count on ``bar`` about every ``every_s``
    seconds (a lap takes 10-40 s: the bar would otherwise stand still for all of it)."""
    last = [time.monotonic()]

    def on_step(k: int) -> None:
        now = time.monotonic()
        if now - last[0] >= every_s:
            last[0] = now
            bar.set_postfix_str(f"episode step {k}")

    return on_step


def play_episode(env: gym.Env, policy: Policy, seed: int, on_step: Callable[[int], None] | None = None) -> dict:
    """One seeded episode of ``policy`` on ``env``; its ``info["episode_metrics"]``. ``on_step(k)`` after each
    step ``k`` (progress)."""
    obs, _ = env.reset(seed=seed)
    policy.reset()
    done, k = False, 0
    while not done:
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        done, k = terminated or truncated, k + 1
        if on_step is not None:
            on_step(k)
    return info["episode_metrics"]


@dataclass(frozen=True)
class EpisodeJob:
    """What a worker process needs to build the same env stack and policy as the parent (plain, picklable)."""

    env: dict
    sensors: dict
    shield: dict
    spec: str
    env_name: str
    checkpoints: str
    label: str


_WORKER: dict = {}


def guard_worker() -> None:
    """In a worker process (an evaluation pool's, a SubprocVecEnv's): end with the parent, and leave Ctrl-C to it.

    - Ctrl-C in a terminal sends SIGINT to the whole process group: every worker would print its own
      KeyboardInterrupt traceback (74 lines for 2 workers). Workers ignore it; the parent, interrupted,
      stops the pool and writes what it measured.
    - A parent killed outright (``kill -9``, the OOM killer) would leave its workers running as orphans, ~180 MB
      each. Linux's ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` has the kernel kill this process when its parent dies;
      if the parent died before the call, this process exits now. Elsewhere (no prctl) the parent's own clean-up
      on SIGINT/SIGTERM still ends them.

    A no-op in the main process: only processes started by ``multiprocessing`` are workers."""
    import multiprocessing
    import os
    import signal

    parent = multiprocessing.parent_process()
    if parent is None:
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        import ctypes

        # The OS parent is not always multiprocessing's parent: a forkserver worker (SB3's SubprocVecEnv default)
        # is the forkserver's child, and the forkserver exits when its last client does, so the signal still
        # follows the process that asked for the worker. The race check therefore compares the OS parent before
        # and after the call (a worker orphaned in between has been re-parented, to init or a subreaper).
        os_parent = os.getppid()
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # no libc symbol: the parent's clean-up is all there is
            return
        if os.getppid() != os_parent:  # the parent died before prctl took effect
            os._exit(1)


def _init_worker(job: EpisodeJob) -> None:
    guard_worker()
    from eval.agents import make_eval_env, resolve_agent

    env = make_eval_env(job.env, job.sensors, job.shield)
    with contextlib.redirect_stdout(io.StringIO()):  # the parent already said which checkpoint it uses
        _, policy = resolve_agent(job.spec, env, job.env_name, job.checkpoints)
    _single_threaded_torch()
    _WORKER.update(env=env, policy=policy)


def _run_one(seed: int) -> dict:
    return play_episode(_WORKER["env"], _WORKER["policy"], seed)


def run_episodes_parallel(job: EpisodeJob, seeds: Iterable[int], n_envs: int, progress: bool = True,
                          out: list | None = None) -> list[dict]:
    """:func:`run_episodes` over ``n_envs`` worker processes, each building ``job``'s env and policy once; rows
    in the order of ``seeds``, identical to the in-process ones (and appended to ``out`` as they come)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from collections import deque
    from itertools import islice

    total = len(seeds) if hasattr(seeds, "__len__") else None
    # spawn, not fork: the parent may hold torch's thread pool and open renderers, which a fork copies half-made.
    ctx = multiprocessing.get_context("spawn")
    workers = max(1, min(n_envs, total if total is not None else n_envs))
    rows = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                             initargs=(job,)) as pool, \
            tqdm(total=total, desc=f"eval {job.label}", unit="ep", disable=not progress, leave=False) as bar:
        # A bounded window of episodes in flight, not one future per seed up front (pool.map submits them all:
        # episodes=10**12 would exhaust memory before the first ran). Rows come back in seed order.
        it = iter(seeds)
        try:
            pending = deque((int(s), pool.submit(_run_one, int(s))) for s in islice(it, 4 * workers))
            while pending:
                seed, future = pending.popleft()
                rows.append({"agent": job.label, "episode": len(rows), "seed": seed, **future.result()})
                if out is not None:
                    out.append(rows[-1])
                bar.update()
                for s in islice(it, 1):
                    pending.append((int(s), pool.submit(_run_one, int(s))))
        except BaseException:  # Ctrl-C, SIGTERM, a failed episode: stop the workers now, not after the queue
            _stop(pool)
            raise
    return rows


def _stop(pool) -> None:
    """Cancel what is queued and end the workers at once (the pool's shutdown would let every running episode,
    and with ``wait=True`` every queued one, finish first)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())  # no public handle on the workers
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(timeout=5)
