"""Numba kernels for the batched left turn: its pairwise parts, and the whole batch tick in one call.

Why compiled code here: highway-env has no batched version of these models, and av_gym/sim/batched.py's numpy
formulation of the pairwise parts (leader search, IDM gap, collisions, the regulation's conflict test, the closest
lane, the ego's TTC) builds (B, N, N), (B, N, N, T) or (vehicles, lanes) arrays, gathers the candidates with
``nonzero`` and evaluates them in many small array calls; at B = 256 that bookkeeping, not the arithmetic, was
most of their cost (docs/performance.md, "Numba kernels"). A loop over the candidates skips the masks and stops at
the first hit. :func:`advance` then runs a policy step's ticks of every env (act, regulation, kinematics, closest
lane, collisions, arrivals) in one call, the pairwise parts as per-env helpers it shares with the batch kernels:
Python runs once per batch step instead of once per part (docs/performance.md, "One compiled batch step");
:func:`turn_features` (``obs["turn"]``, both stacks), :func:`truth`, :func:`observe` and :func:`rewards` compute
what the env layer reads after it.

What stays identical: each kernel evaluates the numpy code's formulas in the same order of operations (no
``fastmath``, so no reassociation or fused multiply-adds), on the same inputs, and makes every decision with the
same comparisons (``<=`` / ``<``, first or last on ties as there; a ``hypot(dx, dy) <= bound`` pre-check is
decided from the squared length where that cannot differ, :func:`_within`). numba's ``math`` calls the C library;
numpy's float64 ufuncs do too on AVX2 builds, where the kernels reproduce the numpy path bit for bit. An AVX-512
numpy build uses its own SIMD sin / cos / tan / arcsin / arctan / power, which differ from the C library's in the
last bit: each kernel still equals the numpy code to 1e-12 relative with identical decisions (tests/_numerics.py),
but over whole runs of the fused tick (which also moves steering and kinematics to the C library) those last bits
grow as any perturbation of the traffic does, so tests/test_kernels.py compares the tick with the numpy path step by
step from the same state, and whole episodes by their outcome (>= 99.5 %; 1,000 / 1,000 measured on AVX-512).
Steering's tan(asin q) and the bicycle's slip angle are computed without the angles (√ and sum formulas) on both
paths alike: a few ulp from highway-env's angle formulas, fewer transcendental calls (_steering_sr, _slip_cos_sin).
``error_model="numpy"``: no zero-divisor check before each division (no kernel divides by zero).
``cache=True``: compiled once per checkout into ``__pycache__`` (cold: ~32 CPU-s for all of them, at load ~8), so
later processes only load them.

The lane table is passed as one (L, 16 + L) float array (:func:`lane_array`); column indices below.
"""

from __future__ import annotations

import ctypes
import math

import numba
import numpy as np
try:  # numba's copy of numpy's ziggurat tables (a private module): without it the spawns keep numpy's own calls
    from numba.np.random._constants import fi_double, ki_double, wi_double, ziggurat_nor_inv_r, ziggurat_nor_r
except ImportError:  # pragma: no cover - another numba layout
    fi_double = ki_double = wi_double = [0]
    ziggurat_nor_inv_r = ziggurat_nor_r = 0.0
    _ZIGGURAT_TABLES = False
else:
    _ZIGGURAT_TABLES = True

OX, OY, DX, DY, CIRC, PHASE0, RADIUS, CDIR, WIDTH, LENGTH, BX0, BY0, BX1, BY1, HEAD, NEAR_N = range(16)
NEAR_0 = NEAR_N + 1  # then the NEAR_N lanes (ids, ascending) whose box is within 2 NEAR_GAP of this lane's box
NEAR_GAP = 0.5  # m: a point within this of a lane's box has only those lanes' boxes within this of it


def lane_array(T) -> np.ndarray:
    """A LaneTable's lanes as one C-contiguous (L, 16 + L) float array for the kernels: the columns above, then
    each lane's near lanes (:func:`_closest_one`)."""
    box = np.asarray(T.box, dtype=float)
    gx = np.maximum(np.maximum(box[:, None, 0] - box[None, :, 2], box[None, :, 0] - box[:, None, 2]), 0.0)
    gy = np.maximum(np.maximum(box[:, None, 1] - box[None, :, 3], box[None, :, 1] - box[:, None, 3]), 0.0)
    near = np.hypot(gx, gy) <= 2 * NEAR_GAP + 1e-6  # box to box, with a margin far above rounding
    table = np.full((len(box), len(box)), -1.0)
    for k in range(len(box)):
        ids = np.nonzero(near[k])[0]
        table[k, :len(ids)] = ids
    return np.ascontiguousarray(np.column_stack([
        T.ox, T.oy, T.dx, T.dy, T.circular.astype(float), T.phase0, T.radius, T.cdir, T.width, T.length, box,
        T.h, near.sum(axis=1), table]))


@numba.njit(cache=True, error_model="numpy", inline="always")
def _wrap(a):
    """wrap_to_pi: (a + π) % 2π − π. The modulo of a value already in [0, 2π) is that value, exactly: the
    remainder (an fmod call) only for the others."""
    q = a + math.pi
    return (q if 0.0 <= q < 2 * math.pi else q % (2 * math.pi)) - math.pi


@numba.njit(cache=True, error_model="numpy", inline="always")
def _local(lt, k, x, y):
    """LaneTable.local for one lane ``k`` and one point: (Straight|Circular)Lane.local_coordinates."""
    ex, ey = x - lt[k, OX], y - lt[k, OY]
    if lt[k, CIRC] != 0.0:
        p0, R, cd = lt[k, PHASE0], lt[k, RADIUS], lt[k, CDIR]
        phi = p0 + _wrap(math.atan2(ey, ex) - p0)
        return cd * (phi - p0) * R, cd * (R - math.hypot(ex, ey))
    dx, dy = lt[k, DX], lt[k, DY]
    return ex * dx + ey * dy, ex * -dy + ey * dx


@numba.njit(cache=True, error_model="numpy")
def closest(lt, x, y, h, hint):
    """LaneTable.closest for 1-d arrays of vehicles: the first lane of least distance_with_heading among the lanes
    whose centreline box is no farther than a first lane's distance (``hint[m]``, a lane id, or -1: the nearest
    box's lane; :func:`_closest_one`): the same lane whatever the hint."""
    out = np.zeros(x.shape[0], dtype=np.int64)
    lb = np.empty((lt.shape[0], 2))
    for m in range(x.shape[0]):
        out[m] = _closest_one(lt, x[m], y[m], h[m], lb, hint[m])
    return out


@numba.njit(cache=True, error_model="numpy", inline="always")
def _within(dx, dy, bound):
    """``math.hypot(dx, dy) <= bound``, exactly, without the hypot where the squared length decides: its rounding
    (a few ulp) is far inside the 1e-9 relative margin, and only the cases within it call hypot."""
    if bound < 0.0:
        return False
    s2, b2 = dx * dx + dy * dy, bound * bound
    if s2 > b2 * (1.0 + 1e-9):
        return False
    if s2 < b2 * (1.0 - 1e-9):
        return True
    return math.hypot(dx, dy) <= bound


@numba.njit(cache=True, error_model="numpy", inline="always")
def _closest_one(lt, xm, ym, hm, lb, hint):
    """:func:`closest` for one vehicle (``lb``: scratch, (L, 2)). The lanes evaluated are those whose box is within
    the distance of one first lane: ``hint`` (>= 0: the vehicle's lane before it moved, usually the winner, so the
    bound is tight), else the nearest box's lane, the first least hypot among the boxes whose squared distance is
    within 1e-9 of the least (no other can equal it). Either way every lane of least distance is among them (a
    lane's box, grown by 1e-6 m, is nearer than its centreline, which is no farther than the distance), each box's
    ``hypot <= bound`` test is :func:`_within`'s, and the first least distance wins: the numpy code's lane."""
    L = lt.shape[0]
    k0 = hint
    if k0 < 0:
        m2 = np.inf
        for k in range(L):
            bx, by = _box_gap(lt, k, xm, ym)
            lb[k, 0], lb[k, 1] = bx, by
            m2 = min(m2, bx * bx + by * by)
        k0, h0 = 0, np.inf
        for k in range(L):
            bx, by = lb[k, 0], lb[k, 1]
            if bx * bx + by * by <= m2 * (1.0 + 1e-9):
                hk = math.hypot(bx, by)
                if hk < h0:
                    k0, h0 = k, hk
    best = _distance_below(lt, k0, xm, ym, hm, np.inf)
    dmin, kmin = np.inf, 0
    # within NEAR_GAP of lane k0 (its box is nearer than its distance), a lane whose box is within best of the
    # point has its box within 2 NEAR_GAP of k0's: only k0's near lanes (ascending ids) can be
    near = best <= NEAR_GAP
    for q in range(int(lt[k0, NEAR_N]) if near else L):
        k = int(lt[k0, NEAR_0 + q]) if near else q
        bx, by = _box_gap(lt, k, xm, ym)
        if _within(bx, by, best):
            # lane k0's is best (_distance_below's, or +inf when bounded below best: then it is not the least)
            d = best if k == k0 else _distance_below(lt, k, xm, ym, hm, min(dmin, best))
            if d < dmin:
                dmin, kmin = d, k
    return kmin


@numba.njit(cache=True, error_model="numpy", inline="always")
def _box_gap(lt, k, x, y):
    """The x and y gaps (m, >= 0) from the point (x, y) to lane k's centreline box."""
    return max(max(lt[k, BX0] - x, x - lt[k, BX1]), 0.0), max(max(lt[k, BY0] - y, y - lt[k, BY1]), 0.0)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _distance_below(lt, k, x, y, h, bound):
    """LaneTable.distance_with_heading for one lane and one vehicle (heading_at: the arc's tangent, or the line's
    heading; :func:`_local`'s operations), or +inf without the arc's atan2 and the angle wraps when |r| alone
    exceeds ``bound`` (+inf: never): the distance is |r| plus
    non-negative terms, and a float sum of non-negative terms is never below its first, so such a lane is farther
    than ``bound`` (the least distance so far, or a first lane's) and cannot be the first least one."""
    ex, ey = x - lt[k, OX], y - lt[k, OY]
    if lt[k, CIRC] != 0.0:
        R, cd = lt[k, RADIUS], lt[k, CDIR]
        r = cd * (R - math.hypot(ex, ey))
        if abs(r) > bound:
            return np.inf
        p0 = lt[k, PHASE0]
        phi = p0 + _wrap(math.atan2(ey, ex) - p0)
        s = cd * (phi - p0) * R
        heading = cd * s / R + p0 + math.pi / 2 * cd
    else:
        dx, dy = lt[k, DX], lt[k, DY]
        s, r = ex * dx + ey * dy, ex * -dy + ey * dx
        if abs(r) > bound:
            return np.inf
        heading = lt[k, HEAD]
    angle = abs(_wrap(h - heading))
    return abs(r) + max(s - lt[k, LENGTH], 0.0) + max(0.0 - s, 0.0) + angle


