"""``python -m eval.interventions``: label every AEB intervention needed or unneeded by a counterfactual replay.

For every intervention (the shield starts to brake), the whole env stack and the agent are deep-copied at that
moment, before the step is simulated (random generators included, as the lookahead oracle does), the copy's
shield is switched off (:attr:`av_gym.shields.aeb.AEBShield.bypass`), and the same episode is played on from the
agent's own action for ``--window`` seconds. The intervention was **needed** if the counterfactual ego collides
in that window, **unneeded** otherwise. The real episode goes on with the brake, unchanged (the copies draw from
their own copied generators), so the labelled run's episode metrics are those of ``python -m eval``.

Why a window and not the rest of the episode: with the shield off for good, a collision 10 s later is another
conflict, one the real shield would meet with its own intervention (and label). The default, 8 s, is the
improved shield's longest horizon; every counterfactual collision time is kept in the CSV, so another cut can be
counted from it.

Each intervention also gets the partner type of the object the shield braked for (its nearest true vehicle in
perceived mode) and of the counterfactual's collision partner, from the road network
(:func:`av_gym.shields.conflicts.partner_type`: oncoming, crossing, merging, ahead, behind).

    python -m eval.interventions --agents always_proceed+aeb,lookahead+aeb --episodes 100 --out runs/iv
    python -m eval.interventions --agents always_proceed+aeb --shield-set target_model=map --episodes 50

Writes ``interventions.csv`` (one row per intervention), ``episodes.csv`` (one row per episode: the metrics of
``python -m eval`` plus the counts) and ``interventions.md`` (the traffic table and the needed/unneeded table by
partner type) into ``--out``, with ``python -m eval``'s guards: the folder is held while the tables are written
(``--out/.lock``; a second run into it is refused), tables already there are replaced only with ``--overwrite``,
the seeds must lie in ``--split`` (default validation; reported runs say ``--split test``), and every count and
duration has bounds. Bad input is one line, exit status 2, before any episode.
"""

from __future__ import annotations

import contextlib
import copy
import io
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from av_gym.atomic import OwnedFolders, csv_text, write_text_atomic
from av_gym.errors import ConfigError
from av_gym.seeds import SPLITS, config_seeds
from av_gym.shields.aeb import find_shield
from av_gym.shields.conflicts import PARTNER_TYPES, partner_type
from eval.runner import play_episode
from conf.cli import ToolParser, held_outputs_problem, items, number, out_folder_problem
from conf.commands import PROCESSES_MAX

WINDOW = 8.0  # s, default counterfactual window (module docstring)


def _ego_s(u) -> float:
    k, s, _ = u.route.locate(u.vehicle.position, 0)
    return float(u.route.path_s(k, s))


def _classify(u, vehicle) -> str:
    if vehicle is None:
        return "unknown"
    from av_gym.envs.left_turn import ROUTE

    return partner_type(vehicle, u.road.network, ROUTE, u.route.starts, _ego_s(u))


def _nearest(u, xy, gate: float = 4.0):
    """The true vehicle nearest to ``xy`` (m) within ``gate`` m, or None."""
    if xy is None or not np.all(np.isfinite(xy)):
        return None
    others = [v for v in u.road.vehicles if v is not u.vehicle]
    if not others:
        return None
    d = [float(np.hypot(*(np.asarray(v.position) - xy))) for v in others]
    i = int(np.argmin(d))
    return others[i] if d[i] <= gate else None


def _collision_partner(u):
    """The crashed vehicle nearest the ego (highway-env flags both vehicles of a collision)."""
    crashed = [v for v in u.road.vehicles if v is not u.vehicle and getattr(v, "crashed", False)]
    if not crashed:
        return None
    return min(crashed, key=lambda v: float(np.hypot(*(np.asarray(v.position) - u.vehicle.position))))


