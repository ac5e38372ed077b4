"""AEB shield cost per decision (target: < 1 ms at 20 road users).

A traffic episode is run until ``--vehicles`` other road users are on the map (extra traffic is spawned with the
env's own spawner, so every vehicle is on a lane with a route, as in an evaluation); then the shield's decision
(:meth:`AEBShield._decide`, everything it does per 0.1 s step except the simulation) is timed on copies of that
state, for each target model of the improved variant, with the old default (``cv``) as the reference run in the
same process. Prints a table: ms per decision (median of ``--repeat`` runs of ``--n`` decisions) and the ratio to
``cv``. Note the load average beside any number you quote.

    python benchmarks/aeb_cost.py --vehicles 20
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import os
import time

import numpy as np


def scene(n_vehicles: int, seed: int, overrides: dict):
    from agents import AlwaysProceed
    from av_gym.make import make_env
    from eval.agents import compose_group
    from av_gym.shields.aeb import find_shield

    shield = compose_group("shield", "aeb")
    shield.update(overrides)
    env = make_env({"name": "left_turn", "spawn_probability": 1.0}, None, shield)
    policy = AlwaysProceed(env.unwrapped.cruise_action())
    obs, _ = env.reset(seed=seed)
    u = env.unwrapped
    # Traffic builds up while the ego waits at the start (held at standstill: the brake actuator is not engaged,
    # the set-point is 0); a spawn is refused where it would overlap a vehicle already there.
    for _ in range(400):
        if len(u.road.vehicles) - 1 >= n_vehicles:
            break
        u._spawn_vehicle(spawn_probability=1.0)
        u.vehicle.speed, u.vehicle.target_speed = 0.0, 0.0
        obs, *_ = env.step(policy.act(obs))
    return env, find_shield(env)


def time_decisions(shield, n: int) -> float:
    """Seconds per decision over ``n`` decisions on the same scene (the clock does not move, so the finite
    differences are skipped; everything else, prediction, overlap tests, trigger, runs every time)."""
    start = time.perf_counter()
    for _ in range(n):
        shield._decide()
    return (time.perf_counter() - start) / n


def main() -> None:
    from conf.cli import ToolParser, number

    ap = ToolParser(prog="benchmarks/aeb_cost.py", description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=number(int, low=0), default=20, help="other road users on the map, >= 0")
    ap.add_argument("--seed", type=int, default=1000)
    # each time is a mean over --n decisions and the table a median over --repeat of them: 0 divided by zero
    ap.add_argument("--n", type=number(int, low=1), default=50, help="decisions per timing, >= 1")
    ap.add_argument("--repeat", type=number(int, low=1), default=5, help="timings per model (median), >= 1")
    a = ap.parse_args()
    rows = []
    # the shipped default (conflict model, indicators read) and the models and options it is compared with
    configs = {"cv": {"target_model": "cv"}, "map": {"target_model": "map"},
               "conflict, no indicators": {"target_model": "conflict", "signals": False},
               "conflict (default)": {}}
    for model, overrides in configs.items():
        env, shield = scene(a.vehicles, a.seed, overrides)
        print(f"[aeb_cost] {model}: {len(env.unwrapped.road.vehicles) - 1} road users", flush=True)
        time_decisions(shield, 5)  # warm the caches (route tables, driven paths), as after the first episode
        times = [time_decisions(shield, a.n) for _ in range(a.repeat)]
        rows.append((model, len(env.unwrapped.road.vehicles) - 1, float(np.median(times)) * 1e3))
    ref = rows[0][2]
    print(f"load average {os.getloadavg()[0]:.2f} (1 min); median of {a.repeat} x {a.n} decisions")
    print("| prediction | road users | ms per decision | ratio to cv |")
    print("| --- | --- | --- | --- |")
    for model, n, ms in rows:
        print(f"| {model} | {n} | {ms:.3f} | {ms / ref:.2f} |")


if __name__ == "__main__":
    main()
