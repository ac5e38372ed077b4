"""Training curves from TensorBoard event files as one PNG (for notes and papers, where TensorBoard is not at hand).

    python -m eval.curves runs/<run>/tb [more runs/.../tb ...] --out curves.png [--tags eval/success eval/collision]

One panel per scalar tag, one line per run (labelled by the run folder), x = environment steps.
"""

from __future__ import annotations

from pathlib import Path

from av_gym.atomic import save_figure_new
from conf.cli import ToolParser, out_figure_problem

DEFAULT_TAGS = ("eval/success", "eval/collision", "eval/interventions", "episode/success", "episode/collision",
                "eval/time_to_exit_s")


def read_scalars(tb_dir: str | Path) -> dict[str, list[tuple[int, float]]]:
    """``tag -> [(step, value), ...]`` from every event file under ``tb_dir`` (later files win on equal steps)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out: dict[str, dict[int, float]] = {}
    for events in sorted(Path(tb_dir).rglob("events.out.tfevents.*")):
        acc = EventAccumulator(str(events), size_guidance={"scalars": 0})
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            out.setdefault(tag, {}).update({e.step: e.value for e in acc.Scalars(tag)})
    return {tag: sorted(points.items()) for tag, points in out.items()}


def plot_curves(runs: dict[str, dict[str, list[tuple[int, float]]]], tags: list[str], out: str | Path) -> Path:
    """One panel per tag present in any run; returns the PNG path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    present = sorted({t for scalars in runs.values() for t in scalars})
    wanted, tags = tags, [t for t in tags if t in present]
    if not tags:
        raise SystemExit(f"error: none of the tags {list(wanted)} is in the event files given; they hold {present}")
    cols = min(3, len(tags))
    rows = (len(tags) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False)
    for ax, tag in zip(axes.ravel(), tags):
        for label, scalars in runs.items():
            if tag in scalars:
                steps, values = zip(*scalars[tag])
                ax.plot(steps, values, label=label, lw=1.4)
        ax.set_title(tag)
        ax.set_xlabel("steps (decisions if action_repeat > 1)")
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(tags):]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_figure_new(fig, out, "--out", dpi=110)  # a new file, whole; one that appeared meanwhile is kept
    plt.close(fig)
    return out


def main() -> None:
    parser = ToolParser(prog="python -m eval.curves", description=__doc__.splitlines()[0])
    parser.add_argument("tb_dirs", nargs="+", help="TensorBoard folders (runs/<run>/tb)")
    parser.add_argument("--out", default="curves.png", help="the figure, a new file (an existing one is refused)")
    parser.add_argument("--tags", nargs="+", default=None,
                        help=f"scalars to plot (default: those of {list(DEFAULT_TAGS)} the runs hold, else the "
                             "rollout/* returns SB3 writes from the first rollout on)")
    args = parser.parse_args()
    missing = [d for d in args.tb_dirs if not Path(d).is_dir()]
    if missing:
        parser.error(f"argument tb_dirs: {missing[0]} is not a folder")
    problem = out_figure_problem(args.out, "--out")
    if problem:  # before reading any event file: unwritable, a suffix matplotlib cannot write, or a file there
        parser.error(f"argument {problem}")
    runs = {Path(d).parent.name if Path(d).name == "tb" else Path(d).name: read_scalars(d) for d in args.tb_dirs}
    tags = args.tags
    if tags is None:  # a short run may have no episode or evaluation yet: show what SB3 logged instead
        present = {t for scalars in runs.values() for t in scalars}
        tags = [t for t in DEFAULT_TAGS if t in present] or sorted(t for t in present if t.startswith("rollout/"))
        tags = tags or list(DEFAULT_TAGS)
    print(f"[curves] {plot_curves(runs, tags, args.out)}")


if __name__ == "__main__":
    from av_gym.errors import run_cli

    run_cli(main)  # a write that fails (a full disk): one line, exit 2
