"""How repeatable ``belief_lookahead``'s label is: the same decision states labelled again on other futures.

    python benchmarks/label_noise.py checkpoints/dagger_curve_s1 --episodes 150 --samples 16 64

The planner labels a state GO when at most ``threshold`` of K futures drawn from its belief collide (agents/belief.py):
a Monte Carlo estimate against a threshold, so a state whose GO risk p lies near it is labelled GO on one draw of the
futures and YIELD on another. With K = 16 and threshold 0.05 the label is GO only when all 16 futures are safe,
P(GO) = (1 - p)^16.

States: ``--episodes`` validation episodes driven on the batch by the DAgger run's student (``--model`` in the run's
folder, deterministic, as it drives its DAgger rounds) or by the planner (``--driver teacher``). At every decision
each K of ``--samples`` labels the state ``--repeats`` times, each time on its own planner seed (the first K's first
replicate on ``--seed``, the planner's own: the label DAgger trained on). Reported, overall and by the state's pooled
risk p̄ (the collision share over every future drawn for it, all K and replicates):

- ``self K``: the share of replicate pairs of K that agree (an unbiased estimate of E[q² + (1-q)²], q = P(GO label));
- ``best K16``: a label predictor with the K=16 label's noise averaged out (GO when the probability that a K=16 label
  is GO, estimated from the largest K's futures alone, is over 1/2), scored against the K=16 labels, whose futures it
  never saw: what a student that learned the planner's function exactly would agree with its labels (a lower bound on
  the best agreement, E[max(q, 1-q)]); self-agreement is not that ceiling, a predictor beats it;
- ``student``: the student's choice against the K=16 labels (DAgger's ``agreement`` in rounds.csv) and against
  that predictor (how well it learned the function, the label noise taken out).

Then, by how many road users alive the student's features leave out (beyond its nearest ``max_objects`` or its
``max_range``; the planner's futures play them all): its agreement and its errors on clear-cut states.

``--out`` writes the table as csv, ``--states`` the per-state arrays (npz); neither overwrites a file.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from av_gym.wrappers import GO, YIELD  # noqa: E402  (after the path above)

EDGES = (0.0, 1e-9, 0.025, 0.05, 0.1, 0.2, 1.0)  # bins of the pooled risk p̄: exactly 0, then up to 1


# ------------------------------------------------------------------------------------------------ the statistics
def pair_agreement(labels: np.ndarray) -> np.ndarray:
    """Per state, the share of its replicate pairs that agree: ``labels`` (n, R) with R >= 2 replicates of each
    state's label (any integers). A state with m GO-like labels of R agrees on (C(m,2) + C(R-m,2)) / C(R,2) pairs,
    counted here for any number of classes."""
    labels = np.asarray(labels)
    n, R = labels.shape
    if R < 2:
        raise ValueError(f"pair agreement needs at least 2 replicates per state, got {R}")
    same = labels[:, :, None] == labels[:, None, :]  # (n, R, R)
    return (same.sum(axis=(1, 2)) - R) / (R * (R - 1))


def p_label_go(collided: np.ndarray, drawn: np.ndarray, K: int, threshold: float) -> np.ndarray:
    """P(a K-future label is GO) for each state, estimated without bias from ``collided`` of ``drawn`` futures of
    the state (drawn >= K): the chance that K of them, drawn without replacement, hold at most ⌊threshold·K⌋
    collisions (the hypergeometric CDF; an unbiased estimate of the binomial P(Binom(K, p) <= m))."""
    from scipy.stats import hypergeom

    m = int(np.floor(float(threshold) * K + 1e-9))  # agents/belief.py: GO when the share is <= threshold (+1e-12)
    collided, drawn = np.asarray(collided, dtype=int), np.asarray(drawn, dtype=int)
    if np.any(drawn < K):
        raise ValueError(f"estimating a {K}-future label needs at least {K} futures per state")
    return hypergeom.cdf(m, drawn, collided, K)


def bins_of(risk: np.ndarray, edges: tuple[float, ...] = EDGES) -> np.ndarray:
    """The bin of each pooled risk: 0 for exactly 0 (below ``edges[1]``), then (edges[i], edges[i+1]]."""
    return np.clip(np.searchsorted(np.asarray(edges), np.asarray(risk), side="left") - 1, 0, len(edges) - 2)


def pooled_risk(states: dict) -> np.ndarray:
    """Each state's colliding share of every future drawn for it (all K, all replicates)."""
    coll = sum(c.sum(axis=1) for c in states["collided"].values())
    return coll / sum(K * lab.shape[1] for K, lab in states["labels"].items())


