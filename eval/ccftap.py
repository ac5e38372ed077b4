"""``python -m eval.ccftap``: the Euro NCAP CCFtap grid for the AEB shield variants and any agent.

3 ego speeds × 3 target speeds × 11 timing offsets Δt = 99 cases (digest 003 §3.3), each run with every agent in
``--agents`` (default: the always-proceed driver, which never yields: every conflict is the shield's to solve), for
every shield variant in ``--variants`` (``none``, ``standard``, ``paper``, ``improved``:
``conf/shield/aeb_standard.yaml``, ``aeb_paper.yaml``, ``aeb.yaml``) × every mode in ``--modes``
(``ground_truth``, ``perceived``: the shield's own detector + tracker, with ``--miss-rate`` and ``--burst-length``
bursty misses).

Agents. Each ``--agents`` entry is an agent spec as ``python -m eval`` takes it (:func:`eval.agents.plan_agent`):
a named config in ``conf/agent/`` (``always_proceed``; ``ppo_turn``, ``ppo_turn_shielded``, ``ppo_turn_perceived``:
the newest checkpoint trained with that config under ``--checkpoints``, else ``checkpoints/reference/<name>/``),
a trained kind (``ppo``), a checkpoint folder or ``.zip`` path, optionally ``@<sensors preset>``. Every agent is
planned once before any run (an unknown agent, a missing checkpoint or one that does not fit the env is one
``error:`` line and exit status 2); each runs with the sensors it needs (a checkpoint's training preset, e.g.
``turn_truth``), the shield is always the grid's variant (a ``+shield`` suffix is refused: use ``--variants``;
``ppo_turn_shielded`` thus also runs under ``none``). Policies are loaded once per worker process.

What a policy's actions mean here. In ccftap mode the left turn's discrete actions are highway-env's
{SLOWER, IDLE, FASTER} over only two speed set-points, ``[0, ego test speed]`` (``av_gym/envs/left_turn.py``
``define_spaces``; traffic mode, where the PPO agents are trained, has ``[0, 4.5, 9] m/s``): FASTER means "go at
the test speed", SLOWER "set-point 0 (brake to a stop)", IDLE "keep the set-point". A go/yield policy
(``agent.actions: go_yield``, :mod:`agents.go_yield`) thus GOes at the test speed; its YIELD asks for the highest
traffic set-point not above the comfortable approach speed ``sqrt(2·3·(d − 0.5))`` at ``d`` m from the stop line,
which here becomes: keep the test speed far from the line, set-point 0 within ~3.9 m of it (at 20 km/h = 5.6 m/s,
above 4.5, the set-point alternates between 0 and the test speed from ~14 m to ~3.9 m before the line). So its
approach is coarser than in training. The episode starts at the test speed either way.
``--action continuous`` needs agents trained on continuous actions.

Per case and agent: collision; intervention (the shield braked at least once); unnecessary intervention (it
braked although the same case and agent without shield is collision-free); stop position of the front bumper
relative to the stop line at the first standstill under braking (m, ≤ 0 = still in its own lane, the paper's
criterion); min gap to the oncoming lane while the target can still reach the ego (m, smallest x of the ego
footprint minus the lane's near edge, until the target's rear has passed the turn; negative = the ego was inside
the oncoming lane then); time to exit (s). Writes ``results.csv`` (one row per case and agent, ``agent``
column), ``results.md`` (aggregates per agent, variant and mode, and per-case grids), ``grid.png`` (every case
coloured by outcome, one row of panels per agent when there are several) and ``timeline.png`` (speed, predicted
TTC and stage over time for one case). A ``--out`` that already holds any of these is refused before any run
(another run's results, or someone's files), unless ``--overwrite``; a value repeated in a grid flag is refused
too (its cases would be run and counted twice).

    python -m eval.ccftap                                    # all four variants × both modes, 2 workers
    python -m eval.ccftap --variants improved --modes ground_truth --out runs/ccftap/gt
    python -m eval.ccftap --agents always_proceed,ppo_turn,ppo_turn_shielded,ppo_turn_perceived
"""