@numba.njit(cache=True, error_model="numpy")
def front(lt, lanes, x, y, alive, vehicle_length):
    """Traffic._front: per vehicle i, among the other live vehicles j within 6 m of lane(i)'s centreline box and on
    it (|r| <= width/2 + 1, -L <= s < length + L) with s_j >= s_i, the one with the smallest s_j, the last in
    slot order on ties (``<=`` while scanning j upwards, as the reversed argmin); -1 if none."""
    B, N = x.shape
    out = np.full((B, N), -1, dtype=np.int64)
    for b in range(B):
        for i in range(N):
            if alive[b, i]:
                k = lanes[b, i]
                out[b, i] = _front_from(lt, k, _local(lt, k, x[b, i], y[b, i])[0], b, i, x, y, alive,
                                        vehicle_length, N)[0]
    return out


@numba.njit(cache=True, error_model="numpy", inline="always")
def _front_from(lt, k, s_self, b, i, x, y, alive, vehicle_length, N):
    """:func:`front` for vehicle i of env b on lane ``k`` with its own ``s_self`` on it already known, among the
    first ``N`` slots (no live one after them): the leader's slot (-1 if none) and its s on lane ``k`` (m; +inf if
    none)."""
    x0, y0 = lt[k, BX0] + -6.0, lt[k, BY0] + -6.0
    x1, y1 = lt[k, BX1] + 6.0, lt[k, BY1] + 6.0
    half, end = lt[k, WIDTH] / 2 + 1, lt[k, LENGTH] + vehicle_length
    best, jbest = np.inf, -1
    for j in range(N):
        if j == i or not alive[b, j]:
            continue
        xj, yj = x[b, j], y[b, j]
        if not (x0 <= xj and xj <= x1 and y0 <= yj and yj <= y1):
            continue
        s, r = _local(lt, k, xj, yj)
        if abs(r) <= half and -vehicle_length <= s and s < end and s_self <= s and s <= best:
            best, jbest = s, j
    return jbest, best


@numba.njit(cache=True, error_model="numpy")
def collisions(x, y, h, v, alive, dt, length, width, crashed, has_impact, impact_x, impact_y):
    """Traffic._collisions in place: for every pair i < j in slot order, the spherical pre-check
    (hypot <= diagonal + v_i dt), then utils.are_polygons_intersecting as batched._polygons_intersecting computes
    it; a pair that will intersect sets both impacts (a later pair overwrites), one that intersects both crash
    flags."""
    lx = np.array([-length / 2, -length / 2, length / 2, length / 2, -length / 2])
    ly = np.array([-width / 2, width / 2, width / 2, -width / 2, -width / 2])
    pa, pb, nrm, dist = np.empty((5, 2)), np.empty((5, 2)), np.empty((8, 2)), np.empty(8)
    for b in range(x.shape[0]):
        _collide_row(b, x, y, h, v, alive, dt, length, width, crashed, has_impact, impact_x, impact_y, lx, ly, pa,
                     pb, nrm, dist, x.shape[1])


@numba.njit(cache=True, error_model="numpy")
def _collide_row(b, x, y, h, v, alive, dt, length, width, crashed, has_impact, impact_x, impact_y, lx, ly, pa, pb,
                 nrm, dist, N):
    """:func:`collisions` for env b (``lx``, ``ly``: the closed polygon's local corners; the rest: scratch) over its
    first ``N`` slots (those after them are not alive)."""
    diagonal = math.sqrt(length**2 + width**2)
    for i in range(N):
        if not alive[b, i]:
            continue
        reach = diagonal + v[b, i] * dt
        for j in range(i + 1, N):
            if not alive[b, j] or not _within(x[b, j] - x[b, i], y[b, j] - y[b, i], reach):
                continue
            ci, si, cj, sj = math.cos(h[b, i]), math.sin(h[b, i]), math.cos(h[b, j]), math.sin(h[b, j])
            for p in range(5):  # RoadObject.polygon
                pa[p, 0] = ci * lx[p] - si * ly[p] + x[b, i]
                pa[p, 1] = si * lx[p] + ci * ly[p] + y[b, i]
                pb[p, 0] = cj * lx[p] - sj * ly[p] + x[b, j]
                pb[p, 1] = sj * lx[p] + cj * ly[p] + y[b, j]
            dax, day = ci * (v[b, i] * dt), si * (v[b, i] * dt)
            dbx, dby = cj * (v[b, j] * dt), sj * (v[b, j] * dt)
            for e in range(8):  # edge normals, a's edges then b's
                q = pa if e < 4 else pb
                m = e % 4
                ex, ey = q[m + 1, 0] - q[m, 0], q[m + 1, 1] - q[m, 1]
                nx, ny = -ey, ex
                norm = math.sqrt(nx * nx + ny * ny)
                nrm[e, 0], nrm[e, 1] = nx / norm, ny / norm
            inter, will = True, True
            for e in range(8):
                nx, ny = nrm[e, 0], nrm[e, 1]
                min_a = max_a = nx * pa[0, 0] + ny * pa[0, 1]
                min_b = max_b = nx * pb[0, 0] + ny * pb[0, 1]
                for p in range(1, 5):
                    qa = nx * pa[p, 0] + ny * pa[p, 1]
                    qb = nx * pb[p, 0] + ny * pb[p, 1]
                    min_a, max_a = min(min_a, qa), max(max_a, qa)
                    min_b, max_b = min(min_b, qb), max(max_b, qb)
                if (min_b - max_a if min_a < min_b else min_a - max_b) > 0:
                    inter = False
                vp = nx * (dax - dbx) + ny * (day - dby)
                if vp < 0:
                    min_a = min_a + vp
                else:
                    max_a = max_a + vp
                dist[e] = min_b - max_a if min_a < min_b else min_a - max_b
                if dist[e] > 0:
                    will = False
            if not (inter or will):
                continue
            kk = 0
            for e in range(1, 8):  # argmin |distance|, first on ties
                if abs(dist[e]) < abs(dist[kk]):
                    kk = e
            dx = (pa[0, 0] + pa[1, 0] + pa[2, 0] + pa[3, 0]) / 4 - (pb[0, 0] + pb[1, 0] + pb[2, 0] + pb[3, 0]) / 4
            dy = (pa[0, 1] + pa[1, 1] + pa[2, 1] + pa[3, 1]) / 4 - (pb[0, 1] + pb[1, 1] + pb[2, 1] + pb[3, 1]) / 4
            ax, ay = nrm[kk, 0], nrm[kk, 1]
            if not dx * ax + dy * ay > 0:
                ax, ay = -ax, -ay
            tx, ty = abs(dist[kk]) * ax, abs(dist[kk]) * ay
            if will:
                impact_x[b, i], impact_y[b, i] = tx / 2, ty / 2
                impact_x[b, j], impact_y[b, j] = -tx / 2, -ty / 2
                has_impact[b, i] = has_impact[b, j] = True
            if inter:
                crashed[b, i] = crashed[b, j] = True


@numba.njit(cache=True, error_model="numpy")
def near_ego(x, y, h, alive, ego, crashed, length, width, margin):
    """:func:`_near_ego_row` for every env (the numpy tick's counterpart of kernels.advance's test)."""
    ca, cb = np.empty((4, 2)), np.empty((4, 2))
    for b in range(x.shape[0]):
        _near_ego_row(b, x, y, h, alive, ego, crashed, length, width, margin, ca, cb, x.shape[1])


@numba.njit(cache=True, error_model="numpy")
def _near_ego_row(b, x, y, h, alive, ego, crashed, length, width, margin, ca, cb, N):
    """A planner's clearance margin (m) in its futures: the ego of env b crashes where another live road user's
    ``length`` x ``width`` box touches the ego's box grown by ``margin`` on every side (a near miss the planner
    avoids as it avoids a contact). Only the ego's flag is set: the other road user drives on, and pairs of others
    keep :func:`_collide_row`'s contact test. ``ca``, ``cb``: (4, 2) scratch. Written here, not taken from a
    library, because it must run inside the compiled tick, frame by frame, as the contact test does."""
    hl, hw = length / 2, width / 2
    reach = math.sqrt((hl + margin) ** 2 + (hw + margin) ** 2) + math.sqrt(hl * hl + hw * hw)
    for e in range(N):
        if not (alive[b, e] and ego[b, e]) or crashed[b, e]:
            continue
        ce, se = math.cos(h[b, e]), math.sin(h[b, e])
        box_corners(x[b, e], y[b, e], ce, se, hl + margin, hw + margin, ca)
        for j in range(N):
            if j == e or not alive[b, j] or not _within(x[b, j] - x[b, e], y[b, j] - y[b, e], reach):
                continue
            box_corners(x[b, j], y[b, j], math.cos(h[b, j]), math.sin(h[b, j]), hl, hw, cb)
            if boxes_overlap(ca, cb):
                crashed[b, e] = True
                break


@numba.njit(cache=True, error_model="numpy")
def conflicts(px, py, ph, alive, length, width):
    """The regulation's pairwise test (Traffic._enforce_road_rules): pair i < j of live vehicles conflicts if at
    some prediction time both centres are within ``length`` (np.hypot) and utils.rotated_rectangles_intersect of
    their (1.5 length, 0.9 width) boxes (9 corner / mid / centre points of each inside the other), as batched.
    _rects_intersect computes it. (b, N, N) bool, upper triangle."""
    b_, N, T = px.shape
    L, W = 1.5 * length, 0.9 * width
    hl, hw = L / 2, W / 2
    lx = np.array([-hl, -hl, hl, hl, 0.0, -hl, hl, 0.0, 0.0])
    ly = np.array([-hw, hw, hw, -hw, 0.0, 0.0, 0.0, -hw, hw])
    out = np.zeros((b_, N, N), dtype=np.bool_)
    for b in range(b_):
        for i in range(N):
            if not alive[b, i]:
                continue
            for j in range(i + 1, N):
                if alive[b, j]:
                    out[b, i, j] = _conflict_pair(px[b], py[b], ph[b], i, j, length, lx, ly, hl, hw)
    return out


