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


def single_threaded_torch() -> None:
    """torch's intra-op pool to one thread, in any process that drives a policy for an evaluation (a worker, the
    parent, the figures' extra lap): call it after the policy is built, before it acts."""
    # A multi-threaded matmul may sum in a different order from one run to the next (and from one process to
    # another), which changes a network's action in the last bit; one thread makes it the same everywhere.
    # Evaluation networks are small, so nothing is lost, and torch's default (one thread per core, OMP_NUM_THREADS
    # if set) spins on a busy machine: with 2 threads on 2 cores shared with other jobs (load 2-3) the figures'
    # lap of PilotNet on the cameras ran at ~7 steps/s instead of ~340 (docs/sensors.md's eval, 2 laps,
    # n_envs=2, OMP_NUM_THREADS unset: 105 CPU-s before this was called for that lap, 41 after).
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def run_episodes(env: gym.Env, policy: Policy, seeds: Iterable[int], label: str,
                 progress: bool = True, out: list | None = None) -> list[dict]:
    """One row per seed: ``{"agent", "episode", "seed", **info["episode_metrics"]}``. ``env`` must be wrapped in
    :class:`av_gym.metrics.recorder.EpisodeMetrics` (as :func:`av_gym.make.make_env` does). Each row is also
    appended to ``out`` (if given) as its episode ends, so that a caller interrupted half-way keeps them."""
    single_threaded_torch()
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
    - Its progress bars lock with a thread lock (:func:`_bars_lock_of_this_process`), so a worker ended by SIGTERM
      or ``terminate()`` leaves no semaphore behind.

    A no-op in the main process: only processes started by ``multiprocessing`` are workers."""
    import multiprocessing
    import os
    import signal

    parent = multiprocessing.parent_process()
    if parent is None:
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _bars_lock_of_this_process()
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


def _bars_lock_of_this_process() -> None:
    """tqdm's bars in this worker lock with a thread lock, not tqdm's default multiprocessing RLock.

    Why: in a spawned process that RLock is a named POSIX semaphore, registered with multiprocessing's resource
    tracker and released only by an orderly exit. A worker's first bar (even a disabled one: ``play_batched``'s
    ``progress=False``) creates it, and the stop path ends workers by SIGTERM or ``terminate()`` mid-task, so with
    that lock the tracker would find one semaphore per worker when the run ends and print "There appear to be N
    leaked semaphore objects". A worker draws no bar (the parent draws the run's), so its own threads are all the
    lock has to order."""
    import threading

    from tqdm import tqdm as bars

    bars.set_lock(threading.RLock())


def _init_worker(job: EpisodeJob) -> None:
    from eval.agents import make_eval_env, resolve_agent

    env = make_eval_env(job.env, job.sensors, job.shield)
    with contextlib.redirect_stdout(io.StringIO()):  # the parent already said which checkpoint it uses
        _, policy = resolve_agent(job.spec, env, job.env_name, job.checkpoints)
    single_threaded_torch()
    _WORKER.update(env=env, policy=policy)


def _run_one(seed: int) -> dict:
    return play_episode(_WORKER["env"], _WORKER["policy"], seed)


def run_episodes_parallel(job: EpisodeJob, seeds: Iterable[int], n_envs: int, progress: bool = True,
                          out: list | None = None) -> list[dict]:
    """:func:`run_episodes` over ``n_envs`` worker processes, each building ``job``'s env and policy once; rows
    in the order of ``seeds``, identical to the in-process ones (and appended to ``out`` as they come)."""
    from collections import deque
    from itertools import islice

    total = len(seeds) if hasattr(seeds, "__len__") else None
    workers = max(1, min(n_envs, total if total is not None else n_envs))
    rows = []
    with WorkerPool(workers, _init_worker, (job,)) as pool, \
            tqdm(total=total, desc=f"eval {job.label}", unit="ep", disable=not progress, leave=False) as bar:
        # A bounded window of episodes in flight, not one future per seed up front (pool.map submits them all:
        # episodes=10**12 would exhaust memory before the first ran). Rows come back in seed order. Ctrl-C,
        # SIGTERM or a failed episode leave the pool at once (WorkerPool), not after the queue.
        it = iter(seeds)
        pending = deque((int(s), pool.submit(_run_one, int(s))) for s in islice(it, 4 * workers))
        while pending:
            seed, future = pending.popleft()
            rows.append({"agent": job.label, "episode": len(rows), "seed": seed, **future.result()})
            if out is not None:
                out.append(rows[-1])
            bar.update()
            for s in islice(it, 1):
                pending.append((int(s), pool.submit(_run_one, int(s))))
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


_SET_UP_FAILED: list = []  # in a worker process: the exception its set-up raised, if any


def _set_up(setup: Callable, args: tuple) -> None:
    """A worker's initializer: :func:`guard_worker`, then ``setup(*args)``, whose exception is kept for the first
    task to raise (a failed initializer only breaks the pool, without the reason)."""
    guard_worker()
    try:
        setup(*args)
    except Exception as exc:
        _SET_UP_FAILED.append(exc)


def _call(fn: Callable, *args):
    if _SET_UP_FAILED:
        raise _SET_UP_FAILED[0]
    return fn(*args)


class WorkerPool:
    """``n`` spawned worker processes, each set up once by ``setup(*args)`` (module-level, picklable), for tasks
    ``fn(*args)`` run there (:meth:`submit`, :meth:`parts`). Spawned, not forked: a fork copies torch's threads
    half-made. Each worker leaves Ctrl-C to the parent and dies with it (:func:`guard_worker`); a set-up error
    comes back as the exception of the worker's first task. Used as a context manager, or closed by
    :meth:`close`: leaving on an exception (a worker's, Ctrl-C, SIGTERM as KeyboardInterrupt) ends every worker at
    once (:func:`_stop`), not after its task."""

    def __init__(self, n: int, setup: Callable, args: tuple = ()) -> None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.n = int(n)
        self.pool = ProcessPoolExecutor(max_workers=self.n, mp_context=multiprocessing.get_context("spawn"),
                                        initializer=_set_up, initargs=(setup, args))

    def submit(self, fn: Callable, *args):
        """``fn(*args)`` in a worker: its future."""
        return self.pool.submit(_call, fn, *args)

    def parts(self, fn: Callable, parts: list, *args) -> list:
        """``fn(part, *args)`` for every part at once, one worker each; their results in the order of ``parts``.
        A part's exception stops the others (:func:`_stop`) and is raised here."""
        from concurrent.futures import FIRST_EXCEPTION, wait

        futures = [self.submit(fn, part, *args) for part in parts]
        try:  # the first part to fail stops the others at once, not after the parts before it have finished
            done, _ = wait(futures, return_when=FIRST_EXCEPTION)
            for future in (f for f in futures if f in done and f.exception() is not None):
                raise future.exception()
            return [future.result() for future in futures]
        except BaseException:
            _stop(self.pool)
            raise

    def close(self, failed: bool = False) -> None:
        """Let the workers end (``failed``: end them now, what is running included)."""
        if failed:
            _stop(self.pool)
        else:
            self.pool.shutdown(wait=True)

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, kind, *_) -> None:
        self.close(failed=kind is not None)
