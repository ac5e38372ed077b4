"""Soak test: many episodes of the left turn with every sensor and the AEB shield, in one process.

    python benchmarks/soak.py [--episodes 2000] [--agent random|always_proceed] [--shield-mode perceived]
                              [--out runs/soak.md] [--tracemalloc]

Runs ``--episodes`` seeded episodes (seed, seed+1, ...) of ``env=left_turn sensors=full shield=aeb`` in a single env
instance, as a long evaluation or training run would, and reports:

- resident memory (RSS) growth between episode 100 (caches and lazy imports are warm by then) and the end, and
  the slope of a line fitted to it (target: < 50 MB in all);
- every exception an episode raised (target: none); the episode is abandoned, the env rebuilt, the run goes on;
- episodes/s and policy steps/s.

Exit status 0 when both targets are met, 1 otherwise.
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gc
import os
import platform
import signal
import sys
import time
import traceback
from pathlib import Path

import numpy as np

TARGET_GROWTH_MB = 50.0
WARM_EPISODE = 100


def rss_mb() -> tuple[float, str]:
    """Current resident set size in MB and where it came from."""
    try:
        import psutil

        return psutil.Process().memory_info().rss / 2**20, "psutil"
    except ImportError:
        pass
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20, "/proc/self/statm"
    except (OSError, ValueError, IndexError):
        # Peak, not current: growth read from it is an upper bound on the real growth.
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak / (2**20 if sys.platform == "darwin" else 2**10), "getrusage peak"


def build(overrides: list[str]):
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from av_gym.make import make_env

    GlobalHydra.instance().clear()
    with initialize_config_module("conf", version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    return make_env(cfg.env, cfg.sensors, cfg.shield), cfg


def make_policy(kind: str, env, seed: int):
    from agents import AlwaysProceed

    if kind == "always_proceed":
        policy = AlwaysProceed(env.unwrapped.cruise_action())
        return lambda obs: policy.act(obs)
    space = env.action_space
    space.seed(seed)  # the random agent is reproducible too
    return lambda obs: space.sample()


class _Stop(BaseException):  # not Exception: the per-episode handler must not swallow it
    pass


def _on_sigterm(signum, frame):  # noqa: ARG001
    raise _Stop


def _episode(env, act, seed: int, st: dict) -> None:
    """One episode on ``seed``, its steps, collision and intervention counted in ``st``."""
    obs, _ = env.reset(seed=seed)
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(act(obs))
        st["steps"] += 1
        done = terminated or truncated
    m = info.get("episode_metrics", {})
    st["collisions"] += int(m.get("collision", 0) or 0)
    st["interventions"] += int(m.get("intervention", 0) or 0)


def _sample(st: dict, n: int, t0: float) -> None:
    """The resident memory after ``n`` episodes (after a collection) and the time they took."""
    gc.collect()
    st["samples"].append((n, rss_mb()[0]))
    st["times"].append((n, time.perf_counter() - t0))


def soak(episodes: int, agent: str, shield_mode: str, seed: int, sample_every: int, use_tracemalloc: bool,
         progress: bool, on_report=None, report_every: int = 100) -> dict:
    """Run the soak; ``on_report(result)`` is called every ``report_every`` episodes and at the end, so a run
    that is stopped (Ctrl-C, SIGTERM) or too long to wait for still leaves figures for the episodes it did."""
    overrides = ["env=left_turn", "sensors=full", "shield=aeb", f"shield.mode={shield_mode}"]
    env, _ = build(overrides)
    act = make_policy(agent, env, seed)
    warm = min(WARM_EPISODE, max(episodes // 2, 0))
    st = {"samples": [], "errors": [], "steps": 0, "collisions": 0, "interventions": 0, "done": 0,
          "snap_warm": None}
    if use_tracemalloc:
        import tracemalloc

        tracemalloc.start(12)
    gc.collect()
    rss0, source = rss_mb()
    st["samples"].append((0, rss0))
    t0 = time.perf_counter()
    st["times"] = [(0, 0.0)]  # (episodes done, seconds): episodes/s over the run, beside the memory

    def result(final: bool) -> dict:
        samples = st["samples"]
        done = st["done"]
        elapsed = time.perf_counter() - t0
        w = warm if done >= warm else 0
        rss_warm = next((r for n, r in samples if n == w), rss0)
        late = np.array([(n, r) for n, r in samples if n >= w], dtype=float)
        slope = float(np.polyfit(late[:, 0], late[:, 1], 1)[0]) * 1000 if len(late) >= 3 else float("nan")
        top = []
        if final and use_tracemalloc and st["snap_warm"] is not None:
            import tracemalloc

            top = [str(d) for d in tracemalloc.take_snapshot().compare_to(st["snap_warm"], "lineno")[:10]]
        return {"episodes": episodes, "done": done, "final": final, "agent": agent, "shield_mode": shield_mode,
                "seed": seed, "steps": st["steps"], "elapsed_s": elapsed, "eps_per_s": done / elapsed,
                "steps_per_s": st["steps"] / elapsed, "rss_start_mb": rss0, "rss_warm_mb": rss_warm,
                "rss_end_mb": samples[-1][1], "rss_peak_mb": max(r for _, r in samples),
                "growth_mb": samples[-1][1] - rss_warm, "warm_episode": w, "slope_mb_per_1000": slope,
                "rss_source": source, "errors": list(st["errors"]), "collisions": st["collisions"],
                "interventions": st["interventions"], "samples": list(samples), "times": list(st["times"]),
                "tracemalloc_top": top}

    old = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        for i in range(episodes):
            ep_seed = seed + i
            try:
                _episode(env, act, ep_seed, st)
            except Exception as exc:  # noqa: BLE001 - a soak test records every failure and keeps going
                st["errors"].append({"episode": i, "seed": ep_seed, "error": f"{type(exc).__name__}: {exc}",
                                     "where": traceback.format_exc().strip().splitlines()[-3:]})
                env.close()
                env, _ = build(overrides)
                act = make_policy(agent, env, seed + 10**6 + i)
            st["done"] = n = i + 1
            if n == warm and use_tracemalloc:
                st["snap_warm"] = tracemalloc.take_snapshot()
            if n % sample_every == 0 or n == warm or n == episodes:
                _sample(st, n, t0)
                if progress and n % max(sample_every, episodes // 20 or 1) == 0:
                    print(f"[soak] {n}/{episodes} episodes, {time.perf_counter() - t0:.0f} s, "
                          f"RSS {st['samples'][-1][1]:.1f} MB, {len(st['errors'])} errors", flush=True)
            if on_report is not None and n % report_every == 0 and n < episodes:
                on_report(result(False))
    except (KeyboardInterrupt, _Stop):
        print(f"[soak] stopped after {st['done']} episodes", flush=True)
        if st["samples"][-1][0] != st["done"]:
            _sample(st, st["done"], t0)
    finally:
        signal.signal(signal.SIGTERM, old)
    env.close()
    r = result(True)
    if use_tracemalloc:
        import tracemalloc

        tracemalloc.stop()
    if on_report is not None:
        on_report(r)
    return r


# ------------------------------------------------------------------------------------------ the mixed soak (--mix)
# Many configurations and agents in one process, short
# episodes. Each entry: (env, sensors, shield, agent, extra overrides); built once, lazily, and reused (a leak shows
# as growth over the reuse), one of them closed and rebuilt every REBUILD_EVERY episodes (building and closing
# must not leak either).
MIX = [
    ("left_turn", "truth", "none", "random", []),
    ("left_turn", "truth", "none", "always_proceed", ["env.action=continuous"]),
    ("left_turn", "turn_truth", "none", "gap_acceptance", []),
    ("left_turn", "turn_truth", "none", "ppo_turn", []),
    ("left_turn", "turn_perceived", "none", "random", []),
    ("left_turn", "gnss_imu", "none", "random", ["env.policy_frequency=20", "env.simulation_frequency=40"]),
    ("left_turn", "detector", "aeb", "random", []),
    ("left_turn", "lidar", "none", "random", ["sensors.lidar.beams=180"]),
    ("left_turn", "localized", "none", "always_proceed", []),
    ("left_turn", "full", "aeb", "random", ["shield.mode=perceived"]),
    ("left_turn", "truth", "aeb", "random", ["env.mode=ccftap", "env.ccftap.dt=0.5"]),
    ("left_turn", "truth", "none", "random", ["env.action=continuous", "shield=aeb"]),
    ("lane_keeping", "truth", "none", "pid_paper", []),
    ("lane_keeping", "gnss_imu", "none", "random", []),
    ("lane_keeping", "camera_centre", "none", "random", []),
    ("lane_keeping", "lane_localized", "none", "random", []),
]
SHORT = {"left_turn": ["env.duration=4"], "lane_keeping": ["env.time_limit=4"]}  # s: many short episodes
REBUILD_EVERY = 50


def _finite(value) -> bool:
    """Every number in ``value`` (nested dicts/lists/arrays) is finite."""
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return all(_finite(v) for v in value)
    if isinstance(value, np.ndarray):
        return not np.issubdtype(value.dtype, np.floating) or bool(np.isfinite(value).all())
    if isinstance(value, (float, np.floating)):
        return bool(np.isfinite(value))
    return True


ALWAYS_DEFINED = ("return", "length", "duration_s", "mean_speed_mps")  # NaN in these is a bug, not "did not happen"


def _bad_metrics(metrics: dict) -> dict:
    """Episode metrics out of their declared kind's range (av_gym/metrics/kinds.py): infinite anywhere; NaN in a
    rate, a count or a quantity every episode has (elsewhere NaN means "did not happen", e.g. time_to_exit_s of
    an episode that never exited); a rate not 0/1; a negative count, duration or non-negative quantity."""
    from av_gym.metrics.kinds import kind_of

    bad = {}
    for name, value in metrics.items():
        if not isinstance(value, (int, float, np.integer, np.floating)) or isinstance(value, bool):
            continue
        kind, v = kind_of(name), float(value)
        if np.isinf(v) or (np.isnan(v) and (kind in ("rate", "count") or name in ALWAYS_DEFINED)) or \
                (kind == "rate" and not np.isnan(v) and v not in (0.0, 1.0)) or \
                (kind in ("count", "duration", "nonnegative") and v < 0):
            bad[name] = v
    return bad


def _mix_entry(entry: tuple, seed: int):
    """(env, act, label) for one MIX entry: rule-based and shipped agents through eval's own resolver."""
    env_name, sensors, shield, agent, extra = entry
    overrides = [f"env={env_name}", f"sensors={sensors}", f"shield={shield}", *SHORT[env_name], *extra]
    env, _ = build(overrides)
    label = " ".join([env_name, f"sensors={sensors}", f"shield={shield}", f"agent={agent}", *extra])
    if agent == "random":
        space = env.action_space
        space.seed(seed)
        return env, (lambda obs: space.sample()), (lambda: None), label
    import contextlib
    import io

    from eval.agents import resolve_agent

    with contextlib.redirect_stdout(io.StringIO()):
        _, policy = resolve_agent(agent, env, env_name, "checkpoints")
    return env, policy.act, policy.reset, label


