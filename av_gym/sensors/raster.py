"""Compiled painter for the cameras: the rig's vertical quads built and sorted (:func:`rig_quads`), projected,
culled and clipped per camera (:func:`project_rig`) and filled (:func:`paint_band`, :func:`paint_depth`), and the
ground's palette looked up (:func:`palette_lookup`), a handful of numba calls per rig.

Why hand-written: OpenCV fills one polygon per Python call (``cv2.fillConvexPoly``, ~1-2 us each plus the numpy
bookkeeping that prepares its arguments); a rig shows 50-90 small quads per camera, so the calls and the per-rig
numpy passes, not the pixels, were most of a frame (docs/sensors.md, "Cost"). No library rasterises a
batch of painter-ordered polygons into a numpy image; these kernels loop over the quads of a whole camera in one
call.

What stays identical: :func:`_fill_convex` is OpenCV's ``FillConvexPoly`` for ``LINE_8`` with sub-pixel
``shift`` (imgproc/src/drawing.cpp: the outline drawn with ``Line2`` in 16-bit fixed point after ``clipLine``,
then the two-edge scan with ``delta1 = delta2 = XY_ONE/2``), transcribed with C's truncating integer division,
so it sets the same pixels as ``cv2.fillConvexPoly`` (tests/test_raster.py checks it on random, clipped,
degenerate and off-image polygons). The projection repeats the numpy renderer's formulas in the same order (no
``fastmath``), and :func:`_shrink` is ``cv2.resize(INTER_AREA)`` at an integer factor (2: ``(sum + 2) >> 2``
per channel, OpenCV's fast path; other factors: the sum times ``1/ss²`` in float32, rounded half to even).
"""

from __future__ import annotations

import math

import numba
import numpy as np

XY_SHIFT = 16  # OpenCV's internal fixed point for lines and polygon edges
XY_ONE = 1 << XY_SHIFT
MAX_VERTS = 8  # corners after clipping a quad at one plane: 5 for a planar convex quad, 8 at most for any


@numba.njit(cache=True, inline="always")
def _tdiv(a, b):
    """C's integer division (truncates towards zero; Python's ``//`` floors)."""
    q = abs(a) // abs(b)
    return q if (a < 0) == (b < 0) else -q


@numba.njit(cache=True, inline="always")
def _put(img, depth, x, y, colour, d, use_depth):
    if 0 <= x < img.shape[1] and 0 <= y < img.shape[0]:
        img[y, x] = colour
        if use_depth:
            depth[y, x] = d


@numba.njit(cache=True)
def _clip_line(w, h, x1, y1, x2, y2):
    """OpenCV's ``clipLine(Size2l, pt1, pt2)``: (inside, x1, y1, x2, y2)."""
    right, bottom = w - 1, h - 1
    c1 = (x1 < 0) + (x1 > right) * 2 + (y1 < 0) * 4 + (y1 > bottom) * 8
    c2 = (x2 < 0) + (x2 > right) * 2 + (y2 < 0) * 4 + (y2 > bottom) * 8
    if (c1 & c2) == 0 and (c1 | c2) != 0:
        if c1 & 12:
            a = 0 if c1 < 8 else bottom
            x1 += _tdiv((a - y1) * (x2 - x1), y2 - y1)
            y1 = a
            c1 = (x1 < 0) + (x1 > right) * 2
        if c2 & 12:
            a = 0 if c2 < 8 else bottom
            x2 += _tdiv((a - y2) * (x2 - x1), y2 - y1)
            y2 = a
            c2 = (x2 < 0) + (x2 > right) * 2
        if (c1 & c2) == 0 and (c1 | c2) != 0:
            if c1:
                a = 0 if c1 == 1 else right
                y1 += _tdiv((a - x1) * (y2 - y1), x2 - x1)
                x1 = a
                c1 = 0
            if c2:
                a = 0 if c2 == 1 else right
                y2 += _tdiv((a - x2) * (y2 - y1), x2 - x1)
                x2 = a
                c2 = 0
    return (c1 | c2) == 0, x1, y1, x2, y2


