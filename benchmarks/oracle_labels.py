"""Oracle labels per second, per-env vs batched, and their agreement on the same states.

    python benchmarks/oracle_labels.py [--episodes 120] [--batch 64] [--quick]
    python benchmarks/oracle_labels.py --drive 1000 --split test     # the oracle's own outcomes, on the batch
    python benchmarks/oracle_labels.py --perceived 64 --batch 32    # the replica labeller on turn_perceived
    python benchmarks/oracle_labels.py --paths 64 --batch 64        # labels/s, numpy vs compiled engine step

The states: ``--episodes`` left-turn episodes (seeds from ``--seed``; the default 7,000,000+ is used nowhere else)
driven on the per-env training stack (``agent=ppo_turn``'s: GO/YIELD, action repeat 5, ``turn_truth``) by the
gap-acceptance rule whose choice is flipped with probability ``--flip`` (a seeded draw per decision), so the
states include the risky ones a learning student visits. At every decision the per-env oracle
(:func:`agents.go_yield.lookahead_teacher`, deep copy + simulated GO future) labels the state. Then the batched
engine replays the same episodes with the same choices and :func:`agents.batched_oracle.oracle_labels` labels every
env's decision at once; the labels are compared decision by decision (a decision counts while both stacks are still
in the same episode step).

Also: how many labels depend on traffic not yet on the map (the same futures without new spawns), a part of the
oracle's edge that no sensor can give a student.

Throughput: labels per second of wall clock and per CPU-second of this process, per-env (as training uses it,
with its exact "still on the safe path" shortcut, and without it: one future per decision) vs batched (``--batch``
envs at a time, all futures rolled together). Prints a markdown table and the load average.
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import os
import time

import numpy as np

from conf.cli import ToolParser

SPAWN_FLIPS = [0, 0]  # batched(): labels that change without the vehicles still to spawn, labels compared


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def stacks():
    """The plain env / sensors configs of ``agent=ppo_turn`` (turn_truth) through Hydra, as ``python -m train``."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    with initialize_config_module("conf", version_base="1.3"):
        cfg = compose("train", overrides=["agent=ppo_turn"])
    return [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]


def per_env(plain, seeds, flip: float, shortcut: bool) -> tuple[dict, float, float, int]:
    """Drive ``seeds`` on the per-env stack; returns {seed: [(choice, oracle label), ...]}, wall s and CPU s spent in
    the oracle, and its number of labels."""
    from agents.go_yield import GapAcceptance, LookaheadParams, go_is_safe, lookahead_teacher
    from av_gym.wrappers import GO, YIELD
    from train.ppo import _env_factory

    env = _env_factory(*plain, 0.0, 5, "go_yield")
    rule = GapAcceptance()
    teacher = lookahead_teacher(LookaheadParams(), "go_yield") if shortcut else \
        (lambda e, o, i: GO if go_is_safe(e, o, lambda _o: GO) else YIELD)
    out, wall, cpu, n = {}, 0.0, 0.0, 0
    for seed in seeds:
        rng = np.random.default_rng([int(seed), 32])
        obs, info = env.reset(seed=int(seed))
        steps, done = [], False
        while not done:
            w0, c0 = time.perf_counter(), time.process_time()
            label = int(teacher(env, obs, info))
            wall, cpu, n = wall + time.perf_counter() - w0, cpu + time.process_time() - c0, n + 1
            choice = rule.choice(obs["turn"])
            if rng.uniform() < flip:
                choice = 1 - choice
            steps.append((choice, label))
            obs, _, terminated, truncated, info = env.step(choice)
            done = terminated or truncated
        out[int(seed)] = steps
    env.close()
    return out, wall, cpu, n