from __future__ import annotations

import csv
import functools
import io
import itertools
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from importlib import resources
from pathlib import Path

import numpy as np
import yaml

from av_gym.atomic import WriteFailed, save_figure_atomic, write_texts_atomic
from av_gym.params import SEED_MAX
from conf.cli import ToolParser, held_outputs_problem, items, number, out_folder_problem
from conf.commands import PROCESSES_MAX

EGO_KMH = (10.0, 15.0, 20.0)
TARGET_KMH = (30.0, 45.0, 60.0)
DTS = (-3.0, -2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 3.0)
VARIANTS = {"none": "none", "standard": "aeb_standard", "paper": "aeb_paper", "improved": "aeb"}
MODES = ("ground_truth", "perceived")
OUTCOMES = {  # code: (label, colour)
    "pass": ("no intervention, no collision", "#d9d9d9"),
    "stop": ("braked, stopped at/behind the stop line, no collision", "#4daf4a"),
    "stop_past": ("braked, stopped past the stop line, no collision", "#ffd92f"),
    "brake_safe": ("braked (no standstill), no collision", "#a6d96a"),
    "collision_braked": ("collision after braking", "#e41a1c"),
    "collision": ("collision, no intervention", "#67000d"),
}


def env_config(ego_kmh: float, target_kmh: float, dt: float, action: str = "discrete") -> dict:
    cfg = {"name": "left_turn"}  # every other field: its Params default
    cfg.update(mode="ccftap", action=action)
    cfg["ccftap"] = {"ego_speed_kmh": ego_kmh, "target_speed_kmh": target_kmh, "dt": dt}
    return cfg


def shield_config(variant: str, mode: str, miss_rate: float | None = None, burst_length: float | None = None,
                  detector_range: float | None = None) -> dict:
    """The shipped ``conf/shield/<name>.yaml`` for ``variant`` with ``mode`` (and perceived-mode overrides)."""
    name = VARIANTS[variant]
    cfg = yaml.safe_load((resources.files("conf") / "shield" / f"{name}.yaml").read_text())
    cfg.pop("defaults", None)  # the variant's Params defaults (/aeb/<variant>): the shield fills them in
    if variant == "none":
        return cfg
    cfg["mode"] = mode
    det = dict(cfg.get("detector") or {})
    for key, value in (("miss_rate", miss_rate), ("burst_length", burst_length), ("max_range", detector_range)):
        if value is not None:
            det[key] = value
    cfg["detector"] = det
    return cfg


DEFAULT_AGENT = "always_proceed"
_POLICIES: dict = {}  # per worker process: (agent spec, sensors, action) -> policy, so a checkpoint loads once


def _policy(task: dict, env):
    """The policy of ``task["agent_spec"]`` for ``env``, loaded once per process (``resolve_agent``)."""
    import contextlib
    import io
    import json

    from eval.agents import resolve_agent

    key = (task["agent_spec"], json.dumps(task.get("sensors"), sort_keys=True), task.get("action", "discrete"))
    held = getattr(_POLICIES.get(key), "env", None)  # an agent bound to the env it drives (lookahead oracle)
    if key not in _POLICIES or (held is not None and held is not env):
        with contextlib.redirect_stdout(io.StringIO()):  # its "[eval] ...: using <checkpoint>" line: said once
            _, _POLICIES[key] = resolve_agent(task["agent_spec"], env, "left_turn", task.get("checkpoints",
                                                                                            "checkpoints"))
        import multiprocessing

        if "torch" in sys.modules and multiprocessing.parent_process() is not None:
            sys.modules["torch"].set_num_threads(1)  # a pool worker: one thread each, the pool uses the cores
    return _POLICIES[key]