@numba.njit(cache=True)
def _line2(img, depth, x1, y1, x2, y2, colour, d, use_depth):
    """OpenCV's ``Line2``: an 8-connected line between 16-bit fixed-point end points."""
    h, w = img.shape[0], img.shape[1]
    inside, x1, y1, x2, y2 = _clip_line(np.int64(w) << XY_SHIFT, np.int64(h) << XY_SHIFT, x1, y1, x2, y2)
    if not inside:
        return
    dx, dy = x2 - x1, y2 - y1
    j = -1 if dx < 0 else 0
    ax = (dx ^ j) - j
    i = -1 if dy < 0 else 0
    ay = (dy ^ i) - i
    if ax > ay:
        dy = (dy ^ j) - j
        x1 ^= x2 & j
        x2 ^= x1 & j
        x1 ^= x2 & j
        y1 ^= y2 & j
        y2 ^= y1 & j
        y1 ^= y2 & j
        x_step = np.int64(XY_ONE)
        y_step = _tdiv(dy << XY_SHIFT, ax | 1)
        ecount = (x2 - x1) >> XY_SHIFT
    else:
        dx = (dx ^ i) - i
        x1 ^= x2 & i
        x2 ^= x1 & i
        x1 ^= x2 & i
        y1 ^= y2 & i
        y2 ^= y1 & i
        y1 ^= y2 & i
        x_step = _tdiv(dx << XY_SHIFT, ay | 1)
        y_step = np.int64(XY_ONE)
        ecount = (y2 - y1) >> XY_SHIFT
    x1 += XY_ONE >> 1
    y1 += XY_ONE >> 1
    _put(img, depth, (x2 + (XY_ONE >> 1)) >> XY_SHIFT, (y2 + (XY_ONE >> 1)) >> XY_SHIFT, colour, d, use_depth)
    if ax > ay:
        x1 >>= XY_SHIFT
        while ecount >= 0:
            _put(img, depth, x1, y1 >> XY_SHIFT, colour, d, use_depth)
            x1 += 1
            y1 += y_step
            ecount -= 1
    else:
        y1 >>= XY_SHIFT
        while ecount >= 0:
            _put(img, depth, x1 >> XY_SHIFT, y1, colour, d, use_depth)
            x1 += x_step
            y1 += 1
            ecount -= 1


@numba.njit(cache=True, inline="always")
def _next_edge(vx, vy, npts, y, idx0, di, edges, shift):
    """One side of ``FillConvexPoly``'s scan: the next polygon edge that ends below row ``y``, walking from
    vertex ``idx0`` in direction ``di``: (found, ye, dx, x, idx, edges)."""
    up = XY_SHIFT - shift
    delta = (1 << shift) >> 1
    idx = idx0 + di
    if idx >= npts:
        idx -= npts
    while True:
        edges -= 1
        if edges < 0:  # C: ``for (; edges-- > 0; )``
            return False, 0, 0, 0, idx0, edges
        ty = (vy[idx] + delta) >> shift
        if ty > y:
            xs, xe = vx[idx0] << up, vx[idx] << up
            return True, ty, _tdiv((xe - xs) * 2 + (ty - y), 2 * (ty - y)), xs, idx, edges
        idx0 = idx
        idx += di
        if idx >= npts:
            idx -= npts