def mix_soak(episodes: int, seed: int, sample_every: int, progress: bool) -> dict:
    """``episodes`` short episodes, each of a MIX entry drawn with a seeded generator; every exception, every
    non-finite reward or metric, and the memory growth after warm-up are recorded."""
    rng = np.random.default_rng(seed)
    built: dict[int, tuple] = {}
    st = {"errors": [], "nonfinite": [], "steps": 0, "per_entry": [0] * len(MIX), "rebuilds": 0,
          "obs_nonfinite": {}}
    warm = min(WARM_EPISODE, max(episodes // 2, 0))
    gc.collect()
    rss0, source = rss_mb()
    samples, times = [(0, rss0)], [(0, 0.0)]
    t0 = time.perf_counter()
    done = 0
    old = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        for i in range(episodes):
            k = int(rng.integers(len(MIX)))
            ep_seed = seed + i
            try:
                if k not in built:
                    built[k] = _mix_entry(MIX[k], seed + k)
                env, act, reset, label = built[k]
                obs, _ = env.reset(seed=ep_seed)
                reset()
                finished = False
                while not finished:
                    obs, reward, terminated, truncated, info = env.step(act(obs))
                    st["steps"] += 1
                    finished = terminated or truncated
                    if not _finite(reward):
                        raise FloatingPointError(f"reward {reward!r}")
                    if not _finite(obs):  # reported, not fatal: a sensor may mark a missing value so
                        st["obs_nonfinite"][label] = st["obs_nonfinite"].get(label, 0) + 1
                bad = _bad_metrics(info.get("episode_metrics", {}))
                if bad:
                    st["nonfinite"].append({"episode": i, "seed": ep_seed, "config": label, "metrics": bad})
                st["per_entry"][k] += 1
            except Exception as exc:  # noqa: BLE001 - a soak records every failure and keeps going
                st["errors"].append({"episode": i, "seed": ep_seed, "config": MIX[k],
                                     "error": f"{type(exc).__name__}: {exc}",
                                     "where": traceback.format_exc().strip().splitlines()[-3:]})
                if k in built:
                    built.pop(k)[0].close()
            done = i + 1
            if done % REBUILD_EVERY == 0 and built:  # close and rebuild one stack: its memory must come back
                j = sorted(built)[int(rng.integers(len(built)))]
                built.pop(j)[0].close()
                st["rebuilds"] += 1
            if done % sample_every == 0 or done == warm or done == episodes:
                gc.collect()
                samples.append((done, rss_mb()[0]))
                times.append((done, time.perf_counter() - t0))
                if progress and done % max(sample_every, episodes // 20 or 1) == 0:
                    print(f"[soak] {done}/{episodes} episodes, {time.perf_counter() - t0:.0f} s, RSS "
                          f"{samples[-1][1]:.1f} MB, {len(st['errors'])} errors, {len(st['nonfinite'])} non-finite",
                          flush=True)
    except (KeyboardInterrupt, _Stop):
        print(f"[soak] stopped after {done} episodes", flush=True)
    finally:
        signal.signal(signal.SIGTERM, old)
        for env, *_ in built.values():
            env.close()
    elapsed = time.perf_counter() - t0
    w = warm if done >= warm else 0
    rss_warm = next((r for n, r in samples if n == w), rss0)
    late = np.array([(n, r) for n, r in samples if n >= w], dtype=float)
    slope = float(np.polyfit(late[:, 0], late[:, 1], 1)[0]) * 1000 if len(late) >= 3 else float("nan")
    return {"mix": True, "episodes": episodes, "done": done, "seed": seed, "steps": st["steps"],
            "elapsed_s": elapsed, "eps_per_s": done / max(elapsed, 1e-9), "rss_start_mb": rss0,
            "rss_warm_mb": rss_warm, "rss_end_mb": samples[-1][1], "rss_peak_mb": max(r for _, r in samples),
            "growth_mb": samples[-1][1] - rss_warm, "warm_episode": w, "slope_mb_per_1000": slope,
            "rss_source": source, "errors": st["errors"], "nonfinite": st["nonfinite"],
            "per_entry": st["per_entry"], "rebuilds": st["rebuilds"], "obs_nonfinite": st["obs_nonfinite"],
            "samples": samples, "times": times, "final": True}


def mix_report(r: dict) -> str:
    ok_mem, ok_err, ok_nan = r["growth_mb"] < TARGET_GROWTH_MB, not r["errors"], not r["nonfinite"]
    rows = [
        ("episodes done", f"{r['done']} of {r['episodes']} (seeds {r['seed']}..{r['seed'] + r['done'] - 1})", ""),
        ("configurations", f"{len(MIX)} (env x sensors x shield x agent), drawn per episode; "
                           f"{r['rebuilds']} stacks closed and rebuilt", ""),
        ("policy steps", f"{r['steps']}", ""),
        ("wall time", f"{r['elapsed_s']:.0f} s ({r['eps_per_s']:.2f} episodes/s)", ""),
        (f"RSS at start / episode {r['warm_episode']} / end",
         f"{r['rss_start_mb']:.1f} / {r['rss_warm_mb']:.1f} / {r['rss_end_mb']:.1f} MB", ""),
        (f"RSS growth, episode {r['warm_episode']} to end", f"{r['growth_mb']:+.1f} MB "
         f"(slope {r['slope_mb_per_1000']:+.2f} MB per 1000 episodes)",
         f"{'PASS' if ok_mem else 'FAIL'} (< {TARGET_GROWTH_MB:.0f} MB)"),
        ("exceptions", f"{len(r['errors'])}", f"{'PASS' if ok_err else 'FAIL'} (none)"),
        ("non-finite rewards, metrics out of their kind's range", f"{len(r['nonfinite'])}",
         f"{'PASS' if ok_nan else 'FAIL'} (none)"),
    ]
    lines = ["| quantity | value | target |", "| --- | --- | --- |"] + [f"| {a} | {b} | {c} |" for a, b, c in rows]
    lines += ["", "| configuration | episodes |", "| --- | --- |"]
    lines += [f"| {' '.join([e[0], 'sensors=' + e[1], 'shield=' + e[2], 'agent=' + e[3], *e[4]])} | {n} |"
              for e, n in zip(MIX, r["per_entry"])]
    if r["obs_nonfinite"]:
        lines.append("\nSteps whose observation held a non-finite value (reported, not a failure): "
                     + ", ".join(f"{k}: {v}" for k, v in r["obs_nonfinite"].items()))
    for e in r["errors"][:20]:
        lines.append(f"\n- episode {e['episode']} (seed {e['seed']}, {e['config']}): {e['error']}")
    for e in r["nonfinite"][:20]:
        lines.append(f"\n- episode {e['episode']} (seed {e['seed']}, {e['config']}): out of range {e['metrics']}")
    lines.append(f"\nRSS from {r['rss_source']}, sampled after gc.collect(); Python {platform.python_version()}, "
                 f"{platform.machine()}, {os.cpu_count()} CPUs.")
    return "\n".join(lines)


def report(r: dict) -> str:
    ok_mem = r["growth_mb"] < TARGET_GROWTH_MB
    ok_err = not r["errors"]
    rows = [
        ("episodes done", f"{r['done']} of {r['episodes']} (seeds {r['seed']}..{r['seed'] + r['done'] - 1})"
         + ("" if r["done"] == r["episodes"] else (" - still running" if not r["final"] else " - stopped early")),
         ""),
        ("stack", f"left_turn (traffic), sensors=full, shield=aeb mode={r['shield_mode']}, agent={r['agent']}", ""),
        ("policy steps", f"{r['steps']}", ""),
        ("wall time", f"{r['elapsed_s']:.0f} s", ""),
        ("episodes/s", f"{r['eps_per_s']:.2f}", ""),
        ("policy steps/s", f"{r['steps_per_s']:.1f}", ""),
        ("RSS at start / episode "
         f"{r['warm_episode']} / end", f"{r['rss_start_mb']:.1f} / {r['rss_warm_mb']:.1f} / {r['rss_end_mb']:.1f} MB",
         ""),
        ("RSS peak (sampled)", f"{r['rss_peak_mb']:.1f} MB", ""),
        (f"RSS growth, episode {r['warm_episode']} to end", f"{r['growth_mb']:+.1f} MB",
         f"{'PASS' if ok_mem else 'FAIL'} (< {TARGET_GROWTH_MB:.0f} MB)"),
        ("fitted slope after warm-up", f"{r['slope_mb_per_1000']:+.2f} MB per 1000 episodes", ""),
        ("exceptions", f"{len(r['errors'])}", f"{'PASS' if ok_err else 'FAIL'} (none)"),
        ("collisions / shield interventions", f"{r['collisions']} / {r['interventions']}", ""),
    ]
    lines = ["| quantity | value | target |", "| --- | --- | --- |"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    for e in r["errors"][:20]:
        lines.append(f"\n- episode {e['episode']} (seed {e['seed']}): {e['error']}")
    if r["tracemalloc_top"]:
        lines.append("\nLargest allocation growth after warm-up (tracemalloc):\n")
        lines += [f"    {t}" for t in r["tracemalloc_top"]]
    lines.append(f"\nRSS from {r['rss_source']}, sampled after gc.collect(); Python {platform.python_version()}, "
                 f"{platform.machine()}, {os.cpu_count()} CPUs.")
    return "\n".join(lines)


def plot(r: dict, png: Path) -> None:
    """RSS and episodes/s against episodes done: a leak is a slope, a slowdown a falling rate."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n, rss = np.array(r["samples"], dtype=float).T
    tn, ts = np.array(r["times"], dtype=float).T
    fig, (a, b) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    a.plot(n, rss, ".-", ms=2)
    a.axvline(r["warm_episode"], color="grey", ls=":", label=f"warm-up ends (episode {r['warm_episode']})")
    a.set_ylabel("RSS (MB)")
    a.set_title(f"Soak: left_turn, sensors=full, shield=aeb ({r['shield_mode']}), agent={r['agent']}")
    a.legend(loc="lower right")
    rate = np.diff(tn) / np.maximum(np.diff(ts), 1e-9)
    b.step(tn[1:], rate, where="pre")
    b.set_ylabel("episodes/s (per sample)")
    b.set_xlabel("episodes done")
    b.set_ylim(bottom=0)
    fig.tight_layout()
    from av_gym.atomic import save_figure_atomic

    save_figure_atomic(fig, png, "--out", dpi=110)  # whole or as it was (this run's own figure, checked new at start)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from conf.cli import ToolParser

    parser = ToolParser(prog="benchmarks/soak.py", description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=2000)
    parser.add_argument("--agent", choices=("random", "always_proceed"), default="random")
    parser.add_argument("--shield-mode", choices=("ground_truth", "perceived"), default="perceived")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sample-every", type=int, default=10, help="episodes between RSS samples")
    parser.add_argument("--out", help="also write the report as Markdown here, a new file, and beside it "
                                      "<stem>_samples.csv and <stem>_memory.png (e.g. runs/soak.md; the committed "
                                      "report is in docs/performance.md)")
    parser.add_argument("--tracemalloc", action="store_true", help="list the allocations that grew (slow)")
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--mix", action="store_true", help="many configurations and agents, short episodes: "
                                                            "exceptions, non-finite values, memory")
    parser.add_argument("--quick", action="store_true", help="--mix on 48 episodes (a test's size)")
    args = parser.parse_args(argv)
    if args.quick:
        args.mix, args.episodes, args.sample_every = True, 48, 8
    if args.episodes < 1:
        parser.error("--episodes must be >= 1")
    if args.out:  # before the run: files already there (a user's, an earlier report) are never replaced
        from av_gym.atomic import new_paths_or_exit

        out = Path(args.out)
        new_paths_or_exit((out, "--out"), *(() if args.mix else (
            (out.with_name(out.stem + "_samples.csv"), "--out (its samples)"),
            (out.with_name(out.stem + "_memory.png"), "--out (its memory plot)"))))
    cmd = "python benchmarks/soak.py " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.mix:
        r = mix_soak(args.episodes, args.seed, max(args.sample_every, 1), not args.quiet)
        text = mix_report(r)
        print("\n" + text)
        if args.out:
            from av_gym.atomic import write_new_or_exit

            write_new_or_exit(args.out, f"# Mixed soak\n\n`{cmd}`\n\n{text}\n", "--out")
        # the quick run is too short for a memory figure after warm-up: it checks exceptions and values only
        memory_ok = args.quick or r["growth_mb"] < TARGET_GROWTH_MB
        return 0 if memory_ok and not r["errors"] and not r["nonfinite"] and r["done"] == r["episodes"] else 1

    def write(r: dict) -> None:
        if not args.out:
            return
        from av_gym.atomic import write_text_atomic

        curve = ", ".join(f"{n}: {m:.0f}" for n, m in r["samples"][:: max(len(r["samples"]) // 20, 1)])
        # rewritten every 100 episodes, each time whole (a hidden temporary file beside it, never <stem>.tmp: a
        # name the user may own); all three were checked new before the run
        write_text_atomic(args.out, f"# Soak test\n\n`{cmd}`\n\n{report(r)}\n\nRSS (MB) by episodes done: "
                                    f"{curve}\n", "--out")
        out = Path(args.out)
        rows = dict(r["times"])
        write_text_atomic(out.with_name(out.stem + "_samples.csv"), "episodes,rss_mb,elapsed_s\n" + "".join(
            f"{n},{m:.2f},{rows.get(n, float('nan')):.1f}\n" for n, m in r["samples"]), "--out")
        plot(r, out.with_name(out.stem + "_memory.png"))

    r = soak(args.episodes, args.agent, args.shield_mode, args.seed, max(args.sample_every, 1), args.tracemalloc,
             not args.quiet, on_report=write)
    print("\n" + report(r))
    passed = r["growth_mb"] < TARGET_GROWTH_MB and not r["errors"] and r["done"] == r["episodes"]
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