def run_case(task: dict) -> dict:
    """One CCFtap case with one agent and one shield config; returns the per-case row (and traces when asked).
    Without ``agent_spec`` in ``task`` the always-proceed driver on the default sensors (the shield variants' grid)."""
    from agents import AlwaysProceed
    from av_gym.make import make_env

    env = make_env(env_config(task["ego_kmh"], task["target_kmh"], task["dt"], task.get("action", "discrete")),
                   task.get("sensors"), task["shield"])
    u = env.unwrapped
    obs, info = env.reset(seed=int(task.get("seed", 0)))
    if task.get("agent_spec", DEFAULT_AGENT) == DEFAULT_AGENT and task.get("sensors") is None:
        policy = AlwaysProceed(u.cruise_action())
    else:
        policy = _policy(task, env)
    policy.reset()
    trace = {k: [] for k in ("time", "speed", "ttc", "stage", "stop_line_offset", "target_distance")}
    intervention, min_gap, min_ttc, t_warn = False, math.inf, math.inf, math.nan
    while True:
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        truth = info["truth"]
        stage = int(info.get("aeb_stage", 0))
        intervention |= stage == 2
        if stage >= 1 and math.isnan(t_warn):
            t_warn = truth["time"]
        min_ttc = min(min_ttc, float(info.get("aeb_ttc", math.inf)))
        if not u._target_passed():
            min_gap = min(min_gap, truth["oncoming_gap"])
        if task.get("trace"):
            trace["time"].append(truth["time"])
            trace["speed"].append(truth["speed"])
            trace["ttc"].append(float(info.get("aeb_ttc", math.inf)))
            trace["stage"].append(stage)
            trace["stop_line_offset"].append(truth["stop_line_offset"])
            trace["target_distance"].append(float(np.linalg.norm(u.ccftap_target.position - u.vehicle.position)))
        if terminated or truncated:
            break
    m = info["episode_metrics"]
    env.close()
    row = {"agent": task.get("agent", DEFAULT_AGENT), "variant": task["variant"], "mode": task["mode"],
           "ego_kmh": task["ego_kmh"], "target_kmh": task["target_kmh"], "dt": task["dt"],
           "collision": int(m["collision"]), "intervention": int(intervention),
           "stop_line_offset_m": _number(info.get("aeb_stop_position")) if intervention else math.nan,
           "min_oncoming_gap_m": min_gap, "time_to_exit_s": m["time_to_exit_s"],
           "brake_time_s": _number(info.get("aeb_brake_time")), "warn_time_s": t_warn,
           "min_pred_ttc_s": min_ttc, "override_fraction": m["override_fraction"], "duration_s": m["duration_s"]}
    if task.get("trace"):
        row["trace"] = trace
    return row


def outcome(row: dict) -> str:
    if row["collision"]:
        return "collision_braked" if row["intervention"] else "collision"
    if not row["intervention"]:
        return "pass"
    off = row["stop_line_offset_m"]
    if off != off:  # NaN: braked but never came to a standstill
        return "brake_safe"
    return "stop" if off <= 1e-6 else "stop_past"


def add_unnecessary(rows: list[dict]) -> None:
    """``unnecessary`` = intervention in a case whose no-shield run (same agent) is collision-free (needs the
    ``none`` rows, run on the fly when absent)."""
    def case(r: dict) -> tuple:
        return r.get("agent", DEFAULT_AGENT), r["ego_kmh"], r["target_kmh"], r["dt"]

    base = {case(r): r["collision"] for r in rows if r["variant"] == "none"}
    for r in rows:
        key = case(r)
        r["baseline_collision"] = base[key]
        r["unnecessary"] = int(bool(r["intervention"]) and not base[key])
        r["outcome"] = outcome(r)


def _group(r: dict) -> tuple:
    return r.get("agent", DEFAULT_AGENT), r["variant"], r["mode"]