def counterfactual(env, policy, action, window: float) -> dict:
    """Play ``env`` (a copy whose shield is bypassed) on from ``action`` with ``policy`` for ``window`` s;
    the collision (and when, and with whom) of the ego."""
    u = env.unwrapped
    t0 = float(u.time)
    obs, _, terminated, truncated, _ = env.step(action)
    while not (terminated or truncated or u.vehicle.crashed) and u.time - t0 < window - 1e-9:
        obs, _, terminated, truncated, _ = env.step(policy.act(obs))
    if not u.vehicle.crashed:
        return {"cf_collision": False, "cf_collision_after_s": float("nan"), "cf_partner": ""}
    return {"cf_collision": True, "cf_collision_after_s": float(u.time) - t0,
            "cf_partner": _classify(u, _collision_partner(u))}


def labelled_episode(env, policy, seed: int, window: float = WINDOW) -> tuple[dict, list[dict]]:
    """One episode of ``policy`` on ``env`` (a stack with an AEB shield and :class:`EpisodeMetrics`), every
    intervention labelled by its counterfactual; ``(episode metrics, intervention rows)``."""
    shield = find_shield(env)
    if shield is None:
        raise ValueError("eval.interventions needs an env stack with an AEB shield (an agent+aeb spec)")
    rows: list[dict] = []

    def on_intervention(sh, action) -> None:
        if sh is not shield:  # a copy's shield inside an agent's own look-ahead (the oracle's simulated futures)
            return
        u = sh.env.unwrapped
        target = _nearest(u, sh.target_xy)
        row = {"time_s": float(u.time), "speed_mps": float(u.vehicle.speed),
               "front_past_line_m": sh._front_past_line(), "target": _classify(u, target)}
        # The stack and the agent in one deep copy, so a policy bound to its env (the oracle) drives the copy.
        cf_env, cf_policy = copy.deepcopy((env, policy))
        find_shield(cf_env).switch_off()
        row.update(counterfactual(cf_env, cf_policy, action, window))
        row["needed"] = bool(row["cf_collision"])
        rows.append(row)

    shield.on_intervention = on_intervention
    try:
        metrics = dict(play_episode(env, policy, seed))
    finally:
        shield.on_intervention = None
    u = env.unwrapped
    metrics["collision_partner"] = _classify(u, _collision_partner(u)) if u.vehicle.crashed else ""
    metrics["withheld"] = shield.withheld  # stop-line brake decisions a second opinion withheld (aeb_belief)
    return metrics, rows


# ----------------------------------------------------------------------------------------------- tables
def partner_table(rows: list[dict]) -> list[dict]:
    """Per agent and partner type (of the object the shield braked for): interventions, needed, unneeded."""
    out = []
    for agent in dict.fromkeys(r["agent"] for r in rows):
        mine = [r for r in rows if r["agent"] == agent]
        for ptype in (*PARTNER_TYPES, "all"):
            sel = mine if ptype == "all" else [r for r in mine if r["target"] == ptype]
            if not sel:
                continue
            needed = sum(bool(r["needed"]) for r in sel)
            out.append({"agent": agent, "partner": ptype, "interventions": len(sel), "needed": needed,
                        "unneeded": len(sel) - needed, "unneeded_share": (len(sel) - needed) / len(sel)})
    return out


def _md(table: list[dict], cols: list[str]) -> str:
    def fmt(v):
        return f"{v:.3f}" if isinstance(v, float) else str(v)
    lines = ["| " + " | ".join(cols) + " |", "| " + " | ".join("---" for _ in cols) + " |"]
    lines += ["| " + " | ".join(fmt(r[c]) for c in cols) + " |" for r in table]
    return "\n".join(lines)


def write_outputs(episodes: list[dict], rows: list[dict], out: Path, meta: str) -> str:
    from eval.report import summary_table

    out.mkdir(parents=True, exist_ok=True)
    for name, data in (("episodes.csv", episodes), ("interventions.csv", rows)):
        write_text_atomic(out / name, csv_text(data, list(dict.fromkeys(k for r in data for k in r)) or ["agent"]),
                          "--out")
    cf_partners = [{"agent": a, "cf_partner": p,
                    "needed": sum(1 for r in rows if r["agent"] == a and r["needed"] and r["cf_partner"] == p)}
                   for a in dict.fromkeys(r["agent"] for r in rows) for p in PARTNER_TYPES]
    cf_partners = [r for r in cf_partners if r["needed"]]
    text = (f"# Counterfactual intervention labels\n\n{meta}\n\n## Episodes\n\n{summary_table(episodes, 'left_turn')}"
            f"\n\n## Interventions by the partner the shield braked for\n\n"
            f"{_md(partner_table(rows), ['agent', 'partner', 'interventions', 'needed', 'unneeded', 'unneeded_share'])}"
            f"\n\n## Needed interventions by the counterfactual's collision partner\n\n"
            f"{_md(cf_partners, ['agent', 'cf_partner', 'needed'])}\n")
    write_text_atomic(out / "interventions.md", text, "--out")
    return text