@numba.njit(cache=True, error_model="numpy", inline="always")
def _conflict_pair(px, py, ph, i, j, length, lx, ly, hl, hw):
    """:func:`conflicts` for vehicles i and j of one env, their predictions (N, T): the first prediction time
    whose centres are within ``length`` and whose boxes intersect decides."""
    for t in range(px.shape[1]):
        x1, y1, x2, y2 = px[i, t], py[i, t], px[j, t], py[j, t]
        if not _within(x2 - x1, y2 - y1, length):
            continue
        c1, s1, c2, s2 = math.cos(ph[i, t]), math.sin(ph[i, t]), math.cos(ph[j, t]), math.sin(ph[j, t])
        if _any_inside(c1, s1, x1, y1, c2, s2, x2, y2, lx, ly, hl, hw) or \
                _any_inside(c2, s2, x2, y2, c1, s1, x1, y1, lx, ly, hl, hw):
            return True
    return False


@numba.njit(cache=True, error_model="numpy", inline="always")
def _any_inside(c1, s1, x1, y1, c2, s2, x2, y2, lx, ly, hl, hw):
    """batched._inside(_rect_points(box 1), box 2): any of box 1's 9 points in box 2 (rotation by +angle, as
    utils.point_in_rotated_rectangle)."""
    for p in range(9):
        qx = c1 * lx[p] - s1 * ly[p] + x1
        qy = s1 * lx[p] + c1 * ly[p] + y1
        dx, dy = qx - x2, qy - y2
        ux, uy = c2 * dx - s2 * dy, s2 * dx + c2 * dy
        if -hl <= ux and ux <= hl and -hw <= uy and uy <= hw:
            return True
    return False


@numba.njit(cache=True, error_model="numpy")
def ttc_rows(rows, x, y, h, v, alive, ego, grid, horizon, dt, length, width):
    """BatchedLeftTurn.ttc for the envs ``rows`` of the batch's (B, N) state (:func:`_ttc_one` per env): the ego its
    first ego slot (slot 0 if none, as np.argmax), the others every other live vehicle; +inf where none is hit."""
    n, N = rows.shape[0], x.shape[1]
    out = np.full(n, np.inf)
    ca, cb = np.empty((4, 2)), np.empty((4, 2))
    other = np.empty(N, dtype=np.bool_)
    for m in range(n):
        b = rows[m]
        for j in range(N):
            other[j] = alive[b, j] and not ego[b, j]
        out[m] = _ttc_one(x[b], y[b], h[b], v[b], other, _ego_of(ego, b), grid, horizon, dt, length, width, ca, cb)
    return out


@numba.njit(cache=True, error_model="numpy")
def _ttc_one(x, y, h, v, other, e, grid, horizon, dt, length, width, ca, cb):
    """One env's TTC (rows ``x``, ``y``, ``h``, ``v``, ``other`` (N,), ego slot ``e``): per pair, the
    constant-velocity overlap interval [t_in, t_out] from the four separating axes, then the per-env box test
    (geometry.box_corners / boxes_overlap arithmetic) at the grid times first..last around it, in ascending order:
    the first hit is the pair's time (the numpy code tests first..first+3, then the rest if none hit: the same times,
    the same minimum). On the axes along the ego's and the other's own heading the angle differences are exactly
    zero (ψ - ψ), so their cosine 1 and sine 0, and the axis' direction is that heading's cosine and sine: constants
    and values already computed, the numpy code's results bit for bit. The ego's normal axis (ψ_e + π/2) is the same
    for every other: computed once. A pair whose centres stay farther apart than the boxes' diagonal (+ 1e-6 m,
    far above the corners' rounding) over [0, horizon + dt] cannot overlap at any grid time: skipped, the same
    result without its 12 further trigonometric calls (most pairs)."""
    K = grid.shape[0]
    best = np.inf
    hl, hw = 0.5 * length, 0.5 * width
    reach2 = (math.sqrt(length * length + width * width) + 1e-6) ** 2  # m²: two boxes' centres when they touch
    t_end = horizon + dt
    ex, ey, eh, ev = x[e], y[e], h[e], v[e]
    ce, se = math.cos(eh), math.sin(eh)
    evx, evy = ev * ce, ev * se
    t1 = eh + math.pi / 2  # the ego's normal axis
    u1x, u1y, c1e, s1e = math.cos(t1), math.sin(t1), math.cos(eh - t1), math.sin(eh - t1)
    for j in range(x.shape[0]):
        if not other[j]:
            continue
        oh = h[j]
        co, so = math.cos(oh), math.sin(oh)
        ovx, ovy = v[j] * co, v[j] * so
        px, py = x[j] - ex, y[j] - ey
        wx, wy = ovx - evx, ovy - evy
        ww = wx * wx + wy * wy  # the relative motion's closest approach over [0, t_end]
        tc = min(max(-(px * wx + py * wy) / ww, 0.0), t_end) if ww > 0.0 else 0.0
        if (px + wx * tc) ** 2 + (py + wy * tc) ** 2 > reach2:
            continue
        t_in, t_out = -np.inf, np.inf
        for a in range(4):
            if a == 0:  # theta = eh
                ux, uy = ce, se
                c_e, s_e, c_o, s_o = 1.0, 0.0, math.cos(oh - eh), math.sin(oh - eh)
            elif a == 2:  # theta = oh
                ux, uy = co, so
                c_e, s_e, c_o, s_o = math.cos(eh - oh), math.sin(eh - oh), 1.0, 0.0
            elif a == 1:  # theta = eh + pi / 2
                ux, uy, c_e, s_e = u1x, u1y, c1e, s1e
                c_o, s_o = math.cos(oh - t1), math.sin(oh - t1)
            else:
                theta = oh + math.pi / 2
                ux, uy = math.cos(theta), math.sin(theta)
                c_e, s_e = math.cos(eh - theta), math.sin(eh - theta)
                c_o, s_o = math.cos(oh - theta), math.sin(oh - theta)
            half = length / 2 * (abs(c_e) + abs(c_o)) + width / 2 * (abs(s_e) + abs(s_o))
            q, r = ux * px + uy * py, ux * wx + uy * wy
            if r != 0.0:
                ta, tb = (-half - q) / r, (half - q) / r
                lo, hi = min(ta, tb), max(ta, tb)
            elif abs(q) <= half:
                lo, hi = -np.inf, np.inf
            else:
                lo, hi = np.inf, -np.inf
            t_in, t_out = max(t_in, lo), min(t_out, hi)
        if not (t_in <= t_out + dt and t_out >= -dt and t_in <= horizon + dt):
            continue
        first = min(max(int(math.floor(max(t_in, 0.0) / dt)) - 1, 0), K - 1)
        last = min(max(int(math.ceil(min(t_out, horizon) / dt)) + 1, 0), K - 1)
        for k in range(first, last + 1):
            tk = grid[k]
            if tk >= best:
                break
            if _boxes_at(ex + tk * evx, ey + tk * evy, ce, se, x[j] + tk * ovx, y[j] + tk * ovy, co, so, hl, hw,
                         ca, cb):
                best = tk
                break
    return best


@numba.njit(cache=True, error_model="numpy", inline="always")
def _boxes_at(ax, ay, ce, se, bx, by, co, so, hl, hw, ca, cb):
    """Whether two length × width boxes centred at (ax, ay) and (bx, by) with headings of cosine/sine (ce, se) and
    (co, so) overlap: box_corners (centre + rot @ local, local corners (hl, hw), (hl, -hw), (-hl, -hw), (-hl, hw))
    into ``ca``, ``cb``, then :func:`boxes_overlap`."""
    box_corners(ax, ay, ce, se, hl, hw, ca)
    box_corners(bx, by, co, so, hl, hw, cb)
    return boxes_overlap(ca, cb)


@numba.njit(cache=True, error_model="numpy", inline="always")
def box_corners(cx, cy, c, s, hl, hw, out):
    """geometry.box_corners for one box into ``out`` (4, 2): the local corners (hl, hw), (hl, -hw), (-hl, -hw),
    (-hl, hw) rotated by the heading of cosine/sine (c, s) (the einsum's ``c·lx + (-s)·ly``, ``s·lx + c·ly``) and
    moved to the centre (cx, cy). Also the AEB shield's footprint test (av_gym.shields.kernels.footprint_hit)."""
    for p in range(4):
        lx = hl if p < 2 else -hl
        ly = hw if p == 0 or p == 3 else -hw
        out[p, 0], out[p, 1] = cx + (c * lx + -s * ly), cy + (s * lx + c * ly)


@numba.njit(cache=True, error_model="numpy", inline="always")
def boxes_overlap(a, b):
    """geometry.boxes_overlap for one pair of (4, 2) corner arrays: two edge normals of each box, touching counts.
    Also the AEB shield's footprint test (av_gym.shields.kernels.footprint_hit)."""
    for poly in range(2):
        c = a if poly == 0 else b
        for i in range(2):
            nx, ny = -(c[i + 1, 1] - c[i, 1]), c[i + 1, 0] - c[i, 0]
            amin = amax = a[0, 0] * nx + a[0, 1] * ny
            bmin = bmax = b[0, 0] * nx + b[0, 1] * ny
            for p in range(1, 4):
                qa, qb = a[p, 0] * nx + a[p, 1] * ny, b[p, 0] * nx + b[p, 1] * ny
                amin, amax, bmin, bmax = min(amin, qa), max(amax, qa), min(bmin, qb), max(bmax, qb)
            if not (amax >= bmin and bmax >= amin):
                return False
    return True


@numba.njit(cache=True, error_model="numpy")
def idm(lt, x, y, h, v, target, delta, lane, front, speed_limit, acc_max, acc_min, distance_wanted, time_wanted):
    """Traffic._idm_acc: IDMVehicle.acceleration with the leader ``front`` (-1: none), the gap measured along the
    current lane (lane_distance_to), utils.not_zero as there; every slot, as the numpy code."""
    B, N = x.shape
    out = np.empty((B, N))
    for b in range(B):
        for i in range(N):
            f = front[b, i]
            # what IDM shares with the leader search, when it has one
            s_i, s_f, ci, si, cf, sf = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            if f >= 0:
                s_i = _local(lt, lane[b, i], x[b, i], y[b, i])[0]
                s_f = _local(lt, lane[b, i], x[b, f], y[b, f])[0]
                ci, si, cf, sf = math.cos(h[b, i]), math.sin(h[b, i]), math.cos(h[b, f]), math.sin(h[b, f])
            out[b, i] = _idm_with(b, i, f, s_i, s_f, ci, si, cf, sf, v, target, delta, lane, speed_limit,
                                  acc_max, acc_min, distance_wanted, time_wanted)
    return out