def by_unseen(states: dict, clear: tuple[float, float] = (0.0, 0.2)) -> list[dict]:
    """The student's agreement with the labels by how many road users its features leave out (``unseen``: alive,
    not among its nearest ``max_objects`` within ``max_range``): 0, 1, 2 or more; ``clear_error`` is the share of
    the group's states that are clear-cut (pooled risk ``clear[0]`` exactly, or over ``clear[1]``) and that the
    student answers otherwise than the labels' first replicate."""
    k0 = min(states["labels"])
    base, student = states["labels"][k0][:, 0], np.asarray(states["student"])
    risk = pooled_risk(states)
    clear_cut = (risk <= clear[0]) | (risk > clear[1])
    group = np.minimum(np.asarray(states["unseen"]), 2)
    rows = []
    for g in range(3):
        sel = group == g
        if sel.any():
            rows.append({"unseen": ("2+" if g == 2 else str(g)), "states": int(sel.sum()), "share": float(sel.mean()),
                         f"student_K{k0}": float(np.mean(student[sel] == base[sel])),
                         "clear_error": float(np.mean(clear_cut[sel] & (student[sel] != base[sel])))})
    return rows


def table(states: dict, threshold: float, edges: tuple[float, ...] = EDGES) -> list[dict]:
    """The rows of the report (``all`` and one per risk bin) from :func:`collect`'s arrays: ``labels[K]`` (n, R),
    ``collided[K]`` (n, R) futures that collided of ``K`` each, ``student`` (n,) the driver's choices."""
    Ks = sorted(states["labels"])
    k0, big = Ks[0], Ks[-1]
    risk = pooled_risk(states)
    q = p_label_go(states["collided"][big].sum(axis=1), big * states["labels"][big].shape[1], k0, threshold)
    best = np.where(q > 0.5, GO, YIELD)
    base, student = states["labels"][k0], np.asarray(states["student"])
    which = bins_of(risk, edges)
    rows = []
    for b in [None, *range(len(edges) - 1)]:
        sel = np.ones(len(risk), bool) if b is None else which == b
        if not sel.any():
            continue
        row = {"risk": "all" if b is None else (f"{edges[b]:g}" if b == 0 else f"({edges[b]:g}, {edges[b + 1]:g}]"),
               "states": int(sel.sum()), "share": float(sel.mean()), "label_go": float(np.mean(base[sel] == GO))}
        for K in Ks:
            row[f"self_K{K}"] = float(pair_agreement(states["labels"][K][sel]).mean())
        if big != k0:  # the predictor's futures are the largest K's only, never the K=16 labels' own
            row[f"best_K{k0}"] = float(np.mean(best[sel, None] == base[sel]))
        row[f"student_K{k0}"] = float(np.mean(student[sel, None] == base[sel]))
        if big != k0:
            row["student_best"] = float(np.mean(student[sel] == best[sel]))
        rows.append(row)
    return rows


