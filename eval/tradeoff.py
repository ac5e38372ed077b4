"""Collision vs success of left-turn drivers, one point per agent, from evaluation rows.

    python -m eval.tradeoff runs/eval/a/results.csv runs/eval/b/results.csv --out tradeoff.png \
        [--point "lookahead (oracle)=0.01,0.92"] [--rule-sweep 2,3,4,6,8 --episodes 300 --seed 1000000]

Each ``results.csv`` is what ``python -m eval`` writes (one row per episode); every agent label in them becomes a
point with 95 % Wilson intervals on both axes. ``--point`` adds a point measured elsewhere (label=collision,success).
``--rule-sweep`` first evaluates the gap-acceptance rule (``conf/agent/gap_acceptance.yaml``'s miss distance) at each
``t_gap`` (s) on ``--episodes`` seeds from ``--seed`` and adds the rule's curve; its rows go beside the PNG
(``<out>.rule_sweep.csv``; given back as a results file, those rows draw the curve without re-running it). A file at
``--out`` or at its sweep file is replaced only with ``--overwrite`` (checked before any episode, as is the figure's
suffix). ``--relabel agent=label`` renames an agent of the rows. The sweep plays on the batched engine (``--n-envs``
episodes at a time; the per-env rows within the engine's equivalence, docs/performance.md), so 500 episodes per
threshold cost about a minute. Labels with the same name before ``#`` (``ppo_turn#s1``) are drawn in one colour, their
mean as a larger marker.

The rows must be one seed set: an agent's seed given twice (the same run named in two files) or agents on different
seeds (a 2,800,000+ run beside a 2,000,000+ one) are refused in one line unless ``--mixed-seeds``, since a point
compared with another on other seeds reads as a difference of drivers. ``--named-only`` leaves out agents given by
path (``checkpoints/reference/seeds/<agent>/s2``: the other training seeds of a results folder), one point per named
agent. The points drawn go beside the PNG (``<out>.points.csv``: label, n, rates, 95 % intervals, seeds, files),
and the PNG's metadata holds that file's sha256, so a figure can be checked against the rows it came from.
"""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path

import numpy as np

from av_gym.metrics.stats import wilson_ci
from av_gym.seeds import SPLITS
from av_gym.atomic import csv_text, save_figure, write_text_atomic, write_text_new
from conf.cli import ToolParser, held_outputs_problem, items, number, out_figure_problem


def read_rows(paths: list[str]) -> list[dict]:
    """Every row of each ``results.csv``, its file under ``"_file"`` (as given)."""
    rows = []
    for path in paths:
        if not Path(path).is_file():
            raise SystemExit(f"error: {path} does not exist (python -m eval writes results.csv in its out_dir)")
        with open(path, newline="") as f:
            rows += [{**r, "_file": path} for r in csv.DictReader(f)]
    return rows


def seeds_problem(rows: list[dict], mixed: bool = False) -> str:
    """'' when every agent's rows are distinct seeds and (unless ``mixed``) all agents share one seed set; else the
    one line saying which agent and files differ. Rows without a ``seed`` column are not checked."""
    by_label: dict[str, dict[int, str]] = {}
    for r in rows:
        if r.get("seed") in (None, ""):
            continue
        mine = by_label.setdefault(r["agent"], {})
        seed = int(r["seed"])
        if seed in mine:
            return (f"{r['agent']} has seed {seed} twice (in {mine[seed]} and {r.get('_file', '?')}): name each "
                    "evaluation once")
        mine[seed] = r.get("_file", "?")
    if mixed or len(by_label) < 2:
        return ""
    (first, ref), *others = by_label.items()
    for label, mine in others:
        if set(mine) != set(ref):
            return (f"{label} ({_span(mine)}, {sorted(set(mine.values()))[0]}) is not on the seeds of {first} "
                    f"({_span(ref)}, {sorted(set(ref.values()))[0]}): name results of one seed set, or give "
                    "--mixed-seeds")
    return ""