# ----------------------------------------------------------------------------------------------- command line
def _value(text: str):
    return yaml.safe_load(text)


def _apply(cfg: dict, assignments: list[str]) -> dict:
    """``key.sub=value`` assignments onto a nested dict (YAML values)."""
    cfg = copy.deepcopy(cfg)
    for item in assignments:
        key, _, val = item.partition("=")
        node = cfg
        *path, leaf = key.split(".")
        for p in path:
            node = node.setdefault(p, {})
        node[leaf] = _value(val)
    return cfg


def build(spec: str, env_set: list[str], shield_set: list[str], checkpoints: str = "checkpoints"):
    """``(label, env, policy)`` for an agent spec as ``python -m eval`` builds it, with overrides; torch's
    intra-op pool left at one thread, as for ``python -m eval``'s episodes."""
    from av_gym.batched.shield import shield_kind
    from eval.agents import compose_group, make_eval_env, plan_agent, resolve_agent
    from eval.runner import single_threaded_torch

    env_cfg = _apply({"name": "left_turn"}, env_set)
    plan = plan_agent(spec, "left_turn", compose_group("sensors", "truth"), compose_group("shield", "none"),
                      checkpoints)
    shield = _apply(plan.shield, shield_set) if shield_kind(plan.shield) != "none" else plan.shield
    env = make_eval_env(env_cfg, plan.sensors, shield)
    with contextlib.redirect_stdout(io.StringIO()):
        _, policy = resolve_agent(plan.spec, env, "left_turn", checkpoints)
    # Each worker (and the parent, with --workers 1) builds its agent here: torch on one thread, as python -m
    # eval's episodes (eval.runner.single_threaded_torch): a default pool spins on busy shared cores (~7 steps/s
    # instead of ~340 for PilotNet) and may sum a network's matmuls in another order than the evaluated episodes.
    single_threaded_torch()
    return plan.label, env, policy


_WORKER: dict = {}


def _init(spec, env_set, shield_set, window):
    label, env, policy = build(spec, env_set, shield_set)
    _WORKER.update(label=label, env=env, policy=policy, window=window)


def _one(seed: int):
    w = _WORKER
    metrics, rows = labelled_episode(w["env"], w["policy"], seed, w["window"])
    return w["label"], seed, metrics, rows


def run(spec: str, seeds, env_set=(), shield_set=(), window: float = WINDOW, workers: int = 1,
        progress: bool = True):
    """Episode rows and intervention rows for one agent spec over ``seeds``."""
    from concurrent.futures import ProcessPoolExecutor
    import multiprocessing

    args = (spec, list(env_set), list(shield_set), window)
    seeds = list(seeds)
    with contextlib.ExitStack() as stack:
        if workers > 1:
            ctx = multiprocessing.get_context("spawn")
            pool = stack.enter_context(ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=args))
            done = pool.map(_one, seeds, chunksize=4)
        else:
            _init(*args)
            done = map(_one, seeds)
        results = []
        for i, result in enumerate(done):
            results.append(result)
            if progress and (i + 1) % 25 == 0:
                print(f"[interventions] {spec}: {i + 1}/{len(seeds)}", file=sys.stderr, flush=True)
    episodes, rows = [], []
    for label, seed, metrics, ivs in results:
        episodes.append({"agent": label, "seed": seed, **metrics, "labelled_interventions": len(ivs),
                         "unneeded": sum(not r["needed"] for r in ivs)})
        rows += [{"agent": label, "seed": seed, "n": i, **r} for i, r in enumerate(ivs)]
    return episodes, rows