def aggregate(rows: list[dict]) -> list[dict]:
    out = []
    for (agent, variant, mode), grp in itertools.groupby(rows, key=_group):
        grp = list(grp)
        stops = [r["stop_line_offset_m"] for r in grp
                 if r["intervention"] and r["stop_line_offset_m"] == r["stop_line_offset_m"]]
        exits = [r["time_to_exit_s"] for r in grp if r["time_to_exit_s"] == r["time_to_exit_s"]]
        out.append({
            "agent": agent, "variant": variant, "mode": mode, "cases": len(grp),
            "collisions": sum(r["collision"] for r in grp),
            "missed (collision, no brake)": sum(r["collision"] and not r["intervention"] for r in grp),
            "interventions": sum(r["intervention"] for r in grp),
            "unnecessary": sum(r["unnecessary"] for r in grp),
            "braking stops": len(stops),
            "stops at/behind line": sum(o <= 1e-6 for o in stops),
            "stop offset mean (max) m": f"{np.mean(stops):+.2f} ({np.max(stops):+.2f})" if stops else "–",
            "time to exit mean s": f"{np.mean(exits):.2f}" if exits else "–",
        })
    return out


def markdown(rows: list[dict], agg: list[dict], meta: str) -> str:
    from av_gym.metrics import markdown_table

    cols = list(agg[0])
    several = len({r.get("agent", DEFAULT_AGENT) for r in rows}) > 1
    title = "agents × AEB shield variants" if several else "AEB shield variants"
    lines = [f"# CCFtap grid: {title}\n\n{meta}\n", markdown_table(agg, cols), ""]
    lines.append("Outcome codes per case below: `.` no intervention and no collision, `S` braked and stopped at or "
                 "behind the stop line, `P` braked and stopped past the stop line, `b` braked without coming to a "
                 "standstill, `X` collision after braking, `#` collision without intervention; a trailing `u` marks "
                 "an unnecessary intervention (the no-shield case is collision-free).\n")
    code = {"pass": ".", "stop": "S", "stop_past": "P", "brake_safe": "b", "collision_braked": "X", "collision": "#"}
    for (agent, variant, mode), grp in itertools.groupby(rows, key=_group):
        grp = {(r["ego_kmh"], r["target_kmh"], r["dt"]): r for r in grp}
        dts = sorted({k[2] for k in grp})
        table = []
        for e, t in sorted({k[:2] for k in grp}):
            line = {"ego/target km/h": f"{e:g}/{t:g}"}
            for dt in dts:
                r = grp[(e, t, dt)]
                off = r["stop_line_offset_m"]
                cell = code[r["outcome"]] + ("u" if r["unnecessary"] else "")
                if off == off:
                    cell += f" {off:+.1f}"
                line[f"{dt:+g}"] = cell
            table.append(line)
        head = f"{agent}: {variant} / {mode}" if several else f"{variant} / {mode}"
        lines += [f"## {head}\n", "Cell: outcome code, then the stop offset of the front bumper past "
                  "the stop line (m) for braking stops.\n", markdown_table(table, list(table[0])), ""]
    return "\n".join(lines)