@numba.njit(cache=True, error_model="numpy", inline="always")
def _idm_with(b, i, f, s_i, s_f, ci, si, cf, sf, v, target, delta, lane, speed_limit, acc_max, acc_min,
              distance_wanted, time_wanted):
    """:func:`idm` for vehicle i of env b with the leader ``f`` (-1: none), given what it shares with the leader
    search: the vehicle's own s and the leader's on the vehicle's lane (``s_i``, ``s_f``, m) and the cosines and
    sines of its heading and the leader's (unused when ``f`` is -1)."""
    ab = -acc_max * acc_min
    k = lane[b, i]
    tg = min(max(target[b, i], 0.0), speed_limit[k])
    tg = tg if abs(tg) > 1e-2 else (1e-2 if tg >= 0 else -1e-2)
    acc = acc_max * (1 - (max(v[b, i], 0.0) / abs(tg)) ** delta[b, i])
    if f >= 0:
        d = s_f - s_i
        d = d if abs(d) > 1e-2 else (1e-2 if d >= 0 else -1e-2)
        dv = (v[b, i] * ci - v[b, f] * cf) * ci + (v[b, i] * si - v[b, f] * sf) * si
        d_star = distance_wanted + v[b, i] * time_wanted + v[b, i] * dv / (2 * math.sqrt(ab))
        acc = acc - acc_max * (d_star / d) ** 2.0
    return acc


# ------------------------------------------------------------------------------------------------ one batch tick
# Traffic.act + Traffic.step for every env, frame after frame, in one call (Traffic.advance): the same formulas as
# the numpy code of av_gym/sim/batched.py in the same order of operations, env by env (envs never interact, so
# stepping env b's frames before env b+1's changes nothing). Constants: one float array, indices below.
# P_EGO_MARGIN (m): a planner's futures only (Traffic.ego_margin); 0, the real engine's, skips its test
(P_VEHICLE_LENGTH, P_LENGTH, P_WIDTH, P_COMFORT_MAX, P_COMFORT_MIN, P_ACC_MAX, P_DISTANCE, P_TIME, P_TAU, P_KP_LAT,
 P_KP_HEAD, P_KP_A, P_MAX_STEER, P_EXIT_DISTANCE, P_EGO_MARGIN) = range(15)
# m/s, highway-env's Vehicle.MAX_SPEED / MIN_SPEED (clip_actions): reached by a fast continuous ego at full throttle
# (a CCFtap target is capped at 144 km/h, 40 m/s); without them the batch split from the per-env stack there
MAX_SPEED, MIN_SPEED = 40.0, -40.0
SLOWER, FASTER = 0, 2


@numba.njit(cache=True, error_model="numpy")
def advance(lt, lanes, x, y, h, v, target, steer, acc, delta, alive, ego, plain, mdp, crashed, yielding, impact_x,
            impact_y, has_impact, lane, tlane, route, rpos, road_steps, active, meta, speeds, cmd, frames, dt,
            reg_period, reg_times, prm, ticks, time, arrived_time):
    """``frames`` ticks (Traffic.act then Traffic.step) of every env b with ``active[b]``: the ego's meta-action
    ``meta[b]`` at the first tick (-1: none), the ego's commanded acceleration ``cmd[frame, b]`` per tick (m/s²,
    the continuous ego's command or the AEB shield's brake; NaN: the discrete ego's speed control), the
    regulation every ``reg_period`` road steps; after each tick ``ticks[b]`` counts and an ego that has arrived
    gets ``arrived_time[b] = time[b]`` once. ``lanes``: (L, 5) per lane id:
    speed limit, priority, leaving lane (1.0), from-node id, to-node id. State arrays are updated in place."""
    B, N = x.shape
    T = reg_times.shape[0]
    lb = np.empty((lt.shape[0], 2))
    px, py, ph = np.empty((N, T)), np.empty((N, T)), np.empty((N, T))
    clx = np.array([-prm[P_LENGTH] / 2, -prm[P_LENGTH] / 2, prm[P_LENGTH] / 2, prm[P_LENGTH] / 2,
                    -prm[P_LENGTH] / 2])
    cly = np.array([-prm[P_WIDTH] / 2, prm[P_WIDTH] / 2, prm[P_WIDTH] / 2, -prm[P_WIDTH] / 2, -prm[P_WIDTH] / 2])
    pa, pb, nrm, dist = np.empty((5, 2)), np.empty((5, 2)), np.empty((8, 2)), np.empty(8)
    ch, sh = np.empty(N), np.empty(N)
    ca, cb = np.empty((4, 2)), np.empty((4, 2))
    for b in range(B):
        if not active[b]:
            continue
        # the slots after the last live one: nobody (no vehicle enters or leaves during the ticks); np.int64, not
        # a literal 0, or _act_row and _collide_row compile once more for Literal[int](0) while n_used is typed
        n_used = np.int64(0)
        for j in range(N):
            if alive[b, j]:
                n_used = j + 1
        for frame in range(frames):
            _act_row(lt, lanes, b, x, y, h, v, target, steer, acc, delta, alive, ego, plain, crashed, lane, tlane,
                     route, rpos, meta[b] if frame == 0 else -1, speeds, cmd[frame, b], prm, ch, sh, n_used)
            road_steps[b] += 1
            if road_steps[b] % reg_period == 0:
                _road_rules_row(lt, lanes, b, x, y, h, v, target, alive, plain, mdp, yielding, lane, route, rpos,
                                reg_times, prm, px, py, ph)
            _kinematics_row(lt, b, x, y, h, v, steer, acc, alive, crashed, impact_x, impact_y, has_impact, lane,
                            dt, prm, lb, ch, sh)
            _collide_row(b, x, y, h, v, alive, dt, prm[P_LENGTH], prm[P_WIDTH], crashed, has_impact, impact_x,
                         impact_y, clx, cly, pa, pb, nrm, dist, n_used)
            if prm[P_EGO_MARGIN] > 0.0:
                _near_ego_row(b, x, y, h, alive, ego, crashed, prm[P_LENGTH], prm[P_WIDTH], prm[P_EGO_MARGIN], ca,
                              cb, n_used)
            ticks[b] += 1
            if math.isnan(arrived_time[b]) and _arrived(lt, lanes, b, x, y, ego, lane, prm[P_EXIT_DISTANCE]):
                arrived_time[b] = time[b]


@numba.njit(cache=True, error_model="numpy", inline="always")
def _arrived(lt, lanes, b, x, y, ego, lane, exit_distance):
    """BatchedLeftTurn.has_arrived for env b's ego (the first ego slot, slot 0 if none, as np.argmax)."""
    e = 0
    for j in range(x.shape[1]):
        if ego[b, j]:
            e = j
            break
    k = lane[b, e]
    return lanes[k, 2] != 0.0 and _local(lt, k, x[b, e], y[b, e])[0] >= exit_distance


@numba.njit(cache=True, error_model="numpy")
def _act_row(lt, lanes, b, x, y, h, v, target, steer, acc, delta, alive, ego, plain, crashed, lane, tlane, route,
             rpos, meta, speeds, cmd, prm, ch, sh, n_used):
    """Traffic.act for env b: the ego's meta-action (MDPVehicle.act), then per controlled vehicle follow_road,
    steering_control and IDM (the min over the current and the target lane's leader while they differ), or the
    ego's speed control / commanded acceleration. ``ch``, ``sh`` (N,): filled with each live vehicle's heading's
    cos and sin; ``n_used``: no live slot after the first n_used."""
    N = n_used
    n_s = speeds.shape[0]
    if meta >= 0 and meta != 1:
        step = 1 if meta == FASTER else -1 if meta == SLOWER else 0
        for i in range(N):
            if ego[b, i] and alive[b, i] and step != 0:
                idx = min(max(np.rint((v[b, i] - speeds[0]) / (speeds[n_s - 1] - speeds[0]) * (n_s - 1)), 0.0),
                          n_s - 1.0)
                target[b, i] = speeds[int(min(max(idx + step, 0.0), n_s - 1.0))]
    for j in range(N):  # IDM reads each heading's cosine and sine up to three times a tick
        if alive[b, j]:
            ch[j], sh[j] = math.cos(h[b, j]), math.sin(h[b, j])
    vl = prm[P_VEHICLE_LENGTH]
    for i in range(N):
        if not alive[b, i] or plain[b, i] or (crashed[b, i] and not ego[b, i]):
            continue  # IDMVehicle.act returns early when crashed; a plain Vehicle keeps its action
        k = tlane[b, i]  # follow_road, then steering on the (new) target lane: one local_coordinates if unchanged
        s, r = _local(lt, k, x[b, i], y[b, i])
        if s > lt[k, LENGTH] - vl / 2:
            _next_route_step(lanes, b, i, k, tlane, route, rpos)
            if tlane[b, i] != k:
                k = tlane[b, i]
                s, r = _local(lt, k, x[b, i], y[b, i])
        steer[b, i] = min(max(_steering_sr(lt, k, s, r, v[b, i], h[b, i], prm), -prm[P_MAX_STEER]), prm[P_MAX_STEER])
        if ego[b, i]:
            if math.isnan(cmd):
                acc[b, i] = prm[P_KP_A] * (target[b, i] - v[b, i])
            else:  # RouteFollowingVehicle.act: no reversing, a standstill is held
                acc[b, i] = max(cmd, -v[b, i] / 0.05)
            continue
        kl = lane[b, i]
        s_l = s if kl == k else _local(lt, kl, x[b, i], y[b, i])[0]
        f, s_f = _front_from(lt, kl, s_l, b, i, x, y, alive, vl, n_used)  # s_f: the leader's, IDM's gap
        a = _idm_with(b, i, f, s_l, s_f, ch[i], sh[i], ch[max(f, 0)], sh[max(f, 0)], v, target, delta, lane,
                      lanes[:, 0], prm[P_COMFORT_MAX], prm[P_COMFORT_MIN], prm[P_DISTANCE], prm[P_TIME])
        if kl != k:  # changing lanes: also the target lane's leader, the gap still measured on the current lane
            f = _front_from(lt, k, s, b, i, x, y, alive, vl, n_used)[0]
            s_f = _local(lt, kl, x[b, f], y[b, f])[0] if f >= 0 else 0.0
            a = min(a, _idm_with(b, i, f, s_l, s_f, ch[i], sh[i], ch[max(f, 0)], sh[max(f, 0)], v, target, delta,
                                 lane, lanes[:, 0], prm[P_COMFORT_MAX], prm[P_COMFORT_MIN], prm[P_DISTANCE],
                                 prm[P_TIME]))
        acc[b, i] = min(max(a, -prm[P_ACC_MAX]), prm[P_ACC_MAX])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _next_route_step(lanes, b, i, k, tlane, route, rpos):
    """Traffic._follow_road for one vehicle past the end of its target lane ``k``: the route's next step."""
    p = rpos[b, i]
    if p < 3 and route[b, i, p] == k:
        p += 1
    if p < 3 and route[b, i, p] >= 0 and lanes[route[b, i, p], 3] == lanes[k, 4]:
        tlane[b, i] = route[b, i, p]
    rpos[b, i] = p


