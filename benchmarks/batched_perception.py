"""Perceived evaluation (``sensors=turn_perceived``: detector → Kalman tracker → turn features), with or without the
AEB shield, on the batch against the per-env stack, both in one run: episodes per CPU-second and their ratio, and
each stack's wall time.

    python benchmarks/batched_perception.py                                  # dagger_turn_perceived, B = 250
    python benchmarks/batched_perception.py --agent gap_acceptance@turn_perceived --batch-episodes 1000
    python benchmarks/batched_perception.py --agent dagger_turn_perceived+aeb --batch-episodes 1000  # shielded

The same agent on validation seeds from 1,000,000: ``--per-env-episodes`` of them one after the other on the per-env
stack (:func:`eval.runner.run_episodes`, what ``python -m eval vec_env=subproc`` runs in each worker), then
``--batch-episodes`` on the batch (:func:`eval.batched.play_batched`, ``--B`` envs stepped together, as ``python -m
eval vec_env=batched n_envs=B``), then the per-env stack again, its two runs averaged (so a change of load during
the run hits both sides alike). Before them, a few untimed episodes of each stack on other seeds, so that numba's
compiling (or reading its cache) on the first call is not timed: the table is the steady state. CPU time is
``time.process_time`` of this process with torch on one thread (robust to other jobs sharing the cores). Prints a
markdown table and ``uptime``'s load average before and after.
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import os
import time

from conf.cli import ToolParser, number

FIRST_SEED = 1_000_000  # the validation split's first seed (the test split is the lead's to report)
WARM_SEED = 1_500_000  # the untimed warm-up's validation seeds, outside every timed range


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def setup(spec: str):
    """The agent ``spec`` as ``python -m eval`` plans it on the left turn: (env config, plan, policy, label)."""
    from av_gym.make import make_env
    from av_gym.presets import compose_group
    from eval.agents import plan_agent, resolve_agent

    env_cfg = compose_group("env", "left_turn")
    plan = plan_agent(spec, "left_turn", compose_group("sensors", "truth"), {"name": "none", "kind": "none"},
                      "checkpoints")
    env = make_env(env_cfg, plan.sensors, plan.shield)
    label, policy = resolve_agent(plan.spec, env, "left_turn", "checkpoints")
    env.close()
    return env_cfg, plan, policy, label


def timed(run, seeds: list[int]) -> tuple[float, float, list[dict]]:
    """CPU seconds and wall seconds of ``run(seeds)``, and its rows."""
    t0, w0 = time.process_time(), time.perf_counter()
    rows = run(seeds)
    return time.process_time() - t0, time.perf_counter() - w0, rows


def main() -> None:
    parser = ToolParser(prog="benchmarks/batched_perception.py", description=__doc__.splitlines()[0])
    parser.add_argument("--agent", default="dagger_turn_perceived", help="an agent spec as python -m eval takes it")
    parser.add_argument("--B", type=number(int, low=1, high=4096), default=250, help="envs on the batch")
    parser.add_argument("--batch-episodes", type=number(int, low=1), default=500)
    parser.add_argument("--per-env-episodes", type=number(int, low=1), default=20, help="per run (two runs)")
    args = parser.parse_args()

    from eval.batched import check_batched_plan, play_batched
    from eval.runner import single_threaded_torch, run_episodes

    single_threaded_torch()
    env_cfg, plan, policy, label = setup(args.agent)
    check_batched_plan(plan, env_cfg)

    def per_env(seeds):
        from eval.agents import make_eval_env

        env = make_eval_env(env_cfg, plan.sensors, plan.shield)
        try:
            return run_episodes(env, policy, seeds, label, progress=False)
        finally:
            env.close()

    def batch(seeds, B: int = args.B):
        return play_batched(env_cfg, plan.sensors, plan.shield, policy, seeds, B, label, progress=False)

    # a kernel compiles on its first call in a process (seconds each, tens in a fresh checkout without numba's
    # cache), whichever stack calls it first: without this the first timed runs measure compiling
    per_env(list(range(WARM_SEED, WARM_SEED + 2)))
    batch(list(range(WARM_SEED, WARM_SEED + 8)), B=min(args.B, 8))
    print(f"load average before: {load()}", flush=True)
    n_per, n_batch = args.per_env_episodes, args.batch_episodes
    cpu_a, wall_a, _ = timed(per_env, list(range(FIRST_SEED, FIRST_SEED + n_per)))
    cpu_b, wall_b, rows = timed(batch, list(range(FIRST_SEED, FIRST_SEED + n_batch)))
    cpu_c, wall_c, _ = timed(per_env, list(range(FIRST_SEED + n_per, FIRST_SEED + 2 * n_per)))
    per_rate, batch_rate = 2 * n_per / (cpu_a + cpu_c), n_batch / cpu_b
    success = sum(r["success"] for r in rows) / len(rows)
    print(f"load average after: {load()}\n")
    shield = (plan.shield or {}).get("name", "none")
    print(f"agent {label}, sensors {plan.sensors.get('name')}, shield {shield}, validation seeds from {FIRST_SEED}\n")
    print("| stack | episodes | CPU-s | wall s | episodes / CPU-s | ratio |\n|---|---:|---:|---:|---:|---:|")
    print(f"| per-env (two runs) | {2 * n_per} | {cpu_a + cpu_c:.1f} | {wall_a + wall_c:.1f} | {per_rate:.2f} | 1.0 |")
    print(f"| batch, B = {args.B} | {n_batch} | {cpu_b:.1f} | {wall_b:.1f} | {batch_rate:.2f} | "
          f"**{batch_rate / per_rate:.1f}** |")
    print(f"\nbatch success rate {success:.3f} over {n_batch} episodes")


if __name__ == "__main__":
    main()