def grid_figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    groups = [(k, list(g)) for k, g in itertools.groupby(rows, key=_group)]
    agents = list(dict.fromkeys(agent for (agent, _, _), _ in groups))
    codes = list(OUTCOMES)
    cmap = ListedColormap([OUTCOMES[c][1] for c in codes])
    if len(agents) == 1:  # one agent: the variant × mode panels two by two
        ncol = 2 if len(groups) > 1 else 1
        nrow = math.ceil(len(groups) / ncol)
        fig, axes = plt.subplots(nrow, ncol, figsize=(7.2 * ncol, 3.6 * nrow + 1.0), squeeze=False)
        panels = list(zip(axes.flat, groups))
    else:  # one row of panels per agent, one column per variant × mode
        configs = list(dict.fromkeys((variant, mode) for (_, variant, mode), _ in groups))
        nrow, ncol = len(agents), len(configs)
        fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 2.9 * nrow + 1.0), squeeze=False)
        panels = [(axes[agents.index(agent), configs.index((variant, mode))], ((agent, variant, mode), grp))
                  for (agent, variant, mode), grp in groups]
    for ax, ((agent, variant, mode), grp) in panels:
        pairs = sorted({(r["ego_kmh"], r["target_kmh"]) for r in grp})
        dts = sorted({r["dt"] for r in grp})
        img = np.zeros((len(pairs), len(dts)))
        for r in grp:
            i, j = pairs.index((r["ego_kmh"], r["target_kmh"])), dts.index(r["dt"])
            img[i, j] = codes.index(r["outcome"])
            if r["unnecessary"]:
                ax.text(j, i, "u", ha="center", va="center", fontsize=8)
        ax.imshow(img, cmap=cmap, vmin=-0.5, vmax=len(codes) - 0.5, aspect="auto")
        ax.set_xticks(range(len(dts)), [f"{d:+g}" for d in dts], fontsize=8)
        ax.set_yticks(range(len(pairs)), [f"{e:g} / {t:g}" for e, t in pairs], fontsize=8)
        if len(agents) == 1:
            ax.set_xlabel("Δt: target reaches the conflict point this long after the ego (s)", fontsize=8)
            ax.set_ylabel("ego / target speed (km/h)", fontsize=8)
        else:  # full labels on the outer panels only
            if agent == agents[-1]:
                ax.set_xlabel("Δt: target at the conflict point\nthis long after the ego (s)", fontsize=8)
            if (variant, mode) == configs[0]:
                ax.set_ylabel("ego / target speed (km/h)", fontsize=8)
        n_col = sum(r["collision"] for r in grp)
        name = f"{variant} / {mode}" if len(agents) == 1 else f"{agent}\n{variant} / {mode}"
        ax.set_title(f"{name}: {n_col}/{len(grp)} collisions", fontsize=9)
        for k in range(1, len(pairs)):
            ax.axhline(k - 0.5, color="white", lw=0.5)
    used = {id(ax) for ax, _ in panels}
    for ax in axes.flat:
        if id(ax) not in used:
            ax.axis("off")
    fig.legend(handles=[Patch(color=OUTCOMES[c][1], label=OUTCOMES[c][0]) for c in codes] +
               [Patch(color="white", label="u = unnecessary intervention")], loc="lower center", ncol=3, fontsize=8)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    try:  # whole or not at all: a full disk would leave an empty grid.png
        save_figure_atomic(fig, path, "--out", dpi=120)
    finally:
        plt.close(fig)


def timeline_figure(traces: dict, case: tuple, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(8, 8.5), sharex=True)
    for label, tr in traces.items():
        t = np.asarray(tr["time"])
        line, = axes[0].plot(t, tr["speed"], label=label)
        if tr.get("collision_time") is not None:
            axes[0].plot([tr["collision_time"]], [tr["speed"][-1]], "x", color=line.get_color(), ms=9, mew=2)
        ttc = np.asarray(tr["ttc"], dtype=float)
        axes[1].plot(t, np.where(np.isfinite(ttc), ttc, np.nan), label=label)
        axes[2].step(t, tr["stage"], where="post", label=label)
        axes[3].plot(t, tr["stop_line_offset"], label=label)
    axes[0].set_ylabel("ego speed (m/s)")
    axes[1].set_ylabel("predicted TTC (s)")
    axes[1].axhline(1.5, color="k", lw=0.6, ls="--")
    axes[2].set_ylabel("stage")
    axes[2].set_yticks([0, 1, 2], ["monitor", "warn", "brake"])
    axes[3].set_ylabel("front bumper past\nstop line (m)")
    axes[3].axhline(0.0, color="k", lw=0.6, ls="--")
    axes[3].set_xlabel("time (s)")
    axes[0].legend(fontsize=8)
    e, tg, dt = case
    axes[0].set_title(f"CCFtap ego {e:g} km/h, target {tg:g} km/h, Δt = {dt:+g} s (x marks a collision)")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    try:
        save_figure_atomic(fig, path, "--out", dpi=120)
    finally:
        plt.close(fig)


