"""Numba kernels for the LiDAR's ray cast and the detector's occlusion test.

Why compiled code here: the numpy ray cast (:func:`av_gym.sensors.lidar._cast`) builds the (object, beam)
candidate pairs with ``repeat``/``searchsorted``, gathers the shapes, solves each kind in a dozen small array calls
and scatters with ``np.minimum.at``: about 60 numpy calls per scan, whose overhead, not the arithmetic (a few
thousand pairs), was most of the LiDAR's cost per step. The detector's occlusion test loops over vehicles in
Python with small array calls. Here one loop over the objects, their beams and the channels does the same
arithmetic with no intermediate arrays; likewise the scan's point cloud (:func:`scan_points`), the vehicles' boxes
(:func:`box_corners`) and the detector's ranges, field of view and occlusion (:func:`detector_view`).
benchmarks/sensor_kernels.py times them against the numpy code: at the left turn a ray cast 0.83 -> 0.15 ms, a
whole scan 1.04 -> 0.24 ms, a detector frame 0.47 -> 0.15 ms (CPU time, 2026-11-25).

What stays identical (as in :mod:`av_gym.sim.kernels`): each kernel evaluates the numpy code's formulas in the same
order of operations (no ``fastmath``: no reassociation, no fused multiply-adds), on the same inputs, and makes every
decision with the same comparisons. The candidate pairs are the numpy code's: the same bounding circles, angular
spans and binary searches over the same sorted beam angles. numba's ``math`` calls the C library, as numpy's
float64 ufuncs do on this project's (AVX2) machines, so the kernels reproduce the numpy path bit for bit (the beam
directions' and headings' cos/sin and the channels' tan/cos are computed by the caller in numpy and passed in;
where a numpy build uses its own SIMD maths, e.g. AVX-512, the asin/atan2/hypot here may differ in the last bit).
tests/test_sensor_kernels.py checks each kernel against the numpy code, and whole seeded drives with and without
the kernels. Each caller keeps the numpy code as the reference behind its module's ``KERNELS`` set.
``cache=True``: compiled once per checkout into ``__pycache__``; later processes only load them.
"""

from __future__ import annotations

import math

import numba
import numpy as np

TWO_PI = 2.0 * np.pi


@numba.njit(cache=True)
def box_corners(x, y, c, s, length, width):
    """:func:`av_gym.geometry.box_corners` for 1-d arrays of boxes → (N, 4, 2); ``c``, ``s`` are the cos and sin
    of the headings (computed by the caller in numpy). The same sums: centre + (rot[i, 0]·local[k, 0] +
    rot[i, 1]·local[k, 1]) with rot = [[c, -s], [s, c]]."""
    n = x.shape[0]
    out = np.empty((n, 4, 2))
    for i in range(n):
        hl, hw = 0.5 * length[i], 0.5 * width[i]
        ci, si, msi = c[i], s[i], -s[i]
        for k in range(4):
            lx = hl if k < 2 else -hl
            ly = hw if (k == 0 or k == 3) else -hw
            out[i, k, 0] = x[i] + (ci * lx + msi * ly)
            out[i, k, 1] = y[i] + (si * lx + ci * ly)
    return out