@numba.njit(cache=True)
def _fill_convex(img, depth, vx, vy, npts, colour, d, shift, use_depth):
    """``cv2.fillConvexPoly(img, v, colour, LINE_8, shift)`` for the first ``npts`` vertices ``(vx, vy)``
    (int64, ``shift`` fractional bits) on a one-channel image ``img`` (H, W) (the RGBA images are filled as
    uint32, one value per pixel); with ``use_depth`` the same pixels of ``depth`` (H, W) are set to ``d``."""
    h, w = img.shape[0], img.shape[1]
    delta = (1 << shift) >> 1
    delta1 = delta2 = XY_ONE >> 1
    up = XY_SHIFT - shift
    p0x, p0y = vx[npts - 1] << up, vy[npts - 1] << up
    xmin = xmax = vx[0]
    ymin = ymax = vy[0]
    imin = 0
    for i in range(npts):
        px, py = vx[i], vy[i]
        if py < ymin:
            ymin = py
            imin = i
        ymax = max(ymax, py)
        xmax = max(xmax, px)
        xmin = min(xmin, px)
        px <<= up
        py <<= up
        _line2(img, depth, p0x, p0y, px, py, colour, d, use_depth)
        p0x, p0y = px, py
    xmin = (xmin + delta) >> shift
    xmax = (xmax + delta) >> shift
    ymin = (ymin + delta) >> shift
    ymax = (ymax + delta) >> shift
    if npts < 3 or xmax < 0 or ymax < 0 or xmin >= w or ymin >= h:
        return
    ymax = min(ymax, h - 1)
    # edge[0] walks the vertices forwards, edge[1] backwards, both from the top vertex
    idx_a, ye_a, x_a, dx_a = imin, ymin, np.int64(-XY_ONE), np.int64(0)
    idx_b, ye_b, x_b, dx_b = imin, ymin, np.int64(-XY_ONE), np.int64(0)
    y = ymin
    edges = npts
    while True:
        if y >= ye_a:
            ok, ye, dx, x0, idx, edges = _next_edge(vx, vy, npts, y, idx_a, 1, edges, shift)
            if ok:
                ye_a, dx_a, x_a, idx_a = ye, dx, x0, idx
        if y >= ye_b:
            ok, ye, dx, x0, idx, edges = _next_edge(vx, vy, npts, y, idx_b, npts - 1, edges, shift)
            if ok:
                ye_b, dx_b, x_b, idx_b = ye, dx, x0, idx
        if edges < 0:
            break
        if y >= 0:
            xl, xr = (x_b, x_a) if x_a > x_b else (x_a, x_b)
            xx1 = (xl + delta1) >> XY_SHIFT
            xx2 = (xr + delta2) >> XY_SHIFT
            if xx2 >= 0 and xx1 < w:
                xx1 = max(xx1, 0)
                xx2 = min(xx2, w - 1)
                img[y, xx1:xx2 + 1] = colour
                if use_depth:
                    depth[y, xx1:xx2 + 1] = d
        x_a += dx_a
        x_b += dx_b
        y += 1
        if y > ymax:
            break


# Columns of the per-camera parameter rows handed to :func:`project_rig` (built in ``camera_render._render_rig``).
FO, LAT, YAW, MOUNT, PITCH, FOCAL, WIDTH, HEIGHT, SS, RANGE, CAM_X, CAM_Y, ROOFS = range(13)


