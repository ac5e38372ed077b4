"""The batched AEB shield's conflict prediction for all its row decisions in one compiled call, written straight into
the flat buffers :meth:`av_gym.shields.conflicts.ConflictModel.predict_rows_flat` hands out.

Why a second rows kernel beside :func:`av_gym.shields.kernels.conflict_predict_rows`: that one calls
:func:`~av_gym.shields.kernels.conflict_predict` per decision, which allocates its scratch and its (K, H, 2) result
per decision, looks its hypotheses up into an (H, K, 2) array, copies that into the (K, H, 2) result, and the rows
kernel copies the result once more into the flat buffers: two copies of every position and heading and ~20 small
allocations per decision, on every decision of every tick. Here the scratch is allocated once per call, sized for
its largest decision, and the look-ups (:func:`~av_gym.shields.kernels._lookups` with ``direct``: its poses on
the route's centreline skip a cos and a sin that add exactly 0) write into a transposed view of the decision's
block of the flat buffers, the constant-velocity hypotheses likewise. Every float is computed by the same
operations in the same order as :func:`~av_gym.shields.kernels.conflict_predict` (the hypotheses, the profiles, the
speed-bin fractions, the missing-bin check, the look-ups, ``p + v t``), so each decision is its own call bit for
bit (tests/test_conflict_rows.py, on random decisions, against the per-decision
kernel and :meth:`~av_gym.shields.conflicts.ConflictModel.predict`).
"""

from __future__ import annotations

import numba
import numpy as np

from av_gym.shields.kernels import (_bin_fractions, _lookups, _missing_bins, along_profiles, conflict_hypotheses,
                                    lane_hypotheses)


@numba.njit(cache=True, error_model="numpy")  # as conflict_predict: weights summing to 0 give NaN
def conflict_predict_rows(row_off, others, speeds, phis, lane_row, lanes, hyp_off, hyp_n, hyp_turn, intent, accels,
                          min_p, on_lane, max_dh, fused, follow, hyp_ids, t, accel_time, data, route, limits, bins,
                          grid_table, h_off, xy, hh, owner, is_map, prob, n_h):
    """:func:`av_gym.shields.kernels.conflict_predict_rows` (same arguments, same outputs, the same floats): decision
    r's road users are rows ``row_off[r]`` .. ``row_off[r + 1]`` of ``others`` (M, 7), ``speeds``, ``phis``,
    ``lane_row``, ``intent``, ``accels``, ``follow``; its H hypotheses (map ones first, then the constant-velocity
    ones) go into its block from hypothesis ``h_off[r]`` on: ``xy`` as a (K, H, 2) block from ``2 K h_off[r]`` (m),
    ``hh`` (K, H) from ``K h_off[r]`` (rad), ``owner``, ``is_map``, ``prob`` from ``h_off[r]``. ``n_h[r]``: H, or
    -1 where its H outgrows its block or a speed bin it reads is not simulated yet (its block's positions and
    headings are then not written: the caller's own :meth:`~av_gym.shields.conflicts.ConflictModel.predict` serves
    it)."""
    K, n_bins = t.shape[0], bins.shape[1]
    R = row_off.shape[0] - 1
    n_big, m_big = 1, 1  # the scratch, once, for the largest decision
    for r in range(R):
        n_big = max(n_big, lane_hypotheses(lane_row, hyp_n, row_off[r], row_off[r + 1]))
        m_big = max(m_big, row_off[r + 1] - row_off[r])
    hyp, starts, rows = np.empty(n_big, np.int64), np.empty(n_big), np.empty(n_big, np.int64)
    own, pr, ids = np.empty(n_big, np.int64), np.empty(n_big), np.empty(n_big, np.int64)
    v_on, a_on, cv = np.empty(m_big), np.empty(m_big), np.empty(m_big, np.int64)
    need = np.zeros((n_big, n_bins), np.bool_)
    for r in range(R):
        a, b = row_off[r], row_off[r + 1]
        n, n_on, n_cv = conflict_hypotheses(others[a:b], speeds[a:b], phis[a:b], lane_row[a:b], lanes, hyp_off, hyp_n,
                                            hyp_turn, intent[a:b], accels[a:b], min_p, on_lane, max_dh, fused,
                                            follow[a:b], hyp, starts, rows, own, pr, v_on, a_on, cv)
        H, o = n + n_cv, h_off[r]
        if H > h_off[r + 1] - o:  # numba does not check bounds: a decision outgrowing its block is not written
            n_h[r] = -1
            continue
        bxy = xy[2 * K * o: 2 * K * (o + H)].reshape((K, H, 2))  # this decision's block, (K, H, 2)
        bhh = hh[K * o: K * (o + H)].reshape((K, H))
        if n:
            dist, v_path = along_profiles(v_on[:n_on], a_on[:n_on], t, accel_time)
            for h in range(n):
                ids[h] = hyp_ids[hyp[h]]
            f = _bin_fractions(v_path, grid_table, n_bins)  # once per road user, for all its hypotheses
            need[:n] = False
            if _missing_bins(bins, limits, ids[:n], starts[:n], dist, f, rows[:n], need[:n]):
                n_h[r] = -1
                continue
            # the map hypotheses' look-ups straight into the block, as (H, K, 2) / (H, K) views of it
            _lookups(data, route, limits, bins, ids[:n], starts[:n], dist, f, rows[:n],
                     bxy[:, :n].transpose((1, 0, 2)), bhh[:, :n].transpose(), np.bool_(True))
            for h in range(n):
                owner[o + h], is_map[o + h], prob[o + h] = own[h], True, pr[h]
        for c in range(n_cv):  # the constant-velocity objects: p + v t (object_predict)
            m, h = cv[c], n + c
            for k in range(K):
                bxy[k, h, 0] = others[a + m, 0] + others[a + m, 2] * t[k]
                bxy[k, h, 1] = others[a + m, 1] + others[a + m, 3] * t[k]
                bhh[k, h] = others[a + m, 4]
            owner[o + h], is_map[o + h], prob[o + h] = m, False, 1.0
        n_h[r] = H
