"""The documented search for the ``tuned`` PID preset (``agents/pid.py`` PRESETS, ``conf/agent/pid_tuned.yaml``).

    python -m train.pid_search                      # the search behind the committed preset (~6 min on 1 core)
    python -m train.pid_search --seeds 0 --grid quick --refine 0     # a smoke run

Where: the TRAINING layout A only, on train-split seeds (default 0..4; av_gym/seeds.py; others are refused).
Evaluation uses the validation (ad hoc, the evaluations during and after training) and test (reported tables)
splits, so neither is ever seen by the search; layout B is held out.

What is minimised, per gain triple (Kp, Ki, Kd) of the per-step PID in ``agents/pid.py`` (same anti-windup and
clipping as the paper preset, input the true CTE as the paper's simulator gave):

    J = mean over seeds of [ mean |CTE| (paper units, lane = 100) + osc_weight · steering sign changes per 100 m ]

subject to two constraints, J = inf otherwise:
  * completion: every lap is completed;
  * gain margin: the same gains multiplied by ``--margin`` (default 2, i.e. 6 dB, the textbook minimum gain
    margin) still complete the first seed's lap without a limit cycle (at most ``--max-osc`` = 20 steering sign
    changes per 100 m; the paper PID makes about 2.5, a limit cycle 80-100).
Why the margin: without it the optimum is P-only at Kp ≈ 7.6 (0.46 paper units on A), one step from the limit cycle
that starts between Kp 8 and 12 (at Kp 12 the steering reverses ~88 times per 100 m). highway-env's car steers its
velocity directly through the slip angle (β ≈ δ/2), so proportional action alone is damped and the derivative
term mostly adds high-frequency gain; a preset sitting on that cliff would fall off it with the first noisy CTE.
The oscillation term (weight 0.1: one sign change per 100 m costs 0.1 paper units) breaks near-ties towards calm gains.

How: (1) a grid over Kp × Ki × Kd (``--grid full``: 6 × 4 × 5 = 120 triples); (2) Nelder–Mead (scipy) from the
best grid point, ``--refine`` function evaluations, gains clipped to >= 0. Prints the best triples, the final
gains and the lines to paste into ``agents/pid.py`` and ``conf/agent/pid_tuned.yaml``; ``--out`` writes JSON.
"""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from av_gym.atomic import write_text_atomic
from av_gym.seeds import SPLITS
from conf.cli import Extend, ToolParser, items

GRIDS = {
    "full": {"kp": [0.5, 1.0, 2.0, 3.0, 4.0, 6.0], "ki": [0.0, 1e-4, 1e-3, 1e-2], "kd": [0.0, 0.5, 1.0, 2.0, 4.0]},
    "quick": {"kp": [0.75, 1.5], "ki": [1e-4], "kd": [1.0, 4.0]},
}
TRAIN_SEEDS = SPLITS["train"]  # av_gym/seeds.py: a search tunes, so it draws from the train split only


def lane_env(track: str = "A"):
    """The lap env exactly as ``python -m eval env=lane_keeping`` builds it for a PID (sensors=truth)."""
    from av_gym.make import make_env

    env_cfg = {"name": "lane_keeping", "track": track}  # every other field: its Params default
    return make_env(env_cfg, {"name": "truth", "keep_state": True})


def run_laps(env, gains: dict, seeds) -> list[dict]:
    """One lap per seed with PID ``gains``; the episode metric rows."""
    from agents.pid import PIDSteering

    pid = PIDSteering(kp=float(gains["kp"]), ki=float(gains["ki"]), kd=float(gains["kd"]))
    rows = []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        pid.reset()
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(pid.act(obs))
            done = terminated or truncated
        rows.append(info["episode_metrics"])
    return rows


def objective(rows: list[dict], osc_weight: float) -> float:
    if not all(r["lap_completed"] == 1.0 for r in rows):
        return float("inf")
    return float(np.mean([r["cte_mean_abs_units"] + osc_weight * r["steering_sign_changes_per_100m"] for r in rows]))