@numba.njit(cache=True)
def project_rig(fa, fb, fz, keys, kind, normals, nm, cams, near, shift, shared):
    """Internal-pixel polygons of every vertical quad each camera draws, in the painter's (given) order.

    ``fa``, ``fb``, ``fz`` (N, 4) vehicle-frame forward, right, up (m) of each quad's corners; ``keys`` (N,) its
    distance (m) from the rig; ``kind`` (N,) 0 scenery, 1 vehicle side or window (back-face culled against
    ``normals`` (N, 2) world and ``nm`` (N,), the face's normal · midpoint), 2 roof (drawn by cameras mounted
    above the roofs); ``cams`` (K, 13) float rows, columns :data:`FO` .. :data:`ROOFS`; ``near`` the near plane
    (m); ``shift`` fractional bits of the pixel coordinates; ``shared``: the windshield rig's formula for
    unclipped corners (``cx + X·(f/Z)``) instead of the general one (``cx + f·X/Z``), as the numpy renderer had.

    Returns ``polys`` (K, N, MAX_VERTS, 2) int64 and ``npts`` (K, N): quad i of camera k is drawn with its first
    ``npts[k, i]`` corners (0: culled or clipped away). Culling: beyond ``RANGE``, wholly behind the near plane or
    beyond one side plane (one output pixel of margin), back faces, roofs; straddlers are clipped at the near
    plane (Sutherland-Hodgman) before the division."""
    n, k_cams = fa.shape[0], cams.shape[0]
    polys = np.zeros((k_cams, n, MAX_VERTS, 2), np.int64)
    npts = np.zeros((k_cams, n), np.int64)
    X = np.empty(4)
    Y = np.empty(4)
    Z = np.empty(4)
    cX = np.empty(MAX_VERTS)
    cY = np.empty(MAX_VERTS)
    cZ = np.empty(MAX_VERTS)
    scale = float(1 << shift)
    for k in range(k_cams):
        fo, lat, h, rng_ = cams[k, FO], cams[k, LAT], cams[k, MOUNT], cams[k, RANGE]
        cy_, sy_ = math.cos(cams[k, YAW]), math.sin(cams[k, YAW])
        ct, st = math.cos(cams[k, PITCH]), math.sin(cams[k, PITCH])
        width, height, ss = cams[k, WIDTH], cams[k, HEIGHT], cams[k, SS]
        tx, ty = (width / 2 + 1) / cams[k, FOCAL], (height / 2 + 1) / cams[k, FOCAL]
        f = cams[k, FOCAL] * ss
        cx, cy = (width * ss - 1) / 2, (height * ss - 1) / 2
        camx, camy, roofs = cams[k, CAM_X], cams[k, CAM_Y], cams[k, ROOFS] != 0.0
        for i in range(n):
            if keys[i] > rng_:
                continue
            if kind[i] == 2 and not roofs:
                continue
            if kind[i] == 1 and not (camx * normals[i, 0] + camy * normals[i, 1] > nm[i]):
                continue
            behind = right = left = below = above = True
            front = True
            for j in range(4):
                a0, b0 = fa[i, j] - fo, fb[i, j] - lat
                a, b = a0 * cy_ + b0 * sy_, -a0 * sy_ + b0 * cy_
                u = fz[i, j] - h
                X[j], Y[j], Z[j] = b, -(a * st + u * ct), a * ct - u * st
                behind &= Z[j] < near
                front &= Z[j] >= near
                right &= X[j] > tx * Z[j]
                left &= -X[j] > tx * Z[j]
                below &= Y[j] > ty * Z[j]
                above &= -Y[j] > ty * Z[j]
            if behind or right or left or below or above:
                continue
            if front:
                for j in range(4):
                    if shared:
                        w = f / Z[j]
                        polys[k, i, j, 0] = np.int64(np.rint((cx + X[j] * w) * scale))
                        polys[k, i, j, 1] = np.int64(np.rint((cy + Y[j] * w) * scale))
                    else:
                        polys[k, i, j, 0] = np.int64(np.rint((cx + f * X[j] / Z[j]) * scale))
                        polys[k, i, j, 1] = np.int64(np.rint((cy + f * Y[j] / Z[j]) * scale))
                npts[k, i] = 4
                continue
            m = 0  # Sutherland-Hodgman against Z >= near, as camera_render._clip_near
            for j in range(4):
                q = (j + 1) % 4
                p_in, q_in = Z[j] >= near, Z[q] >= near
                if p_in:
                    cX[m], cY[m], cZ[m] = X[j], Y[j], Z[j]
                    m += 1
                if p_in != q_in:
                    t = (near - Z[j]) / (Z[q] - Z[j])
                    cX[m], cY[m], cZ[m] = X[j] + t * (X[q] - X[j]), Y[j] + t * (Y[q] - Y[j]), Z[j] + t * (Z[q] - Z[j])
                    m += 1
            if m < 3:
                continue
            for j in range(m):
                polys[k, i, j, 0] = np.int64(np.rint((cx + f * cX[j] / cZ[j]) * scale))
                polys[k, i, j, 1] = np.int64(np.rint((cy + f * cY[j] / cZ[j]) * scale))
            npts[k, i] = m
    return polys, npts