@numba.njit(cache=True, error_model="numpy", inline="always")
def _heading_at(lt, k, s):
    """LaneTable.heading_at for one lane."""
    if lt[k, CIRC] != 0.0:
        return lt[k, CDIR] * s / lt[k, RADIUS] + lt[k, PHASE0] + math.pi / 2 * lt[k, CDIR]
    return lt[k, HEAD]


@numba.njit(cache=True, error_model="numpy", inline="always")
def _not_zero(a):
    return a if abs(a) > 1e-2 else (1e-2 if a >= 0 else -1e-2)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _clip(a, lo, hi):
    return min(max(a, lo), hi)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _steering_sr(lt, k, s, r, v, h, prm):
    """Traffic._steering (ControlledVehicle.steering_control) for one vehicle at (s, r) on its target lane k."""
    future_heading = _heading_at(lt, k, s + v * prm[P_TAU])
    v_nz = _not_zero(v)
    heading_cmd = math.asin(_clip(-prm[P_KP_LAT] * r / v_nz, -1.0, 1.0))
    heading_ref = future_heading + _clip(heading_cmd, -math.pi / 4, math.pi / 4)
    rate = prm[P_KP_HEAD] * _wrap(heading_ref - h)
    q = _clip(prm[P_LENGTH] / 2 / v_nz * rate, -1.0, 1.0)  # sin(slip)
    # tan(slip) = tan(asin(q)) = q / sqrt(1 - q²) (±inf at |q| = 1, whose atan is ±π/2): no slip angle, the same
    # steering to a few ulp (batched.Traffic._steering computes it so too)
    tan_slip = q / math.sqrt(1.0 - q * q) if abs(q) < 1.0 else math.copysign(np.inf, q)
    return _clip(math.atan(2 * tan_slip), -prm[P_MAX_STEER], prm[P_MAX_STEER])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _slip_cos_sin(steer):
    """cos β and sin β of the bicycle's slip angle β = atan(tan(steer) / 2) from t = tan β: 1 / sqrt(1 + t²) and
    t / sqrt(1 + t²), no angle (batched.Traffic._kinematics computes them so too; a few ulp from cos / sin of β)."""
    t = 1 / 2 * math.tan(steer)
    cb = 1.0 / math.sqrt(1.0 + t * t)
    return cb, t * cb


@numba.njit(cache=True, error_model="numpy")
def _kinematics_row(lt, b, x, y, h, v, steer, acc, alive, crashed, impact_x, impact_y, has_impact, lane, dt, prm,
                    lb, ch, sh):
    """Traffic._kinematics for env b: clip_actions, the kinematic bicycle, a pending impact, the closest lane.
    ``ch``, ``sh``: each live vehicle's cos and sin of its heading (_act_row's)."""
    for i in range(x.shape[1]):
        if not alive[b, i]:
            continue
        if crashed[b, i]:
            steer[b, i], acc[b, i] = 0.0, -1.0 * v[b, i]
        # clip_actions writes into the vehicle's action: kept in acc, as a plain vehicle keeps its action
        if v[b, i] > MAX_SPEED:
            acc[b, i] = min(acc[b, i], 1.0 * (MAX_SPEED - v[b, i]))
        elif v[b, i] < MIN_SPEED:
            acc[b, i] = max(acc[b, i], 1.0 * (MIN_SPEED - v[b, i]))
        cb, sb = _slip_cos_sin(steer[b, i])
        xn = x[b, i] + v[b, i] * (ch[i] * cb - sh[i] * sb) * dt  # cos(h + β)
        yn = y[b, i] + v[b, i] * (sh[i] * cb + ch[i] * sb) * dt  # sin(h + β)
        if has_impact[b, i]:
            xn, yn = xn + impact_x[b, i], yn + impact_y[b, i]
            crashed[b, i], has_impact[b, i] = True, False
        hn = h[b, i] + v[b, i] * sb / (prm[P_LENGTH] / 2) * dt
        x[b, i], y[b, i], h[b, i], v[b, i] = xn, yn, hn, v[b, i] + acc[b, i] * dt
        lane[b, i] = _closest_one(lt, xn, yn, hn, lb, lane[b, i])  # hint: its lane before the move


@numba.njit(cache=True, error_model="numpy")
def _road_rules_row(lt, lanes, b, x, y, h, v, target, alive, plain, mdp, yielding, lane, route, rpos, reg_times,
                    prm, px, py, ph):
    """Traffic._enforce_road_rules for env b: release the yielding vehicles, predict along the routes, then
    respect_priorities for every conflicting pair in pair order."""
    N = x.shape[1]
    for i in range(N):
        if yielding[b, i]:
            target[b, i] = lanes[lane[b, i], 0]
            yielding[b, i] = False
    for i in range(N):
        if alive[b, i]:  # (the numpy code predicts every slot; only live vehicles' predictions are read)
            _predict_one(lt, b, i, x, y, h, v, plain, lane, route, rpos, reg_times, px, py, ph)
    L, W = 1.5 * prm[P_LENGTH], 0.9 * prm[P_WIDTH]
    hl, hw = L / 2, W / 2
    lx = np.array([-hl, -hl, hl, hl, 0.0, -hl, hl, 0.0, 0.0])
    ly = np.array([-hw, hw, hw, -hw, 0.0, 0.0, 0.0, -hw, hw])
    for i in range(N):
        if not alive[b, i]:
            continue
        for j in range(i + 1, N):
            if not alive[b, j] or not _conflict_pair(px, py, ph, i, j, prm[P_LENGTH], lx, ly, hl, hw):
                continue
            p1, p2 = lanes[lane[b, i], 1], lanes[lane[b, j], 1]
            if p1 > p2:
                yv = j
            elif p1 < p2:
                yv = i
            else:  # the vehicle behind yields: front_distance_to
                dx, dy = x[b, j] - x[b, i], y[b, j] - y[b, i]
                fi = math.cos(h[b, i]) * dx + math.sin(h[b, i]) * dy
                fj = -(math.cos(h[b, j]) * dx + math.sin(h[b, j]) * dy)
                yv = i if fi > fj else j
            if not (mdp[b, yv] or plain[b, yv]):
                target[b, yv] = 0.0
                yielding[b, yv] = True


@numba.njit(cache=True, error_model="numpy", inline="always")
def _predict_one(lt, b, i, x, y, h, v, plain, lane, route, rpos, reg_times, px, py, ph):
    """Traffic._predict for one vehicle into row i of (N, T) ``px``, ``py``, ``ph``: constant speed along the rest
    of its route (a plain vehicle: a straight line along its heading)."""
    if plain[b, i]:
        for t in range(reg_times.shape[0]):
            tt = reg_times[t]
            px[i, t] = x[b, i] + v[b, i] * math.cos(h[b, i]) * tt
            py[i, t] = y[b, i] + v[b, i] * math.sin(h[b, i]) * tt
            ph[i, t] = h[b, i]
        return
    s0 = _local(lt, lane[b, i], x[b, i], y[b, i])[0]
    rp = rpos[b, i]
    n_left = min(max(3 - rp, 0), 3)
    head = route[b, i, min(rp, 2)]
    if head < 0:
        n_left = 0
    first = head if n_left > 0 else lane[b, i]
    for t in range(reg_times.shape[0]):
        lon = s0 + v[b, i] * reg_times[t]
        k, left, pos = first, max(n_left, 1), rp
        for _ in range(2):  # while len(route) > 1 and longitudinal > lane.length: move on
            if left > 1 and lon > lt[k, LENGTH]:
                lon = lon - lt[k, LENGTH]
                pos, left = pos + 1, left - 1
                k = route[b, i, min(pos, 2)]
        if lt[k, CIRC] != 0.0:
            phi = lt[k, CDIR] * lon / lt[k, RADIUS] + lt[k, PHASE0]
            rad = lt[k, RADIUS] - 0.0 * lt[k, CDIR]
            px[i, t], py[i, t] = lt[k, OX] + rad * math.cos(phi), lt[k, OY] + rad * math.sin(phi)
        else:
            px[i, t] = lt[k, OX] + lon * lt[k, DX] + 0.0 * -lt[k, DY]
            py[i, t] = lt[k, OY] + lon * lt[k, DY] + 0.0 * lt[k, DX]
        ph[i, t] = _heading_at(lt, k, lon)


@numba.njit(cache=True, error_model="numpy")
def path_conflict(p, v, path, path_s, t_max):
    """turn_features.path_conflict for (n, M, 2) positions ``p`` and velocities ``v``: per object the
    constant-velocity closest approach to each point of the ego's ``path`` (P, 2) (:func:`_closest_approach`);
    returns t* (s), miss (m) and the path point's ``path_s`` (m), each (n, M)."""
    n, M, P = p.shape[0], p.shape[1], path.shape[0]
    t_out, miss_out, s_out = np.empty((n, M)), np.empty((n, M)), np.empty((n, M))
    tk, qx, qy, q2 = np.empty(P), np.empty(P), np.empty(P), np.empty(P)
    for a in range(n):
        for m in range(M):
            t_out[a, m], miss_out[a, m], s_out[a, m] = _closest_approach(p[a, m, 0], p[a, m, 1], v[a, m, 0],
                                                                         v[a, m, 1], path, path_s, t_max, tk, qx,
                                                                         qy, q2)
    return t_out, miss_out, s_out


