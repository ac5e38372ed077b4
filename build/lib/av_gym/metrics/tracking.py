"""Object-list quality: recall, precision and position RMSE of a detector's or a tracker's output against ground
truth (digest 004 §10.4), so the same scorer measures "before" (raw detections) and "after" (tracks).

Per frame the true objects and the estimates are matched one-to-one by the Hungarian algorithm on Euclidean
centre distance, pairs farther apart than ``gate`` (2 m) rejected. Matched pairs are true positives, unmatched
estimates false positives, unmatched truths false negatives; RMSE is over the matched pairs' centre errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["TrackingScore", "match_objects"]


def match_objects(truth_xy: np.ndarray, est_xy: np.ndarray, gate: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(truth_idx, est_idx)`` of the optimal one-to-one matching of truth (N, 2) to estimates (M, 2)
    with centre distance ≤ ``gate`` m."""
    truth_xy = np.asarray(truth_xy, dtype=float).reshape(-1, 2)
    est_xy = np.asarray(est_xy, dtype=float).reshape(-1, 2)
    if not len(truth_xy) or not len(est_xy):
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    d = np.linalg.norm(truth_xy[:, None] - est_xy[None], axis=-1)
    cost = np.where(d <= gate, d, 1e6)
    rows, cols = linear_sum_assignment(cost)
    ok = d[rows, cols] <= gate
    return rows[ok], cols[ok]


@dataclass
class TrackingScore:
    """Accumulates frames; :meth:`summary` gives recall, precision, F1 and position RMSE (m). Also the
    *recovered-miss rate*: of the true objects the raw detector missed in a frame (``missed`` mask passed to
    :meth:`add`), the fraction the scored output still reports within the gate (digest 004's Fig. 1 effect)."""

    gate: float = 2.0
    tp: int = 0
    fp: int = 0
    fn: int = 0
    sq_err: float = 0.0
    missed: int = 0
    recovered: int = 0

    def add(self, truth_xy: np.ndarray, est_xy: np.ndarray, missed: np.ndarray | None = None) -> None:
        truth_xy = np.asarray(truth_xy, dtype=float).reshape(-1, 2)
        est_xy = np.asarray(est_xy, dtype=float).reshape(-1, 2)
        ti, ei = match_objects(truth_xy, est_xy, self.gate)
        self.tp += len(ti)
        self.fp += len(est_xy) - len(ei)
        self.fn += len(truth_xy) - len(ti)
        self.sq_err += float(np.sum((truth_xy[ti] - est_xy[ei]) ** 2))
        if missed is not None:
            missed = np.asarray(missed, dtype=bool)
            self.missed += int(missed.sum())
            self.recovered += int(missed[ti].sum())

    def summary(self) -> dict[str, float]:
        nan = float("nan")
        recall = self.tp / (self.tp + self.fn) if self.tp + self.fn else nan
        precision = self.tp / (self.tp + self.fp) if self.tp + self.fp else nan
        f1 = 2 * recall * precision / (recall + precision) if recall == recall and precision == precision \
            and recall + precision > 0 else nan
        return {"recall": recall, "precision": precision, "f1": f1,
                "rmse_m": float(np.sqrt(self.sq_err / self.tp)) if self.tp else nan,
                "recovered_miss_rate": self.recovered / self.missed if self.missed else nan,
                "tp": float(self.tp), "fp": float(self.fp), "fn": float(self.fn)}
