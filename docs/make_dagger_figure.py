"""DAgger students' curves: success and collision on the validation seeds after each round, against the labels
the oracle gave and against wall-clock, one line per run; or, with ``--curve``, the learning curve of the planner's
students against labels (log scale) beside the planner's own validation line.

    python docs/make_dagger_figure.py docs/dagger/rounds.csv [more rounds.csv ...] [--out docs/dagger.png]
    python docs/make_dagger_figure.py --curve docs/dagger/learning_curve.csv --out docs/dagger_learning_curve.png

A ``rounds.csv`` is what ``python -m train agent=dagger_turn`` writes beside its checkpoints (train/dagger.py), one
run per file (named by its folder); docs/dagger/rounds.csv and rounds_perceived.csv hold several runs, each row
prefixed by its ``run`` column (``s1``, ``perceived_s1``, ...).

``--curve CSV`` with rounds.csv files and ``--planner`` (an evaluation's results.csv of the planner on the
validation split) first writes CSV: one row per round of the runs ``--runs`` selects and one for the planner, each
with its validation episodes and Wilson 95 % intervals (a run's episodes from train.eval_n in the config.yaml
beside its rounds.csv, else ``--val-n``); it never writes over an existing CSV (the rounds it keeps are the record).
Without rounds.csv files it plots CSV as it is. ``--extend`` adds the rounds CSV does not hold yet (another training
seed's, or a resumed run's later rounds) to an existing CSV: its rows are kept as they are (a round it holds must
come back with the same values), the new rows go after their run's, before its planner row, and the file is
replaced at once (docs/dagger.md, "Learning curve").
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import csv
import fnmatch
import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from av_gym.atomic import save_figure_atomic, write_text_atomic  # noqa: E402
from conf.cli import ToolParser  # noqa: E402

CURVE_FIELDS = ("series", "run", "round", "labels", "val_episodes", "val_success", "success_lo", "success_hi",
                "val_collision", "collision_lo", "collision_hi")


def run_name(path: Path) -> str:
    """A one-run rounds.csv's name: its checkpoint folder's (``checkpoints/<run>/rounds.csv``), else the file's."""
    return path.parent.name if path.stem == "rounds" else path.stem.replace("rounds_", "")


def read(path: Path) -> dict[str, dict[str, list[float]]]:
    """Run name -> column -> values: the ``run`` column's runs, or the file's one run (:func:`run_name`)."""
    with open(path) as f:
        rows = list(csv.DictReader(f))
    runs: dict[str, list[dict]] = {}
    for r in rows:
        runs.setdefault(r.get("run") or run_name(path), []).append(r)
    return {name: {k: [float(r[k]) for r in got] for k in ("round", "labels", "wall_s", "val_success",
                                                            "val_collision", "drive_success", "drive_collision")}
            for name, got in runs.items()}


def plot_rounds(paths: list[str], out: str, sensors: str):
    """The runs' validation after each round against labels and against wall-clock (s); the legend below both
    panels (ten runs' twenty entries inside one covered its lines). Returns the figure."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    runs = [(name, d) for path in paths for name, d in read(Path(path)).items()]
    for k, (name, d) in enumerate(runs):
        for ax, x in zip(axes, ("labels", "wall_s")):
            ax.plot(d[x], d["val_success"], "o-", color=f"C{k}", label=f"{name} success")
            ax.plot(d[x], d["val_collision"], "s--", color=f"C{k}", label=f"{name} collision")
    axes[0].set_xlabel("teacher labels (aggregate)")
    axes[1].set_xlabel("wall-clock (s, 2 shared cores)")
    axes[0].set_ylabel("share of validation episodes")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(f"DAgger students ({sensors}) after each round, validation episodes")
    fig.tight_layout()
    # legend entries fill columns first: an even number of rows keeps each run's success and collision together
    rows = 2 * -(-len(runs) // 5)
    fig.legend(*axes[0].get_legend_handles_labels(), fontsize=7, loc="upper center", bbox_to_anchor=(0.5, 0.0),
               ncol=max(1, -(-2 * len(runs) // rows)), frameon=False)
    save_figure_atomic(fig, out, "--out", dpi=110, bbox_inches="tight")  # the canvas grown to hold the legend
    return fig


# ------------------------------------------------------------------------------------------- the learning curve
def point(series: str, run: str, rnd: str, labels: str, n: int, success: float, collision: float) -> dict:
    """One row of the curve's csv: shares of ``n`` validation episodes with their Wilson 95 % intervals."""
    from av_gym.metrics.stats import wilson_ci

    _, s_lo, s_hi = wilson_ci(round(success * n), n)
    _, c_lo, c_hi = wilson_ci(round(collision * n), n)
    return {"series": series, "run": run, "round": rnd, "labels": labels, "val_episodes": n,
            "val_success": f"{success:.4f}", "success_lo": f"{s_lo:.4f}", "success_hi": f"{s_hi:.4f}",
            "val_collision": f"{collision:.4f}", "collision_lo": f"{c_lo:.4f}", "collision_hi": f"{c_hi:.4f}"}