@numba.njit(cache=True)
def cast(origins, ref_x, ref_y, slack, cos_a, sin_a, order, doubled, tan_e, cos_e, mount_height,
         segments, seg_h, circles, circ_h, corners, box_h, max_range):
    """lidar._cast after its input checks: (ranges (E, B), is_vehicle (E, B)).

    ``origins`` (B, 2) per-beam origins, or (1, 2) one origin; ``ref_x``, ``ref_y``, ``slack``: the culling origin
    and how far the beam origins stray from it; ``cos_a``, ``sin_a`` (B,): beam directions; ``order`` (B,) and
    ``doubled`` (2B,): the stable argsort of the beam angles mod 2π and the sorted angles followed by them + 2π
    (lidar._candidate_pairs); ``tan_e``, ``cos_e`` (E,): the channels; shapes and heights as in lidar._cast, heights
    already broadcast to one per object. Objects are culled and paired with beams exactly as _candidate_pairs does,
    each pair solved as _ray_segments / _ray_circles / _ray_boxes then _hit_ranges do, and the nearest hit kept
    per (channel, beam) as np.minimum.at does (a miss is ``inf``, never NaN, so the order of the updates does not
    matter)."""
    n_beams, n_ch = cos_a.shape[0], tan_e.shape[0]
    per_beam = origins.shape[0] > 1
    n_seg, n_circ, n_box = segments.shape[0], circles.shape[0], corners.shape[0]
    best = np.full((n_ch, n_beams), np.inf)
    best_static = np.full((n_ch, n_beams), np.inf)
    h = mount_height
    for m in range(n_seg + n_circ + n_box):
        # the object's bounding circle, as _cast computes it
        if m < n_seg:
            kind, q = 0, m
            cx = 0.5 * (segments[q, 0] + segments[q, 2])
            cy = 0.5 * (segments[q, 1] + segments[q, 3])
            rad = 0.5 * math.hypot(segments[q, 2] - segments[q, 0], segments[q, 3] - segments[q, 1])
            height = seg_h[q]
        elif m < n_seg + n_circ:
            kind, q = 1, m - n_seg
            cx, cy, rad = circles[q, 0], circles[q, 1], circles[q, 2]
            height = circ_h[q]
        else:
            kind, q = 2, m - n_seg - n_circ
            cx = (((corners[q, 0, 0] + corners[q, 1, 0]) + corners[q, 2, 0]) + corners[q, 3, 0]) / 4.0
            cy = (((corners[q, 0, 1] + corners[q, 1, 1]) + corners[q, 2, 1]) + corners[q, 3, 1]) / 4.0
            rad = 0.0
            for k in range(4):
                dx, dy = corners[q, k, 0] - cx, corners[q, k, 1] - cy
                rk = math.sqrt(dx * dx + dy * dy)
                if rk > rad:
                    rad = rk
            height = box_h[q]
        # _candidate_pairs: range cull, then the beams within the circle's angular span
        dx, dy = cx - ref_x, cy - ref_y
        dist = math.hypot(dx, dy)
        r = rad + slack
        if not dist - r < max_range:
            continue
        if dist > r:
            half = math.asin(min(max(r / dist, 0.0), 1.0))
        else:
            half = math.pi  # origin inside: every beam
        lo = (math.atan2(dy, dx) - half) % TWO_PI
        i0 = np.searchsorted(doubled, lo, side="left")
        count = min(np.searchsorted(doubled, lo + 2.0 * half, side="right") - i0, n_beams)
        if kind == 2:  # _ray_boxes' slab frame of this box
            e1x, e1y = corners[q, 1, 0] - corners[q, 0, 0], corners[q, 1, 1] - corners[q, 0, 1]
            e2x, e2y = corners[q, 3, 0] - corners[q, 0, 0], corners[q, 3, 1] - corners[q, 0, 1]
            len1, len2 = math.sqrt(e1x * e1x + e1y * e1y), math.sqrt(e2x * e2x + e2y * e2y)
            a1x, a1y, a2x, a2y = e1x / len1, e1y / len1, e2x / len2, e2y / len2
            half1, half2 = 0.5 * len1, 0.5 * len2
        idx = i0 - n_beams if i0 >= n_beams else i0  # (i0 + j) mod n_beams without an integer division
        for _ in range(count):
            k = order[idx]
            idx += 1
            if idx == n_beams:
                idx = 0
            b = k if per_beam else 0
            ox, oy, ux, uy = origins[b, 0], origins[b, 1], cos_a[k], sin_a[k]
            if kind == 0:  # _ray_segments
                ax, ay = segments[q, 0], segments[q, 1]
                vx, vy = segments[q, 2] - ax, segments[q, 3] - ay
                wx, wy = ax - ox, ay - oy
                denom = ux * vy - uy * vx
                if denom == 0:
                    continue
                t = (wx * vy - wy * vx) / denom
                s = (wx * uy - wy * ux) / denom
                if not (t >= 0 and s >= 0 and s <= 1):
                    continue  # t = inf in the numpy code: no hit on any channel
                t_in, t_out = t, t
            elif kind == 1:  # _ray_circles
                wx, wy = cx - ox, cy - oy
                bb = wx * ux + wy * uy
                c = wx * wx + wy * wy - rad * rad
                disc = bb * bb - c
                root = math.sqrt(max(disc, 0.0))
                t_in, t_out = bb - root, bb + root
                if not (disc >= 0 and t_out >= 0):
                    continue  # t_in = inf: no hit
            else:  # _ray_boxes
                t_in, t_out = -np.inf, np.inf
                for axis in range(2):
                    axx, axy, hf = (a1x, a1y, half1) if axis == 0 else (a2x, a2y, half2)
                    p = (ox - cx) * axx + (oy - cy) * axy
                    d = ux * axx + uy * axy
                    if abs(d) < 1e-12:
                        d = 1e-12
                    t1, t2 = (-hf - p) / d, (hf - p) / d
                    t_in = max(t_in, min(t1, t2))
                    t_out = min(t_out, max(t1, t2))
            for e in range(n_ch):  # _hit_ranges
                te = tan_e[e]
                lo_e, hi_e = -np.inf, np.inf
                if te > 0:
                    hi_e = (height - h) / te
                elif te < 0:
                    lo_e, hi_e = (height - h) / te, -h / te
                elif te == 0 and not (h >= 0.0 and h <= height):
                    hi_e = -np.inf
                start = max(max(t_in, lo_e), 0.0)
                if start <= min(t_out, hi_e):
                    if start < best[e, k]:
                        best[e, k] = start
                    if kind < 2 and start < best_static[e, k]:
                        best_static[e, k] = start
    ranges = np.empty((n_ch, n_beams))
    is_vehicle = np.empty((n_ch, n_beams), dtype=np.bool_)
    for e in range(n_ch):
        for k in range(n_beams):
            slant = best[e, k] / cos_e[e]
            ranges[e, k] = slant if slant < max_range else max_range
            is_vehicle[e, k] = best[e, k] < best_static[e, k] and slant < max_range
    return ranges, is_vehicle