def has_margin(env, gains: dict, seed: int, margin: float, max_osc: float) -> bool:
    """Gains × ``margin`` still complete the lap on ``seed`` without a limit cycle."""
    if margin <= 0:
        return True
    row = run_laps(env, {k: margin * float(v) for k, v in gains.items()}, [seed])[0]
    return row["lap_completed"] == 1.0 and row["steering_sign_changes_per_100m"] <= max_osc


def search(grid: dict, seeds, track: str = "A", osc_weight: float = 0.1, refine: int = 60, margin: float = 2.0,
           max_osc: float = 20.0, log=tqdm.write, progress: bool = True) -> dict:
    """Grid then Nelder–Mead; returns ``{"best": {kp, ki, kd}, "objective", "mean_abs_cte_units" (paper units, lane
    = 100), "mean_abs_cte_m", "sign_changes_per_100m", "evaluations", "top": [...]}``.
    ``log`` gets a line as each phase starts and ends;
    ``progress``: a bar of the evaluations (each a lap per seed, ~2 s), with the best J so far."""
    from scipy.optimize import minimize

    seeds = [int(s) for s in seeds]
    if any(s not in TRAIN_SEEDS for s in seeds):
        raise ValueError(f"seeds must lie in the train split ({TRAIN_SEEDS.start}..{TRAIN_SEEDS.stop - 1}), "
                         f"got {seeds}")
    env = lane_env(track)
    table: list[dict] = []
    n_grid = int(np.prod([len(v) for v in grid.values()]))
    log(f"[pid_search] grid: {n_grid} gain triples x {len(seeds)} laps on layout {track}"
        f"{' (+1 lap at x' + format(margin, 'g') + ' gain for the margin)' if margin > 0 else ''}, then up to "
        f"{max(int(refine), 0)} Nelder-Mead evaluations")
    bar = tqdm(total=n_grid + max(int(refine), 0), desc="pid_search", unit="eval", disable=not progress)

    def evaluate(kp: float, ki: float, kd: float) -> float:
        gains = {"kp": float(kp), "ki": float(ki), "kd": float(kd)}
        rows = run_laps(env, gains, seeds)
        j = objective(rows, osc_weight)
        margin_ok = bool(np.isfinite(j) and has_margin(env, gains, seeds[0], margin, max_osc))
        j = j if margin_ok else float("inf")
        table.append({**gains, "objective": j, "margin_ok": margin_ok,
                      "mean_abs_cte_units": float(np.mean([r["cte_mean_abs_units"] for r in rows])),
                      "mean_abs_cte_m": float(np.mean([r["cte_mean_abs_m"] for r in rows])),
                      "sign_changes_per_100m": float(np.mean([r["steering_sign_changes_per_100m"] for r in rows])),
                      "laps_completed": float(np.mean([r["lap_completed"] for r in rows]))})
        bar.update()
        bar.set_postfix_str(f"best J {min(r['objective'] for r in table):.3f}")
        return j

    t0 = time.time()
    for kp, ki, kd in itertools.product(grid["kp"], grid["ki"], grid["kd"]):
        evaluate(kp, ki, kd)
    start = min(table, key=lambda r: r["objective"])
    log(f"[pid_search] grid: {n_grid} triples x {len(seeds)} laps in {time.time() - t0:.0f} s; best "
        f"Kp {start['kp']:g} Ki {start['ki']:g} Kd {start['kd']:g}: J = {start['objective']:.3f}")
    if refine > 0 and np.isfinite(start["objective"]):
        x0 = np.array([start["kp"], start["ki"], start["kd"]])
        step = np.maximum(np.abs(x0) * 0.25, [0.1, 1e-3, 0.5])
        simplex = np.vstack([x0, x0 + np.diag(step)])
        minimize(lambda x: evaluate(*np.maximum(x, 0.0)), x0, method="Nelder-Mead",
                 options={"initial_simplex": simplex, "maxfev": int(refine), "xatol": 1e-4, "fatol": 1e-3})
        log(f"[pid_search] Nelder-Mead: {len(table) - n_grid} evaluations, {time.time() - t0:.0f} s in all")
    bar.close()
    env.close()
    best = min(table, key=lambda r: r["objective"])
    top = sorted(table, key=lambda r: r["objective"])[:10]
    return {"best": {k: round(best[k], 6) for k in ("kp", "ki", "kd")}, "objective": best["objective"],
            "mean_abs_cte_units": best["mean_abs_cte_units"], "mean_abs_cte_m": best["mean_abs_cte_m"],
            "sign_changes_per_100m": best["sign_changes_per_100m"],
            "evaluations": len(table), "grid_evaluations": n_grid, "top": top, "track": track, "seeds": seeds,
            "osc_weight": osc_weight, "margin": margin, "max_osc": max_osc}


