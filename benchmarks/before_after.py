"""The left turn's loops before and after a change, in one process, timed in alternation.

    git worktree add /tmp/before <commit>
    python benchmarks/before_after.py --before /tmp/before [--rounds 20] [--sizes 16 256]

Why one process: on shared cores (other jobs, a 2-core machine) two runs of ``benchmarks/batched_speed.py`` a
minute apart differ by 10-15 %, more than a change has to be judged by. Here the ``av_gym`` of the ``--before``
checkout is imported as ``av_gym_before`` (a copy with its imports and Gymnasium ids renamed, in a temporary
folder), and each loop runs before/after/after/before... in short rounds, so that the load weighs on both alike.
Env steps per CPU-second (``time.process_time``), median and best over the rounds; the loops are ``batched_speed.py``'s
(per-env left turn + ``TurnFeatures``; the batched engine with auto-reset and TTC) and the ``turn_truth`` stacks
with go/yield actions (per env; the training batch).
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import os
import re
import shutil
import tempfile
import time

import gymnasium as gym
import numpy as np

from conf.cli import Extend, ToolParser, items

OLD = "av_gym_before"


def import_before(checkout: Path, into: Path) -> None:
    """Copy ``checkout/av_gym`` to ``into/av_gym_before``, its imports and Gymnasium ids renamed; put it on the path."""
    dest = into / OLD
    shutil.copytree(checkout / "av_gym", dest, ignore=shutil.ignore_patterns("__pycache__"))
    for path in dest.rglob("*.py"):
        text = path.read_text()
        text = re.sub(r"\bav_gym(?=\.|\s+import\b|$)", OLD, text, flags=re.M).replace('"av_gym/', f'"{OLD}/')
        path.write_text(text)
    sys.path.insert(0, str(into))


def per_env_turn(ns: str, features_cls):
    """batched_speed.py's per-env loop: the left turn + TurnFeatures, random meta-actions."""
    from av_gym.make import highway_config

    _, config = highway_config({"name": "left_turn"})
    env = features_cls(gym.make(f"{ns}/UnprotectedLeftTurn-v0", config=config))
    rng, state = np.random.default_rng(0), {"seed": 0}
    env.reset(seed=0)

    def run(n: int) -> None:
        for _ in range(n):
            _, _, term, trunc, _ = env.step(int(rng.integers(0, 3)))
            if term or trunc:
                state["seed"] += 1
                env.reset(seed=state["seed"])
    return run


def per_env_stack(make_env, meta_action, env_cfg: dict, sensors: dict):
    """The turn_truth stack (features, signals, intent) with go/yield choices mapped to meta-actions."""
    env = make_env(env_cfg, sensors, None)
    rng, state = np.random.default_rng(0), {"seed": 0}
    state["obs"], _ = env.reset(seed=0)

    def run(n: int) -> None:
        for _ in range(n):
            state["obs"], _, term, trunc, _ = env.step(meta_action(int(rng.integers(0, 2)), state["obs"]["turn"]))
            if term or trunc:
                state["seed"] += 1
                state["obs"], _ = env.reset(seed=state["seed"])
    return run


def engine(cls, B: int):
    """batched_speed.py's batched loop: step_autoreset + TTC, random meta-actions."""
    from av_gym.make import highway_config

    _, config = highway_config({"name": "left_turn"})
    e = cls(B, config, pool=max(8, B // 4))
    e.reset(list(range(B)))
    rng = np.random.default_rng(0)

    def run(n: int) -> None:
        for _ in range(n):
            e.step_autoreset(rng.integers(0, 3, B))
            e.ttc()
    return run


def training_batch(cls, B: int, env_cfg: dict, sensors: dict):
    """The training batch on turn_truth with go/yield actions (what agent.vec_env=batched steps)."""
    b = cls(env_cfg, sensors, None, B, actions="go_yield")
    b.seed(0)
    b.reset()
    rng = np.random.default_rng(0)

    def run(n: int) -> None:
        for _ in range(n):
            b.step(rng.integers(0, 2, B))
    return run


def compare(name: str, before, after, steps: int, envs: int, rounds: int) -> None:
    before(steps), after(steps)  # warm-up: compilation, pools
    times: dict[str, list[float]] = {"before": [], "after": []}
    for r in range(rounds):
        order = (("before", before), ("after", after)) if r % 2 == 0 else (("after", after), ("before", before))
        for label, run in order:
            t0 = time.process_time()
            run(steps)
            times[label].append((time.process_time() - t0) / (steps * envs))
    b, a = np.median(times["before"]), np.median(times["after"])
    fb, fa = min(times["before"]), min(times["after"])  # the least disturbed round of each
    print(f"| {name} | {1 / b:.0f} | {1 / a:.0f} | {100 * (b / a - 1):+.1f} % | {1 / fb:.0f} | {1 / fa:.0f} | "
          f"{100 * (fb / fa - 1):+.1f} % |", flush=True)


def main() -> None:
    parser = ToolParser(prog="benchmarks/before_after.py", description=__doc__.splitlines()[0])
    parser.add_argument("--before", required=True, help="a checkout of the code before (git worktree add ...)")
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--sizes", type=items(int, low=1, high=4096), nargs="+", action=Extend, default=[16, 256],
                        help="batch sizes, [16,256]")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        import_before(Path(args.before).resolve(), Path(tmp))
        from hydra import compose, initialize_config_module
        from omegaconf import OmegaConf

        import av_gym.wrappers as new_wrappers
        from av_gym.batched.left_turn import BatchedLeftTurn
        from av_gym.batched.vec_env import BatchedLeftTurnBatch
        from av_gym.estimation.turn_features import TurnFeatures
        from av_gym.make import make_env

        old = {name: __import__(f"{OLD}.{name}", fromlist=["_"]) for name in
               ("wrappers", "batched.left_turn", "batched.vec_env", "estimation.turn_features", "make")}
        with initialize_config_module("conf", version_base="1.3"):
            cfg = compose("eval", overrides=["env=left_turn", "sensors=turn_truth"])
        env_cfg, sensors = (OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors))
        print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
        print("| loop | before (median) | after (median) | after vs before | before (best) | after (best) | after vs "
              "before |\n|---|---:|---:|---:|---:|---:|---:|")
        compare("per-env left turn + TurnFeatures", per_env_turn(OLD, old["estimation.turn_features"].TurnFeatures),
                per_env_turn("av_gym", TurnFeatures), 150, 1, args.rounds)
        compare("per-env turn_truth stack, go/yield",
                per_env_stack(old["make"].make_env, old["wrappers"].meta_action, env_cfg, sensors),
                per_env_stack(make_env, new_wrappers.meta_action, env_cfg, sensors), 150, 1, args.rounds)
        for B in args.sizes:
            steps = max(4, 5000 // B)
            compare(f"batched engine, B = {B}", engine(old["batched.left_turn"].BatchedLeftTurn, B),
                    engine(BatchedLeftTurn, B), steps, B, args.rounds)
            compare(f"training batch (turn_truth, go/yield), B = {B}",
                    training_batch(old["batched.vec_env"].BatchedLeftTurnBatch, B, env_cfg, sensors),
                    training_batch(BatchedLeftTurnBatch, B, env_cfg, sensors), steps, B, args.rounds)
        print(f"\nload average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
