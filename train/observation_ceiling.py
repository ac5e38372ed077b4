"""How well can a student's observation tell its labels apart? The observation's own ceiling on a DAgger aggregate:
``python -m train.observation_ceiling checkpoints/<run> [--resolutions 0.05 0.02 0.01] [--queries 4000]
[--k 1 5 25] [--out runs/ceiling/x.json]``.

A student that fits its aggregate to only 0.94 (docs/dagger.md, "Why it flattens") is short either in its
representation (a function of the observation that would fit better exists, the refits do not find it) or in the
observation (states the teacher tells apart look the same to the student, with different labels). Two estimates of
the second, neither using a fitted model nor smoothing the labels:

- **near-duplicates**: the observation (every column of every key, flattened) rounded to a grid of ``resolution``
  (the features are scaled to about [-1, 1]); states in one cell from *different* episodes are near-identical
  observations of different moments. Per state that has such twins, the share of them whose label differs; its mean
  D estimates E[2 q (1 - q)], q = P(GO | cell), without bias (two labels of a cell are independent draws), and the
  Bayes error of a student that sees only the cell, E[min(q, 1 - q)], lies in [D / 2, D]. A coarser grid merges
  states that differ and raises D: the finest grid with enough twins is the bound that counts.
- **nearest neighbours**: for ``--queries`` random states, their k nearest states of other episodes (Euclidean on the
  flattened observation); the error of the neighbours' majority label for each k. Asymptotically the 1-NN error
  R1 bounds the Bayes error R* from both sides (Cover and Hart 1967, two classes): (1 - sqrt(1 - 2 R1)) / 2 <= R* <=
  R1; on a finite sample in ~140 dimensions R1 also counts neighbours that are far (an overestimate of both bounds).

Episodes: DAgger aggregates its states episode by episode in order (train/dagger.py); an episode starts where the
elapsed-time feature (obs["turn"] column ``time``) does not grow. The same split keeps a held-out share of episodes
away from a fit (train/dagger_forms.py ``--holdout``), so that a fit is told from memorisation.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from av_gym.errors import ConfigError, run_cli
from conf.cli import ToolParser


def episode_ids(elapsed: np.ndarray) -> np.ndarray:
    """Each state's episode (0, 1, ...) in an aggregate stored episode by episode: a new episode wherever the
    elapsed time (any unit) does not grow from the state before."""
    elapsed = np.asarray(elapsed, dtype=np.float64)
    starts = np.concatenate([[False], np.diff(elapsed) <= 0.0])
    return np.cumsum(starts)


def holdout_mask(episodes: np.ndarray, share: float, seed: int) -> np.ndarray:
    """True for the states of a random ``share`` of the episodes (at least one, when share > 0), drawn from a
    generator seeded ``seed``."""
    ids = np.unique(episodes)
    if not 0.0 <= share < 1.0:
        raise ConfigError(f"--holdout must be in [0, 1), got {share}")
    n = 0 if share == 0 else max(1, int(round(share * len(ids))))
    held = np.random.default_rng(seed).choice(ids, size=n, replace=False)
    return np.isin(episodes, held)


def flat_observations(obs: dict[str, np.ndarray]) -> np.ndarray:
    """The observation's keys (sorted) flattened side by side, one row a state."""
    return np.concatenate([np.asarray(obs[k], dtype=np.float64).reshape(len(obs[k]), -1) for k in sorted(obs)],
                          axis=1)


def twin_disagreement(x: np.ndarray, labels: np.ndarray, episodes: np.ndarray, resolution: float) -> dict:
    """Near-duplicates on a grid of ``resolution``: per state with at least one twin (same cell, another episode),
    the share of its twins labelled otherwise; returns their mean ``D`` (the Bayes bracket [D/2, D]), the share of
    states with twins, the cells holding them and the plug-in minority share of those cells (biased low)."""
    cells = np.unique(np.round(np.asarray(x) / resolution).astype(np.int64), axis=0, return_inverse=True)[1].ravel()
    classes, cls = np.unique(np.asarray(labels), return_inverse=True)
    cls, n_cls = cls.ravel(), len(classes)
    # the state's cell and episode together: its twins are the cell's states less those of its own episode
    pairs = np.unique(cells * (int(np.max(episodes)) + 1) + np.asarray(episodes), return_inverse=True)[1].ravel()
    twins = np.bincount(cells)[cells] - np.bincount(pairs)[pairs]
    alike_cell = np.bincount(cells * n_cls + cls)[cells * n_cls + cls]  # same label in the cell (itself included)
    alike_own = np.bincount(pairs * n_cls + cls)[pairs * n_cls + cls]  # ... in the cell's own episode
    other = twins - (alike_cell - alike_own)  # twins labelled otherwise
    has = twins > 0
    d = float(np.mean(other[has] / twins[has])) if has.any() else float("nan")
    used = np.unique(cells[has])
    counts = np.bincount(cells * n_cls + cls, minlength=(cells.max() + 1) * n_cls).reshape(-1, n_cls)[used]
    plug = float((counts.sum() - counts.max(axis=1).sum()) / max(counts.sum(), 1))
    return {"resolution": resolution, "states_with_twins": float(np.mean(has)), "cells": int(len(used)),
            "D": d, "bayes_low": d / 2, "bayes_high": d, "minority_plugin": plug}