def plan_agents(specs: list[str], checkpoints: str, action: str, case: tuple) -> list:
    """Plan every agent spec (:func:`eval.agents.plan_agent`) and try it once on the first case's env, before any
    run: raises :class:`ConfigError` for an unknown agent, a missing checkpoint, a checkpoint that does not fit the
    env (sensors preset, action space) or a duplicate. The default agent keeps the default sensors (``None``)."""
    from dataclasses import replace

    from av_gym.errors import ConfigError
    from av_gym.make import make_env
    from eval.agents import check_plan, plan_agent, resolve_agent

    truth = yaml.safe_load((resources.files("conf") / "sensors" / "truth.yaml").read_text())
    no_shield = shield_config("none", "ground_truth")
    plans = []
    for spec in specs:
        if "+" in spec:
            raise ConfigError(f"--agents: {spec!r}: the shield comes from --variants here, not from a '+shield' "
                              f"suffix; use {spec.partition('+')[0]!r} with --variants")
        plan = plan_agent(spec, "left_turn", None, no_shield, checkpoints)
        if any(q.label == plan.label for q in plans):
            raise ConfigError(f"--agents: {spec!r} is given twice")
        check_plan(replace(plan, sensors=plan.sensors or truth, shield=no_shield), "left_turn")
        if plan.spec != DEFAULT_AGENT or plan.sensors is not None:  # load it once here: fits the env?
            env = make_env(env_config(*case, action), plan.sensors, None)
            try:
                resolve_agent(plan.spec, env, "left_turn", checkpoints)
            finally:
                env.close()
        plans.append(plan)
    return plans


def _ccftap_bounds() -> dict[str, dict]:
    """``{field: {"low": ge, "high": le}}`` of :class:`~av_gym.envs.left_turn.CCFtapParams`: the grid flags take
    what ``env.ccftap.*`` takes."""
    import dataclasses

    from av_gym.envs.left_turn import CCFtapParams

    return {f.name: {"low": f.metadata.get("ge"), "high": f.metadata.get("le")}
            for f in dataclasses.fields(CCFtapParams)}


OUTPUTS = ("results.csv", "results.md", "grid.png", "timeline.png")  # what a run writes in --out


class _Refused(Exception):
    """A bad flag found once the arguments are parsed: ``error: <message>``, exit status 2."""


def main(argv: list[str] | None = None) -> int:
    p = _parser()
    a = p.parse_args(argv)
    if a.out is not None and out_folder_problem(a.out, "--out"):  # before any run: results need somewhere to go
        p.error(f"argument {out_folder_problem(a.out, '--out')}")
    if len(a.plot_case) != 3:
        p.error(f"argument --plot-case: expected [ego km/h, target km/h, dt], got {a.plot_case}")
    held = a.out is not None and held_outputs_problem("--out", a.out, OUTPUTS, a.overwrite)
    if held:  # another run's results, or the user's files: before any run
        p.error(f"argument {held}")
    try:
        _ccftap(a, argv)
    except _Refused as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def _parser() -> ToolParser:
    p = ToolParser(prog="python -m eval.ccftap", description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", default=[DEFAULT_AGENT], type=items(str),
                   help="list of agent specs, [a,b] as for `python -m eval` (conf/agent/ name, ppo, checkpoint path, "
                        "name@sensors); default always_proceed")
    p.add_argument("--checkpoints", default="checkpoints", help="where named trained agents' checkpoints are found")
    p.add_argument("--variants", default=list(VARIANTS), type=items(str, choices=list(VARIANTS), unique=True))
    p.add_argument("--modes", default=list(MODES), type=items(str, choices=list(MODES), unique=True))
    bounds = _ccftap_bounds()  # the bounds env.ccftap.* declares (CCFtapParams): 1e9 s would hang the run
    p.add_argument("--ego", default=list(EGO_KMH), type=items(float, **bounds["ego_speed_kmh"], unique=True),
                   help="ego speeds, km/h, [10,15,20]")
    p.add_argument("--target", default=list(TARGET_KMH), type=items(float, **bounds["target_speed_kmh"], unique=True),
                   help="target speeds, km/h")
    p.add_argument("--dts", default=list(DTS), type=items(float, **bounds["dt"], unique=True), help="timing offsets, s")
    p.add_argument("--miss-rate", type=float, default=None, help="perceived mode: detector miss rate (yaml: 0.3)")
    p.add_argument("--burst-length", type=float, default=None, help="perceived mode: mean miss run, frames (yaml: 5)")
    p.add_argument("--detector-range", type=float, default=None, help="perceived mode: detector range, m")
    p.add_argument("--set", action="append", default=[], metavar="VARIANT.KEY=VALUE",
                   help="override a shield parameter, e.g. paper.standstill_hold=null or paper.brake.delay=0")
    p.add_argument("--action", default="discrete", choices=["discrete", "continuous"])
    p.add_argument("--seed", type=number(int, low=0, high=SEED_MAX), default=0)
    p.add_argument("--workers", type=number(int, low=1, high=PROCESSES_MAX), default=2)
    p.add_argument("--plot-case", default=[15.0, 45.0, 0.0], type=items(float),
                   help="ego km/h, target km/h, dt for timeline.png: [15,45,0]")
    p.add_argument("--out", default=None, help="output folder (default runs/ccftap/<time>)")
    p.add_argument("--overwrite", action="store_true", help=f"replace the {', '.join(OUTPUTS)} --out already holds")
    return p