# ------------------------------------------------------------------------------------------------ the states
def _stack(run_dir: Path, n_envs: int):
    """The run's batch (its env, sensors, shield from config.yaml), its agent config and the planner's params."""
    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from agents.checkpoint import read_config_yaml
    from train.imitation import make_teacher

    cfg = read_config_yaml(run_dir / "config.yaml")
    agent = cfg.get("agent", {})
    if agent.get("teacher") is None:
        from av_gym.errors import ConfigError

        raise ConfigError(f"{run_dir} is not a DAgger run's folder (config.yaml names no agent.teacher)")
    repeat, actions = int(agent["action_repeat"]), str(agent["actions"])
    teacher = make_teacher(str(agent["teacher"]), actions, str(cfg["env"]["name"]), repeat)
    if getattr(teacher, "belief", None) is None:
        from av_gym.errors import ConfigError

        raise ConfigError(f"agent.teacher={agent['teacher']} of {run_dir} is not a belief planner")
    venv = BatchedLeftTurnVecEnv(cfg["env"], cfg["sensors"], cfg["shield"], n_envs, action_repeat=repeat,
                                 actions=actions, timeout_is_terminal=bool(agent["timeout_is_terminal"]), pool=0)
    return venv, teacher.belief


def _labellers(venv, belief, samples: list[int], repeats: int, seed: int) -> dict[int, list]:
    """R labellers per K, each DAgger's own BatchedLabels on its own planner seed (seed, seed + 1, ... in the
    order of ``samples``, then replicates): independent futures, the same readings."""
    from dataclasses import replace
    from types import SimpleNamespace

    from train.dagger import BatchedLabels

    out, s = {}, seed
    for K in samples:
        out[K] = []
        for _ in range(repeats):
            teacher = SimpleNamespace(belief=replace(belief, samples=int(K), seed=s))
            out[K].append(BatchedLabels(venv, teacher, True, 0.0))
            s += 1
    return out


def collect(run_dir: Path, model_name: str, driver: str, episodes: int, n_envs: int, samples: list[int],
            repeats: int, seed: int, first: int | None) -> tuple[dict, float]:
    """Drive ``episodes`` validation episodes, labelling every decision ``repeats`` times per K; the per-state
    arrays (``labels``/``collided`` per K, (n, R); the driver's ``student`` choices) and the planner's threshold."""
    from tqdm import tqdm

    from agents.checkpoint import load_sb3
    from av_gym.seeds import config_seeds

    venv, belief = _stack(run_dir, n_envs)
    model = load_sb3(run_dir / model_name, device="cpu")
    labellers = _labellers(venv, belief, samples, repeats, seed)
    labels = {K: [] for K in samples}
    collided = {K: [] for K in samples}
    chosen, unseen = [], []
    obs = venv.play(iter(config_seeds("validation", episodes, first, "--first")))
    B = venv.num_envs
    bar = tqdm(desc="label_noise: decision states labelled", unit="state", leave=False)  # minutes on real runs
    while not venv.idle.all():
        rows = np.nonzero(~venv.idle)[0]
        bar.update(len(rows))
        for K in samples:
            got = [lab(rows, obs) for lab in labellers[K]]
            labels[K].append(np.stack(got, axis=1))
            collided[K].append(np.stack([np.rint((1.0 - lab.go_safe) * K) for lab in labellers[K]], axis=1))
        student = np.asarray(model.predict(obs, deterministic=True)[0]).reshape(B)
        actions = student.copy()
        if driver == "teacher":
            actions[rows] = labels[samples[0]][-1][:, 0]
        chosen.append(student[rows])
        unseen.append(_unseen(venv.engine, rows))
        obs, _, _, _ = venv.step(actions)
    bar.close()
    venv.close()
    states = {"labels": {K: np.concatenate(v) for K, v in labels.items()},
              "collided": {K: np.concatenate(v).astype(int) for K, v in collided.items()},
              "student": np.concatenate(chosen), "unseen": np.concatenate(unseen)}
    return states, float(belief.threshold)


def _unseen(engine, rows: np.ndarray) -> np.ndarray:
    """Per row, the road users alive that ``obs["turn"]`` does not describe (beyond its nearest ``max_objects`` or
    its ``max_range``): what the planner's futures play and the student never sees."""
    from agents.belief import described

    t = engine.traffic
    _, present, _ = described(engine, rows)
    return (t.alive[rows] & ~t.ego[rows]).sum(axis=1) - present.sum(axis=1)


