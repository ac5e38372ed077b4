"""Numba kernel for the AEB shield's driven-path look-up (< 1 ms per decision at 20 road users).

:meth:`av_gym.shields.predict.DrivenPath.poses` places one path hypothesis on its driven path: about twenty small
numpy calls (interpolations, masks, a blend of two speed bins), ~0.18 ms, and the conflict model makes ~40 such
look-ups per decision at 20 road users, most of the shield's cost (docs/shield.md).
:func:`driven_poses` does the look-ups of every hypothesis of a decision in one call, on the tables of every driven
path packed into one growing float array (:class:`Store`).

What stays identical (the project's kernel rule, av_gym/sim/kernels.py): the numpy reference
(:meth:`DrivenPath.poses_numpy`) is kept; the kernel evaluates its formulas in the same order of operations (no
``fastmath``: no reassociation, no fused multiply-adds), ``np.interp`` exactly as numpy's C code does (the last
table index ``j`` with ``xp[j] <= x``, the end values outside, ``fp[j]`` on an exact knot, the slope
``(fp[j+1] - fp[j]) / (xp[j+1] - xp[j])``), and the speed-bin blend as the reference accumulates it. numba's
``math.cos``/``sin`` are the C library's, as numpy's float64 ufuncs are on this project's (AVX2) machines, so the
results are the reference's bit for bit (tests/test_aeb.py checks it on random look-ups and whole episodes).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

from av_gym.sim import fmath
from av_gym.sim.kernels import box_corners, boxes_overlap  # the engine's box geometry, one copy of the maths


class Store:
    """Every driven path's tables in one growing float64 array, and each path's place in it, so that one kernel
    call can read the tables of any number of paths (module-level: shared by every shield of the process, as the
    paths themselves are, and left out of deep copies of a shield).

    A registered path (:meth:`register`, on the speed bins ``grid``) has an id: row ``id`` of ``route`` (offset
    and length of its route table: columns s, x, y, heading), ``limits`` (its table's start distance ``s_start``
    and the route's length) and ``bins`` (offset and length of each speed bin's driven table: columns distance,
    x, y, heading, route position; length 0 until the bin is simulated)."""

    def __init__(self, grid: np.ndarray, capacity: int = 1 << 16, paths: int = 64) -> None:
        self.grid = np.asarray(grid, dtype=float)
        self.grid_table = np.concatenate([self.grid, np.arange(len(self.grid), dtype=float)])  # xp, then fp
        self.data = np.zeros(capacity)
        self.n = 0
        self.route = np.zeros((paths, 2), dtype=np.int64)
        self.limits = np.zeros((paths, 2))
        self.bins = np.zeros((paths, len(self.grid), 2), dtype=np.int64)
        self.paths = 0

    def add(self, *columns: np.ndarray) -> int:
        """Append equal-length columns one after the other; the offset of the first."""
        need = sum(len(c) for c in columns)
        if self.n + need > len(self.data):
            grown = np.zeros(max(2 * len(self.data), self.n + need))
            grown[: self.n] = self.data[: self.n]
            self.data = grown
        off = self.n
        for c in columns:
            self.data[self.n: self.n + len(c)] = np.asarray(c, dtype=float)
            self.n += len(c)
        return off

    def register(self, route_columns: tuple, s_start: float, route_length: float) -> int:
        """A new path (its route table's columns s, x, y, heading); its id."""
        if self.paths == len(self.route):
            self.route = np.concatenate([self.route, np.zeros_like(self.route)])
            self.limits = np.concatenate([self.limits, np.zeros_like(self.limits)])
            self.bins = np.concatenate([self.bins, np.zeros_like(self.bins)])
        i = self.paths
        self.route[i] = (self.add(*route_columns), len(route_columns[0]))
        self.limits[i] = (s_start, route_length)
        self.paths += 1
        return i

    def add_bin(self, path_id: int, i: int, columns: tuple) -> None:
        """Speed bin ``i`` of path ``path_id``, just simulated (columns distance, x, y, heading, route position)."""
        self.bins[path_id, i] = (self.add(*columns), len(columns[0]))


LIKELY_IN_CACHE_SIZE = 8  # numpy's binary_search_with_guess


@numba.njit(cache=True, inline="always")
def _search(key, data, xo, n, guess):
    """numpy's ``binary_search_with_guess`` (numpy/_core/src/multiarray/compiled_base.c), step for step: on a
    sorted table the last j with ``xp[j] <= key``, and on one that is not sorted (a driven table's route positions
    step back where the simulated car switches lanes) the same j as numpy's."""
    if key > data[xo + n - 1]:
        return n
    if key < data[xo]:
        return -1
    if n <= 4:  # linear_search(key, arr, len, 1)
        i = 1
        while i < n and key >= data[xo + i]:
            i += 1
        return i - 1
    imin, imax = 0, n
    if guess > n - 3:
        guess = n - 3
    if guess < 1:
        guess = 1
    if key < data[xo + guess]:
        if key < data[xo + guess - 1]:
            imax = guess - 1
            if guess > LIKELY_IN_CACHE_SIZE and key >= data[xo + guess - LIKELY_IN_CACHE_SIZE]:
                imin = guess - LIKELY_IN_CACHE_SIZE
        else:
            return guess - 1
    else:
        if key < data[xo + guess + 1]:
            return guess
        if key < data[xo + guess + 2]:
            return guess + 1
        imin = guess + 2
        if guess < n - LIKELY_IN_CACHE_SIZE - 1 and key < data[xo + guess + LIKELY_IN_CACHE_SIZE]:
            imax = guess + LIKELY_IN_CACHE_SIZE
    while imin < imax:
        imid = imin + ((imax - imin) >> 1)
        if key >= data[xo + imid]:
            imin = imid + 1
        else:
            imax = imid
    return imin - 1


@numba.njit(cache=True, inline="always")
def _at(x, j, data, xo, fo, n):
    """``np.interp``'s value for one ``x`` whose search gave ``j`` (:func:`_search`), as numpy's C code computes it
    (the end values outside the table, ``fp[j]`` on an exact knot or at the last one, else the slope
    ``(fp[j+1] - fp[j]) / (xp[j+1] - xp[j])``, and its NaN fall-backs)."""
    if x != x:  # NaN
        return x
    if n == 1:
        return data[fo]
    if j == -1:
        return data[fo]
    if j >= n - 1:
        return data[fo + n - 1]
    xj = data[xo + j]
    if xj == x:
        return data[fo + j]
    x1, f0, f1 = data[xo + j + 1], data[fo + j], data[fo + j + 1]
    slope = (f1 - f0) / (x1 - xj)
    r = slope * (x - xj) + f0
    if r != r:
        r = slope * (x - x1) + f1
        if r != r and f0 == f1:
            r = f0
    return r


@numba.njit(cache=True, inline="always")
def _route_pose(data, ro, rn, r_len, s, guess, direct):
    """RouteTable.poses for one arc length: (x, y, heading, the search's index for the next guess). The route's
    arc lengths are sorted, so the index (one search for the three columns) does not depend on the guess.

    ``direct``: on the route (``extra`` 0) the cos and sin are not computed where they add exactly 0: ``x + 0
    cos(h)`` is ``x`` for ``x`` and ``y`` not 0 (where +0 and -0 could differ in sign) and ``h`` finite; the same
    floats. Why: most hypotheses of road users on the approach lanes lie wholly before their driven table, on the
    route's centreline, and these two calls per slice were a third of the batch's rows kernel
    (av_gym/shields/conflict_rows.py); the per-env stack keeps them (``direct`` False)."""
    sc = min(max(s, 0.0), r_len)
    j = _search(sc, data, ro, rn, guess) if sc == sc and rn > 1 else 0
    x = _at(sc, j, data, ro, ro + rn, rn)
    y = _at(sc, j, data, ro, ro + 2 * rn, rn)
    h = _at(sc, j, data, ro, ro + 3 * rn, rn)
    extra = s - sc
    if direct and extra == 0.0 and x != 0.0 and y != 0.0 and math.isfinite(h):
        return x, y, h, max(j, 0)
    return x + extra * math.cos(h), y + extra * math.sin(h), h, max(j, 0)


@numba.njit(cache=True, inline="always")
def _bin_index(v, grid_table, B):
    """``np.clip(np.interp(v, grid, np.arange(B)), 0, B - 1)`` for one speed (``grid_table``: the sorted grid, then
    0..B-1)."""
    return min(max(_at(v, _search(v, grid_table, 0, B, 0), grid_table, 0, B, B), 0.0), B - 1.0)


@numba.njit(cache=True)
def driven_poses(data, route, limits, bins, grid_table, ids, s0, ds, speeds, xy, hh, need):
    """DrivenPath.poses for H look-ups at once, into ``xy`` (H, K, 2) and ``hh`` (H, K): look-up m on the path
    ``ids[m]`` of the :class:`Store` (``data``, ``route``, ``limits``, ``bins``) from route position ``s0[m]``,
    distances ``ds[m]`` and speeds ``speeds[m]``; ``grid_table`` the store's speed bins then their indices.

    First every speed bin a look-up will read is checked: where one is not simulated yet, ``need[m, i]`` is set,
    nothing is computed, and the number of such bins is returned (the caller simulates them and calls again, so
    bins are simulated lazily, the same ones as the reference's); 0 when done (:func:`_missing_bins`,
    :func:`_lookups`, which :func:`conflict_predict` calls with one profile per road user for its hypotheses)."""
    H = ds.shape[0]
    f = _bin_fractions(speeds, grid_table, bins.shape[1])
    rows = np.arange(H)
    missing = _missing_bins(bins, limits, ids, s0, ds, f, rows, need)
    if missing:
        return missing
    # views typed 'A' and a non-literal bool, as conflict_rows' direct call passes (strided block views, True):
    # numba compiles _lookups once per layout and per literal value, so otherwise twice (~15 CPU-s of compiling)
    _lookups(data, route, limits, bins, ids, s0, ds, f, rows, xy[:, :xy.shape[1]], hh[:, :hh.shape[1]],
             np.bool_(False))
    return 0


@numba.njit(cache=True)
def _bin_fractions(speeds, grid_table, B):
    """(R, K) the fractional speed bin ``np.clip(np.interp(speed, grid, arange(B)), 0, B - 1)`` of each of
    ``speeds`` (R, K) m/s, as numpy computes it."""
    R, K = speeds.shape
    f = np.empty((R, K))
    for m in range(R):
        for k in range(K):
            f[m, k] = _bin_index(speeds[m, k], grid_table, B)
    return f


@numba.njit(cache=True)
def _missing_bins(bins, limits, ids, s0, ds, f, rows, need):
    """:func:`driven_poses`' check: the speed bins look-up m (profile row ``rows[m]`` of ``ds`` and the bin
    fractions ``f``) reads that its path lacks, flagged in ``need[m]``; their count (look-ups wholly before their
    path's table read none)."""
    H, K = ids.shape[0], ds.shape[1]
    B = bins.shape[1]
    missing = 0
    for m in range(H):
        p, q = ids[m], rows[m]
        if s0[m] + (ds[q, K - 1] if K else 0.0) < limits[p, 0]:
            continue
        for k in range(K):
            lo = int(math.floor(f[q, k]))
            hi = min(lo + 1, B - 1)
            if bins[p, lo, 1] == 0 and not need[m, lo]:
                need[m, lo] = True
                missing += 1
            if bins[p, hi, 1] == 0 and not need[m, hi]:
                need[m, hi] = True
                missing += 1
    return missing


@numba.njit(cache=True)
def _lookups(data, route, limits, bins, ids, s0, ds, f, rows, xy, hh, direct):
    """:func:`driven_poses`' look-ups, every bin present: look-up m from ``s0[m]`` along the distances ``ds[rows[m]]``
    with the bin fractions ``f[rows[m]]`` (rows: the look-ups of one road user's hypotheses share its profile).

    Per bin, the start distance ``d0`` (the reference's scalar ``np.interp`` on the bin's route positions, which are
    not sorted where the simulated car switches lanes: numpy's search from guess 0 exactly) is computed once; the
    distance and route-position searches carry their guess from slice to slice (both tables are sorted, so the
    index found is the same from any guess)."""
    H, K = ids.shape[0], ds.shape[1]
    B = bins.shape[1]
    d0s = np.empty(B)
    have = np.zeros(B, dtype=np.bool_)
    guess = np.zeros(B, dtype=np.int64)
    for m in range(H):
        p, q = ids[m], rows[m]
        ro, rn, sm = route[p, 0], route[p, 1], s0[m]
        s_start, r_len = limits[p, 0], limits[p, 1]
        rg = 0
        if sm + (ds[q, K - 1] if K else 0.0) < s_start:  # the whole prediction before the table
            for k in range(K):
                x, y, h, rg = _route_pose(data, ro, rn, r_len, sm + ds[q, k], rg, direct)
                xy[m, k, 0], xy[m, k, 1], hh[m, k] = x, y, h
            continue
        have[:] = False
        guess[:] = 0
        for k in range(K):
            lo = int(math.floor(f[q, k]))
            hi = min(lo + 1, B - 1)
            w = f[q, k] - lo
            ax, ay, ah = 0.0, 0.0, 0.0
            for r in range(2):
                i = lo if r == 0 else hi
                if r == 1 and hi == lo:
                    break
                bo, bn = bins[p, i, 0], bins[p, i, 1]
                d_last = data[bo + bn - 1]
                if not have[i]:
                    if sm <= s_start:
                        d0s[i] = sm
                    else:
                        past = sm - data[bo + 5 * bn - 1]
                        j0 = _search(sm, data, bo + 4 * bn, bn, 0) if sm == sm and bn > 1 else 0
                        d0s[i] = _at(sm, j0, data, bo + 4 * bn, bo, bn) + (past if not (0.0 > past) else 0.0)
                    have[i] = True
                d = d0s[i] + ds[q, k]
                if d >= s_start and d <= d_last:  # on the driven table
                    j = _search(d, data, bo, bn, guess[i]) if bn > 1 else 0
                    guess[i] = max(j, 0)
                    x = _at(d, j, data, bo, bo + bn, bn)
                    y = _at(d, j, data, bo, bo + 2 * bn, bn)
                    h = _at(d, j, data, bo, bo + 3 * bn, bn)
                else:  # the centreline before it, shifted one for one after it
                    arg = d if d < s_start else d - d_last + data[bo + 5 * bn - 1]
                    x, y, h, rg = _route_pose(data, ro, rn, r_len, arg, rg, direct)
                # the reference's weight of bin i: where(lo == i, 1 - w, 0) + where(hi == i, w, 0)
                wi = ((1.0 - w) if lo == i else 0.0) + (w if hi == i else 0.0)
                ax += wi * x
                ay += wi * y
                ah += wi * h
            xy[m, k, 0], xy[m, k, 1], hh[m, k] = ax, ay, ah


# ----------------------------------------------------------------------------------------------- footprint test
SAME_DIRECTION = float(np.radians(45))  # footprint_ttc's "heading the same way" (rad)


@numba.njit(cache=True)
def footprint_hit(ego_xy, ego_h, length, width, oxy, oh, osize, reach, rear):
    """:func:`av_gym.shields.predict.footprint_ttc`'s first hit: (slice k, other m) of the first overlap in slice
    order, then the others' order, of the ego box (``ego_xy`` (K, 2), ``ego_h`` (K,), ``length`` x ``width``, the
    margin included) with another box (``oxy`` (K, M, 2), ``oh`` (K, M), ``osize`` (M, 2)), (-1, -1) if none.

    The reference's steps per (slice, other) pair in the same arithmetic: the centre-distance pre-check
    (geometry.may_overlap with ``reach`` (M,), the half-diagonals' sums), the separating-axis test on the corners
    (geometry.box_corners, boxes_overlap), and with ``rear[m]`` an overlap with another behind the ego heading the
    same way (within 45°) skipped."""
    K, M = oxy.shape[0], oxy.shape[1]
    ea, eb = np.empty((4, 2)), np.empty((4, 2))
    for k in range(K):
        ex, ey, eh = ego_xy[k, 0], ego_xy[k, 1], ego_h[k]
        built = False
        for m in range(M):
            dx, dy = oxy[k, m, 0] - ex, oxy[k, m, 1] - ey
            if not (dx ** 2 + dy ** 2 <= (reach[m] * (1 + 1e-9) + 1e-9) ** 2):
                continue
            if not built:
                box_corners(ex, ey, math.cos(eh), math.sin(eh), 0.5 * length, 0.5 * width, ea)
                built = True
            box_corners(oxy[k, m, 0], oxy[k, m, 1], math.cos(oh[k, m]), math.sin(oh[k, m]), 0.5 * osize[m, 0],
                        0.5 * osize[m, 1], eb)
            if not boxes_overlap(ea, eb):
                continue
            if rear[m]:
                ahead = dx * math.cos(eh) + dy * math.sin(eh)
                if abs((oh[k, m] - eh + np.pi) % (2 * np.pi) - np.pi) < SAME_DIRECTION and ahead < 0:
                    continue
            return k, m
    return -1, -1


@numba.njit(cache=True, inline="always")
def _path_speed(d, prev_d, t, prev_t):
    """:func:`av_gym.shields.predict.profile_speeds`' one element: ``(d - prev_d) / np.maximum(t - prev_t, 1e-9)``
    floored by ``np.maximum(., 0.0)`` (m/s; numpy's maximum keeps its first argument where it is NaN or equal)."""
    step = t - prev_t
    vk = (d - prev_d) / (step if step >= 1e-9 or step != step else 1e-9)
    return vk if vk >= 0.0 or vk != vk else 0.0


@numba.njit(cache=True)
def driven_ttc(data, route, limits, bins, grid_table, path_id, s0, ds, t, length, width, oxy, oh, osize, reach,
               rear, need):
    """The ego's first footprint hit driving the distance profile ``ds`` (K,, m, at the times ``t`` (K,, s)) along
    the driven path ``path_id`` of the :class:`Store` from route position ``s0`` (m): its speeds by finite
    differences (:func:`av_gym.shields.predict.profile_speeds`), its poses (:func:`driven_poses`, one look-up) and
    :func:`footprint_hit` against ``oxy`` (K, M, 2), ``oh`` (K, M), ``osize`` (M, 2) with ``reach`` and ``rear``
    (M,), in one call. Returns (missing speed bins, slice k, other m): where bins are missing (``need[0, i]`` set,
    as :func:`driven_poses`) nothing is tested and (count, -1, -1) comes back; (0, -1, -1) for no hit. K >= 1."""
    K = ds.shape[0]
    d2, v2 = np.empty((1, K)), np.empty((1, K))
    prev_d, prev_t = 0.0, 0.0
    for k in range(K):
        d2[0, k] = ds[k]
        v2[0, k] = _path_speed(ds[k], prev_d, t[k], prev_t)
        prev_d, prev_t = ds[k], t[k]
    ids, start = np.full(1, path_id, dtype=np.int64), np.full(1, s0)
    xy, hh = np.empty((1, K, 2)), np.empty((1, K))
    missing = driven_poses(data, route, limits, bins, grid_table, ids, start, d2, v2, xy, hh, need)
    if missing:
        return missing, -1, -1
    k, m = footprint_hit(xy[0], hh[0], length, width, oxy, oh, osize, reach, rear)
    return 0, k, m


@numba.njit(cache=True)
def driven_ttc_rows(data, route, limits, bins, grid_table, path_id, s0, ds, n, t, length, width, xy, hh, h_off, n_h,
                    osize, reach, rear, need):
    """:func:`driven_ttc` of R decisions in one call, each on its own slices (the same floats as its own call):
    decision r drives ``ds[r, :n[r]]`` (m) at ``t[:n[r]]`` (s) from route position ``s0[r]`` (m) along path
    ``path_id`` against its ``n_h[r]`` hypotheses from ``h_off[r]`` of :func:`conflict_predict_rows`' flat buffers
    (``xy`` a (K, H, 2) block from ``2 K h_off[r]``, ``hh`` (K, H) from ``K h_off[r]``; ``osize`` (., 2), ``reach``
    and ``rear`` per hypothesis, aligned with them), its flags of missing speed bins in ``need[r]``. Returns per
    decision (missing speed bins, slice k, hypothesis m) as :func:`driven_ttc`; (0, -1, -1) for no slice or no
    hypothesis (the caller's ``(inf, -1)``), and nothing tested for a decision with ``n_h[r] < 0``."""
    R, K = ds.shape[0], t.shape[0]
    missing, ks, ms = np.zeros(R, np.int64), np.full(R, -1, np.int64), np.full(R, -1, np.int64)
    for r in range(R):
        H, o, nr = n_h[r], h_off[r], n[r]
        if H <= 0 or nr <= 0:
            continue
        oxy = xy[2 * K * o: 2 * K * (o + H)].reshape(K, H, 2)
        ohh = hh[K * o: K * (o + H)].reshape(K, H)
        missing[r], ks[r], ms[r] = driven_ttc(data, route, limits, bins, grid_table, path_id, s0[r], ds[r, :nr],
                                              t[:nr], length, width, oxy[:nr], ohh[:nr], osize[o: o + H],
                                              reach[o: o + H], rear[o: o + H], need[r: r + 1])
    return missing, ks, ms


# ----------------------------------------------------------------------------------------------- brake actuator
@numba.njit(cache=True)
def brake_profile(v0, a_before, n, dt, decel, delay, jerk):
    """:meth:`av_gym.shields.actuator.BrakeActuator.profile`'s ticks: distance (m) and speed (m/s) after each of
    ``n`` ticks of ``dt`` s when the brake is commanded at speed ``v0`` (already clipped at 0) and the vehicle keeps
    ``a_before`` (m/s²) during the ``delay``: the deceleration of :meth:`BrakeActuator.deceleration`, never
    reversing; the same float operations in the same order (plain IEEE arithmetic, no transcendental)."""
    xs, vs = np.empty(n), np.empty(n)
    x, v = 0.0, v0
    for i in range(n):
        elapsed = i * dt
        if elapsed < delay - 1e-9:
            a = a_before
        else:
            d = decel if jerk <= 0 else min(decel, jerk * (elapsed - delay + dt))
            a = max(-d, -v / dt)
        x += v * dt
        v = max(v + a * dt, 0.0)
        xs[i], vs[i] = x, v
    return xs, vs


# ----------------------------------------------------------------------------------------------- ego set-point profile
@numba.njit(cache=True)
def setpoint_ticks(v0, target_speeds, step, t, dt, tau):
    """:func:`av_gym.shields.predict.setpoint_profile` with highway-env's ``MDPVehicle.act`` for a repeated FASTER
    (``step`` +1) or SLOWER (-1) as ``set_at``: at the start of every interval of ``t`` (s) the set-point is the
    target speed one index from the one nearest the speed then (``speed_to_index``: ``np.round`` of the fraction,
    clipped), then ``round((t_i - t_prev) / dt)`` ticks of the first-order response with time constant ``tau`` (s);
    distance (m) at each time in ``t``. The same float operations in the same order as the Python reference."""
    n = target_speeds.shape[0]
    lo, hi = target_speeds[0], target_speeds[n - 1]
    out = np.empty(t.shape[0])
    v, s, prev = v0, 0.0, 0.0
    for i in range(t.shape[0]):
        x = (v - lo) / (hi - lo)
        idx = int(min(max(np.rint(x * (n - 1)), 0.0), n - 1.0))
        v_set = target_speeds[min(max(idx + step, 0), n - 1)]
        for _ in range(int(np.rint((t[i] - prev) / dt))):
            s += v * dt
            v += (v_set - v) / tau * dt
        prev = t[i]
        out[i] = s
    return out


# ----------------------------------------------------------------------------------------------- conflict model
STRAIGHT_LANE, CIRCULAR_LANE = 0.0, 1.0  # column 0 of a conflict-model lane row (ConflictModel's lane registry)


@intrinsic
def _fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (LLVM's fma): numpy's ``np.dot`` of two 2-vectors where its BLAS fuses them."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return sig, codegen


@numba.njit(cache=True, inline="always")
def _dot2(a0, a1, b0, b1, fused):
    """``np.dot([a0, a1], [b0, b1])`` as this machine's numpy computes it: ``a0*b0 + a1*b1``, or with the second
    product fused (``fused``: :data:`DOT_FUSED`)."""
    return _fma(a1, b1, a0 * b0) if fused else a0 * b0 + a1 * b1


DOT_FUSED = fmath.DOT_FUSED  # how this machine's numpy computes a 2-vector dot (None: neither sum)


@numba.njit(cache=True, inline="always")
def _stock_local(lanes, k, x, y, phi, fused):
    """highway-env's ``(Straight|Circular)Lane.local_coordinates`` for the lane row ``k`` ([kind, then a straight
    lane's start x, y, direction x, y, lateral direction x, y and heading; a circular lane's centre x, y, radius,
    start phase, direction]), ``phi``: a circular lane's ``np.arctan2`` of the point from its centre (numpy's own:
    an AVX-512 numpy's differs from the C library's); the stock formulas in the same order, ``np.dot`` and the norm
    (``sqrt(dot(d, d))``) as this machine's numpy computes them (:func:`_dot2`)."""
    dx, dy = x - lanes[k, 1], y - lanes[k, 2]
    if lanes[k, 0] == CIRCULAR_LANE:
        radius, phase, direction = lanes[k, 3], lanes[k, 4], lanes[k, 5]
        phi = phase + (((phi - phase + math.pi) % (2 * math.pi)) - math.pi)
        return direction * (phi - phase) * radius, direction * (radius - math.sqrt(_dot2(dx, dy, dx, dy, fused)))
    return _dot2(dx, dy, lanes[k, 3], lanes[k, 4], fused), _dot2(dx, dy, lanes[k, 5], lanes[k, 6], fused)


@numba.njit(cache=True, inline="always")
def _stock_heading(lanes, k, s):
    """highway-env's ``heading_at(s)`` for the lane row ``k`` (:func:`_stock_local`'s layout)."""
    if lanes[k, 0] == CIRCULAR_LANE:
        direction = lanes[k, 5]
        return direction * s / lanes[k, 3] + lanes[k, 4] + math.pi / 2 * direction
    return lanes[k, 7]


@numba.njit(cache=True)
def locate_rows(lanes, lengths, closed, hint, x, y, phi, fused, out_k, out_s, out_lat):
    """:meth:`av_gym.envs.lane_path.LanePath.locate` of R points (``x``, ``y`` (R,) m) from their hint lanes
    ``hint`` (R,) on a path of the lane rows ``lanes`` (L, 8; :func:`_stock_local`'s layout) of lengths ``lengths``
    (L,) m, ``closed`` a loop; ``phi`` (R, L): numpy's ``arctan2`` of each point from each lane's centre (read for
    the circular lanes). The same walk from the hint and the same floats as the method's
    ``local_coordinates`` calls; writes each point's lane, s on it (m) and lateral offset (m)."""
    n = lanes.shape[0]
    for r in range(x.shape[0]):
        k = hint[r]
        s, lat = _stock_local(lanes, k, x[r], y[r], phi[r, k], fused)
        step = 1 if s > lengths[k] else -1 if s < 0 else 0
        if step != 0:
            for _ in range(n):
                nxt = k + step
                if not closed and not 0 <= nxt < n:
                    break
                k = nxt % n
                s, lat = _stock_local(lanes, k, x[r], y[r], phi[r, k], fused)
                if (step > 0 and s <= lengths[k]) or (step < 0 and s >= 0):
                    break
        out_k[r], out_s[r], out_lat[r] = k, s, lat


@numba.njit(cache=True, error_model="numpy")  # a division by 0 gives inf or NaN, as numpy's, not an exception
def conflict_hypotheses(others, speeds, phis, lane_row, lanes, hyp_off, hyp_n, hyp_turn, intent, accels, min_p,
                        on_lane, max_dh, fused, follow, out_hyp, out_s0, out_row, out_owner, out_prob, v_on, a_on, cv):
    """:meth:`av_gym.shields.conflicts.ConflictModel.predict`'s choice of hypotheses for the objects ``others``
    (M, 7) on the lane rows ``lane_row`` (M,; -1 off the map) of ``lanes`` (``speeds``: numpy's hypot of their
    velocities, ``phis``: numpy's arctan2 of each from its lane's centre where circular; ``fused``:
    :data:`DOT_FUSED`): an object at >= 0.5 m/s (or marked in ``follow`` (M,), at any speed > 0: the
    :meth:`~av_gym.shields.conflicts.ConflictModel.predict` argument) within ``on_lane`` m of its lane and
    ``max_dh`` rad of its heading gets the lane's hypotheses ``hyp_off[k]`` ..
    ``+ hyp_n[k]`` (``hyp_turn``: each one's turn, -1 / 0 / +1), weighted by its indicator readings ``intent`` (M, 3;
    a NaN in a row: never read, uniform weights), normalised, those below ``min_p`` dropped when any is; every other
    object the constant-velocity hypothesis.

    Writes per map hypothesis (in the reference's order) its hypothesis index, start position along the lane (m),
    object's place among the objects on the map, object row and probability; per object on the map its speed (m/s)
    and acceleration along its velocity (m/s², from ``accels`` (M, 2)); the constant-velocity objects' rows. Returns
    (map hypotheses, objects on the map, constant-velocity objects)."""
    n, n_on, n_cv = 0, 0, 0
    p = np.empty(hyp_n.max() if hyp_n.shape[0] else 1)
    for m in range(others.shape[0]):
        k = lane_row[m]
        speed = speeds[m]
        if k < 0 or not (speed >= 0.5 or follow[m]):
            cv[n_cv] = m
            n_cv += 1
            continue
        s0, lat = _stock_local(lanes, k, others[m, 0], others[m, 1], phis[m], fused)
        dh = abs((_stock_heading(lanes, k, s0) - others[m, 4] + math.pi) % (2 * math.pi) - math.pi)
        if not (abs(lat) <= on_lane and dh <= max_dh):
            cv[n_cv] = m
            n_cv += 1
            continue
        off, nh = hyp_off[k], hyp_n[k]
        read = True
        for j in range(3):
            if not math.isfinite(intent[m, j]):
                read = False
        if read:  # the reference's np.array([...]) / n_h, then p / p.sum()
            total = 0.0
            for j in range(nh):
                p[j] = intent[m, int(hyp_turn[off + j]) + 1] / nh
                total = p[j] if j == 0 else total + p[j]
            for j in range(nh):
                p[j] = p[j] / total if total != 0 else 1.0 / nh  # every continuation weighed 0: uniform
        else:
            for j in range(nh):
                p[j] = 1.0 / nh
        least = p[0]
        for j in range(1, nh):
            if p[j] < least:
                least = p[j]
        for j in range(nh):
            if least < min_p and p[j] < min_p:
                continue
            out_hyp[n], out_s0[n], out_row[n], out_owner[n], out_prob[n] = off + j, s0, n_on, m, p[j]
            n += 1
        v_on[n_on] = speed
        a_on[n_on] = _dot2(accels[m, 0], accels[m, 1], others[m, 2], others[m, 3], fused) / speed
        n_on += 1
    return n, n_on, n_cv


@numba.njit(cache=True)
def along_profiles(v, a, t, accel_time):
    """:meth:`av_gym.shields.conflicts.ConflictModel.along_many` and the path speeds :func:`av_gym.shields.predict.
    profile_speeds` gives each row, for speeds ``v`` (M,, m/s) and along-path accelerations ``a`` (M,, m/s²) at
    times ``t`` (K,, s): distances (M, K) m, each keeping its acceleration for ``accel_time`` s (a braking one
    stops, never reverses) then its speed, and speeds (M, K) m/s (finite differences, floored at 0); the same
    float operations in the same order as the numpy code."""
    M, K = v.shape[0], t.shape[0]
    dist, speed = np.empty((M, K)), np.empty((M, K))
    for m in range(M):
        prev_d, prev_t = 0.0, 0.0
        for k in range(K):
            ta = min(t[k], accel_time)
            if a[m] < 0:
                stop = v[m] / -a[m]
                ta = stop if stop < ta else ta  # np.minimum: the first where equal (the same value)
            s = v[m] * ta + 0.5 * a[m] * (ta * ta)
            d = s + (v[m] + a[m] * ta) * (t[k] - ta)
            dist[m, k], speed[m, k] = d, _path_speed(d, prev_d, t[k], prev_t)
            prev_d, prev_t = d, t[k]
    return dist, speed


@numba.njit(cache=True)
def lane_hypotheses(lane_row, hyp_n, a, b):
    """The most map hypotheses road users ``a`` .. ``b`` can have: the lane hypotheses of each one on a lane row
    (``lane_row`` >= 0; ``hyp_n`` per row), none for one off the map."""
    n = 0
    for m in range(a, b):
        if lane_row[m] >= 0:
            n += hyp_n[lane_row[m]]
    return n


@numba.njit(cache=True, error_model="numpy")  # as conflict_hypotheses
def conflict_predict(others, speeds, phis, lane_row, lanes, hyp_off, hyp_n, hyp_turn, intent, accels, min_p,
                     on_lane, max_dh, fused, follow, hyp_ids, t, accel_time, data, route, limits, bins, grid_table,
                     need):
    """:meth:`av_gym.shields.conflicts.ConflictModel.predict` in one call: the hypotheses
    (:func:`conflict_hypotheses`, same arguments), the distances and speeds along them (:func:`along_profiles` at
    the times ``t`` (K,, s) with ``accel_time`` s), every map hypothesis on its driven path (:func:`driven_poses` on
    the :class:`Store` ``data`` ... ``grid_table``, path ids ``hyp_ids`` per hypothesis index) and the
    constant-velocity objects (:func:`av_gym.shields.predict.object_predict`: ``p + v t``), in the reference's
    order: the map hypotheses, then the constant-velocity objects.

    Returns (missing speed bins, hypothesis index per map hypothesis, positions (K, H, 2) m, headings (K, H) rad,
    owner (H,), is a map hypothesis (H,), probability (H,)). Where speed bins are missing (``need[h, i]`` set for
    map hypothesis h, as :func:`driven_poses`) only the count and the hypothesis indices are meaningful: the caller
    simulates those bins and calls again."""
    M, K = others.shape[0], t.shape[0]
    n_max = lane_hypotheses(lane_row, hyp_n, 0, M)
    hyp, starts, rows, owner_map = np.empty(n_max, np.int64), np.empty(n_max), np.empty(n_max, np.int64), \
        np.empty(n_max, np.int64)
    prob_map, v_on, a_on, cv = np.empty(n_max), np.empty(M), np.empty(M), np.empty(M, np.int64)
    n, n_on, n_cv = conflict_hypotheses(others, speeds, phis, lane_row, lanes, hyp_off, hyp_n, hyp_turn, intent,
                                        accels, min_p, on_lane, max_dh, fused, follow, hyp, starts, rows,
                                        owner_map, prob_map, v_on, a_on, cv)
    H = n + n_cv
    xy, hh = np.empty((K, H, 2)), np.empty((K, H))
    owner, is_map, prob = np.empty(H, np.int64), np.empty(H, np.bool_), np.empty(H)
    if n:
        dist, v_path = along_profiles(v_on[:n_on], a_on[:n_on], t, accel_time)
        ids = np.empty(n, np.int64)
        for h in range(n):
            ids[h] = hyp_ids[hyp[h]]
        # driven_poses with each hypothesis on its road user's profiles (rows), their bin fractions once per road user
        f = _bin_fractions(v_path, grid_table, bins.shape[1])
        pxy, phh = np.empty((n, K, 2)), np.empty((n, K))
        missing = _missing_bins(bins, limits, ids, starts[:n], dist, f, rows[:n], need)
        if missing:
            return missing, hyp[:n], xy, hh, owner, is_map, prob
        _lookups(data, route, limits, bins, ids, starts[:n], dist, f, rows[:n], pxy[:, :K], phh[:, :K],
                 np.bool_(False))  # 'A' views, a non-literal bool: one specialization of _lookups (driven_poses)
        for h in range(n):
            for k in range(K):
                xy[k, h, 0], xy[k, h, 1], hh[k, h] = pxy[h, k, 0], pxy[h, k, 1], phh[h, k]
            owner[h], is_map[h], prob[h] = owner_map[h], True, prob_map[h]
    for c in range(n_cv):
        m, h = cv[c], n + c
        for k in range(K):
            xy[k, h, 0] = others[m, 0] + others[m, 2] * t[k]
            xy[k, h, 1] = others[m, 1] + others[m, 3] * t[k]
            hh[k, h] = others[m, 4]
        owner[h], is_map[h], prob[h] = m, False, 1.0
    return 0, hyp[:n], xy, hh, owner, is_map, prob


@numba.njit(cache=True, error_model="numpy")  # as conflict_predict
def conflict_predict_rows(row_off, others, speeds, phis, lane_row, lanes, hyp_off, hyp_n, hyp_turn, intent, accels,
                          min_p, on_lane, max_dh, fused, follow, hyp_ids, t, accel_time, data, route, limits, bins,
                          grid_table, h_off, xy, hh, owner, is_map, prob, n_h):
    """:func:`conflict_predict` of many decisions in one call: decision r's road users are rows ``row_off[r]`` ..
    ``row_off[r + 1]`` of ``others``, ``speeds``, ``phis``, ``lane_row``, ``intent``, ``accels`` and ``follow`` (the
    other arguments as :func:`conflict_predict`'s, shared). Each decision is :func:`conflict_predict` on its own
    slices (the same floats as its own call); its H hypotheses are written from ``h_off[r]`` into the flat buffers:
    ``xy`` from ``2 K h_off[r]`` and ``hh`` from ``K h_off[r]`` as (K, H, 2) and (K, H) blocks, ``owner``,
    ``is_map``, ``prob`` from ``h_off[r]`` (its block, ``h_off[r + 1] - h_off[r]``: at least H, each road user's
    lane hypotheses or one). ``n_h[r]``: its H, or -1 where a speed bin it reads is not simulated yet or its H
    outgrows its block (nothing written: the caller's own :meth:`~av_gym.shields.conflicts.ConflictModel.predict`
    serves it, simulating missing bins lazily as the reference)."""
    K, n_bins = t.shape[0], bins.shape[1]
    for r in range(row_off.shape[0] - 1):
        a, b = row_off[r], row_off[r + 1]
        need = np.zeros((lane_hypotheses(lane_row, hyp_n, a, b), n_bins), np.bool_)
        missing, _, pxy, phh, pown, pmap, pprob = conflict_predict(
            others[a:b], speeds[a:b], phis[a:b], lane_row[a:b], lanes, hyp_off, hyp_n, hyp_turn, intent[a:b],
            accels[a:b], min_p, on_lane, max_dh, fused, follow[a:b], hyp_ids, t, accel_time, data, route, limits,
            bins, grid_table, need)
        H, o = pown.shape[0], h_off[r]
        if missing or H > h_off[r + 1] - o:  # numba does not check bounds: a row outgrowing its block is not written
            n_h[r] = -1
            continue
        n_h[r] = H
        for k in range(K):
            for h in range(H):
                j = o * K + k * H + h
                xy[2 * j], xy[2 * j + 1], hh[j] = pxy[k, h, 0], pxy[k, h, 1], phh[k, h]
        for h in range(H):
            owner[o + h], is_map[o + h], prob[o + h] = pown[h], pmap[h], pprob[h]