@numba.njit(cache=True)
def scan_points(ranges, is_vehicle, noise, dropped, range_sigma, min_range, max_range, cos_phi, sin_phi, frac,
                sin_e, cos_e, planar, label_static, label_vehicle):
    """The end of Lidar._scan: the noisy returns ``measured = ranges + range_sigma·noise``, valid where hit, not
    dropped and within [min_range, max_range); the observation (E, B) float32 (``max_range`` where not valid) and
    the valid returns in channel-major, beam order as np.nonzero gives them: points (N, 3) in the sensor frame,
    per-point times (N,) and labels (N,). ``cos_phi``, ``sin_phi`` (B,) of the sensor azimuths and ``sin_e``,
    ``cos_e`` (E,) of the elevations are computed by the caller in numpy."""
    n_ch, n_beams = ranges.shape
    obs = np.empty((n_ch, n_beams), dtype=np.float32)
    measured = np.empty((n_ch, n_beams))
    valid = np.empty((n_ch, n_beams), dtype=np.bool_)
    n = 0
    for e in range(n_ch):
        for k in range(n_beams):
            m = ranges[e, k] + range_sigma * noise[e, k]
            ok = ranges[e, k] < max_range and not dropped[e, k] and m >= min_range and m < max_range
            measured[e, k], valid[e, k] = m, ok
            obs[e, k] = np.float32(m if ok else max_range)
            n += ok
    points = np.empty((n, 3))
    times = np.empty(n)
    labels = np.empty(n, dtype=np.int64)
    i = 0
    for e in range(n_ch):
        for k in range(n_beams):
            if not valid[e, k]:
                continue
            r = measured[e, k]
            horiz = r if planar else r * cos_e[e]
            points[i, 0] = horiz * cos_phi[k]
            points[i, 1] = horiz * sin_phi[k]
            points[i, 2] = 0.0 if planar else r * sin_e[e]
            times[i] = frac[k]
            labels[i] = label_vehicle if is_vehicle[e, k] else label_static
            i += 1
    return obs, points, times, labels


@numba.njit(cache=True)
def occluded(ex, ey, x, y, c, s, length, width, probes, fraction):
    """Detector._occluded: per vehicle, whether at least ``fraction`` of the ``probes`` (the fractions of its
    bearing interval that are tested, np.linspace(0.05, 0.95, 9)) lie within the bearing interval of a nearer
    vehicle. Headings as ``c``, ``s`` (cos, sin computed by the caller); the same corners, bearings, unwrapping and
    comparisons as the numpy code."""
    n = x.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    if n < 2:
        return out
    corners = box_corners(x, y, c, s, length, width)
    lo = np.empty(n)
    hi = np.empty(n)
    dist = np.empty(n)
    for i in range(n):
        centre = math.atan2(y[i] - ey, x[i] - ex)
        rmin, rmax = np.inf, -np.inf
        for k in range(4):
            bearing = math.atan2(corners[i, k, 1] - ey, corners[i, k, 0] - ex)
            rel = (bearing - centre + math.pi) % (2 * math.pi) - math.pi
            rmin, rmax = min(rmin, rel), max(rmax, rel)
        lo[i], hi[i] = centre + rmin, centre + rmax
        dx, dy = x[i] - ex, y[i] - ey
        dist[i] = math.sqrt(dx * dx + dy * dy)
    n_probes = probes.shape[0]
    for i in range(n):
        covered = 0
        for j in range(n_probes):
            probe = lo[i] + (hi[i] - lo[i]) * probes[j]
            for m in range(n):
                if dist[m] < dist[i]:
                    d = (probe - (lo[m] + hi[m]) / 2 + math.pi) % (2 * math.pi) - math.pi
                    if abs(d) <= (hi[m] - lo[m]) / 2:
                        covered += 1
                        break
        out[i] = covered / n_probes >= fraction
    return out


