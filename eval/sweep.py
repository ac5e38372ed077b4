"""Aggregate a Hydra multirun folder into one table and a robustness curve.

``python -m eval.sweep runs/multirun/<stamp> [--x shield.detector.miss_rate] [--metric collision]``

Every job of a ``python -m train -m ...`` or ``python -m eval -m ...`` sweep leaves ``<job>/results.csv`` (one
row per episode and agent) and ``<job>/.hydra/overrides.yaml``. Jobs are grouped by the overrides that vary across
the sweep, except the replicate keys (``seed``, ``train.eval_seed``): each job gives one mean per metric and agent,
and a group's cell is the mean over its replicates with a Student-t 95% interval over them, so the spread is
between seeds, not between episodes of one seed. Writes ``sweep.md``, ``sweep.csv`` and
``sweep_<metric>_vs_<x>.png`` into the multirun folder (or ``--out``)."""

from __future__ import annotations

import csv
import math
import textwrap
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from av_gym.atomic import csv_text, save_figure_atomic, write_text_atomic
from av_gym.errors import ConfigError
from av_gym.metrics import aggregate, format_ci, interval, kind_of, markdown_table, mean_ci, wilson_ci
from conf.cli import Extend, ToolParser, items

REPLICATE_KEYS = ("seed", "train.eval_seed")


try:
    from hydra.experimental.callback import Callback
except ImportError:  # pragma: no cover - hydra-core < 1.1
    Callback = object


class JobSetup(Callback):
    """Hydra callback (``hydra.callbacks.job_setup`` in conf/train.yaml and conf/eval.yaml) run at the start of
    every job, in the job's own process.

    The joblib launcher runs jobs in loky workers, which set the process-wide multiprocessing start method to
    ``loky``. A process started from there (SB3's SubprocVecEnv, eval's worker processes) is told to use that
    method, cannot (loky is not imported yet in the child) and dies with "cannot find context for 'loky'".
    Resetting it to the platform default makes a sweep job behave like a plain run."""

    def on_job_start(self, config: Any = None, **kwargs: Any) -> None:
        import multiprocessing as mp

        if mp.get_start_method(allow_none=True) not in (None, *mp.get_all_start_methods()):
            mp.set_start_method(None, force=True)
DEFAULT_METRIC = {"left_turn": "collision", "lane_keeping": "cte_mean_abs_m"}


@dataclass
class Job:
    path: Path
    overrides: dict[str, Any]
    scenario: str | None
    rows: list[dict] = field(default_factory=list)