# ------------------------------------------------------------------------------------------------ the command
def _args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", nargs="?", default="checkpoints/dagger_curve_s1",
                    help="a DAgger run's folder whose teacher is belief_lookahead (config.yaml and --model)")
    ap.add_argument("--model", default="best.zip", help="the student in run_dir that drives (--driver student)")
    ap.add_argument("--driver", default="student", choices=["student", "teacher"],
                    help="whose choices drive the episodes: the student's states (DAgger's) or the planner's")
    ap.add_argument("--episodes", type=int, default=2, help="validation episodes (the split's first)")
    ap.add_argument("--first", type=int, default=None, help="first validation seed (default: the split's first)")
    ap.add_argument("--n-envs", type=int, default=2, help="episodes stepped together on the batch")
    ap.add_argument("--samples", type=int, nargs="+", default=[16, 64],
                    help="futures per label (K), each labelled --repeats times; the first is the labels' K")
    ap.add_argument("--repeats", type=int, default=2, help="independent labels per state and K (planner seeds)")
    ap.add_argument("--seed", type=int, default=0, help="the first planner seed (0: the planner's own, DAgger's)")
    ap.add_argument("--out", default=None, help="write the table here as csv (an existing file is refused)")
    ap.add_argument("--states", default=None, help="write the per-state arrays here as npz (never overwritten)")
    args = ap.parse_args(argv)
    for name in ("episodes", "n_envs"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.repeats < 2:
        ap.error(f"--repeats must be >= 2 (agreement is between replicates), got {args.repeats}")
    if min(args.samples) < 1 or args.samples[0] != min(args.samples):
        ap.error(f"--samples must be >= 1 with the labels' K first and smallest, got {args.samples}")
    from av_gym.atomic import FileExists, new_paths

    try:  # before the episodes (minutes); _write asks again before writing either
        new_paths((args.out, "--out"), (args.states, "--states"))
    except FileExists as exc:
        ap.error(str(exc))
    return args


def _write(args: argparse.Namespace, rows: list[dict], states: dict) -> None:
    from av_gym.atomic import csv_text, new_path, new_paths, write_text_new

    # both still free before either is written (one that appeared since _args' check would leave half a pair);
    # each linked into place (av_gym.atomic.new_path): a file that appears meanwhile is kept, not replaced
    new_paths((args.out, "--out"), (args.states, "--states"))
    if args.out:
        write_text_new(args.out, csv_text(rows), "--out")
    if args.states:
        arrays = {f"{k}_K{K}": v for k in ("labels", "collided") for K, v in states[k].items()}
        with new_path(args.states, "--states") as tmp, open(tmp, "wb") as f:
            np.savez_compressed(f, student=states["student"], unseen=states["unseen"], **arrays)


def main(argv: list[str] | None = None) -> None:
    args = _args(argv)
    import torch

    torch.set_num_threads(1)
    start, cpu = time.perf_counter(), time.process_time()
    states, threshold = collect(Path(args.run_dir), args.model, args.driver, args.episodes, args.n_envs,
                                list(args.samples), args.repeats, args.seed, args.first)
    rows = table(states, threshold)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    print(f"{len(states['student'])} decision states of {args.episodes} validation episodes driven by the "
          f"{args.driver} ({args.run_dir}/{args.model}); planner threshold {threshold:g}, K {args.samples} x "
          f"{args.repeats} replicates; {wall:.0f} s wall, {cpu:.0f} CPU-s")
    keys = list(rows[0])
    print(" | ".join(keys))
    for r in rows:
        print(" | ".join(f"{r[k]:.3f}" if isinstance(r[k], float) else str(r[k]) for k in keys))
    groups = by_unseen(states)
    print("by road users the student's features leave out:")
    for r in groups:
        print(" | ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()))
    _write(args, rows, states)


if __name__ == "__main__":
    from av_gym.errors import run_cli

    run_cli(main)