@numba.njit(cache=True)
def detector_view(ex, ey, psi, x, y, c, s, length, width, max_range, half_fov, occlusion, probes, fraction):
    """Detector._frame's geometry in one pass: per other vehicle its range ``r`` (as np.linalg.norm), whether it is
    in view (within ``max_range`` and ``half_fov`` of the heading ``psi``, the wrapped bearing compared as there),
    and whether it is occluded (:func:`occluded`; all False without ``occlusion``)."""
    n = x.shape[0]
    r = np.empty(n)
    in_view = np.empty(n, dtype=np.bool_)
    for i in range(n):
        dx, dy = x[i] - ex, y[i] - ey
        r[i] = math.sqrt(dx * dx + dy * dy)
        bearing = math.atan2(dy, dx) - psi
        in_view[i] = r[i] <= max_range and abs((bearing + math.pi) % (2 * math.pi) - math.pi) <= half_fov
    if occlusion:
        return r, in_view, occluded(ex, ey, x, y, c, s, length, width, probes, fraction)
    return r, in_view, np.zeros(n, dtype=np.bool_)


@numba.njit(cache=True)
def detector_view_rows(ex, ey, psi, off, x, y, c, s, length, width, max_range, half_fov, occlusion, probes,
                       fraction):
    """:func:`detector_view` of F frames in one call (the batch's detector): frame f sees the vehicles
    ``off[f]:off[f + 1]`` of the flat columns from its ego at (``ex[f]``, ``ey[f]``) m with heading ``psi[f]``
    rad; each frame is :func:`detector_view` on its own slices, so the same numbers. Returns the flat ranges (m),
    in-view and occluded flags."""
    n = x.shape[0]
    r = np.empty(n)
    in_view = np.zeros(n, dtype=np.bool_)
    hidden = np.zeros(n, dtype=np.bool_)
    for f in range(off.shape[0] - 1):
        a, b = off[f], off[f + 1]
        if b > a:
            r_f, view_f, hidden_f = detector_view(ex[f], ey[f], psi[f], x[a:b], y[a:b], c[a:b], s[a:b], length[a:b],
                                                  width[a:b], max_range, half_fov, occlusion, probes, fraction)
            r[a:b], in_view[a:b], hidden[a:b] = r_f, view_f, hidden_f
    return r, in_view, hidden


_LOGGAM_A = np.array([8.333333333333333e-02, -2.777777777777778e-03, 7.936507936507937e-04, -5.952380952380952e-04,
                      8.417508417508418e-04, -1.917526917526918e-03, 6.410256410256410e-03, -2.955065359477124e-02,
                      1.796443723688307e-01, -1.39243221690590e+00])
"""The coefficients of numpy's ``random_loggam`` (numpy/random/src/distributions/distributions.c)."""


@numba.njit(cache=True)
def _loggam(x):
    """numpy's ``random_loggam(x)``: log Γ(x) (x > 0) by its series, the argument shifted up to 7 (which
    :func:`poisson`'s acceptance test compares against; the same floats as numpy 2.4.6's own on x = 1 .. 200,000,
    compared against the wheel's library)."""
    if x == 1.0 or x == 2.0:
        return 0.0
    n = int(7 - x) if x < 7.0 else 0
    x0 = x + n
    x2 = (1.0 / x0) * (1.0 / x0)
    gl0 = _LOGGAM_A[9]
    for k in range(8, -1, -1):
        gl0 *= x2
        gl0 += _LOGGAM_A[k]
    gl = gl0 / x0 + 0.5 * 1.8378770664093453 + (x0 - 0.5) * math.log(x0) - x0
    if x < 7.0:
        for _ in range(n):
            gl -= math.log(x0 - 1.0)
            x0 -= 1.0
    return gl