def _ccftap(a, argv: list[str] | None) -> None:
    """The grid: every agent × shield config × case, run (in worker processes), then the tables and figures."""
    from av_gym.errors import ConfigError

    egos, targets, dts, plot_case = a.ego, a.target, a.dts, tuple(a.plot_case)
    if not a.agents:
        raise _Refused("--agents: give at least one agent")
    try:
        plans = plan_agents(a.agents, a.checkpoints, a.action, (egos[0], targets[0], dts[0]))
    except ConfigError as exc:
        raise _Refused(" ".join(str(exc).split())) from None
    out = Path(a.out or f"runs/ccftap/{time.strftime('%Y%m%d-%H%M%S')}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _Refused(f"--out={out}: cannot be made: {exc.strerror or exc}") from None
    configs = [("none", "-")]  # the no-shield baseline is always run: it defines unnecessary interventions
    configs += [(v, m) for v in a.variants if v != "none" for m in a.modes]
    shields = _shields(a, configs)
    tasks = []
    for plan in plans:  # agent-major, then config, then case: the order the tables group by
        agent = {} if plan.spec == DEFAULT_AGENT and plan.sensors is None and len(plans) == 1 else \
            {"agent_spec": plan.spec, "sensors": plan.sensors, "checkpoints": str(a.checkpoints)}
        for (variant, mode), shield in zip(configs, shields):
            for e, tg, dt in itertools.product(egos, targets, dts):
                tasks.append({"agent": plan.label, **agent, "variant": variant, "mode": mode, "ego_kmh": e,
                              "target_kmh": tg, "dt": dt, "shield": shield, "action": a.action, "seed": a.seed,
                              "trace": (e, tg, dt) == plot_case and mode in ("-", "ground_truth")})
    n_cases = len(egos) * len(targets) * len(dts)
    t0 = time.time()
    print(f"[ccftap] {len(tasks)} runs ({len(plans)} agents × {len(configs)} configs × {n_cases} cases), "
          f"{a.workers} workers → {out}", flush=True)
    rows = _run_tasks(tasks, a.workers)
    add_unnecessary(rows)
    if "none" not in a.variants:
        rows = [r for r in rows if r["variant"] != "none"]
    several = len(plans) > 1
    traces = {f"{r['agent']} / {r['variant']}" if several else r["variant"]:
              dict(r.pop("trace"), collision_time=(r["duration_s"] if r["collision"] else None))
              for r in rows if "trace" in r}
    for r in rows:
        r.pop("trace", None)
    _write(a, argv, plans, rows, traces, out, t0)


def _shields(a, configs: list[tuple[str, str]]) -> list[dict]:
    """Each (variant, mode)'s shield section with the ``--set`` overrides of its variant; each built once on the
    first case before any run, so a bad one fails fast in one line."""
    from av_gym.errors import ConfigError
    from av_gym.make import make_env

    overrides = []
    for item in a.set:
        key, sep, value = item.partition("=")
        variant_key, _, path = key.partition(".")
        if not sep or variant_key not in VARIANTS or not path:
            raise _Refused(f"--set {item!r}: expected VARIANT.KEY=VALUE with VARIANT in {list(VARIANTS)}")
        overrides.append((variant_key, path.split("."), yaml.safe_load(value)))
    shields = []
    for variant, mode in configs:
        shield = shield_config(variant, mode if mode != "-" else "ground_truth", a.miss_rate, a.burst_length,
                               a.detector_range)
        for v, path, value in overrides:
            if v == variant:
                node = shield
                for part in path[:-1]:
                    node = node.setdefault(part, {})
                node[path[-1]] = value
        shields.append(shield)
    for shield in shields:
        try:
            make_env(env_config(a.ego[0], a.target[0], a.dts[0], a.action), None, shield).close()
        except ConfigError as exc:
            raise _Refused(str(exc)) from None
    return shields


def _run_tasks(tasks: list[dict], workers: int) -> list[dict]:
    """Each task's row (:func:`run_case`), in ``workers`` processes, in the order of ``tasks``; a progress bar of
    the runs on a terminal, else a line every ~5 s (the full grid takes minutes)."""
    from conf.run_log import progress

    bar = functools.partial(progress, total=len(tasks), desc="ccftap", unit="run")
    if workers <= 1:
        return [run_case(t) for t in bar(tasks)]
    import multiprocessing

    # a trained policy was loaded here (torch): workers start fresh rather than fork this process
    ctx = multiprocessing.get_context("spawn") if any("agent_spec" in t for t in tasks) else None
    with ProcessPoolExecutor(workers, mp_context=ctx) as pool:
        return list(bar(pool.map(run_case, tasks, chunksize=4)))


def _write(a, argv: list[str] | None, plans: list, rows: list[dict], traces: dict, out: Path, t0: float) -> None:
    """results.csv, results.md (with how it was run), grid.png and timeline.png, each whole or as it was."""
    from av_gym.metrics import markdown_table
    from av_gym.shields.aeb import ImprovedParams

    agg = aggregate(rows)
    # the yaml names only what differs from the Params defaults (the shield completes the section the same way)
    pert = {**ImprovedParams().detector.as_dict(),
            **shield_config("improved", "perceived", a.miss_rate, a.burst_length, a.detector_range)["detector"]}
    driver = "always-proceed driver" if [q.label for q in plans] == [DEFAULT_AGENT] else \
        "agents " + ", ".join(f"{q.label} ({q.spec}, sensors {(q.sensors or {}).get('name', 'truth')})"
                              for q in plans)
    meta = (f"`python -m eval.ccftap {' '.join(argv if argv is not None else sys.argv[1:])}`; {driver}, "
            f"{a.action} actions, seed {a.seed}; {len(rows) // max(1, len(agg))} cases per row "
            f"({len(a.ego)} ego × {len(a.target)} target speeds × {len(a.dts)} Δt). Perceived mode: the shield's own "
            f"detector (miss_rate {pert.get('miss_rate')}, burst_length {pert.get('burst_length')} frames, "
            f"max_range {pert.get('max_range')} m) + Kalman tracker. Wall time {time.time() - t0:.0f} s.")
    table = io.StringIO()
    w = csv.DictWriter(table, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    md = markdown(rows, agg, meta)
    try:  # each file whole or as it was (a full disk): one line, no traceback, no empty png
        write_texts_atomic({out / "results.csv": table.getvalue(), out / "results.md": md}, field="--out")
        grid_figure(rows, out / "grid.png")
        if traces:
            timeline_figure(traces, tuple(a.plot_case), out / "timeline.png")
    except WriteFailed as exc:
        raise _Refused(str(exc)) from None
    print(markdown_table(agg, list(agg[0])))
    print(f"[ccftap] {time.time() - t0:.0f} s; wrote {out}/results.csv, results.md, grid.png"
          + (", timeline.png" if traces else ""))


def _number(value: float | None) -> float:
    """An info value that is inf until it happens (``av_gym.shields.aeb.NOT_YET``; ``None`` too, as a caller's
    ``info.get`` gives without a shield), as a float (NaN: it did not happen)."""
    return math.nan if value is None or math.isinf(value) else float(value)


if __name__ == "__main__":
    sys.exit(main())