def batched(plain, recorded: dict, B: int, margin: float = 0.0) -> tuple[dict, float, float, int]:
    """Replay the recorded choices on the batched engine, ``B`` envs at a time; label every decision with the
    batched oracle. Returns {seed: [label, ...]}, wall s and CPU s spent in the oracle, number of labels."""
    from agents.batched_oracle import go_futures, oracle_labels
    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from av_gym.wrappers import YIELD

    venv = BatchedLeftTurnVecEnv(*plain, B, action_repeat=5, actions="go_yield")
    venv.play(iter(recorded))
    labels = {s: [] for s in recorded}
    wall = cpu = 0.0
    n = 0
    SPAWN_FLIPS[:] = [0, 0]
    while not venv.idle.all():
        rows = np.nonzero(~venv.idle)[0]
        w0, c0 = time.perf_counter(), time.process_time()
        y, _ = oracle_labels(venv.engine, rows, margin)
        wall, cpu, n = wall + time.perf_counter() - w0, cpu + time.process_time() - c0, n + len(rows)
        known = go_futures(venv.engine, rows, spawns=False).labels(margin)
        SPAWN_FLIPS[0] += int((known != y).sum())
        SPAWN_FLIPS[1] += len(rows)
        actions = np.full(B, YIELD)
        for r, label in zip(rows, y):
            seed = venv.row_seed[r]
            k = len(labels[seed])
            labels[seed].append(int(label))
            # the recorded choice; past the recorded episode's end (the stacks diverged) the row just yields
            actions[r] = recorded[seed][k][0] if k < len(recorded[seed]) else YIELD
        venv.step(actions)
    return labels, wall, cpu, n


def drive(plain, split: str, n: int, B: int) -> tuple[float, float, float]:
    """The look-ahead oracle driving ``n`` episodes of ``split`` on the batched engine (its labels executed, as
    train/dagger.py's round 0): (collision, success, wall s). The same decisions as ``python -m eval
    agents=[lookahead]`` on the per-env stack (the agreement above), at the batch's cost."""
    from agents.batched_oracle import oracle_labels  # noqa: F401 - the labeller below uses it
    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from av_gym.seeds import seeds as split_seeds
    from train.dagger import BatchedLabels, drive_batched

    class _Never:  # the teacher drives: the student's choice is recorded, never executed
        @staticmethod
        def predict(obs, deterministic=True):
            return np.zeros(len(next(iter(obs.values()))), np.int64), None

    venv = BatchedLeftTurnVecEnv(*plain, B, action_repeat=5, actions="go_yield", timeout_is_terminal=True, pool=0)
    t0 = time.perf_counter()
    out = drive_batched(venv, _Never, BatchedLabels(venv, None, True, 0.0), split_seeds(split, n), True, 0.95)
    coll, succ = np.mean(out.outcomes, axis=0)
    return float(coll), float(succ), time.perf_counter() - t0


