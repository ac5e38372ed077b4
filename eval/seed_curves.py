"""Learning curves of several training seeds of one configuration, from each run's periodic evaluations.

    python -m eval.seed_curves runs/ppo_turn_s1 runs/ppo_turn_s2 runs/ppo_turn_s3 --out curves.png \
        [--label ppo_turn] [--repeat 5] [--milestone 0.75,0.05]

Reads ``<run>/eval.csv`` (written by :class:`train.callbacks.PeriodicEval`: agent decisions, wall-clock seconds and
the metrics of the fixed evaluation seeds) and draws success and collision against env steps (decisions ×
``--repeat``) and against wall-clock time: each seed thin, the mean across seeds thick with its 95 % CI (Student t
over the seeds). Prints, per seed, the first evaluation that reached each milestone (success ≥ s with collision ≤ c)
with its env steps and wall-clock seconds, and the curve's last values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from av_gym.atomic import save_figure_atomic
from conf.cli import Extend, ToolParser, items


def load(runs: list[str]) -> list[pd.DataFrame]:
    frames = []
    for run in runs:
        path = Path(run) / "eval.csv"
        if not path.is_file():
            raise SystemExit(f"error: {path} does not exist (train with train.eval_every > 0 to write it)")
        frames.append(pd.read_csv(path))
    return frames


def mean_ci(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over axis 0 and the half-width of its 95 % Student-t interval (0 for a single seed)."""
    from scipy import stats

    n = values.shape[0]
    mean = values.mean(axis=0)
    if n < 2:
        return mean, np.zeros_like(mean)
    return mean, stats.t.ppf(0.975, n - 1) * values.std(axis=0, ddof=1) / np.sqrt(n)


def milestones(frames: list[pd.DataFrame], targets: list[tuple[float, float]], repeat: int,
               names: list[str] | None = None) -> list[str]:
    """Per run (named by ``names``, default "seed run k"): the first evaluation reaching each target, and the last."""
    names = names or [f"seed run {k}" for k in range(len(frames))]
    lines = []
    for name, f in zip(names, frames):
        for s, c in targets:
            hit = f[(f.success >= s) & (f.collision <= c)]
            where = (f"{int(hit.steps.iloc[0]) * repeat:,} env steps, {hit.wall_clock_s.iloc[0]:.0f} s"
                     if len(hit) else "not reached")
            lines.append(f"{name}: success >= {s:.2f} at collision <= {c:.2f}: {where}")
        last = f.iloc[-1]
        lines.append(f"{name}: last evaluation at {int(last.steps) * repeat:,} env steps: collision "
                     f"{last.collision:.2f}, success {last.success:.2f}")
    return lines


def plot(frames: list[pd.DataFrame], out: Path, label: str, repeat: int, names: list[str] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = names or [f"seed run {k}" for k in range(len(frames))]
    n = min(len(f) for f in frames)  # evaluations every seed reached (same schedule)
    steps = frames[0].steps.to_numpy()[:n] * repeat
    wall = np.mean([f.wall_clock_s.to_numpy()[:n] for f in frames], axis=0)
    fig, axes = plt.subplots(2, 2, figsize=(10, 7), sharey="row")
    for row, metric in enumerate(("success", "collision")):
        values = np.array([f[metric].to_numpy()[:n] for f in frames])
        mean, ci = mean_ci(values)
        for col, x in enumerate((steps, wall)):
            ax = axes[row, col]
            for name, f in zip(names, frames):
                xs = f.steps.to_numpy() * repeat if col == 0 else f.wall_clock_s.to_numpy()
                ax.plot(xs, f[metric], lw=0.8, alpha=0.5, label=name)
            ax.plot(x, mean, lw=2.2, color="k", label=f"mean of {len(frames)}")
            ax.fill_between(x, np.clip(mean - ci, 0, 1), np.clip(mean + ci, 0, 1), color="k", alpha=0.15, label="95 % CI")
            ax.set_xlabel("env steps" if col == 0 else "wall-clock s (mean over seeds)")
            ax.set_ylabel(metric)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{label}: periodic evaluation on fixed held-out seeds")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    save_figure_atomic(fig, out, "--out", dpi=110)  # whole or as it was
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = ToolParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="run folders holding eval.csv")
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--label", default="")
    parser.add_argument("--repeat", type=int, default=5, help="env steps per agent decision (agent.action_repeat)")
    parser.add_argument("--milestone", action="append", default=[],
                        help="success,collision pair (repeatable); default 0.75,0.05 and 0.85,0.03")
    args = parser.parse_args(argv)
    targets = [tuple(float(v) for v in m.split(",")) for m in args.milestone] or [(0.75, 0.05), (0.85, 0.03)]
    frames = load(args.runs)
    names = [Path(run).name for run in args.runs]
    plot(frames, args.out, args.label or names[0], args.repeat, names)
    print("\n".join(milestones(frames, targets, args.repeat, names)))
    print(f"[seed_curves] {args.out}")


if __name__ == "__main__":
    from av_gym.errors import run_cli

    run_cli(main)  # a write that fails (a full disk): one line, exit 2
