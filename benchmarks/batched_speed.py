"""Batched left turn vs the per-env fast stack, side by side in one run: the compiled batch step, the compiled step
with obs["turn"], truth and rewards in numpy (the step before those kernels: ``batched.OBSERVE_KERNELS`` left out)
and the numpy step (with the pairwise kernels: the engine before the compiled step), interleaved in one process.

    python benchmarks/batched_speed.py [--sizes 1 4 16 64 256 1024] [--seconds 4] [--out runs/speed.png] # a new file
    python benchmarks/batched_speed.py --sizes 256 1024 --seconds 6        # the sizes the targets name, ~2 min
    python benchmarks/batched_speed.py --profile 256                       # one batch step, profiled
    python benchmarks/batched_speed.py --ppo 1024 --agent ppo_turn_shielded # PPO learn, per env vs batch, shielded

Env steps per CPU-second on one core (``time.process_time``: robust to other jobs sharing the cores; numpy's
elementwise maths is single-threaded), both producing ``obs["turn"]`` (TurnFeatures, source=truth) every policy
step, and the ego's constant-velocity TTC (``info["truth"]["ttc"]`` on the per-env stack, ``BatchedLeftTurn.ttc``
on the batch: the episode metrics' min TTC), random meta-actions, episodes reset as they end (the batch through its
auto-reset pool, as its VecEnv does).
Per-env: ``UnprotectedLeftTurn-v0`` (``fast: true``) + ``TurnFeatures``, one env stepped in a loop (the per-env
rate does not depend on how many are stepped one after the other). Memory per env: the batch's state arrays
(bytes / B). The batch paths alternate in slices of ``--seconds`` / 4 (their CPU time summed), so a change of
the machine's load hits both alike. Prints a markdown table and ``uptime``'s load average, and saves a plot.
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import os
import time

import gymnasium as gym
import numpy as np
from omegaconf import OmegaConf

from av_gym.batched.left_turn import BatchedLeftTurn
from av_gym.estimation.turn_features import TurnFeatures
from av_gym.make import highway_config
from av_gym.sim import batched
from av_gym.atomic import exit_with, save_figure_new
from av_gym.errors import ConfigError
from conf.cli import Extend, ToolParser, items, number, out_figure_problem

# the numpy step (the pairwise kernels only), the compiled step with obs["turn"], truth and rewards in numpy (before
# their kernels), the compiled step
PATHS = {"numpy step": batched.PAIRWISE_KERNELS,
         "compiled step, numpy obs": frozenset(batched.KERNELS) - batched.OBSERVE_KERNELS,
         "compiled step": frozenset(batched.KERNELS)}


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def per_env_rate(config: dict, seconds: float) -> float:
    env_id, _ = highway_config({"name": "left_turn"})
    env = TurnFeatures(gym.make(env_id, config=config))
    rng = np.random.default_rng(0)
    seed, n = 0, 0
    env.reset(seed=seed)
    t0 = time.process_time()
    while time.process_time() - t0 < seconds:
        _, _, term, trunc, _ = env.step(int(rng.integers(0, 3)))
        n += 1
        if term or trunc:
            seed += 1
            env.reset(seed=seed)
    return n / (time.process_time() - t0)


def batched_rates(config: dict, B: int, seconds: float, slices: int = 4) -> tuple[dict, float]:
    """Env steps per CPU-second over whole episodes (resets included) of each of :data:`PATHS`, the paths taking
    turns in ``slices`` slices of ``seconds`` / ``slices`` each; and the state's bytes per env."""
    engines, steps, cpu = {}, dict.fromkeys(PATHS, 0), dict.fromkeys(PATHS, 0.0)
    for name, names in PATHS.items():
        with batched.using_kernels(names):
            bt = BatchedLeftTurn(B, config, pool=max(8, B // 4))
            bt.reset(list(range(B)))
            engines[name] = (bt, np.random.default_rng(0))
    for _ in range(slices):
        for name, names in PATHS.items():
            bt, rng = engines[name]
            with batched.using_kernels(names):
                t0 = time.process_time()
                while time.process_time() - t0 < seconds / slices:
                    bt.step_autoreset(rng.integers(0, 3, B))
                    bt.ttc()  # the per-env stack computes info["truth"]["ttc"] every step too
                    steps[name] += B
                cpu[name] += time.process_time() - t0
    return {name: steps[name] / cpu[name] for name in PATHS}, engines["compiled step"][0].state_bytes() / B


def profile(config: dict, B: int, steps: int = 200) -> None:
    """cProfile of ``steps`` batch steps (step_autoreset + ttc) at B on each path: Python-level calls per batch
    step and where the time goes (tottime, the first 25 functions)."""
    import cProfile
    import pstats

    for name, names in PATHS.items():
        with batched.using_kernels(names):
            bt = BatchedLeftTurn(B, config, pool=max(8, B // 4))
            bt.reset(list(range(B)))
            rng = np.random.default_rng(0)
            for _ in range(20):  # past the first pool refills
                bt.step_autoreset(rng.integers(0, 3, B))
            prof = cProfile.Profile()
            t0 = time.process_time()
            prof.enable()
            for _ in range(steps):
                bt.step_autoreset(rng.integers(0, 3, B))
                bt.ttc()
            prof.disable()
            used = time.process_time() - t0
        stats = pstats.Stats(prof)
        print(f"\n## {name}, B={B}: {stats.total_calls / steps:.0f} Python-level calls per batch step, "
              f"{used / steps * 1e3:.2f} ms per batch step under the profiler; load {load()}")
        stats.sort_stats("tottime").print_stats(25)


def ppo_rate(batched: bool, decisions: int, agent_name: str = "ppo_turn") -> tuple[float, float]:
    """``agent=<agent_name>`` (ppo_turn: GO/YIELD, action repeat 5, its hyperparameters; ppo_turn_shielded: the
    same behind the AEB shield with its intervention cost; no cloning) in SB3's ``learn``: env steps per second of
    wall clock and per CPU-second of this process and its children. Per-env: ``train/ppo.py``'s stack, 2 subprocess
    envs × 256 decisions per rollout (``python -m train agent=ppo_turn agent.vec_env=subproc``); batched: 64 envs ×
    8 (the same 512-decision rollout, so the same update cost)."""
    import functools
    import resource

    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf as OC
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    from agents.ppo import make_ppo
    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from train.ppo import _env_factory

    import torch

    with initialize_config_module("conf", version_base="1.3"):
        cfg = compose("train", overrides=[f"agent={agent_name}"])
    torch.set_num_threads(int(cfg.train.torch_threads))  # as python -m train
    plain = [OC.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
    agent = OC.to_container(cfg.agent, resolve=True)
    cost = float(agent["intervention_cost"])
    if batched:
        agent.update(n_envs=64, n_steps=8)
        venv = BatchedLeftTurnVecEnv(*plain, 64, action_repeat=5, actions="go_yield", timeout_is_terminal=True,
                                     intervention_cost=cost)
        venv.seed(0)
    else:
        agent.update(n_envs=2, n_steps=256)
        venv = make_vec_env(functools.partial(_env_factory, *plain, cost, 5, "go_yield", timeout_is_terminal=True),
                            n_envs=2, seed=0, vec_env_cls=SubprocVecEnv, vec_env_kwargs={"start_method": "fork"})
    model = make_ppo(venv, agent, seed=0, tensorboard_log=None, device="cpu")

    def cpu() -> float:
        me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime

    t0, c0 = time.time(), cpu()
    model.learn(decisions)
    venv.close()  # children's CPU counts once they are reaped
    wall, used = time.time() - t0, cpu() - c0
    steps = model.num_timesteps * 5  # env steps (action repeat 5; the last decisions of episodes may be shorter)
    return steps / wall, steps / used


def main() -> None:
    parser = ToolParser(prog="benchmarks/batched_speed.py", description=__doc__.splitlines()[0])
    # 4096 envs hold ~40 MB of state; more says nothing new about the batch's scaling
    parser.add_argument("--sizes", type=items(int, low=1, high=4096), nargs="+", action=Extend,
                        default=[1, 4, 16, 64, 256, 1024], help="batch sizes, [1,16,256]")
    parser.add_argument("--seconds", type=float, default=4.0, help="CPU seconds per path and size, > 0")
    parser.add_argument("--out", default=None,
                        help="the plot, a new file (default runs/benchmarks/batched_speed_<time>.png; a tool writes "
                             "into docs/ only when told to)")
    parser.add_argument("--ppo", type=number(int, low=0), default=0,
                        help="also time PPO learn for this many decisions per path")
    parser.add_argument("--agent", choices=["ppo_turn", "ppo_turn_shielded"], default="ppo_turn",
                        help="the agent --ppo trains (ppo_turn_shielded: with the AEB shield and its cost)")
    parser.add_argument("--profile", type=number(int, low=1, high=4096), default=None,
                        help="profile batch steps at this B on both paths instead of timing them")
    args = parser.parse_args()
    if not args.seconds > 0:  # the rates divide by it (-1 was a ZeroDivisionError traceback); NaN is not > 0
        parser.error(f"argument --seconds: expected a number > 0, got {args.seconds:g}")
    args.out = args.out or f"runs/benchmarks/batched_speed_{time.strftime('%Y%m%d-%H%M%S')}.png"
    problem = not (args.profile or args.ppo) and out_figure_problem(args.out, "--out")
    if problem:  # before minutes of timing: a taken or unwritable --out, or a suffix matplotlib cannot write
        parser.error(f"argument {problem}")
    if args.profile:
        profile(highway_config({"name": "left_turn"})[1], args.profile)
        return
    if args.ppo:
        print(f"load average: {load()}")
        print(f"| {args.agent} learn | env steps/s (wall) | env steps / CPU-s |\n|---|---:|---:|")
        for on_batch in (False, True):
            wall, per_cpu = ppo_rate(on_batch, args.ppo, args.agent)
            name = "batched, 64 envs x 8" if on_batch else "per-env, 2 subprocess envs x 256"
            print(f"| {name} | {wall:.0f} | {per_cpu:.0f} |", flush=True)
        print(f"load average: {load()}")
        return
    _, config = highway_config({"name": "left_turn"})
    print(f"load average before: {load()}")
    base = per_env_rate(config, args.seconds)
    rows = []
    for B in args.sizes:
        rates, mem = batched_rates(config, B, args.seconds)
        rows.append((B, rates, mem))
        print(f"B={B}: " + ", ".join(f"{name} {rate:.0f} steps/s ({rate / base:.1f}x)" for name, rate in rates.items())
              + f"; load {load()}", flush=True)
    base_after = per_env_rate(config, args.seconds)
    print(f"\nper-env fast stack + TurnFeatures: {base:.0f} steps/s before, {base_after:.0f} after; load {load()}\n")
    ref = 0.5 * (base + base_after)
    print("| B | " + " | ".join(f"{name}, steps/CPU-s" for name in PATHS) + " | per-env steps/CPU-s | "
          + " | ".join(f"{name} / per-env" for name in PATHS)
          + " | compiled / numpy | after / before | state bytes / env |")
    print("|---:" * (2 * len(PATHS) + 5) + "|")
    for B, rates, mem in rows:
        print(f"| {B} | " + " | ".join(f"{rates[name]:.0f}" for name in PATHS) + f" | {ref:.0f} | "
              + " | ".join(f"{rates[name] / ref:.1f}" for name in PATHS)
              + f" | {rates['compiled step'] / rates['numpy step']:.2f}"
              + f" | {rates['compiled step'] / rates['compiled step, numpy obs']:.2f} | {mem:.0f} |")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    sizes = [r[0] for r in rows]
    for name in PATHS:
        ax.plot(sizes, [r[1][name] for r in rows], "o-", label=f"batched, {name}")
    ax.axhline(ref, color="grey", ls="--", label="per-env fast stack")
    ax.axhline(100 * ref, color="tab:red", ls=":", label="100x target")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("environments per batch B")
    ax.set_ylabel("env steps / CPU-second (1 core)")
    ax.set_title("left turn + obs['turn']")
    ax.legend(fontsize=8)
    fig.tight_layout()
    try:  # a new file, whole: one that appeared during the run is kept (the table above is printed either way)
        save_figure_new(fig, args.out, "--out", dpi=120)
    except ConfigError as exc:
        exit_with(exc)
    print(f"\nplot: {args.out}")

if __name__ == "__main__":
    main()
