"""Stock highway-env code vs av-gym's fast paths: same seeds, same actions, in one run.

    python benchmarks/sim_speed.py [--steps 400] [--repeats 3] [--ppo-steps 2048]

Prints simulation ticks/s and policy steps/s for ``fast=False`` (highway-env's own code) and ``fast=True`` (the
default, ``av_gym.sim``), and their ratio, from the CPU time of ``env.step``, for the unprotected left turn
(traffic and CCFtap) and the lap, bare and with the ``full`` sensor preset. Best of ``--repeats`` runs per row, to suppress scheduler noise.
The trajectories are identical (tests/test_fast_sim.py).

Then SB3 PPO throughput: env steps per second of wall time during ``model.learn`` (rollouts *and* gradient
updates, the agent config's hyperparameters, CPU), ``--ppo-steps`` steps, ``n_envs`` = 1 (in-process) and 2 (one
process per env, as ``python -m train`` does), stock vs fast, truth sensors.
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse
import time

import numpy as np
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from av_gym.make import make_env

SCENARIOS = [("left_turn", []), ("left_turn", ["env.mode=ccftap"]), ("lane_keeping", [])]


def _plain(node) -> dict:
    """A composed config section as plain containers (the Params checkers want lists, not OmegaConf's ListConfig)."""
    return OmegaConf.to_container(node, resolve=True)


def steps_per_second(env, steps: int) -> float:
    actions = np.random.default_rng(0)
    seed, n, busy = 0, 0, 0.0
    env.reset(seed=seed)
    while n < steps:
        a = np.array([actions.uniform(-0.1, 0.1)], np.float32) if env.unwrapped.scenario == "lane_keeping" else 1
        t0 = time.process_time()  # CPU time: robust to other jobs sharing the cores
        _, _, terminated, truncated, _ = env.step(a)
        busy += time.process_time() - t0
        n += 1
        if terminated or truncated:
            seed += 1
            env.reset(seed=seed)
    return n / busy


def ppo_steps_per_second(cfg, fast: bool, n_envs: int, steps: int) -> float:
    """Env steps/s during ``PPO.learn``: per second of wall clock and per CPU-second (all processes; the
    throughput on otherwise idle cores), hyperparameters from ``conf/agent/ppo.yaml``."""
    import functools

    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    env_cfg, sensors = {**_plain(cfg.env), "fast": fast}, _plain(cfg.sensors)
    subproc = n_envs > 1
    venv = make_vec_env(functools.partial(make_env, env_cfg, sensors, record_metrics=False), n_envs=n_envs, seed=0,
                        vec_env_cls=SubprocVecEnv if subproc else DummyVecEnv,
                        vec_env_kwargs={"start_method": "fork"} if subproc else None)  # workers = our children
    a = cfg.agent
    model = PPO(a.policy, venv, n_steps=int(a.n_steps), batch_size=int(a.batch_size), n_epochs=int(a.n_epochs),
                learning_rate=float(a.learning_rate), seed=0, device="cpu", verbose=0,
                policy_kwargs={"net_arch": list(a.net_arch)})
    t0, cpu0, children0 = time.perf_counter(), time.process_time(), _children_cpu()
    model.learn(total_timesteps=steps)
    elapsed = time.perf_counter() - t0
    venv.close()  # joins the workers, so their CPU time is counted below
    cpu = time.process_time() - cpu0 + _children_cpu() - children0
    return model.num_timesteps / elapsed, model.num_timesteps / cpu


def _children_cpu() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--ppo-steps", type=int, default=2048, help="0 = skip the PPO throughput table")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 20 steps, 1 repeat, no PPO table")
    args = parser.parse_args()
    if args.quick:
        args.steps, args.repeats, args.ppo_steps = 20, 1, 0
    rows = []
    with initialize_config_module("conf", version_base="1.3"):
        for scenario, extra in SCENARIOS:
            for sensors in ("truth", "full"):
                cfg = compose("train", overrides=[f"env={scenario}", f"sensors={sensors}", *extra])
                rates = {}
                for fast in (False, True):
                    env_cfg = {**_plain(cfg.env), "fast": fast}
                    env = make_env(env_cfg, _plain(cfg.sensors), record_metrics=False)
                    rates[fast] = max(steps_per_second(env, args.steps) for _ in range(args.repeats))
                ticks = cfg.env.simulation_frequency // cfg.env.policy_frequency
                label = f"{scenario}{' ccftap' if extra else ''}"
                rows.append((label, sensors, rates[False], rates[True], ticks))
        ppo_rows = []
        for scenario in ("left_turn", "lane_keeping") if args.ppo_steps else ():
            cfg = compose("train", overrides=[f"env={scenario}", "sensors=truth", "agent=ppo"])
            for n_envs in (1, 2):
                rates = {fast: ppo_steps_per_second(cfg, fast, n_envs, args.ppo_steps) for fast in (False, True)}
                ppo_rows.append((scenario, n_envs, *rates[False], *rates[True]))
    print(f"\n{'scenario':<18} {'sensors':<7} {'stock steps/s':>13} {'fast steps/s':>12} {'stock ticks/s':>13} "
          f"{'fast ticks/s':>12} {'ratio':>6}")
    for label, sensors, slow, fast, ticks in rows:
        print(f"{label:<18} {sensors:<7} {slow:>13.0f} {fast:>12.0f} {slow * ticks:>13.0f} {fast * ticks:>12.0f} "
              f"{fast / slow:>6.2f}")
    if ppo_rows:
        print(f"\nSB3 PPO, env steps/s during learn ({args.ppo_steps} steps, truth sensors): per wall-clock second"
              " and per CPU-second")
        print(f"{'scenario':<18} {'n_envs':>6} {'stock wall':>10} {'fast wall':>9} {'ratio':>6} {'stock cpu':>9} "
              f"{'fast cpu':>8} {'ratio':>6}")
        for scenario, n_envs, slow_wall, slow_cpu, fast_wall, fast_cpu in ppo_rows:
            print(f"{scenario:<18} {n_envs:>6} {slow_wall:>10.0f} {fast_wall:>9.0f} {fast_wall / slow_wall:>6.2f} "
                  f"{slow_cpu:>9.0f} {fast_cpu:>8.0f} {fast_cpu / slow_cpu:>6.2f}")


if __name__ == "__main__":
    main()