def _span(seeds: dict[int, str]) -> str:
    return f"{len(seeds)} seeds {min(seeds)}-{max(seeds)}"


def rule_sweep(t_gaps: list[float], episodes: int, seed: int, n_envs: int = 250) -> list[dict]:
    """The gap-acceptance rule at each ``t_gap`` on the left turn's traffic, the same seeds for every threshold,
    ``n_envs`` episodes at a time on the batched engine."""
    from agents.go_yield import GapAcceptance
    from eval.agents import compose_group, load_agent_config
    from eval.batched import play_batched

    miss = float(load_agent_config("gap_acceptance")["miss"])
    stack = [compose_group("env", "left_turn"), compose_group("sensors", "turn_truth"), compose_group("shield", "none")]
    rows = []
    for t_gap in t_gaps:
        rows += play_batched(*stack, GapAcceptance(t_gap=t_gap, miss=miss), range(seed, seed + episodes), n_envs,
                             f"gap_acceptance t_gap={t_gap:g}s")
    return rows


def points(rows: list[dict]) -> dict[str, tuple]:
    """label → (collision, success, (c_lo, c_hi), (s_lo, s_hi), n)."""
    out = {}
    for label in dict.fromkeys(r["agent"] for r in rows):
        mine = [r for r in rows if r["agent"] == label]
        n = len(mine)
        c = sum(float(r["collision"]) for r in mine)
        s = sum(float(r["success"]) for r in mine)
        c_mean, c_lo, c_hi = wilson_ci(int(round(c)), n)
        s_mean, s_lo, s_hi = wilson_ci(int(round(s)), n)
        out[label] = (c_mean, s_mean, (c_lo, c_hi), (s_lo, s_hi), n)
    return out


POINT_COLUMNS = ["label", "n", "collision", "success", "collision_lo", "collision_hi", "success_lo", "success_hi",
                 "seed_first", "seed_last", "files"]


def point_rows(pts: dict[str, tuple], rows: list[dict]) -> list[dict]:
    """The sidecar's rows (``<out>.points.csv``): each point as drawn (rates and 95 % Wilson bounds, full
    precision), its seeds' first and last (blank where the rows have none) and the files its rows came from
    (``;``-joined; ``--point`` for a point given on the command line)."""
    out = []
    for label, (c, s, (c_lo, c_hi), (s_lo, s_hi), n) in pts.items():
        mine = [r for r in rows if r["agent"] == label]
        seeds = [int(r["seed"]) for r in mine if r.get("seed") not in (None, "")]
        files = ";".join(dict.fromkeys(r.get("_file", "") for r in mine)) if mine else "--point"
        out.append(dict(zip(POINT_COLUMNS, [label, n, repr(float(c)), repr(float(s)), repr(float(c_lo)),
                                            repr(float(c_hi)), repr(float(s_lo)), repr(float(s_hi)),
                                            min(seeds) if seeds else "", max(seeds) if seeds else "", files])))
    return out


ZOOM = (0.12, 0.6)  # the zoom panel: collision <= 0.12 and success >= 0.6, where the learned drivers crowd


