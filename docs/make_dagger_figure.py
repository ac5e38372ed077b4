"""DAgger students' curves: success and collision on the validation seeds after each round, against the labels
the oracle gave and against wall-clock, one line per run.

    python docs/make_dagger_figure.py docs/dagger/rounds.csv [more rounds.csv ...] [--out docs/dagger.png]

A ``rounds.csv`` is what ``python -m train agent=dagger_turn`` writes beside its checkpoints (train/dagger.py), one
run per file (named by the file); docs/dagger/rounds.csv and rounds_perceived.csv hold several runs, each row
prefixed by its ``run`` column (``s1``, ``perceived_s1``, ...).
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import csv

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from av_gym.atomic import save_figure_atomic  # noqa: E402
from conf.cli import ToolParser  # noqa: E402


def read(path: Path) -> dict[str, dict[str, list[float]]]:
    """Run name -> column -> values: the ``run`` column's runs, or the file's one run named by the file."""
    with open(path) as f:
        rows = list(csv.DictReader(f))
    runs: dict[str, list[dict]] = {}
    for r in rows:
        runs.setdefault(r.get("run") or path.stem.replace("rounds_", ""), []).append(r)
    return {name: {k: [float(r[k]) for r in got] for k in ("labels", "wall_s", "val_success", "val_collision",
                                                            "drive_success", "drive_collision")}
            for name, got in runs.items()}


def main() -> None:
    parser = ToolParser(prog="docs/make_dagger_figure.py", description=__doc__.splitlines()[0])
    parser.add_argument("rounds", nargs="+", help="rounds.csv files (one per run)")
    parser.add_argument("--out", default="runs/dagger.png", help="the figure (docs/dagger.png for the docs)")
    parser.add_argument("--sensors", default="turn_truth", help="what the students see, for the title")
    args = parser.parse_args()
    missing = [p for p in args.rounds if not Path(p).is_file()]
    if missing:
        parser.error(f"no such rounds.csv: {missing[0]}")
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    runs = [(name, d) for path in args.rounds for name, d in read(Path(path)).items()]
    for k, (name, d) in enumerate(runs):
        for ax, x in zip(axes, ("labels", "wall_s")):
            ax.plot(d[x], d["val_success"], "o-", color=f"C{k}", label=f"{name} success")
            ax.plot(d[x], d["val_collision"], "s--", color=f"C{k}", label=f"{name} collision")
    axes[0].set_xlabel("teacher labels (aggregate)")
    axes[1].set_xlabel("wall-clock (s, 2 shared cores)")
    axes[0].set_ylabel("share of validation episodes")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7, loc="center right")
    fig.suptitle(f"DAgger students ({args.sensors}) after each round, validation episodes")
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    save_figure_atomic(fig, args.out, "--out", dpi=110)
    print(f"plot: {args.out}")


if __name__ == "__main__":
    main()