@numba.njit(cache=True, error_model="numpy")  # a division by us = 0 gives inf, as in numpy's C, not an exception
def poisson(rng, lam):
    """``rng.poisson(lam)`` as numpy's ``Generator`` draws it (``lam`` >= 0, the mean): the same count and the same
    uniforms taken from ``rng``'s bit generator, written here after numpy's ``random_poisson``: none drawn for 0,
    the product of uniforms below 10, Hörmann's PTRS transformed rejection from 10 on. Why not numba's own
    ``Generator.poisson``: its PTRS takes the candidate with ``int()``, which truncates, where numpy takes ``floor``,
    so a candidate in (-1, 0) is 0 there and may be accepted where numpy rejects it and draws on (about one draw in
    3e4-1e5 at lam 10-12, and every later draw of that generator then differs; measured: numba 0.68.1 / numpy
    2.4.6, seed 1, first at draw 33,172 for lam 10 and 120,863 for lam 12). ``rng.random()`` is numpy's
    ``next_double``, the uniform numpy's samplers draw."""
    if lam < 10.0:
        if lam == 0:
            return np.int64(0)
        enlam, count, prod = math.exp(-lam), 0, 1.0
        while True:
            prod *= rng.random()
            if prod > enlam:
                count += 1
            else:
                return np.int64(count)
    slam, loglam = math.sqrt(lam), math.log(lam)
    b = 0.931 + 2.53 * slam
    a = -0.059 + 0.02483 * b
    invalpha = 1.1239 + 1.1328 / (b - 3.4)
    vr = 0.9277 - 3.6224 / (b - 2)
    while True:
        u = rng.random() - 0.5
        v = rng.random()
        us = 0.5 - abs(u)
        k = np.floor((2 * a / us + b) * u + lam + 0.43)  # a float: us = 0 only at u = -0.5, so -inf, rejected (k < 0)
        if us >= 0.07 and v <= vr:
            return np.int64(k)
        if k < 0 or (us < 0.013 and v > us):
            continue
        if math.log(v) + math.log(invalpha) - math.log(a / (us * us) + b) <= -lam + k * loglam - _loggam(k + 1):
            return np.int64(k)


@numba.njit(cache=True)
def frame_draws_span(rng, state, owner, token, keys, in_view, hidden, a, b, miss_rate, p, q, clutter_rate, half_fov,
                     frame, src, frame_of, draws, n, clutter, clutter_frame, n_c):
    """:func:`av_gym.sensors.detector.frame_draws` of one frame (the road users ``a`` .. ``b`` of the flat columns
    ``keys`` (vehicle ids), ``in_view``, ``hidden``) in one compiled call: the same draws from ``rng`` (numba's
    ``np.random.Generator`` methods are numpy's algorithms on the generator's own bit generator, so its state moves
    as numpy's calls move it; the Poisson count by :func:`poisson`) in the same order: per road user in view its
    miss chain's uniform (a first sight against ``miss_rate``, then P(miss | seen) ``p``, P(seen | missed) ``q``),
    seven standard normals per detection; then the clutter count (Poisson, ``clutter_rate``) and per false positive
    its three uniforms (the range's square; the bearing in [-``half_fov``, ``half_fov``) rad; the heading in
    [-pi, pi) rad). :mod:`av_gym.sensors.draws_check` checks these draws against numpy's once per process before
    the batch's detector uses this kernel.

    The miss chains by vehicle id: ``state[key]`` missed last frame, valid where ``owner[key]`` is this episode's
    ``token`` (else a first sight, as the per-env detector's empty dict at an episode's start). Appends detection
    ``n`` on: its row ``src`` (index in the flat columns), ``frame_of`` = ``frame`` and its (7,) ``draws``; the
    clutter from ``n_c`` on into ``clutter`` (c, 3) and ``clutter_frame``. Returns (detections, clutter rows, -1),
    or, where the clutter does not fit in ``clutter``, (detections, ``n_c``, its count) with its uniforms not drawn
    (the caller draws them in the same order)."""
    for i in range(a, b):
        if not in_view[i]:
            continue
        key = keys[i]
        if owner[key] != token:
            missing = rng.random() < miss_rate
        elif state[key]:
            missing = rng.random() >= q
        else:
            missing = rng.random() < p
        owner[key], state[key] = token, missing
        if missing or hidden[i]:
            continue
        for j in range(7):
            draws[n, j] = rng.standard_normal()
        src[n], frame_of[n] = i, frame
        n += 1
    count = poisson(rng, clutter_rate)
    if n_c + count > clutter.shape[0]:
        return n, n_c, count
    for j in range(n_c, n_c + count):
        clutter[j, 0] = rng.random()
        clutter[j, 1] = rng.uniform(-half_fov, half_fov)
        clutter[j, 2] = rng.uniform(-math.pi, math.pi)
        clutter_frame[j] = frame
    return n, n_c + count, -1