def val_episodes(path: Path, default: int) -> int:
    """train.eval_n of the run whose rounds.csv is ``path`` (its config.yaml beside it), else ``default``."""
    from omegaconf import OmegaConf

    config = path.parent / "config.yaml"
    if path.stem != "rounds" or not config.is_file():
        return default
    return int(OmegaConf.load(config).train.eval_n)


def planner_point(results: Path) -> dict:
    """The planner's row: its evaluation's episodes (an ``eval`` results.csv with one agent, validation split)."""
    with open(results) as f:
        rows = list(csv.DictReader(f))
    agents = sorted({r["agent"] for r in rows})
    splits = sorted({r.get("split", "validation") for r in rows})
    if len(agents) != 1 or splits != ["validation"]:
        raise ValueError(f"--planner: {results} must hold one agent on the validation split, got agents {agents}, "
                         f"splits {splits}")
    n = len(rows)
    return point("planner", agents[0], "", "", n, sum(float(r["success"]) for r in rows) / n,
                 sum(float(r["collision"]) for r in rows) / n)


def curve_rows(paths: list[str], runs: list[str], planner: Path | None, val_n: int) -> list[dict]:
    """The csv's rows: every validated round of the runs matching ``runs`` (fnmatch patterns), then the planner
    (none without ``planner``)."""
    out = []
    for path in map(Path, paths):
        n = val_episodes(path, val_n)
        for name, d in read(path).items():
            if not any(fnmatch.fnmatch(name, p) for p in runs):
                continue
            for k, labels, s, c in zip(d["round"], d["labels"], d["val_success"], d["val_collision"]):
                if s == s:  # NaN: a round without validation
                    out.append(point("student", name, str(int(k)), str(int(labels)), n, s, c))
    return [*out, planner_point(planner)] if planner is not None else out


def write_curve(rows: list[dict], path: Path) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CURVE_FIELDS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(path, buf.getvalue(), "--curve")


def plot_curve(rows: list[dict], out: str, highlight: list[str]) -> None:
    """Validation success and collision against labels (log x): each run's rounds (the runs matching
    ``highlight`` in colour with Wilson bars, the others grey), the planner as a line with its interval."""
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 4.0))
    students = [r for r in rows if r["series"] == "student"]
    names = list(dict.fromkeys(r["run"] for r in students))
    colours = iter(f"C{k}" for k in range(10))
    for name in names:
        got = [r for r in students if r["run"] == name]
        lit = any(fnmatch.fnmatch(name, p) for p in highlight)
        colour = next(colours) if lit else "0.6"
        for ax, key in zip(axes, ("success", "collision")):
            x, y = [float(r["labels"]) for r in got], [float(r[f"val_{key}"]) for r in got]
            err = [[v - float(r[f"{key}_lo"]) for v, r in zip(y, got)], [float(r[f"{key}_hi"]) - v
                                                                          for v, r in zip(y, got)]]
            ax.errorbar(x, y, yerr=err if lit else None, fmt="o-" if lit else ".-", color=colour, capsize=2,
                        lw=1.5 if lit else 0.8, label=f"{name} ({got[0]['val_episodes']} val. episodes)")
    for planner in (r for r in rows if r["series"] == "planner"):
        for ax, key in zip(axes, ("success", "collision")):
            ax.axhline(float(planner[f"val_{key}"]), color="k", lw=1.2,
                       label=f"{planner['run']} ({planner['val_episodes']} val. episodes)")
            ax.axhspan(float(planner[f"{key}_lo"]), float(planner[f"{key}_hi"]), color="k", alpha=0.08)
    for ax, key in zip(axes, ("success", "collision")):
        ax.set_xscale("log")
        ax.set_xlabel("teacher labels (aggregate)")
        ax.set_ylabel(f"validation {key}")
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle("The planner's students (turn_truth_memory) against labels: validation after each DAgger round")
    fig.tight_layout()
    save_figure_atomic(fig, out, "--out", dpi=110)