@numba.njit(cache=True, error_model="numpy", inline="always")
def _closest_approach(px, py, vx, vy, path, path_s, t_max, tk, qx, qy, q2):
    """One object's constant-velocity closest approach to each point c of ``path``: t* = clip(-(p - c)·v /
    max(|v|², 1e-6), 0, t_max) and miss = hypot(p + v t* - c); the first point of least miss gives (t* (s), miss
    (m), its ``path_s`` (m)). The same sums in the same order as the numpy code (two terms each); ``tk``, ``qx``,
    ``qy``, ``q2`` (P,) are scratch."""
    P = path.shape[0]
    vv = max(vx * vx + vy * vy, 1e-6)
    m2 = np.inf
    for k in range(P):
        dx, dy = px - path[k, 0], py - path[k, 1]
        tk[k] = min(max(-(dx * vx + dy * vy) / vv, 0.0), t_max)
        qx[k], qy[k] = dx + vx * tk[k], dy + vy * tk[k]
        q2[k] = qx[k] * qx[k] + qy[k] * qy[k]
        m2 = min(m2, q2[k])
    # the least miss is among the points whose squared miss is within 1e-9 of the least (hypot's and the square's
    # rounding are a few ulp): hypot only for those, the first of equal minima as np.argmin
    best, kb = np.inf, 0
    for k in range(P):
        if q2[k] <= m2 * (1.0 + 1e-9):
            miss = math.hypot(qx[k], qy[k])
            if miss < best:
                best, kb = miss, k
    return tk[kb], best, path_s[kb]


# ------------------------------------------------------------------------------------------------ obs["turn"], truth
# The turn features (av_gym.estimation.turn_features.turn_features) and the batch's truth and rewards
# (BatchedLeftTurn.truth / _reward / observe) in one call each: numpy's formulas in numpy's order; only cos / sin /
# tan / atan / atan2 are the C library's (numpy's own SIMD code on AVX-512 builds: the last bit may differ there).
# ego inputs of a feature row (turn_features.EGO_INPUTS' order)
E_X, E_Y, E_HEADING, E_SPEED, E_SET_POINT, E_STOP_LINE, E_TO_CONFLICT, E_TIME = range(8)
# truth's columns (BatchedLeftTurn.truth's keys, in TRUTH_FIELDS' order)
TRUTH_FIELDS = ("time", "x", "y", "heading", "speed", "yaw_rate", "acceleration", "steering", "route_s", "cte",
                "stop_line_offset", "distance_to_conflict", "oncoming_gap", "collision", "arrived", "arrived_time",
                "set_point")
(T_TIME, T_X, T_Y, T_HEADING, T_SPEED, T_YAW_RATE, T_ACC, T_STEER, T_ROUTE_S, T_CTE, T_STOP_LINE, T_TO_CONFLICT,
 T_ONCOMING_GAP, T_COLLISION, T_ARRIVED, T_ARRIVED_TIME, T_SET_POINT) = range(17)
# truth's geometry (``geo``): vehicle length, width (m), the conflict point's route position (m), the oncoming
# lane's near edge x (m), the arrival distance along a leaving lane (m)
G_LENGTH, G_WIDTH, G_CONFLICT_S, G_ONCOMING_EDGE, G_EXIT_DISTANCE = range(5)
# rewards' parameters (``prm``): UnprotectedLeftTurnEnv._reward's config values, its dt (s) and the arrival distance
(R_SPEED_REWARD, R_SPEED_LO, R_SPEED_HI, R_DT, R_PROGRESS, R_COMFORT, R_COLLISION, R_ARRIVED,
 R_EXIT_DISTANCE) = range(9)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _encode(value, scale):
    """TurnEncoding.encode for one value: value / scale clipped to [-1, 1], NaN → 0, as float32."""
    q = value / scale
    if math.isnan(q):
        return np.float32(0.0)
    return np.float32(min(max(q, -1.0), 1.0))


@numba.njit(cache=True, error_model="numpy", inline="always")
def _before(a, b):
    """np.argsort's order of two distances: NaN after every number, else the smaller first."""
    return not math.isnan(a) and (math.isnan(b) or a < b)


@numba.njit(cache=True, error_model="numpy")
def _features_row(out, order, present, a, ego, others, valid, path, path_s, conflict, max_range, ego_scales,
                  obj_scales, t_max, d, idx, tk, qx, qy, q2):
    """turn_features for one ego: ``ego`` (8,) its EGO_INPUTS (SI), ``others`` (N, ≥4) ``[x, y, vx, vy]`` (m, m/s)
    with ``valid`` (N,); writes row ``a`` of ``out`` (n, width) float32, ``order`` and ``present`` (n, m).
    ``d``, ``idx`` (N,) and ``tk``, ``qx``, ``qy``, ``q2`` (P,) are scratch."""
    N, m, F = others.shape[0], order.shape[1], obj_scales.shape[0]
    ex, ey, ev = ego[E_X], ego[E_Y], ego[E_SPEED]
    for j in range(N):
        d[j] = math.hypot(others[j, 0] - ex, others[j, 1] - ey) if valid[j] else np.inf
        idx[j] = j
    for j in range(1, N):  # np.argsort(kind="stable"): insertion, so equal distances stay in row order
        cur, k = idx[j], j
        while k > 0 and _before(d[cur], d[idx[k - 1]]):
            idx[k] = idx[k - 1]
            k -= 1
        idx[k] = cur
    out[a, 0], out[a, 1] = _encode(ev, ego_scales[0]), _encode(ego[E_SET_POINT], ego_scales[1])
    out[a, 2], out[a, 3] = _encode(-ego[E_STOP_LINE], ego_scales[2]), _encode(ego[E_TO_CONFLICT], ego_scales[3])
    out[a, 4] = _encode(ego[E_TIME], ego_scales[4])
    c, s = math.cos(ego[E_HEADING]), math.sin(ego[E_HEADING])
    for r in range(m):
        j = idx[r]
        order[a, r], present[a, r] = j, d[j] <= max_range
        if not present[a, r]:  # a zero row (out starts as zeros)
            continue
        ox, oy, ovx, ovy = others[j, 0], others[j, 1], others[j, 2], others[j, 3]
        rx, ry = ox - ex, oy - ey  # relative position and velocity in the ego frame (x forward, y left)
        rvx, rvy = ovx - ev * c, ovy - ev * s
        t_star, miss, ps = _closest_approach(ox, oy, ovx, ovy, path, path_s, t_max, tk, qx, qy, q2)
        row = (1.0, rx * c + ry * s, rx * -s + ry * c, rvx * c + rvy * s, rvx * -s + rvy * c, ox - conflict[0],
               oy - conflict[1], ovx, ovy, t_star, miss, ps)
        for f in range(F):
            out[a, ego_scales.shape[0] + F * r + f] = _encode(row[f], obj_scales[f])


@numba.njit(cache=True, error_model="numpy")
def turn_features(ego, others, valid, path, path_s, conflict, max_objects, max_range, ego_scales, obj_scales,
                  t_max):
    """av_gym.estimation.turn_features.turn_features for n egos: ``ego`` (n, 8) EGO_INPUTS, ``others`` (n, N, ≥4)
    with ``valid`` (n, N); the encoding's scales. Returns the features (n, width) float32, ``order`` and
    ``present`` (n, min(max_objects, N)), as the numpy function."""
    n, N = valid.shape
    m = min(max_objects, N)
    out = np.zeros((n, ego_scales.shape[0] + obj_scales.shape[0] * max_objects), dtype=np.float32)
    order, present = np.zeros((n, m), dtype=np.int64), np.zeros((n, m), dtype=np.bool_)
    d, idx = np.empty(N), np.empty(N, dtype=np.int64)
    P = path.shape[0]
    tk, qx, qy, q2 = np.empty(P), np.empty(P), np.empty(P), np.empty(P)
    for a in range(n):
        _features_row(out, order, present, a, ego[a], others[a], valid[a], path, path_s, conflict, max_range,
                      ego_scales, obj_scales, t_max, d, idx, tk, qx, qy, q2)
    return out, order, present


@numba.njit(cache=True, error_model="numpy", inline="always")
def _ego_of(ego, b):
    """The first ego slot of env b (slot 0 if none, as np.argmax)."""
    for j in range(ego.shape[1]):
        if ego[b, j]:
            return j
    return 0


@numba.njit(cache=True, error_model="numpy", inline="always")
def _route_position(lt, route, route_starts, route_k, b, x, y):
    """BatchedLeftTurn._route_s for one ego at (x, y) (LanePath.locate from the hint ``route_k[b]``, which it moves
    along): the route position (m) and the lateral offset (m)."""
    R = route.shape[0]
    k = route_k[b]
    s, lat = _local(lt, route[k], x, y)
    step = 1 if s > lt[route[k], LENGTH] else (-1 if s < 0 else 0)
    for _ in range(R):
        if step == 0 or k + step < 0 or k + step >= R:
            break
        k += step
        s, lat = _local(lt, route[k], x, y)
        if (step > 0 and s <= lt[route[k], LENGTH]) or (step < 0 and s >= 0):
            step = 0
    route_k[b] = k
    return route_starts[k] + s, lat


@numba.njit(cache=True, error_model="numpy")
def truth(lt, lanes, route, route_starts, geo, rows, x, y, h, v, steer, acc, target, ego, crashed, lane, route_k,
          time, arrived_time):
    """BatchedLeftTurn.truth for the envs ``rows``: (n, 17) float, columns TRUTH_FIELDS (collision and arrived as
    0 / 1); ``route_k`` moves along as _route_s moves it. ``geo``: G_* values."""
    n = rows.shape[0]
    out = np.empty((n, len(TRUTH_FIELDS)))
    half_l, half_w = geo[G_LENGTH] / 2, geo[G_WIDTH] / 2
    for a in range(n):
        b = rows[a]
        e = _ego_of(ego, b)
        xe, ye, he, ve = x[b, e], y[b, e], h[b, e], v[b, e]
        route_s, lat = _route_position(lt, route, route_starts, route_k, b, xe, ye)
        beta = math.atan(0.5 * math.tan(steer[b, e]))
        c, s = math.cos(he), math.sin(he)
        gap = np.inf
        for sx, sy in ((-1.0, -1.0), (-1.0, 1.0), (1.0, 1.0), (1.0, -1.0)):  # the box's corners, rear left first
            gap = min(gap, xe + sx * half_l * c - sy * half_w * s)
        o = out[a]
        o[T_TIME], o[T_X], o[T_Y], o[T_HEADING], o[T_SPEED] = time[b], xe, ye, he, ve
        o[T_YAW_RATE], o[T_ACC], o[T_STEER] = ve * math.sin(beta) / half_l, acc[b, e], steer[b, e]
        o[T_ROUTE_S], o[T_CTE], o[T_STOP_LINE] = route_s, lat, route_s + half_l - route_starts[1]
        o[T_TO_CONFLICT], o[T_ONCOMING_GAP] = geo[G_CONFLICT_S] - route_s, gap - geo[G_ONCOMING_EDGE]
        o[T_COLLISION] = 1.0 if crashed[b, e] else 0.0
        o[T_ARRIVED] = 1.0 if _arrived(lt, lanes, b, x, y, ego, lane, geo[G_EXIT_DISTANCE]) else 0.0
        o[T_ARRIVED_TIME], o[T_SET_POINT] = arrived_time[b], target[b, e]
    return out


