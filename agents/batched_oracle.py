"""The look-ahead oracle (:class:`agents.go_yield.Lookahead`) for a whole batch of left turns at once.

The per-env oracle deep-copies one env and plays its GO future to the end (~0.1 s per decision). Here the states of
every env of a :class:`~av_gym.batched.left_turn.BatchedLeftTurn` that needs a label are copied as arrays
(traffic rows, clocks, and each env's random generator, so the future spawns are the real ones) into one future
batch, which is stepped with GO in all rows together until each row's episode ends. A row's label is the oracle's:
GO is safe now iff its GO future ends without a collision. The future also gives the *margin* of that decision: the
smallest centre distance between the ego and any other vehicle along it (m), and when it arrives (s): a label
richer than the argmax, from which a student can learn calibrated risk and a user can pick an operating point
(``margin``: GO only where the future also keeps that distance).

benchmarks/oracle_labels.py measures its agreement with the per-env oracle on the same states and the labels per
second of both; tests/test_dagger.py checks the agreement on a few hundred decisions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from av_gym.batched.vec_env import meta_actions
from av_gym.batched.left_turn import BatchedLeftTurn
from av_gym.wrappers import GO, YIELD

__all__ = ["GoFutures", "go_futures", "oracle_labels"]


@dataclass
class GoFutures:
    """What the GO futures of a set of rows gave, one entry per row."""

    safe: np.ndarray
    """bool: the GO future ends without a collision (the oracle's choice: GO)"""
    min_gap: np.ndarray
    """m: the smallest centre distance between the ego and another vehicle along the future (inf: none seen)"""
    end_time: np.ndarray
    """s: the episode time at which the future ended (arrival, collision or the time limit)"""
    arrived: np.ndarray
    """bool: the future ended with the ego's arrival"""

    def labels(self, margin: float = 0.0) -> np.ndarray:
        """GO (1) where GO is safe and keeps at least ``margin`` metres from everyone, else YIELD (0)."""
        return np.where(self.safe & (self.min_gap >= float(margin)), GO, YIELD).astype(np.int64)


def go_futures(engine: BatchedLeftTurn, rows: np.ndarray | None = None, spawns: bool = True) -> GoFutures:
    """Play the GO future of each env ``rows`` of ``engine`` (default: all) to its episode's end, all together:
    GO at every env step (its meta-action from the features, as :class:`~av_gym.wrappers.GoYieldActions`) in a
    fork of the engine (:meth:`~av_gym.batched.left_turn.BatchedLeftTurn.fork`: each row's generator deep-copied,
    so the future draws the spawns the real episode will draw; ``spawns=False``: no vehicle enters it); the rows
    whose episode ended are no longer stepped."""
    rows = np.arange(engine.B) if rows is None else np.asarray(rows, dtype=int)
    n = len(rows)
    out = GoFutures(np.ones(n, bool), np.full(n, np.inf), np.zeros(n), np.zeros(n, bool))
    if n == 0:
        return out
    f = engine.fork(rows, spawns=spawns)
    active, live = np.ones(n, bool), np.arange(n)
    actions = np.full(n, GO)  # meta-actions; the ended rows' entries are not read
    turn = f.observe()
    while len(live):  # features only of the rows still playing (each row's are its own)
        actions[live] = meta_actions(np.full(len(live), GO), turn)
        _, terminated, truncated = f.step(actions, active)
        out.min_gap[live] = np.minimum(out.min_gap[live], _nearest(f, live))
        ended = (terminated | truncated) & active
        if ended.any():
            e = np.nonzero(ended)[0]
            slots = f.ego_slot(e)
            out.safe[e] = ~f.traffic.crashed[e, slots]
            out.arrived[e] = f.has_arrived(e, slots)
            out.end_time[e] = f.time[e]
            active &= ~ended
        live = np.nonzero(active)[0]
        if len(live):
            turn = f.observe(live)
    return out


def _nearest(f: BatchedLeftTurn, rows: np.ndarray) -> np.ndarray:
    """Centre distance from each row's ego to its nearest other vehicle (m; inf if alone)."""
    t = f.traffic
    e = f.ego_slot(rows)
    d = np.hypot(t.x[rows] - t.x[rows, e][:, None], t.y[rows] - t.y[rows, e][:, None])
    d = np.where(t.alive[rows] & ~t.ego[rows], d, np.inf)
    return d.min(axis=1)


def oracle_labels(engine: BatchedLeftTurn, rows: np.ndarray, margin: float = 0.0) -> tuple[np.ndarray, GoFutures]:
    """The oracle's GO/YIELD labels for the envs ``rows`` (see :meth:`GoFutures.labels`) and their futures."""
    futures = go_futures(engine, rows)
    return futures.labels(margin), futures