def report_lines(res: dict) -> list[str]:
    """The printed result of :func:`search`: the best triples' table and the best line, the mean |CTE| in metres
    with paper 001's units named beside it (J's scale: the lane is 100 units wide), never a bare "units"."""
    lines = ["", "| Kp | Ki | Kd | J | mean abs CTE (m) | mean abs CTE (paper units, lane = 100) | sign changes "
             "/ 100 m | laps | margin |", "|---|---|---|---|---|---|---|---|---|"]
    for r in res["top"]:
        lines.append(f"| {r['kp']:.4g} | {r['ki']:.4g} | {r['kd']:.4g} | {r['objective']:.3f} | "
                     f"{r['mean_abs_cte_m']:.4f} | {r['mean_abs_cte_units']:.3f} | {r['sign_changes_per_100m']:.2f} | "
                     f"{r['laps_completed']:.2f} | {'ok' if r['margin_ok'] else 'no'} |")
    b = res["best"]
    lines += ["", f"best: Kp {b['kp']:g}, Ki {b['ki']:g}, Kd {b['kd']:g}: mean |CTE| {res['mean_abs_cte_m']:.4f} m "
              f"({res['mean_abs_cte_units']:.3f} paper units, lane = 100), {res['sign_changes_per_100m']:.2f} sign "
              f"changes / 100 m ({res['evaluations']} evaluations)"]
    return lines


def main(argv=None) -> dict:
    p = ToolParser(prog="python -m train.pid_search", description=__doc__.split("\n\n")[0])
    p.add_argument("--track", default="A", help="training layout (default A; B is held out)")
    p.add_argument("--seeds", type=items(int, low=TRAIN_SEEDS.start, high=TRAIN_SEEDS.stop - 1), nargs="+",
                   action=Extend, default=[0, 1, 2, 3, 4], help="seeds of the train split (av_gym/seeds.py)")
    p.add_argument("--grid", choices=sorted(GRIDS), default="full")
    p.add_argument("--refine", type=int, default=60, help="Nelder-Mead evaluations after the grid (0 = none)")
    p.add_argument("--osc-weight", type=float, default=0.1,
                   help="J's cost of one steering sign change per 100 m, in paper CTE units (lane = 100)")
    p.add_argument("--margin", type=float, default=2.0, help="gain margin required (0 = none)")
    p.add_argument("--max-osc", type=float, default=20.0, help="sign changes per 100 m that count as a limit cycle")
    p.add_argument("--out", type=Path, default=None, help="write the result as JSON here")
    a = p.parse_args(argv)
    if a.track == "B":
        p.error("layout B is the held-out evaluation layout; tune on A")
    res = search(GRIDS[a.grid], a.seeds, a.track, a.osc_weight, a.refine, a.margin, a.max_osc)
    print("\n".join(report_lines(res)))
    b = res["best"]
    print(f'agents/pid.py PRESETS:  "tuned": {{"kp": {b["kp"]:g}, "ki": {b["ki"]:g}, "kd": {b["kd"]:g}}},')
    if a.out:
        write_text_atomic(a.out, json.dumps(res, indent=2), "--out")
        print(f"[pid_search] result: {a.out}")
    return res


if __name__ == "__main__":
    main()