OUTPUTS = ("episodes.csv", "interventions.csv", "interventions.md")
OUT_DIRS = OwnedFolders()  # the --out folders this process is writing


def _parser() -> ToolParser:
    ap = ToolParser(prog="python -m eval.interventions", description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", default=["always_proceed+aeb", "lookahead+aeb"], type=items(str),
                    help="agent+shield specs, [a+aeb,b+aeb]")
    ap.add_argument("--episodes", type=number(int, low=1, high=100_000), default=100, help="episodes, [1, 100000]")
    ap.add_argument("--split", choices=list(SPLITS), default="validation",
                    help="the seeds' split (av_gym/seeds.py; default validation: shield development looks at "
                         "validation, never test)")
    ap.add_argument("--seed", type=number(int), default=None, help="first seed (default: the split's first)")
    ap.add_argument("--window", type=number(float, low=0.1, high=600.0), default=WINDOW,
                    help="counterfactual window (s), [0.1, 600]")
    ap.add_argument("--env-set", action="append", default=[], metavar="KEY=VALUE", help="env field override")
    ap.add_argument("--shield-set", action="append", default=[], metavar="KEY=VALUE",
                    help="shield field override (e.g. target_model=map, mode=perceived)")
    ap.add_argument("--workers", type=number(int, low=1, high=PROCESSES_MAX), default=1,
                    help=f"worker processes, [1, {PROCESSES_MAX}]")
    ap.add_argument("--out", default="runs/interventions", help="folder of the tables (held while they are written)")
    ap.add_argument("--overwrite", action="store_true", help="replace the tables --out already holds")
    return ap


def claim_out(out: str, overwrite: bool) -> None:
    """``--out`` for this process alone while it runs (``out/.lock``, as ``python -m eval`` holds its out_dir), then
    checked under the lock: a folder that holds another run's tables is refused unless ``overwrite``. One line
    (:class:`ConfigError`) otherwise; a refused claim leaves nothing behind."""
    problem = out_folder_problem(out, "--out")
    if problem:
        raise ConfigError(problem)
    OUT_DIRS.claim(out, "--out", "another eval.interventions")
    problem = held_outputs_problem("--out", out, OUTPUTS, overwrite, whose=" of an earlier run")
    if problem:
        OUT_DIRS.release(out)
        raise ConfigError(problem)


def main(argv: list[str] | None = None) -> int:
    """The command line: every flag checked (bounds, the seeds in their split, ``--out`` writable and ours) before
    any episode, then each agent's labelled episodes, the tables rewritten after each agent."""
    a = _parser().parse_args(argv)
    bare = [spec for spec in a.agents if "+" not in spec]
    if bare:
        raise ConfigError(f"--agents: {bare[0]!r} has no shield: use an agent+aeb spec")
    seeds = list(config_seeds(a.split, a.episodes, a.seed, "--seed"))
    claim_out(a.out, a.overwrite)
    try:
        text = _label_all(a, seeds)
    finally:
        OUT_DIRS.release(a.out)
    print(text)
    return 0


def _label_all(a, seeds: list[int]) -> str:
    """Each agent's labelled episodes; the tables written after each agent (a long run stopped later keeps what it
    measured); returns the markdown."""
    episodes, rows = [], []
    start = time.perf_counter()
    for spec in a.agents:
        e, r = run(spec, seeds, a.env_set, a.shield_set, a.window, a.workers)
        episodes += e
        rows += r
        meta = (f"{a.episodes} episodes of the {a.split} split from seed {seeds[0]}, window {a.window:g} s, env "
                f"overrides {a.env_set or '-'}, shield overrides {a.shield_set or '-'}; "
                f"{time.perf_counter() - start:.0f} s wall")
        text = write_outputs(episodes, rows, Path(a.out), meta)
    return text


if __name__ == "__main__":
    from av_gym.errors import run_cli

    run_cli(lambda: sys.exit(main()))  # bad input or a write that fails (a full disk): one line, exit 2