def _parse_value(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def _parse_overrides(lines: list[str]) -> dict[str, Any]:
    out = {}
    for line in lines:
        key, sep, value = str(line).partition("=")
        # Launcher and other hydra.* settings say how a job ran, not what it measured.
        if not sep or key.startswith(("hydra.", "hydra/", "~")):
            continue
        out[key.lstrip("+")] = _parse_value(value)
    return out


def _read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        for k, v in row.items():
            if k == "agent":
                continue
            try:
                row[k] = float(v) if v != "" else math.nan
            except ValueError:
                pass
    return rows


def load_jobs(root: str | Path) -> tuple[list[Job], list[Path]]:
    """The finished jobs under a multirun folder, and the job folders that have no ``results.csv`` (failed,
    still running, or cancelled)."""
    root = Path(root)
    if not root.is_dir():
        raise ConfigError(f"{root} is not a folder")
    jobs, missing = [], []
    for ov in sorted(root.glob("**/.hydra/overrides.yaml")):
        job_dir = ov.parent.parent
        if ".submitit" in job_dir.parts:
            continue
        results = job_dir / "results.csv"
        if not results.is_file():
            missing.append(job_dir)
            continue
        cfg_path = job_dir / ".hydra" / "config.yaml"
        cfg = yaml.safe_load(cfg_path.read_text()) if cfg_path.is_file() else {}
        scenario = ((cfg or {}).get("env") or {}).get("name")
        jobs.append(Job(job_dir, _parse_overrides(yaml.safe_load(ov.read_text()) or []), scenario,
                        _read_rows(results)))
    if not jobs:
        raise ConfigError(f"no job under {root} has results.csv (was it a python -m train/eval -m sweep?)")
    return jobs, missing


def swept_keys(jobs: list[Job]) -> list[str]:
    """Overrides whose value differs between jobs, in the order they were given."""
    keys = list(dict.fromkeys(k for j in jobs for k in j.overrides))
    return [k for k in keys if len({repr(j.overrides.get(k)) for j in jobs}) > 1]


def _sort_key(v: Any) -> tuple:
    return (0, float(v), "") if isinstance(v, (int, float)) and not isinstance(v, bool) else (1, 0.0, str(v))


def summarise(jobs: list[Job], group_keys: list[str], replicate_keys: list[str], metrics: list[str],
              confidence: float = 0.95) -> tuple[list[dict], list[str]]:
    """One dict per (group values, agent): ``n_seeds``, ``episodes`` and per metric the mean over replicates,
    its interval bounds (``_lo``/``_hi``) and, for 0/1 episode metrics, a Wilson interval over all pooled
    episodes (``_pooled_lo``/``_pooled_hi``). Also returns warnings about the replicates."""
    per_job: dict[tuple, list[dict]] = {}
    episodes: dict[tuple, list[dict]] = {}
    for job in jobs:
        for agg in aggregate(job.rows, group_key="agent", metrics=metrics):
            key = (tuple(repr(job.overrides.get(k)) for k in group_keys), agg["agent"])
            per_job.setdefault(key, []).append(
                {"values": {k: job.overrides.get(k) for k in group_keys}, "agent": agg["agent"],
                 "replicate": tuple(job.overrides.get(k) for k in replicate_keys),
                 "seeds": frozenset(r.get("seed") for r in job.rows if r["agent"] == agg["agent"]
                                    and isinstance(r.get("seed"), float) and not math.isnan(r["seed"])),
                 **{m: agg[m] for m in metrics}})
            episodes.setdefault(key, []).extend(r for r in job.rows if r["agent"] == agg["agent"])
    binary = {m: kind_of(m) == "rate" for m in metrics}  # declared (av_gym/metrics/kinds.py), not guessed

    out, warnings = [], []
    for key, reps in per_job.items():
        eps = episodes[key]
        line: dict[str, Any] = {**reps[0]["values"], "agent": reps[0]["agent"], "n_seeds": len(reps),
                                "episodes": len(eps)}
        # One replicate has no seed-to-seed spread: its cell shows the interval over its episodes instead
        # (t for a mean, Wilson for a rate), named in ``interval`` so the table and the plot can say so.
        line["interval"] = "replicates" if len(reps) > 1 else "episodes"
        for m in metrics:
            mean, half = mean_ci([r[m] for r in reps], confidence)
            vals = np.array([r.get(m, math.nan) for r in eps], dtype=float)
            vals = vals[~np.isnan(vals)]
            line[m], line[m + "_lo"], line[m + "_hi"] = mean, mean - half, mean + half
            if len(reps) == 1 and not binary[m]:  # the interval over its episodes that the metric's kind calls for
                _, line[m + "_lo"], line[m + "_hi"] = interval(vals, kind_of(m), confidence)
            elif kind_of(m) in ("count", "duration", "nonnegative"):  # a t over few seeds may cross zero
                line[m + "_lo"] = max(line[m + "_lo"], 0.0)
            if binary[m]:
                # A rate cannot leave [0, 1]; the t interval over a few seeds can.
                line[m + "_lo"], line[m + "_hi"] = max(line[m + "_lo"], 0.0), min(line[m + "_hi"], 1.0)
                _, line[m + "_pooled_lo"], line[m + "_pooled_hi"] = wilson_ci(int(vals.sum()), int(vals.size),
                                                                              confidence)
                if len(reps) == 1:
                    line[m + "_lo"], line[m + "_hi"] = line[m + "_pooled_lo"], line[m + "_pooled_hi"]
        out.append(line)
        label = ", ".join(f"{k}={v}" for k, v in reps[0]["values"].items()) or "all jobs"
        if len(reps) > 1 and all(all(_same(r[m], reps[0][m]) for m in metrics) for r in reps):
            warnings.append(f"{label}, {reps[0]['agent']}: every replicate gave the same metrics, so the interval "
                            "is 0 wide (expected for a rule-based baseline; to replicate a rule-based agent, sweep "
                            "train.eval_seed, the episode seeds `python -m train` evaluates on, not seed)")
        # The same episode seeds in every replicate is a paired design (PPO seeds on one held-out set); seed
        # ranges that merely overlap (eval seed=0,1,2 with 20 episodes) make replicates share most episodes.
        sets = [r["seeds"] for r in reps]
        if any(a != b and a & b for i, a in enumerate(sets) for b in sets[i + 1:]):
            warnings.append(f"{label}, {reps[0]['agent']}: replicates share some episode seeds, so they are not "
                            "independent; space the seeds at least `episodes` apart")
    out.sort(key=lambda d: (*(_sort_key(d[k]) for k in group_keys), str(d["agent"])))
    return out, warnings


_EPISODE_NOTE = (" Cells with a single replicate (interval: episodes) show the interval over their episodes "
                 "instead: Wilson for a rate, a bootstrap for a non-negative quantity, t for a signed one; it measures episode-to-episode spread under one "
                 "seed, not seed-to-seed.")


def _same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


def table_markdown(summary: list[dict], group_keys: list[str], metrics: list[str], binary: dict[str, bool]) -> str:
    """One row per cell; an ``interval`` column (over ``replicates`` or ``episodes``) when any cell had a single
    replicate."""
    shown = ("interval",) if any(line["interval"] == "episodes" for line in summary) else ()
    cells = []
    for line in summary:
        cell = {k: line[k] for k in (*group_keys, "agent", "n_seeds", "episodes", *shown)}
        for m in metrics:
            cell[m] = format_ci(line[m], line[m + "_lo"], line[m + "_hi"], binary[m])
        cells.append(cell)
    return markdown_table(cells, [*group_keys, "agent", "n_seeds", "episodes", *shown, *metrics])


def plot_curve(summary: list[dict], x: str, metric: str, group_keys: list[str], path: Path, title: str,
               ylabel: str | None = None) -> Path:
    """``metric`` against swept parameter ``x``, one line per agent and value of the other swept parameters,
    error bars the interval over replicates."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    others = [k for k in group_keys if k != x]
    lines: dict[str, list[dict]] = {}
    for line in summary:
        label = ", ".join([str(line["agent"]), *(f"{k}={line[k]}" for k in others)])
        lines.setdefault(label, []).append(line)
    xs_all = sorted({repr(line[x]): line[x] for line in summary}.values(), key=_sort_key)
    numeric = all(_sort_key(v)[0] == 0 for v in xs_all)
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, pts in lines.items():
        pts = sorted(pts, key=lambda d: _sort_key(d[x]))
        xs = [float(p[x]) if numeric else xs_all.index(p[x]) for p in pts]
        ys = np.array([p[metric] for p in pts], dtype=float)
        lo = np.array([p[metric + "_lo"] for p in pts], dtype=float)
        hi = np.array([p[metric + "_hi"] for p in pts], dtype=float)
        err = np.vstack([np.nan_to_num(ys - lo), np.nan_to_num(hi - ys)])
        ax.errorbar(xs, ys, yerr=err, marker="o", capsize=4, label=label)
    if not numeric:
        ax.set_xticks(range(len(xs_all)), [str(v) for v in xs_all])
    ax.set_xlabel(x)
    ax.set_ylabel(ylabel or metric)
    ax.set_title(textwrap.fill(title, 80), fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure_atomic(fig, path, "--out", dpi=120)  # whole or as it was
    plt.close(fig)
    return path


def _write_csv(summary: list[dict], path: Path) -> None:
    write_text_atomic(path, csv_text(summary), "--out")


def sweep_report(root: str | Path, x: str | None = None, metric: str | None = None,
                 metrics: list[str] | None = None, replicate_keys: list[str] | None = None,
                 out: str | Path | None = None, plot: bool = True) -> dict:
    """Aggregate ``root`` (a multirun folder); returns the summary rows, the Markdown table and where the files
    went."""
    from eval.labels import swept_label
    from eval.report import HEADLINE

    jobs, missing = load_jobs(root)
    replicate_keys = list(REPLICATE_KEYS if replicate_keys is None else replicate_keys)
    swept = swept_keys(jobs)
    group_keys = [k for k in swept if k not in replicate_keys]
    for job in jobs:  # an agent is one line over the swept values, which its row labels also name (eval/labels.py)
        for r in job.rows:
            r["agent"] = swept_label(str(r["agent"]), group_keys)
    scenarios = {j.scenario for j in jobs}
    scenario = next(iter(scenarios)) if len(scenarios) == 1 else None
    available = list(dict.fromkeys(k for j in jobs for r in j.rows for k in r if k not in ("agent", "episode",
                                                                                           "seed")))
    if metrics is None:
        metrics = [m for m in HEADLINE.get(scenario, available) if m in available]
    metric = metric or DEFAULT_METRIC.get(scenario, metrics[0] if metrics else None)
    for m in (metric, *metrics):
        if m not in available:
            raise ConfigError(f"metric {m!r} is not in the jobs' results.csv; available: {available}")
    if metric not in metrics:
        metrics = [metric, *metrics]
    if x is None:
        numeric = [k for k in group_keys if all(_sort_key(j.overrides.get(k))[0] == 0 for j in jobs)]
        x = (numeric or group_keys or [None])[0]
    elif x not in group_keys:
        raise ConfigError(f"--x {x!r} was not swept (swept, not replicates: {group_keys})")

    summary, warnings = summarise(jobs, group_keys, replicate_keys, metrics)
    binary = {m: kind_of(m) == "rate" for m in metrics}
    table = table_markdown(summary, group_keys, metrics, binary)
    out_dir = Path(out) if out else Path(root)
    out_dir.mkdir(parents=True, exist_ok=True)
    _write_csv(summary, out_dir / "sweep.csv")
    n_seeds = sorted({line["n_seeds"] for line in summary})
    header = (f"# Sweep {Path(root).resolve().name}: {len(jobs)} jobs"
              f"{f', {len(missing)} without results' if missing else ''}\n\n"
              f"Grouped by {', '.join(group_keys) or '(nothing swept)'}; replicates: "
              f"{', '.join(k for k in replicate_keys if k in swept) or 'none'} ({'/'.join(map(str, n_seeds))} per "
              f"cell). Each cell is the mean over replicates of the per-replicate mean, with a Student-t 95% "
              f"interval over replicates (rates too, clipped to [0, 1]; sweep.csv adds a Wilson interval over "
              f"the pooled episodes)."
              f"{_EPISODE_NOTE if any(line['interval'] == 'episodes' for line in summary) else ''}\n")
    text = header + "\n" + table + "\n"
    for w in warnings:
        text += f"\n> warning: {w}\n"
    if missing:
        text += "\nJobs without results.csv: " + ", ".join(str(p) for p in missing) + "\n"
    png = None
    if plot and x is not None:
        png = out_dir / f"sweep_{metric}_vs_{x.replace('/', '_')}.png"
        # The overrides every job shared say what was held fixed; paths and display flags say nothing about that.
        fixed = [f"{k}={v}" for k, v in jobs[0].overrides.items() if k not in swept
                 and not k.startswith("paths.") and not k.endswith("progress_bar")]
        over = (f"{'/'.join(map(str, n_seeds))} replicates" if n_seeds != [1]
                else "episodes (one replicate per cell)")
        title = (f"{scenario or ''} {metric} vs {x}: mean ± 95% CI over {over}"
                 f"{'; ' + ' '.join(fixed) if fixed else ''}").strip()
        plot_curve(summary, x, metric, group_keys, png, title, f"{metric} (rate)" if binary[metric] else metric)
        text += f"\n![{metric} vs {x}]({png.name})\n"
    write_text_atomic(out_dir / "sweep.md", text, "--out")
    return {"summary": summary, "table": table, "warnings": warnings, "missing": missing, "markdown": text,
            "csv": out_dir / "sweep.csv", "md": out_dir / "sweep.md", "png": png, "x": x, "metric": metric}


def main(argv: list[str] | None = None) -> int:
    parser = ToolParser(prog="python -m eval.sweep", description=__doc__.split("\n\n")[0])
    parser.add_argument("multirun", help="a multirun folder, e.g. runs/multirun/20260101-120000")
    parser.add_argument("--x", help="swept parameter on the curve's x axis (default: the first numeric one)")
    parser.add_argument("--metric", help="metric on the curve (default: collision / cte_mean_abs_m)")
    parser.add_argument("--metrics", type=items(str),
                        help="table columns, [collision,success] (default: the scenario's headline)")
    parser.add_argument("--replicate", default=list(REPLICATE_KEYS), type=items(str),
                        help="overrides that are replicates, not groups, [seed,train.eval_seed] (default: %(default)s)")
    parser.add_argument("--out", help="output folder (default: the multirun folder)")
    parser.add_argument("--no-plot", action="store_true")
    args = parser.parse_args(argv)
    result = sweep_report(args.multirun, x=args.x, metric=args.metric, metrics=args.metrics,
                          replicate_keys=args.replicate, out=args.out, plot=not args.no_plot)
    print(result["markdown"])
    print(f"[sweep] table: {result['md']}  numbers: {result['csv']}" + (f"  curve: {result['png']}"
                                                                          if result["png"] else ""))
    return 0


if __name__ == "__main__":
    from av_gym.errors import run_cli

    run_cli(lambda: sys.exit(main()))  # a write that fails (a full disk): one line, exit 2