@numba.njit(cache=True)
def paint_band(small, polys, npts, colours, ss, shift, whole):
    """Paint the polygons (``polys``/``npts`` of one camera, :func:`project_rig`) over ``small`` (H, W) uint32 (an
    RGBA image viewed one pixel per value), the camera's ground image at the output size, in place: the band they
    cover (bounding box plus one output pixel; the whole image with ``whole``) is enlarged ``ss`` times (nearest),
    painted in order with ``colours[i]`` (RGBA packed the same way) and area-averaged back; the pixels outside the
    band are final already. Both resamplings work block by block, so the band gives the pixels painting the whole
    image would."""
    h, w = small.shape[0], small.shape[1]
    n = npts.shape[0]
    lox = loy = np.int64(1) << 62
    hix = hiy = -lox
    drawn = 0
    for i in range(n):
        for j in range(npts[i]):
            lox, hix = min(lox, polys[i, j, 0]), max(hix, polys[i, j, 0])
            loy, hiy = min(loy, polys[i, j, 1]), max(hiy, polys[i, j, 1])
        drawn += npts[i] > 0
    if drawn == 0:
        return
    if whole:
        r0, r1, c0, c1 = 0, h, 0, w
    else:
        c0, r0 = max(0, (lox >> shift) // ss - 1), max(0, (loy >> shift) // ss - 1)
        c1, r1 = min(w, (hix >> shift) // ss + 2), min(h, (hiy >> shift) // ss + 2)
    if r1 <= r0 or c1 <= c0:
        return
    img = _enlarge(small, r0, r1, c0, c1, ss)
    depth = np.zeros((1, 1), np.float32)
    ox, oy = (c0 * ss) << shift, (r0 * ss) << shift
    vx = np.empty(MAX_VERTS, np.int64)
    vy = np.empty(MAX_VERTS, np.int64)
    for i in range(n):
        m = npts[i]
        if m == 0:
            continue
        for j in range(m):
            vx[j], vy[j] = polys[i, j, 0] - ox, polys[i, j, 1] - oy
        _fill_convex(img, depth, vx, vy, m, colours[i], 0.0, shift, False)
    _shrink(img, small, r0, c0, ss)


@numba.njit(cache=True)
def paint_depth(img, depth, polys, npts, colours, dists, shift):
    """Paint the polygons over the internal-resolution image ``img`` (Hs, Ws) uint32 (RGBA) and set the same pixels of
    ``depth`` (Hs, Ws) float32 to each quad's distance ``dists[i]`` (m), in place (fog and night need both)."""
    vx = np.empty(MAX_VERTS, np.int64)
    vy = np.empty(MAX_VERTS, np.int64)
    for i in range(npts.shape[0]):
        m = npts[i]
        if m == 0:
            continue
        for j in range(m):
            vx[j], vy[j] = polys[i, j, 0], polys[i, j, 1]
        _fill_convex(img, depth, vx, vy, m, colours[i], dists[i], shift, True)


@numba.njit(cache=True)
def _enlarge(small, r0, r1, c0, c1, ss):
    """Rows r0..r1, columns c0..c1 of ``small`` (H, W) enlarged ``ss`` times, each pixel an ss×ss block."""
    img = np.empty(((r1 - r0) * ss, (c1 - c0) * ss), small.dtype)
    for r in range(r1 - r0):
        for dy in range(ss):
            row = img[r * ss + dy]
            for c in range(c1 - c0):
                v = small[r0 + r, c0 + c]
                for dx in range(ss):
                    row[c * ss + dx] = v
    return img


@numba.njit(cache=True)
def _shrink(img, small, r0, c0, ss):
    """``cv2.resize(INTER_AREA)`` of the RGBA image ``img`` (Hs, Ws) uint32 by the integer factor ``ss`` into
    ``small`` at (r0, c0). For ss = 2 all four channels at once: channels 0 and 2, then 1 and 3, sit in 16-bit
    lanes of an int64 (four bytes and the rounding 2 sum to at most 1022), ``(sum + 2) >> 2`` in each lane."""
    m = np.int64(0x00FF00FF)
    half = np.int64(0x00020002)
    for r in range(img.shape[0] // ss):
        if ss == 2:
            top, bot = img[2 * r], img[2 * r + 1]
            for c in range(img.shape[1] // 2):
                a, b = np.int64(top[2 * c]), np.int64(top[2 * c + 1])
                e, f = np.int64(bot[2 * c]), np.int64(bot[2 * c + 1])
                lo = (a & m) + (b & m) + (e & m) + (f & m) + half
                hi = ((a >> 8) & m) + ((b >> 8) & m) + ((e >> 8) & m) + ((f >> 8) & m) + half
                small[r0 + r, c0 + c] = np.uint32(((lo >> 2) & m) | (((hi >> 2) & m) << 8))
            continue
        inv = np.float32(1.0) / np.float32(ss * ss)
        for c in range(img.shape[1] // ss):
            out = np.int64(0)
            for ch in range(4):
                s = np.int64(0)
                for dy in range(ss):
                    for dx in range(ss):
                        s += (np.int64(img[r * ss + dy, c * ss + dx]) >> (8 * ch)) & 0xFF
                out |= np.int64(np.rint(np.float32(s) * inv)) << (8 * ch)
            small[r0 + r, c0 + c] = np.uint32(out)


@numba.njit(cache=True)
def rig_quads(ends, centre, radius, z0s, z1s, scenery_colour, nw, pose, fo, mount, pitch, tx, reach, side, lo, hi,
              near, others, vehicle):
    """Every vertical quad a rig may see, in the vehicle frame and far to near (the painter's order): the
    roadside scenery culled by bounding circle, and all faces of the other vehicles' boxes.

    Flat arguments because a numba kernel takes arrays and scalars; callers use ``camera_render.rig_quads(scenery,
    view, others)`` with the two dataclasses ``camera_scene.RigScenery`` and ``camera_render.RigView``.

    Scenery (``RigScenery``, built once per scene): ``ends`` (Pw, 4) wall pieces' ends A, B (world x, y);
    ``centre`` (P, 2), ``radius`` (P,) bounding circles of walls then posts (cylinders, tree crowns
    after their trunks); ``z0s``/``z1s`` (P,) bottom/top heights (m); ``scenery_colour`` (P, 4) RGBA. Each item is
    dropped when no part can be within ``reach`` m of the rig centre (the lens position of the base camera,
    ``fo`` m ahead of the vehicle centre at ``mount`` m, ``pitch`` rad down) and, for a windshield rig (``side``:
    the cameras' lateral offsets span ``lo``..``hi`` m), when no part can be ahead of the ``near`` plane or inside
    the outer side planes (``tx``: tan of half the horizontal FOV, one pixel of margin); conservative, the exact
    per-camera culling is :func:`project_rig`'s. Walls stand on A→B; a cylinder is a rectangle ``2r`` wide facing
    the rig centre (for a side camera 0.6 m away the facing is off by atan(0.6/d), < 1 % of a 0.3 m pole's width
    beyond 5 m).

    Vehicles: ``others`` (n, 7+) world ``[x, y, _, _, heading, length, width]``, those within ``reach`` plus their
    half-diagonal of the rig centre; per box 4 sides, 4 windows (a band inset in each side, listed after the
    sides so the stable sort draws each over its own side) and a roof; ``vehicle`` = (height, body R, G, B, window
    R, G, B, window inset fraction, window bottom, window top, sun x, sun y): faces are shaded by
    ``0.62 + 0.38·max(0, normal·sun)``. Sides and windows carry their outward normal and normal·midpoint for the
    per-camera back-face test; roofs are drawn only by cameras above them.

    Returns ``fa``, ``fb``, ``fz`` (M, 4) forward, right, up (m) of the corners ``[(A, z0), (B, z0), (B, z1),
    (A, z1)]``, ``keys`` (M,) distance (m) from the rig centre (a vehicle's faces: its centre's), ``colours``
    (M, 4) RGBA, ``kind`` (M,) 0 scenery, 1 side or window, 2 roof, ``normals`` (M, 2) world, ``nm`` (M,), sorted
    far to near (stable), items beyond ``reach`` dropped. The formulas are the numpy renderer's, in its order."""
    x, y, psi = pose[0], pose[1], pose[2]
    cf, sf = math.cos(psi), math.sin(psi)
    ct, stp = math.cos(pitch), math.sin(pitch)
    p_all = centre.shape[0]
    keys_s = np.empty(p_all)
    ca = np.empty(p_all)
    cb = np.empty(p_all)
    sel = np.empty(p_all, np.int64)
    m_s = 0
    for i in range(p_all):
        d0, d1 = centre[i, 0] - x, centre[i, 1] - y
        ca[i], cb[i] = d0 * cf + d1 * sf, -d0 * sf + d1 * cf
        keys_s[i] = math.hypot(ca[i] - fo, cb[i])
        r = radius[i]
        ok = keys_s[i] <= reach + r
        if ok and side:
            zmax = (ca[i] + r - fo) * ct + max((mount - z0s[i]) * stp, (mount - z1s[i]) * stp)
            ok = (zmax >= near) and (cb[i] - r - hi <= tx * zmax) and (lo - cb[i] - r <= tx * zmax)
        if ok:
            sel[m_s] = i
            m_s += 1
    cx, cy = x + fo * cf, y + fo * sf
    n_o = others.shape[0]
    keep_o = np.empty(n_o, np.int64)
    m_o = 0
    for v in range(n_o):
        if math.hypot(others[v, 0] - cx, others[v, 1] - cy) <= reach + math.hypot(others[v, 5], others[v, 6]):
            keep_o[m_o] = v
            m_o += 1
    total = m_s + 9 * m_o
    fa = np.empty((total, 4))
    fb = np.empty((total, 4))
    fz = np.empty((total, 4))
    keys = np.empty(total)
    colours = np.empty((total, 4), np.int64)
    kind = np.zeros(total, np.int8)
    normals = np.zeros((total, 2))
    nm = np.zeros(total)
    for j in range(m_s):
        i = sel[j]
        if i < nw:
            e0a, e1a = ends[i, 0] - x, ends[i, 1] - y
            e0b, e1b = ends[i, 2] - x, ends[i, 3] - y
            a_a, b_a = e0a * cf + e1a * sf, e0b * cf + e1b * sf
            a_b, b_b = -e0a * sf + e1a * cf, -e0b * sf + e1b * cf
        else:
            pa, pb = ca[i], cb[i]
            ray_a, ray_b = pa - fo, pb
            k = radius[i] / max(math.hypot(ray_a, ray_b), 1e-6)
            qa, qb = -ray_b * k, ray_a * k
            a_a, b_a = pa - qa, pa + qa
            a_b, b_b = pb - qb, pb + qb
        fa[j, 0], fa[j, 1], fa[j, 2], fa[j, 3] = a_a, b_a, b_a, a_a
        fb[j, 0], fb[j, 1], fb[j, 2], fb[j, 3] = a_b, b_b, b_b, a_b
        fz[j, 0], fz[j, 1], fz[j, 2], fz[j, 3] = z0s[i], z0s[i], z1s[i], z1s[i]
        keys[j] = keys_s[i]
        colours[j] = scenery_colour[i]
    height, inset, wz0, wz1, sunx, suny = vehicle[0], vehicle[7], vehicle[8], vehicle[9], vehicle[10], vehicle[11]
    ax, ay = np.empty(4), np.empty(4)
    bx, by = np.empty(4), np.empty(4)
    nxs, nys = np.empty(4), np.empty(4)
    box_x = (1.0, 1.0, -1.0, -1.0)
    box_y = (1.0, -1.0, -1.0, 1.0)
    for jv in range(m_o):
        v = keep_o[jv]
        c, s = math.cos(others[v, 4]), math.sin(others[v, 4])
        for q in range(4):
            lx, ly = others[v, 5] / 2 * box_x[q], others[v, 6] / 2 * box_y[q]
            ax[q], ay[q] = others[v, 0] + c * lx - s * ly, others[v, 1] + s * lx + c * ly
        for q in range(4):
            bx[q], by[q] = ax[(q + 1) % 4], ay[(q + 1) % 4]
        nxs[0], nxs[1], nxs[2], nxs[3] = c, s, -c, -s  # outward unit normals: front, right, rear, left side
        nys[0], nys[1], nys[2], nys[3] = s, -c, -s, c
        dist = math.hypot(others[v, 0] - cx, others[v, 1] - cy)
        for q in range(4):
            shade = 0.62 + 0.38 * min(max(nxs[q] * sunx + nys[q] * suny, 0.0), 1.0)
            ex, ey = bx[q] - ax[q], by[q] - ay[q]
            mx, my = (ax[q] + bx[q]) / 2, (ay[q] + by[q]) / 2
            for w in range(2):  # 0 side, 1 window
                j = m_s + (4 * w) * m_o + 4 * jv + q
                if w == 0:
                    x0, y0, x1, y1, z0, z1 = ax[q], ay[q], bx[q], by[q], 0.0, height
                else:
                    x0, y0 = ax[q] + inset * ex, ay[q] + inset * ey
                    x1, y1 = bx[q] - inset * ex, by[q] - inset * ey
                    z0, z1 = wz0, wz1
                a0, b0 = _to_vehicle(x0, y0, x, y, cf, sf)  # corners 0 and 3 stand on A, 1 and 2 on B
                a1, b1 = _to_vehicle(x1, y1, x, y, cf, sf)
                fa[j, 0], fa[j, 1], fa[j, 2], fa[j, 3] = a0, a1, a1, a0
                fb[j, 0], fb[j, 1], fb[j, 2], fb[j, 3] = b0, b1, b1, b0
                fz[j, 0], fz[j, 1], fz[j, 2], fz[j, 3] = z0, z0, z1, z1
                keys[j] = dist
                for ch in range(3):
                    colours[j, ch] = np.int64(np.rint(min(max(vehicle[1 + 3 * w + ch] * shade, 0.0), 255.0)))
                colours[j, 3] = 255
                kind[j] = 1
                normals[j, 0], normals[j, 1] = nxs[q], nys[q]
                nm[j] = nxs[q] * mx + nys[q] * my
        j = m_s + 8 * m_o + jv
        for q in range(4):
            fa[j, q], fb[j, q] = _to_vehicle(ax[q], ay[q], x, y, cf, sf)
            fz[j, q] = height
        keys[j] = dist
        for ch in range(3):
            colours[j, ch] = np.int64(np.rint(min(max(min(vehicle[1 + ch] * 1.1, 255.0), 0.0), 255.0)))
        colours[j, 3] = 255
        kind[j] = 2
    idx = np.flatnonzero(keys <= reach)
    order = idx[np.argsort(-keys[idx], kind="mergesort")]  # stable: far to near, ties in listed order
    return fa[order], fb[order], fz[order], keys[order], colours[order], kind[order], normals[order], nm[order]


@numba.njit(cache=True, inline="always")
def _to_vehicle(px, py, x, y, cf, sf):
    """World point (px, py) → (forward, right) of the vehicle at (x, y) with heading cos ``cf``, sin ``sf``."""
    d0, d1 = px - x, py - y
    return d0 * cf + d1 * sf, -d0 * sf + d1 * cf


@numba.njit(cache=True)
def palette_lookup(v, palette):
    """``out[r, c] = palette[r, v[r, c]]``: each ground pixel's colour from its texture byte and its row's palette
    (``v`` (R, W) uint8, ``palette`` (R, 256) uint32 RGBA) → (R, W) uint32. What ``cv2.remap(palette, v, row,
    INTER_NEAREST)`` computed, without converting the bytes to a float map first."""
    out = np.empty(v.shape, np.uint32)
    for r in range(v.shape[0]):
        row = palette[r]
        for c in range(v.shape[1]):
            out[r, c] = row[v[r, c]]
    return out