def neighbour_errors(x: np.ndarray, labels: np.ndarray, episodes: np.ndarray, ks: list[int], queries: int,
                     seed: int, chunk: int = 64) -> dict:
    """For ``queries`` states drawn from a generator seeded ``seed``: the error of the majority label of their k
    nearest states in other episodes (Euclidean; ties of the vote go to the nearest neighbour's label), per k; with
    the Cover-Hart bracket from the 1-NN error when k = 1 is asked."""
    x = np.asarray(x, dtype=np.float32)
    labels, episodes = np.asarray(labels), np.asarray(episodes)
    picked = np.random.default_rng(seed).choice(len(labels), size=min(queries, len(labels)), replace=False)
    sq = np.einsum("ij,ij->i", x, x)
    kmax, wrong = max(ks), {k: 0 for k in ks}
    for start in range(0, len(picked), chunk):
        q = picked[start:start + chunk]
        d2 = sq[q, None] + sq[None, :] - 2.0 * (x[q] @ x.T)
        d2[episodes[q, None] == episodes[None, :]] = np.inf  # only other episodes: no moment's own neighbours
        near = np.argpartition(d2, kmax - 1, axis=1)[:, :kmax]
        near = np.take_along_axis(near, np.argsort(np.take_along_axis(d2, near, axis=1), axis=1), axis=1)
        for k in ks:
            wrong[k] += int(np.sum(_vote(labels[near[:, :k]]) != labels[q]))
    out = {"queries": int(len(picked)), "error": {str(k): wrong[k] / len(picked) for k in ks}}
    if 1 in ks:
        r1 = out["error"]["1"]
        out["cover_hart"] = [(1.0 - np.sqrt(max(1.0 - 2.0 * r1, 0.0))) / 2.0, r1]
    return out


def _vote(votes: np.ndarray) -> np.ndarray:
    """The most frequent label of each row, the first (nearest) of the tied ones on a tie."""
    out = np.empty(len(votes), dtype=votes.dtype)
    for i, row in enumerate(votes):
        values, counts = np.unique(row, return_counts=True)
        best = values[counts == counts.max()]
        out[i] = next(v for v in row if v in best)
    return out


def load_states(run_dir: Path) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The aggregate of ``run_dir``'s latest.zip as arrays per observation key, and its labels."""
    import io

    from train.dagger import read_aggregate

    npz = read_aggregate(run_dir / "latest.zip", lambda raw: np.load(io.BytesIO(raw)))
    return {k[len("obs:"):]: npz[k] for k in npz.files if k.startswith("obs:")}, npz["labels"]


def elapsed_column(obs: dict[str, np.ndarray]) -> np.ndarray:
    """The elapsed-time feature of obs["turn"] (av_gym/estimation/turn_features.py EGO_FEATURES)."""
    from av_gym.estimation.turn_features import EGO_FEATURES

    if "turn" not in obs:
        raise ConfigError(f"the aggregate's observation has no 'turn' key (has {sorted(obs)}): its episodes are "
                          f"told apart by obs['turn']'s elapsed time")
    return obs["turn"][:, EGO_FEATURES.index("time")]


def ceiling(run_dir: Path, resolutions: list[float], ks: list[int], queries: int, seed: int) -> dict:
    """Both estimates on ``run_dir``'s aggregate (module docstring)."""
    obs, labels = load_states(run_dir)
    episodes = episode_ids(elapsed_column(obs))
    x = flat_observations(obs)
    row = {"run": str(run_dir), "states": int(len(labels)), "episodes": int(episodes.max() + 1),
           "columns": int(x.shape[1]), "label_go": float(np.mean(labels == np.max(labels)))}
    row["twins"] = [twin_disagreement(x, labels, episodes, r) for r in resolutions]
    if queries > 0:
        row["neighbours"] = neighbour_errors(x, labels, episodes, ks, queries, seed)
    return row


def main(argv: list[str] | None = None) -> None:
    from train.checkpoint import write_text_atomic

    parser = ToolParser(prog="python -m train.observation_ceiling", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="checkpoints/<run_name>/ of a DAgger run (its latest.zip)")
    parser.add_argument("--resolutions", type=float, nargs="+", default=[0.05, 0.02, 0.01],
                        help="grids of the near-duplicates (feature units, the features scaled to about [-1, 1])")
    parser.add_argument("--queries", type=int, default=2000, help="states whose nearest neighbours vote (0: none)")
    parser.add_argument("--k", type=int, nargs="+", default=[1, 5, 25], help="neighbours that vote")
    parser.add_argument("--seed", type=int, default=0, help="the draw of the query states")
    parser.add_argument("--out", default=None, help="write the row as JSON here (a file that exists is refused)")
    args = parser.parse_args(argv)
    if any(r <= 0 for r in args.resolutions) or any(k < 1 for k in args.k) or args.queries < 0:
        parser.error(f"--resolutions must be > 0, --k >= 1 and --queries >= 0, got {args.resolutions}, {args.k}, "
                     f"{args.queries}")
    if args.out and Path(args.out).exists():
        parser.error(f"--out {args.out} exists: another measurement's row; choose another file")
    row = ceiling(Path(args.run_dir), args.resolutions, args.k, args.queries, args.seed)
    print(json.dumps(row, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(args.out), json.dumps(row, indent=1) + "\n")


if __name__ == "__main__":
    run_cli(main)