class Coin:
    """A stand-in student: GO with probability 0.6 from a seeded generator, so that the episodes visit yielding,
    waiting and going states."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def predict(self, obs: dict, deterministic: bool = True):
        return (self.rng.uniform(size=len(next(iter(obs.values())))) < 0.6).astype(np.int64), None


def replica_stack(B: int, overrides: tuple[str, ...] = (), replica_env: dict | None = None):
    """``B`` per-env stacks of ``agent=dagger_turn_perceived`` (+ Hydra ``overrides``), the oracle's batched replica
    of them (its env config updated with ``replica_env``: a replica that is *not* the episodes, for the test that
    it is caught) and its labeller, as train/dagger.py builds them."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from train.dagger import BatchedLabels, replica_sensors
    from train.ppo import _env_factory

    with initialize_config_module("conf", version_base="1.3"):
        cfg = compose("train", overrides=["agent=dagger_turn_perceived", *overrides])
    plain = [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
    envs = [_env_factory(*plain, 0.0, 5, "go_yield", timeout_is_terminal=True) for _ in range(B)]
    replica = BatchedLeftTurnVecEnv({**plain[0], **(replica_env or {})}, replica_sensors(cfg.sensors), plain[2], B,
                                    action_repeat=5, actions="go_yield", timeout_is_terminal=True, pool=0)
    return envs, replica, BatchedLabels(replica, None, True, 0.0)


def perceived(episodes: int, B: int, seed: int) -> tuple[int, int, int, float, float, float]:
    """The replica labeller of train/dagger.py on ``agent=dagger_turn_perceived``'s per-env stack (detector +
    tracker), a seeded :class:`Coin` driving: each decision labelled by the batched oracle on the replica and by the
    per-env oracle on the per-env env itself. Returns (decisions, agreeing, per-env GO count, per-env oracle s,
    replica oracle s, whole drive s)."""
    from agents.go_yield import go_is_safe
    from av_gym.wrappers import GO, YIELD
    from train.dagger import drive_replica

    envs, replica, inner = replica_stack(B)
    pairs, clock = [], [0.0, 0.0]

    class Checked:  # the replica's labels, each checked against the per-env oracle on the same env
        on_go_future = inner.on_go_future

        def __call__(self, rows, obs):
            t0 = time.perf_counter()
            labels = inner(rows, obs)
            t1 = time.perf_counter()
            pairs.extend((int(y), GO if go_is_safe(envs[r], None, lambda _o: GO) else YIELD)
                         for r, y in zip(rows, labels))
            clock[0] += time.perf_counter() - t1
            clock[1] += t1 - t0
            return labels

        def executed(self, *args):
            inner.executed(*args)

    t0 = time.perf_counter()
    drive_replica(envs, replica, Coin(seed), Checked(), range(seed, seed + episodes), False, 0.95)
    wall = time.perf_counter() - t0 - clock[0]
    mine, ref = np.array(pairs).T
    return len(pairs), int((mine == ref).sum()), int(ref.sum()), clock[0], clock[1], wall


def path_rates(plain, seeds, B: int) -> tuple[dict, int, int]:
    """The batched oracle on each engine path (benchmarks/batched_speed.py's PATHS: the numpy step, the compiled
    step with obs["turn"], truth and rewards in numpy, the compiled step) labelling the same states in turn, a seeded :class:`Coin` driving
    on the compiled path: labels per CPU-second of each, and how many labels (of how many) the numpy step and the
    compiled step agree on."""
    from agents.batched_oracle import oracle_labels
    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from av_gym.sim import batched as engine
    from batched_speed import PATHS

    venv = BatchedLeftTurnVecEnv(*plain, B, action_repeat=5, actions="go_yield", pool=0)
    obs = venv.play(iter(seeds))
    coin, cpu, agree, n = Coin(seeds[0]), dict.fromkeys(PATHS, 0.0), 0, 0
    while not venv.idle.all():
        rows = np.nonzero(~venv.idle)[0]
        labels = {}
        for name, names in PATHS.items():
            with engine.using_kernels(names):
                c0 = time.process_time()
                labels[name] = oracle_labels(venv.engine, rows)[0]
                cpu[name] += time.process_time() - c0
        agree, n = agree + int((labels["numpy step"] == labels["compiled step"]).sum()), n + len(rows)
        obs, _, _, _ = venv.step(coin.predict(obs)[0])
    return {name: n / cpu[name] for name in PATHS}, agree, n


def agreement(recorded: dict, labels: dict) -> tuple[int, int, int, int]:
    """(decisions compared, agreeing, per-env GO count, episodes whose lengths differ)."""
    n = agree = go = differ = 0
    for seed, steps in recorded.items():
        mine = labels[seed]
        differ += len(mine) != len(steps)
        for (_, ref), lab in zip(steps, mine):
            n, agree, go = n + 1, agree + (ref == lab), go + ref
    return n, agree, go, differ


def main() -> None:
    parser = ToolParser(prog="benchmarks/oracle_labels.py", description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=120, help="episodes (decisions: ~20 each)")
    parser.add_argument("--seed", type=int, default=7_000_000, help="first seed (7,000,000+: used nowhere else)")
    parser.add_argument("--batch", type=int, default=64, help="envs labelled together on the batch")
    parser.add_argument("--flip", type=float, default=0.25, help="probability of flipping the rule's choice")
    parser.add_argument("--quick", action="store_true", help="12 episodes, batch 12 (a smoke run, ~1 min); with "
                        "--perceived: 2 episodes, batch 2")
    parser.add_argument("--drive", type=int, default=0, help="instead: the oracle drives this many episodes of --split")
    parser.add_argument("--split", default="test", choices=["train", "validation", "test"])
    parser.add_argument("--perceived", type=int, default=0, help="instead: this many episodes of the replica "
                        "labeller on turn_perceived (detector + tracker), checked against the per-env oracle")
    parser.add_argument("--paths", type=int, default=0, help="instead: this many episodes labelled on every engine "
                        "path (batched_speed.PATHS) in turn: labels / CPU-s of each")
    args = parser.parse_args()
    if args.paths > 0:
        print(f"load average before: {load()}", flush=True)
        rates, agree, n = path_rates(stacks(), list(range(args.seed, args.seed + args.paths)), args.batch)
        print(f"load average after: {load()}\n\nthe two paths' labels agree on {agree}/{n}\n")
        print("| batched oracle, engine path | labels / CPU-s |\n|---|---:|")
        for name, rate in rates.items():
            print(f"| {name} | {rate:.1f} |")
        return
    if args.quick and args.perceived > 0:  # the smoke form of --perceived: two episodes side by side
        args.perceived, args.batch = 2, 2
    if args.perceived > 0:
        print(f"load average before: {load()}", flush=True)
        n, agree, go, t_pe, t_rep, wall = perceived(args.perceived, args.batch, args.seed)
        print(f"load average after: {load()}\n\nreplica vs per-env oracle on turn_perceived states: {agree}/{n} "
              f"decisions agree = {agree / max(n, 1):.4f} (per-env GO on {go})\n")
        print("| oracle on turn_perceived | labels | labels/s (wall) |\n|---|---:|---:|")
        print(f"| per-env, one future per decision (deep copy of the tracker stack) | {n} | {n / t_pe:.1f} |")
        print(f"| replica, {args.batch} envs: the oracle alone | {n} | {n / t_rep:.1f} |")
        print(f"| replica, {args.batch} envs: driving the per-env stack + labelling (DAgger's rate) | {n} | "
              f"{n / wall:.1f} |")
        return
    if args.drive > 0:
        coll, succ, wall = drive(stacks(), args.split, args.drive, args.batch)
        print(f"| lookahead (batched oracle) | {args.split} | {args.drive} | {coll:.3f} | {succ:.3f} | {wall:.0f} s |")
        return
    if args.episodes < 1 or args.batch < 1 or not 0 <= args.flip <= 1:
        parser.error("--episodes and --batch must be >= 1 and --flip in [0, 1]")
    if args.quick:
        args.episodes, args.batch = 12, 12
    plain = stacks()
    seeds = range(args.seed, args.seed + args.episodes)
    print(f"load average before: {load()}", flush=True)
    recorded, w_pe, c_pe, n_pe = per_env(plain, seeds, args.flip, shortcut=True)
    print(f"per-env oracle (with the safe-path shortcut): {n_pe} labels in {w_pe:.1f} s", flush=True)
    k = max(1, args.episodes // 4)  # the shortcut-free per-env cost on a quarter of the episodes
    _, w_raw, c_raw, n_raw = per_env(plain, seeds[:k], args.flip, shortcut=False)
    labels, w_b, c_b, n_b = batched(plain, recorded, args.batch)
    n, agree, go, differ = agreement(recorded, labels)
    print(f"load average after: {load()}\n")
    print(f"agreement: {agree}/{n} decisions = {agree / max(n, 1):.4f} (per-env labels GO on {go}; "
          f"{differ} of {len(recorded)} episodes differ in length between the stacks)\n")
    print("| oracle | labels | labels/s (wall) | labels / CPU-s |")
    print("|---|---:|---:|---:|")
    print(f"| per-env, one future per decision | {n_raw} | {n_raw / w_raw:.1f} | {n_raw / c_raw:.1f} |")
    print(f"| per-env, safe-path shortcut (as training) | {n_pe} | {n_pe / w_pe:.1f} | {n_pe / c_pe:.1f} |")
    print(f"| batched, {args.batch} envs | {n_b} | {n_b / w_b:.1f} | {n_b / c_b:.1f} |")
    flips, total = SPAWN_FLIPS
    print(f"\nlabels that change when no vehicle still to spawn enters the GO future (information no sensor "
          f"carries): {flips}/{total} = {flips / max(total, 1):.4f}")


if __name__ == "__main__":
    main()