@numba.njit(cache=True, error_model="numpy")
def observe(lt, lanes, route, route_starts, geo, rows, x, y, h, v, steer, acc, target, alive, ego, crashed, lane,
            route_k, time, arrived_time, path, path_s, conflict, max_objects, max_range, ego_scales, obj_scales,
            t_max):
    """BatchedLeftTurn.observe for the envs ``rows``: :func:`truth`'s columns, then :func:`turn_features` of each
    ego with every other vehicle of its env (``[x, y, v cos h, v sin h]``). Returns (truth, features, order,
    present)."""
    tr = truth(lt, lanes, route, route_starts, geo, rows, x, y, h, v, steer, acc, target, ego, crashed, lane,
               route_k, time, arrived_time)
    n, N, P = rows.shape[0], x.shape[1], path.shape[0]
    m = min(max_objects, N)
    out = np.zeros((n, ego_scales.shape[0] + obj_scales.shape[0] * max_objects), dtype=np.float32)
    order, present = np.zeros((n, m), dtype=np.int64), np.zeros((n, m), dtype=np.bool_)
    others, valid, inputs = np.empty((N, 4)), np.empty(N, dtype=np.bool_), np.empty(8)
    d, idx = np.empty(N), np.empty(N, dtype=np.int64)
    tk, qx, qy, q2 = np.empty(P), np.empty(P), np.empty(P), np.empty(P)
    for a in range(n):
        b = rows[a]
        for j in range(N):  # an invalid row is never described (its distance is +inf): its values are not read
            valid[j] = alive[b, j] and not ego[b, j]
            if valid[j]:
                others[j, 0], others[j, 1] = x[b, j], y[b, j]
                others[j, 2], others[j, 3] = v[b, j] * math.cos(h[b, j]), v[b, j] * math.sin(h[b, j])
        inputs[E_X], inputs[E_Y], inputs[E_HEADING], inputs[E_SPEED] = tr[a, T_X], tr[a, T_Y], tr[a, T_HEADING], \
            tr[a, T_SPEED]
        inputs[E_SET_POINT], inputs[E_STOP_LINE] = tr[a, T_SET_POINT], tr[a, T_STOP_LINE]
        inputs[E_TO_CONFLICT], inputs[E_TIME] = tr[a, T_TO_CONFLICT], tr[a, T_TIME]
        _features_row(out, order, present, a, inputs, others, valid, path, path_s, conflict, max_range, ego_scales,
                      obj_scales, t_max, d, idx, tk, qx, qy, q2)
    return tr, out, order, present


@numba.njit(cache=True, error_model="numpy")
def rewards(lt, lanes, route, route_starts, rows, x, y, v, acc, ego, crashed, lane, route_k, progress_s,
            progress_total, prm):
    """UnprotectedLeftTurnEnv._reward (BatchedLeftTurn._reward) for the envs ``rows``, the progress and route hint
    updated in place; ``prm``: R_* values. Returns the rewards, and whether each ego crashed and has arrived."""
    n = rows.shape[0]
    reward, crashed_out, arrived_out = np.empty(n), np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
    lo, hi, dt = prm[R_SPEED_LO], prm[R_SPEED_HI], prm[R_DT]
    for a in range(n):
        b = rows[a]
        e = _ego_of(ego, b)
        r = prm[R_SPEED_REWARD] * min(max((v[b, e] - lo) / (hi - lo), 0.0), 1.0) * dt
        if prm[R_PROGRESS] != 0.0:
            s = _route_position(lt, route, route_starts, route_k, b, x[b, e], y[b, e])[0]
            gain = s - progress_s[b]
            r = r + prm[R_PROGRESS] * (gain if gain > 0.0 or math.isnan(gain) else 0.0) / progress_total[b]
            progress_s[b] = s if s > progress_s[b] or math.isnan(s) else progress_s[b]
        if prm[R_COMFORT] != 0.0:
            r = r - prm[R_COMFORT] * (acc[b, e] / 3.0) ** 2 * dt
        crashed_out[a] = crashed[b, e]
        arrived_out[a] = _arrived(lt, lanes, b, x, y, ego, lane, prm[R_EXIT_DISTANCE])
        reward[a] = r + (prm[R_COLLISION] if crashed_out[a] else (prm[R_ARRIVED] if arrived_out[a] else 0.0))
    return reward, crashed_out, arrived_out


# ------------------------------------------------------------------------------------------------ generator draws
# numpy Generator draws inside the kernels, on each env's own generator. Every env of the batch has its own
# np.random.Generator whose stream must stay the one highway-env's calls make on the per-env stack (uniform,
# choice(range(4), 2, replace=False), normal, in highway-env's order); a Python call per draw costs 1-25 us. Here a
# kernel calls the bit generator's own C functions (BitGenerator.ctypes: next_uint64, next_uint32, next_double)
# through their pointers on each generator's state address, and runs numpy's distribution code
# (numpy/random/src/distributions/distributions.c: random_standard_normal's ziggurat with numba's copy of numpy's
# tables, random_bounded_uint64's Lemire rejection, Generator.choice's Floyd sampling and shuffle) in the same order
# of operations: a draw advances the same state by the same amount to the same value as the numpy call, so Python
# and kernel draws interleave freely on one generator (tests/test_kernels.py::
# test_kernel_draws_are_the_generators_own_stream: values and states, many seeds). The pointers are declared with a
# uint64 argument for the ``void *`` state (the same integer register on the x86-64 and AArch64 C conventions;
# numba has no integer-to-pointer cast). Only PCG64 generators are drawn from here (generator_states).
_U64 = ctypes.CFUNCTYPE(ctypes.c_uint64, ctypes.c_uint64)
_U32 = ctypes.CFUNCTYPE(ctypes.c_uint32, ctypes.c_uint64)
_DBL = ctypes.CFUNCTYPE(ctypes.c_double, ctypes.c_uint64)
_PCG64_FUNCTIONS = []
# a private prototype (not ctypes.pythonapi's shared attribute, whose argtypes other code may set)
_CAPSULE_POINTER = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
    ("PyCapsule_GetPointer", ctypes.pythonapi))
ZIG_KI, ZIG_WI, ZIG_FI = (np.asarray(ki_double, dtype=np.uint64), np.asarray(wi_double, dtype=np.float64),
                          np.asarray(fi_double, dtype=np.float64))
ZIG_R, ZIG_INV_R = float(ziggurat_nor_r), float(ziggurat_nor_inv_r)


def pcg64_functions() -> tuple:
    """PCG64's (next_uint64, next_uint32, next_double) as ctypes functions of a state address (the same C functions
    for every PCG64 instance), for the kernels' ``fns`` argument."""
    if not _PCG64_FUNCTIONS:
        c = np.random.PCG64(0).ctypes
        address = lambda f: ctypes.cast(f, ctypes.c_void_p).value  # noqa: E731
        _PCG64_FUNCTIONS.extend((_U64(address(c.next_uint64)), _U32(address(c.next_uint32)),
                                 _DBL(address(c.next_double))))
    return tuple(_PCG64_FUNCTIONS)


def generator_states(rngs) -> np.ndarray | None:
    """The state addresses (uint64) of ``rngs``' bit generators, or None when one is not a PCG64, or two rows share a
    generator (numpy's calls then keep an order across rows that a kernel's env-by-env loop would change). The
    caller holds the generators while a kernel uses the addresses."""
    try:
        bgs = [g.bit_generator for g in rngs]
    except AttributeError:  # not a Generator (None: a view whose futures get theirs later)
        return None
    if {type(bg) for bg in bgs} - {np.random.PCG64} or not _ZIGGURAT_TABLES or ctypes.sizeof(ctypes.c_void_p) != 8:
        return None  # the state pointer passes as a uint64 only where a pointer is 64 bits
    # bitgen_t's first field is the state pointer (what BitGenerator.ctypes.state_address gives): read through the
    # capsule every BitGenerator holds, since .ctypes builds three ctypes functions on its first use (~10 us), and
    # most generators here are new (forks' copies, the planner's futures)
    get, name, pointer_at = _CAPSULE_POINTER, b"BitGenerator", ctypes.c_void_p.from_address
    addresses = [pointer_at(get(bg.capsule, name)).value for bg in bgs]
    return np.array(addresses, dtype=np.uint64) if len(set(addresses)) == len(addresses) else None


@numba.njit(cache=True, error_model="numpy", inline="always")
def standard_normal(fns, st):
    """Generator.normal() / standard_normal() on the generator at state address ``st``: numpy's
    random_standard_normal (the 256-layer ziggurat)."""
    while True:
        r = fns[0](st)
        idx = np.int64(r & np.uint64(0xFF))
        r = r >> np.uint64(8)
        sign = r & np.uint64(1)
        rabs = (r >> np.uint64(1)) & np.uint64(0x000FFFFFFFFFFFFF)
        x = rabs * ZIG_WI[idx]
        if sign != np.uint64(0):
            x = -x
        if rabs < ZIG_KI[idx]:
            return x  # 99.3 % of the draws
        if idx == 0:
            while True:
                xx = -ZIG_INV_R * math.log1p(-fns[2](st))
                yy = -math.log1p(-fns[2](st))
                if yy + yy > xx * xx:
                    return -(ZIG_R + xx) if (rabs >> np.uint64(8)) & np.uint64(1) else ZIG_R + xx
        elif (ZIG_FI[idx - 1] - ZIG_FI[idx]) * fns[2](st) + ZIG_FI[idx] < math.exp(-0.5 * x * x):
            return x