def read_curve(path: Path) -> list[dict]:
    with open(path) as f:
        rows = list(csv.DictReader(f))
    if not rows or set(CURVE_FIELDS) - set(rows[0]):
        raise ValueError(f"--curve: {path} is not a learning curve's csv (columns {', '.join(CURVE_FIELDS)})")
    return rows


def main() -> None:
    parser = ToolParser(prog="docs/make_dagger_figure.py", description=__doc__.splitlines()[0])
    parser.add_argument("rounds", nargs="*", help="rounds.csv files (one per run, or with a run column)")
    parser.add_argument("--out", default="runs/dagger.png", help="the figure (docs/dagger.png for the docs)")
    parser.add_argument("--sensors", default="turn_truth", help="what the students see, for the title")
    parser.add_argument("--curve", help="the learning curve's csv: written from the rounds.csv files and --planner "
                                        "when they are given (never over an existing file), else plotted")
    parser.add_argument("--planner", help="--curve: the planner's evaluation on the validation split (results.csv)")
    parser.add_argument("--runs", nargs="+", default=["*"], help="--curve: the runs to keep (fnmatch patterns)")
    parser.add_argument("--highlight", nargs="+", default=["*"], help="--curve: runs drawn in colour (the others "
                                                                      "grey)")
    parser.add_argument("--extend", action="store_true", help="--curve: add the rounds.csv files' rounds to the "
                                                               "existing CSV (its rows kept; new rounds only)")
    parser.add_argument("--val-n", type=int, default=200, help="--curve: validation episodes per round of a "
                                                                "rounds.csv without a config.yaml beside it")
    args = parser.parse_args()
    missing = [p for p in [*args.rounds, args.planner or ""] if p and not Path(p).is_file()]
    if missing:
        parser.error(f"no such file: {missing[0]}")
    if args.curve is None:
        if not args.rounds:
            parser.error("give rounds.csv files, or --curve CSV for the learning curve")
        plot_rounds(args.rounds, args.out, args.sensors)
    else:
        try:
            plot_curve(_curve(args, parser), args.out, args.highlight)
        except ValueError as exc:
            parser.error(str(exc))
    print(f"plot: {args.out}")


def _curve(args, parser) -> list[dict]:
    """The curve's rows: built from the rounds and written to ``--curve`` (a new file), or read from it."""
    path = Path(args.curve)
    if not args.rounds:
        if not path.is_file():
            parser.error(f"--curve: no such file: {path} (give rounds.csv files and --planner to write it)")
        return read_curve(path)
    if args.extend:
        return _extend(args, parser, path)
    if args.planner is None:
        parser.error("--curve with rounds.csv files needs --planner (the planner's validation results.csv)")
    if path.exists():
        parser.error(f"--curve: {path} exists; it is not written over (the rounds it keeps are the record): "
                     f"give a new path")
    rows = curve_rows(args.rounds, args.runs, Path(args.planner), args.val_n)
    write_curve(rows, path)
    print(f"curve: {path} ({len(rows)} points)")
    return rows


def _extend(args, parser, path: Path) -> list[dict]:
    """``--extend``: the existing curve's rows kept as they are; the rounds it does not hold yet (another training
    seed's, or the later rounds of a resumed run) added after their run's rows, before the planner row; written at
    once. A round it holds must come back with the same values (the csv is the record of untracked runs)."""
    if not path.is_file():
        parser.error(f"--extend: no such file: {path} (without --extend the rounds and --planner write a new one)")
    kept = read_curve(path)
    new = curve_rows(args.rounds, args.runs, None, args.val_n)
    held = {(r["run"], r["round"]): r for r in kept if r["series"] == "student"}
    for r in new:
        old = held.get((r["run"], r["round"]))
        if old is not None and any(str(old[k]) != str(r[k]) for k in CURVE_FIELDS):
            parser.error(f"--extend: {path} holds round {r['round']} of run {r['run']} with other values: its rows "
                         f"are the record; give the rounds.csv of the run it holds, or another run")
    new = [r for r in new if (r["run"], r["round"]) not in held]
    if not new:
        parser.error(f"--extend: no validated round in {', '.join(args.rounds)} that {path} does not hold matches "
                     f"--runs {' '.join(args.runs)}")
    students = [r for r in kept if r["series"] != "planner"]
    rows = [r for run in dict.fromkeys(r["run"] for r in [*students, *new])
            for r in [*(r for r in students if r["run"] == run), *(r for r in new if r["run"] == run)]]
    rows += [r for r in kept if r["series"] == "planner"]
    write_curve(rows, path)
    print(f"curve: {path} ({len(new)} points added, {len(rows)} in all)")
    return rows


if __name__ == "__main__":
    main()