def plot(pts: dict[str, tuple], rule: list[str], out: Path, title: str, overwrite: bool = False,
         metadata: dict[str, str] | None = None) -> None:
    """``metadata``: the PNG's text fields (the sidecar's sha256). The whole plane on the left; on the right the crowded corner of low collision and high success (ZOOM), each
    agent's name written where it can be read (in the left panel only the points outside that corner are named)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    groups: dict[str, list[str]] = {}
    for label in pts:
        groups.setdefault(label.split("#")[0], []).append(label)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    if len(groups) > len(colours):  # the default cycle repeats after 10: two agents would share a colour
        colours = [plt.get_cmap("tab20")(i) for i in range(20) if i not in (14, 15)]  # its greys are the rule's
    centre = {g: (np.mean([pts[x][0] for x in ls]), np.mean([pts[x][1] for x in ls])) for g, ls in groups.items()}
    inside = {g for g, (c, s) in centre.items() if c <= ZOOM[0] and s >= ZOOM[1]}
    fig, axes = plt.subplots(1, 2 if inside else 1, figsize=(14, 6) if inside else (7.5, 6), squeeze=False)
    for panel, ax in enumerate(axes[0]):
        zoom = panel == 1
        if rule:  # the rule's trade-off as a line, thresholds in order
            xs, ys = [pts[k][0] for k in rule], [pts[k][1] for k in rule]
            ax.plot(xs, ys, "-", color="0.6", zorder=1, label=None if zoom else "gap_acceptance, t_gap swept")
        for k, (group, labels) in enumerate(groups.items()):
            colour = "0.4" if labels[0] in rule else colours[k % len(colours)]
            for label in labels:
                c, s, (c_lo, c_hi), (s_lo, s_hi), _ = pts[label]
                ax.errorbar(c, s, xerr=[[c - c_lo], [c_hi - c]], yerr=[[s - s_lo], [s_hi - s]], fmt="o", ms=4,
                            color=colour, alpha=0.6 if len(labels) > 1 else 1.0, capsize=2, zorder=2)
            cs, ss = centre[group]
            ax.plot(cs, ss, "D" if len(labels) > 1 else "o", ms=9 if len(labels) > 1 else 5, color=colour,
                    zorder=3, label=group if labels[0] not in rule and not zoom else None)
            if zoom == (group in inside):
                name = group.replace("gap_acceptance t_gap=", "t_gap ") if labels[0] in rule else group
                ax.annotate(name, (cs, ss), textcoords="offset points", xytext=(6, 4), fontsize=8, color=colour)
        ax.set_xlabel("collision rate (95 % Wilson interval)")
        ax.grid(alpha=0.3)
        if zoom:
            cs = [centre[g][0] for g in inside]
            ss = [centre[g][1] for g in inside]
            ax.set_xlim(-0.005, max(cs) + 0.03)
            ax.set_ylim(min(ss) - 0.04, max(ss) + 0.03)
            ax.set_title("zoom: the low-collision, high-success corner", fontsize=10)
        else:
            ax.set_ylabel("success rate (arrived within the time limit)")
            ax.set_xlim(left=-0.01)
            ax.legend(fontsize=8, loc="best")  # the empty corner: points move with what is plotted
            ax.set_title(title, fontsize=10)
            if inside:
                ax.add_patch(Rectangle((-0.005, ZOOM[1]), ZOOM[0] + 0.005, 1.0 - ZOOM[1], fill=False, ls="--",
                                       color="0.5", lw=0.8))
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, out, "--out", overwrite, dpi=110, metadata=metadata)  # whole or as it was; a file there kept unless --overwrite
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = ToolParser(prog="python -m eval.tradeoff", description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="*", help="results.csv files of python -m eval")
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--point", action="append", default=[], help='"label=collision,success"')
    parser.add_argument("--rule-sweep", default=[], type=items(float, low=0), help="t_gap values (s), [2,4,8]")
    parser.add_argument("--episodes", type=number(int, low=1), default=300, help="seeds per t_gap, >= 1")
    parser.add_argument("--seed", type=int, default=SPLITS["validation"].start,
                        help="first seed of the rule sweep (default: the validation split's first, av_gym/seeds.py)")
    parser.add_argument("--n-envs", type=number(int, low=1), default=250,
                        help="episodes stepped together in the rule sweep, >= 1")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace --out (and with --rule-sweep its .rule_sweep.csv) if there")
    parser.add_argument("--relabel", action="append", default=[],
                        help='"agent in results.csv=label" (repeatable): e.g. seeds of one run as "ppo_turn#s1"')
    parser.add_argument("--title", default="Left turn in traffic: safety vs progress")
    parser.add_argument("--named-only", action="store_true",
                        help="leave out agents given by path (checkpoints/reference/seeds/...): one point per named "
                             "agent")
    parser.add_argument("--mixed-seeds", action="store_true",
                        help="draw agents evaluated on different seeds side by side (refused otherwise)")
    args = parser.parse_args(argv)
    sweep_csv = args.out.with_suffix(".rule_sweep.csv")
    points_csv = args.out.with_suffix(".points.csv")
    problem = out_figure_problem(str(args.out), "--out", args.overwrite)  # before any row is read or played
    if not problem and args.rule_sweep:  # the sweep's rows, written beside the figure
        problem = held_outputs_problem("--out", sweep_csv.parent, [sweep_csv.name], args.overwrite, given=args.out,
                                       whose=" (the rule sweep's rows)")
    if not problem:  # the points drawn, written beside the figure
        problem = held_outputs_problem("--out", points_csv.parent, [points_csv.name], args.overwrite,
                                       given=args.out, whose=" (the points of a figure)")
    if problem:
        parser.error(f"argument {problem}")
    rows = read_rows(args.results)
    relabel = dict(r.split("=", 1) for r in args.relabel)
    for r in rows:
        r["agent"] = relabel.get(r["agent"], r["agent"])
    if args.named_only:  # a checkpoint given by path: another training seed of a named agent
        rows = [r for r in rows if "/" not in r["agent"]]
    # a sweep's rows read back (<out>.rule_sweep.csv of an earlier run) draw the rule's curve too
    rule = sorted(dict.fromkeys(r["agent"] for r in rows if r["agent"].startswith("gap_acceptance t_gap=")),
                  key=lambda k: float(k.split("=")[1].rstrip("s")))
    problem = seeds_problem(rows, args.mixed_seeds)
    given = {int(r["seed"]) for r in rows if r.get("seed") not in (None, "")}
    if not problem and args.rule_sweep and given and not args.mixed_seeds \
            and given != set(range(args.seed, args.seed + args.episodes)):  # refused before the sweep plays
        problem = (f"the rows are on {_span(dict.fromkeys(given, ''))}, the rule sweep would play --episodes "
                   f"{args.episodes} from --seed {args.seed}: give the rows' seeds, or --mixed-seeds")
    if problem:
        parser.error(problem)
    if args.rule_sweep:
        swept = rule_sweep(args.rule_sweep, args.episodes, args.seed,
                           args.n_envs)
        sweep_csv.parent.mkdir(parents=True, exist_ok=True)
        (write_text_atomic if args.overwrite else write_text_new)(sweep_csv, csv_text(swept), "--out")
        rule = list(dict.fromkeys(r["agent"] for r in swept))  # the new sweep replaces any rule rows read back
        rows = [r for r in rows if not r["agent"].startswith("gap_acceptance t_gap=")]
        rows += [{**{k: str(v) for k, v in r.items()}, "_file": str(sweep_csv)} for r in swept]
    problem = seeds_problem(rows, args.mixed_seeds)
    if problem:
        parser.error(problem)
    pts = points(rows)
    for extra in args.point:
        label, _, values = extra.partition("=")
        c, s = (float(v) for v in values.split(","))
        pts[label] = (c, s, (c, c), (s, s), 0)
    for label, (c, s, _, _, n) in pts.items():
        print(f"{label:40s} n={n:4d}  collision {c:.3f}  success {s:.3f}")
    table = csv_text(point_rows(pts, rows), POINT_COLUMNS)
    digest = hashlib.sha256(table.encode()).hexdigest()
    plot(pts, rule, args.out, args.title, args.overwrite, {"Description": f"points.csv sha256 {digest}"})
    (write_text_atomic if args.overwrite else write_text_new)(points_csv, table, "--out")
    print(f"[tradeoff] {args.out} (points: {points_csv})")


if __name__ == "__main__":
    from av_gym.errors import run_cli

    run_cli(main)  # a write that fails (a full disk): one line, exit 2