@numba.njit(cache=True, error_model="numpy", inline="always")
def bounded(fns, st, rng):
    """random_bounded_uint64(off=0, rng, use_masked=False) for 0 < rng < 2**32 - 1: an integer in [0, rng] by
    Lemire's rejection on next_uint32 (which uses the bit generator's own 32-bit buffer)."""
    rng_excl = np.uint64(rng) + np.uint64(1)
    m = np.uint64(fns[1](st)) * rng_excl
    leftover = m & np.uint64(0xFFFFFFFF)
    if leftover < rng_excl:
        threshold = (np.uint64(0xFFFFFFFF) - np.uint64(rng)) % rng_excl
        while leftover < threshold:
            m = np.uint64(fns[1](st)) * rng_excl
            leftover = m & np.uint64(0xFFFFFFFF)
    return np.int64(m >> np.uint64(32))


@numba.njit(cache=True, error_model="numpy", inline="always")
def choice2(fns, st, n):
    """Generator.choice(n, size=2, replace=False) for 2 <= n <= 10000: Floyd's sampling of two of range(n), then
    the shuffle (_shuffle_int(2, 1)). Returns the pair."""
    a = bounded(fns, st, n - 2) if n > 2 else np.int64(0)  # a bound of 0 draws nothing
    val = bounded(fns, st, n - 1)
    b = n - 1 if val == a else val
    if bounded(fns, st, 1) == 0:
        a, b = b, a
    return a, b


# ------------------------------------------------------------------------------------------------ spawns
# IntersectionEnv._spawn_vehicle for many envs in one call (BatchedLeftTurn._spawn's draws and arithmetic, in its
# order of operations), each env drawing from its own generator (above); the vehicle is added as Traffic.add does and
# settled (its closest lane) at once: spawns read no lane, so settling each at once equals settling all at the end.
# Spawn lanes are straight (o -> ir): the pose is LaneTable.pose's straight-lane arithmetic. ``lanes`` (4, 6) per
# origin r: the entry lane, the turn lanes ir_r -> il_d for d = 0..3 (columns 1-4; -1: none), the exit lane il_r ->
# o_r (column 5: the route's last step when r is the destination). ``prior``: speed, speed_sd, delta_lo, delta_hi.
# ``fl`` / ``flags``: tuples of the state's float arrays (x, y, h, v, target, delta, steer, acc, impact_x, impact_y)
# and bool arrays (crashed, yielding, has_impact), written in place; ``it``: lane, tlane, rpos, vid (int, (B, N)).
SPAWN_CLEAR = 15.0  # m, no spawn this close to another vehicle (IntersectionEnv._spawn_vehicle)


@numba.njit(cache=True, error_model="numpy")
def _spawn_one(fns, st, lt, lanes, prior, b, longitudinal, position_deviation, speed_deviation, p, go_straight, u,
               fl, alive, ego, plain, mdp, flags, it, route, next_id, lb, pending):
    """One spawn try in env b (``u``: its first draw when the caller made it, NaN: drawn here). Returns 1 if a
    vehicle was added (with id ``next_id``), else 0; -1 if it drew a vehicle but the row has no free slot: then
    ``pending`` holds Traffic.add's arguments (entry lane, s, x, y, heading, speed, delta, the route's two next
    lanes) for the caller, who grows the arrays as Traffic.add does."""
    if math.isnan(u):
        u = fns[2](st)  # uniform(): 0 + 1 * the double
    if u > p:
        return 0
    r0, r1 = choice2(fns, st, 4)
    if go_straight:
        r1 = (r0 + 2) % 4
    k = lanes[r0, 0]
    s = longitudinal + 5.0 + standard_normal(fns, st) * position_deviation
    speed = prior[0] + standard_normal(fns, st) * (prior[1] * speed_deviation)
    x0, y0 = lt[k, OX] + s * lt[k, DX] + 0.0 * -lt[k, DY], lt[k, OY] + s * lt[k, DY] + 0.0 * lt[k, DX]
    slot = 0
    for j in range(alive.shape[1]):  # live slots are a prefix: the new one is their count
        if alive[b, j]:
            slot += 1
            if math.hypot(fl[0][b, j] - x0, fl[1][b, j] - y0) < SPAWN_CLEAR:
                return 0
    delta = prior[2] + (prior[3] - prior[2]) * fns[2](st)  # uniform(lo, hi): lo + (hi - lo) * the double
    if slot >= alive.shape[1]:
        for q, value in enumerate((float(k), s, x0, y0, lt[k, HEAD], speed, delta, float(lanes[r0, 1 + r1]),
                                   float(lanes[r1, 5]))):
            pending[q] = value
        return -1
    alive[b, slot], ego[b, slot], plain[b, slot], mdp[b, slot] = True, False, False, False
    for q, value in enumerate((x0, y0, lt[k, HEAD], speed, speed, delta, 0.0, 0.0, 0.0, 0.0)):
        fl[q][b, slot] = value
    for q in range(3):
        flags[q][b, slot] = False
    closest_lane = _closest_one(lt, x0, y0, lt[k, HEAD], lb, -1)  # Traffic.settle
    it[0][b, slot] = it[1][b, slot] = route[b, slot, 0] = closest_lane
    route[b, slot, 1], route[b, slot, 2] = lanes[r0, 1 + r1], lanes[r1, 5]
    it[2][b, slot], it[3][b, slot] = 0, next_id
    return 1


@numba.njit(cache=True, error_model="numpy")
def spawn_tries(fns, states, rows, start, p, lt, lanes, prior, fl, alive, ego, plain, mdp, flags, it, route,
                next_id, pending):
    """BatchedLeftTurn._clear_and_spawn's spawn tries from ``rows[start]`` on: env rows[k] (generator state
    ``states[k]``) draws u and spawns if u <= p. Returns the number of vehicles added (ids from ``next_id`` on, in
    row order) and -1, or, when a spawn found its row full, the count so far and that k (``pending``: the vehicle,
    see _spawn_one)."""
    lb = np.empty((lt.shape[0], 2))
    n = 0
    for k in range(start, rows.shape[0]):
        u = fns[2](states[k])
        if u <= p:
            # np.bool_, not a literal: numba compiles a callee once per literal value it is called with
            added = _spawn_one(fns, states[k], lt, lanes, prior, rows[k], 0.0, 1.0, 1.0, p, np.bool_(False), u, fl,
                               alive, ego, plain, mdp, flags, it, route, next_id + n, lb, pending)
            if added < 0:
                return n, k
            n += added
    return n, -1


@numba.njit(cache=True, error_model="numpy")
def spawn_initial(fns, states, starts, p, lt, lanes, prior, fl, alive, ego, plain, mdp, flags, it, route, next_id):
    """_make_vehicles' initial traffic: env b (generator state ``states[b]``) tries one spawn at each offset of
    ``starts`` (m) with probability ``p``, env after env (the caller makes room for them all). Returns the number
    of vehicles added."""
    lb = np.empty((lt.shape[0], 2))
    n = 0
    for b in range(states.shape[0]):
        for k in range(starts.shape[0]):
            n += _spawn_one(fns, states[b], lt, lanes, prior, b, starts[k], 1.0, 1.0, p, np.bool_(False), np.nan, fl,
                            alive, ego, plain, mdp, flags, it, route, next_id + n, lb, np.empty(9))
    return n


@numba.njit(cache=True, error_model="numpy")
def spawn_challengers(fns, states, lt, lanes, prior, fl, alive, ego, plain, mdp, flags, it, route, next_id, ego_s,
                      ego_id):
    """_make_vehicles' challenger (60 m in, going straight, position deviation 0.1 m, the prior's mean speed) and the
    ego's draw after it, ``ego_s[b] = 60 + 5 normal(1)`` (m), env after env; the ego's id (``ego_id[b]``, the one
    after its challenger's, as Traffic.add numbers them) is reserved for the caller, who adds the ego. Returns the
    number of ids used."""
    lb = np.empty((lt.shape[0], 2))
    n = 0
    for b in range(states.shape[0]):
        n += _spawn_one(fns, states[b], lt, lanes, prior, b, 60.0, 0.1, 0.0, 1.0, np.bool_(True), np.nan, fl, alive,
                        ego, plain, mdp, flags, it, route, next_id + n, lb, np.empty(9))
        ego_s[b] = 60.0 + 5.0 * (1.0 + 1.0 * standard_normal(fns, states[b]))  # normal(loc=1): loc + scale * z
        ego_id[b] = next_id + n
        n += 1
    return n


@numba.njit(cache=True, error_model="numpy")
def clear_exits(lt, lanes, rows, exit_margin, fl, bl, il, route):
    """IntersectionEnv._clear_vehicles for the envs ``rows`` (BatchedLeftTurn._clear_and_spawn): a live non-ego
    vehicle on a leaving lane (``lanes[:, 2]``) with s >= the lane's length - ``exit_margin`` (m) is removed; then,
    if any was, Traffic.compact: every env's live slots first, the dead ones after them, each in slot order (a
    stable partition, as the stable argsort there). ``fl``: the float state arrays (x and y first), ``bl`` the bool
    ones (alive, ego first), ``il`` the int ones (the lane first), ``route`` (B, N, 3); all written in place.
    Returns the count."""
    alive, ego, x, y = bl[0], bl[1], fl[0], fl[1]
    B, N = alive.shape
    gone = 0
    for q in range(rows.shape[0]):
        b = rows[q]
        for i in range(N):
            k = il[0][b, i]
            if alive[b, i] and not ego[b, i] and lanes[k, 2] != 0.0 \
                    and _local(lt, k, x[b, i], y[b, i])[0] >= lt[k, LENGTH] - exit_margin:
                alive[b, i] = False
                gone += 1
    if gone == 0:
        return 0
    order = np.empty(N, np.int64)
    for b in range(B):
        n = 0
        for i in range(N):
            if alive[b, i]:
                order[n] = i
                n += 1
        if n == 0 or order[n - 1] == n - 1:
            continue  # the live slots are a prefix already: the partition leaves the row as it is
        for i in range(N):
            if not alive[b, i]:
                order[n] = i
                n += 1
        for a in fl:  # element loops: numba compiles tuples of fancy-indexed copies ~4 s slower
            _permute_row(a[b], order)
        for a in bl:
            _permute_row(a[b], order)
        for a in il:
            _permute_row(a[b], order)
        for c in range(3):
            _permute_row(route[b, :, c], order)
    return gone


@numba.njit(cache=True, error_model="numpy")
def _permute_row(row, order):
    """row[:] = row[order] in place (from a copy: ``order`` moves slots both ways)."""
    tmp = row.copy()
    for j in range(order.shape[0]):
        row[j] = tmp[order[j]]
