"""The AEB shield's set-off rule (:meth:`ImprovedAEB._setoff_predict`, the prediction :meth:`ImprovedAEB._setoff_stop`
tests) for many decisions at once, on flat buffers as :meth:`ConflictModel.predict_rows_flat` has them.

Why by hand: the rule is the shield's own (digest 003's stop-line trigger with a standing car that may set off); no
library has it. Each function here is the per-decision code's operations element by element (the same floats by
construction; tests/test_setoff_rows.py checks them bit for bit against the per-decision code): the batch shield's
screen (:meth:`av_gym.batched.shield.BatchedShield._screen`) uses them to decide, for all rows at once, the rows at the
stop-line trigger point whose set-off rule finds nothing, instead of each row's ~1 ms of Python.
"""

from __future__ import annotations

import numpy as np


def box_lanes(index) -> np.ndarray:
    """(L,) bool per lane id of the engine's lane table ``index`` (lane index tuples): a lane through the box (its
    start node ``ir...``), :meth:`ImprovedAEB._setoff_predict`'s ``box`` test."""
    return np.array([li is not None and str(li[0]).startswith("ir") for li in index], dtype=bool)


def setoff_slow(others: np.ndarray, in_box: np.ndarray, recent: np.ndarray, setoff_speed: float) -> np.ndarray:
    """(M,) bool: the road users the set-off rule predicts setting off (:meth:`ImprovedAEB._setoff_predict`'s
    ``slow``): on a lane through the box (``in_box``), slower than ``setoff_speed`` (m/s; numpy's hypot of
    ``others`` (M, 7)'s velocity) and moving lately (``recent``); rows of many decisions one after the other."""
    speed = np.hypot(others[:, 2], others[:, 3]) if len(others) else np.zeros(0)
    return in_box & (speed < setoff_speed) & recent


def setoff_start(others: np.ndarray, setoff_accel: float) -> tuple[np.ndarray, np.ndarray]:
    """The standing road users ``others`` (M, 7) as the set-off rule predicts them: their rows with the velocity
    0.5 m/s along the heading, and the acceleration ``setoff_accel`` (m/s²) along it, (M, 2) world frame."""
    mod = others.copy()
    direction = np.stack([np.cos(mod[:, 4]), np.sin(mod[:, 4])], 1)
    mod[:, 2:4] = 0.5 * direction
    return mod, setoff_accel * direction


def predict_rows_following(model, others: np.ndarray, row_off: np.ndarray, lane_indices: list, accels: np.ndarray,
                           t: np.ndarray, intent: np.ndarray | None, accel_time: float) -> tuple | None:
    """:meth:`ConflictModel.predict` with every road user following its lanes (``follow`` all True) and keeping its
    acceleration ``accel_time`` s (:meth:`ImprovedAEB._accel_predict`'s call) for many decisions in one compiled
    call: :meth:`ConflictModel.predict_rows_flat`'s arguments and buffers ``(h_off, n_h, xy, hh, owner, is_map,
    prob)`` (decision r's ``n_h[r]`` hypotheses, -1 where a speed bin is missing or it outgrows its block); None
    where the kernels are switched off or cannot read the lanes (the caller's rows then decide themselves)."""
    from av_gym.shields import conflicts
    from av_gym.shields.kernels import conflict_predict_rows
    from av_gym.shields.predict import DrivenPath

    if not (conflicts.CONFLICT_KERNEL and DrivenPath.kernel):
        return None
    inputs = model._kernel_inputs(others, lane_indices, accels, intent, np.ones(len(others), bool))
    if inputs is None:
        return None
    reg, args = inputs
    row_off = np.asarray(row_off, dtype=np.int64)
    t = np.ascontiguousarray(t, dtype=float)
    h_off = conflicts._row_blocks(reg, args[3], row_off)
    K, n_all, R = len(t), int(h_off[-1]), len(row_off) - 1
    xy, hh, prob = np.empty(2 * K * n_all), np.empty(K * n_all), np.empty(n_all)
    owner, is_map, n_h = np.empty(n_all, np.int64), np.empty(n_all, np.bool_), np.empty(R, np.int64)
    conflict_predict_rows(row_off, *args, reg.ids, t, float(accel_time), *conflicts._store_arrays(), h_off, xy, hh,
                          owner, is_map, prob, n_h)
    return h_off, n_h, xy, hh, owner, is_map, prob
