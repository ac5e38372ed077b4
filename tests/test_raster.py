"""The compiled camera painter (av_gym/sensors/raster.py) sets the pixels OpenCV would."""

import cv2
import numpy as np
import pytest

from av_gym.sensors import raster
from av_gym.sensors.camera_render import _clip_near
from av_gym.sensors.camera_scene import _SHIFT, NEAR_PLANE


def _random_polygon(rng, t, h, w):
    """A convex polygon (3-5 corners, ``_SHIFT`` fractional bits) around a random centre, some of them partly or
    wholly off the image, huge, reversed (clockwise), degenerate (all corners equal) or with a repeated corner."""
    n = int(rng.integers(3, 6))
    c = rng.uniform(-0.3, 1.3, 2) * [w, h]
    r = rng.uniform(0.1, 60) * (10 if t % 10 == 0 else 1)
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    if t % 7 == 0:
        ang = ang[::-1]
    pts = np.stack([c[0] + r * np.cos(ang), c[1] + r * np.sin(ang)], 1)
    if t % 13 == 0:
        pts[:] = pts[0]
    if t % 17 == 0:
        pts[1] = pts[0]
    return np.round(pts * (1 << _SHIFT)).astype(np.int32)


def test_fill_sets_the_pixels_cv2_fillconvexpoly_sets():
    rng = np.random.default_rng(0)
    for t in range(1500):
        h, w = int(rng.integers(5, 140)), int(rng.integers(5, 420))
        img = rng.integers(0, 256, (h, w, 4), dtype=np.uint8)
        depth = rng.uniform(0, 100, (h, w)).astype(np.float32)
        ref, ref_depth = img.copy(), depth.copy()
        p = _random_polygon(rng, t, h, w)
        colour = rng.integers(0, 256, 4).astype(np.uint8)
        d = float(rng.uniform(0, 80))
        cv2.fillConvexPoly(ref, p, colour.tolist(), cv2.LINE_8, _SHIFT)
        cv2.fillConvexPoly(ref_depth, p, d, cv2.LINE_8, _SHIFT)
        # through paint_depth (one polygon): _fill_convex with the depth buffer as the cameras call it; called from
        # Python it would compile a specialization of its own (a plain bool, not the literal True), ~4 CPU-s cold
        raster.paint_depth(img.view(np.uint32)[..., 0], depth, p.astype(np.int64)[None], np.array([len(p)]),
                           colour.view(np.uint32), np.array([d]), _SHIFT)
        assert np.array_equal(img, ref), t
        assert np.array_equal(depth, ref_depth), t


def test_a_changed_rounding_would_be_seen():
    """The comparison above can fail: OpenCV's half-pixel offset (delta) moved by one fixed-point step changes
    pixels on most polygons, so matching them is not a property of any fill."""
    rng = np.random.default_rng(1)
    changed = 0
    for t in range(200):
        h, w = 60, 200
        p = _random_polygon(rng, t, h, w)
        ref = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(ref, p, 255, cv2.LINE_8, _SHIFT)
        moved = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(moved, p + 3, 255, cv2.LINE_8, _SHIFT)  # a 3/8-pixel shift of the same polygon
        changed += not np.array_equal(ref, moved)
    assert changed > 100


@pytest.mark.parametrize("ss", [2, 3, 4])
def test_enlarge_and_shrink_are_opencvs(ss):
    rng = np.random.default_rng(ss)
    for _ in range(100):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 60))
        big = rng.integers(0, 256, (h * ss, w * ss, 4), dtype=np.uint8)
        out = np.zeros((h + 3, w + 2, 4), np.uint8)
        raster._shrink(big.view(np.uint32)[..., 0], out.view(np.uint32)[..., 0], 1, 2, ss)
        assert np.array_equal(out[1:1 + h, 2:2 + w], cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA))
        small = rng.integers(0, 256, (h, w, 4), dtype=np.uint8)
        e = raster._enlarge(small.view(np.uint32)[..., 0], 0, h, 0, w, ss)
        assert np.array_equal(e.view(np.uint8).reshape(h * ss, w * ss, 4),
                              cv2.resize(small, (w * ss, h * ss), interpolation=cv2.INTER_NEAREST_EXACT))


def test_quads_straddling_the_near_plane_are_clipped_as_the_numpy_clip():
    """project_rig's Sutherland-Hodgman clip gives the corners camera_render._clip_near gives, projected the same way."""
    rng = np.random.default_rng(3)
    n = 400
    fa = rng.uniform(-2, 6, (n, 4))  # forward (m): many quads cross the lens plane
    fb = rng.uniform(-4, 4, (n, 4))
    fz = np.tile([0.0, 0.0, 1.5, 1.5], (n, 1))
    keys = np.hypot(fa.mean(1), fb.mean(1))
    # camera at the origin looking forward, no pitch, 66x200, focal 100, ss 2
    cams = np.array([[0.0, 0.0, 0.0, 1.4, 0.0, 100.0, 200, 66, 2, 80.0, 0.0, 0.0, 0.0]])
    polys, npts = raster.project_rig(fa, fb, fz, keys, np.zeros(n, np.int8), np.zeros((n, 2)), np.zeros(n), cams,
                                     NEAR_PLANE, _SHIFT, True)
    f, cx, cy = 200.0, (400 - 1) / 2, (132 - 1) / 2
    clipped = 0
    for i in range(n):
        pc = np.stack([fb[i], -(fz[i] - 1.4), fa[i]], -1)  # X right, Y down, Z forward
        if (pc[:, 2] >= NEAR_PLANE).all() or (pc[:, 2] < NEAR_PLANE).all():
            continue
        if npts[0, i] == 0:  # culled by a side plane or the top/bottom
            continue
        c = _clip_near(pc)
        uv = np.round(np.stack([cx + f * c[:, 0] / c[:, 2], cy + f * c[:, 1] / c[:, 2]], -1) * (1 << _SHIFT))
        assert npts[0, i] == len(c)
        assert np.array_equal(polys[0, i, :len(c)], uv.astype(np.int64))
        clipped += 1
    assert clipped > 50


@pytest.mark.parametrize("whole", [False, True])
def test_paint_band_paints_what_opencv_paints_on_the_whole_enlarged_image(whole):
    """Polygons painted in order at 2x, then area-averaged: the band (or whole image) path of paint_band against
    cv2 (enlarge everything, fillConvexPoly each, INTER_AREA), including polygons partly off the image and the
    culled ones (npts 0), which must leave no trace."""
    rng = np.random.default_rng(7)
    for t in range(60):
        h, w, ss = 66, 200, 2
        small = rng.integers(0, 256, (h, w, 4), dtype=np.uint8)
        small[..., 3] = 255
        n = int(rng.integers(1, 40))
        polys = np.zeros((n, raster.MAX_VERTS, 2), np.int64)
        npts = np.zeros(n, np.int64)
        cols = rng.integers(0, 256, (n, 4)).astype(np.uint8)
        cols[:, 3] = 255
        ref = cv2.resize(small, (w * ss, h * ss), interpolation=cv2.INTER_NEAREST_EXACT)
        for i in range(n):
            p = _random_polygon(rng, t * 40 + i, h * ss, w * ss)
            if rng.uniform() < 0.2:
                continue  # culled: npts stays 0
            polys[i, :len(p)], npts[i] = p, len(p)
            cv2.fillConvexPoly(ref, p, cols[i].tolist(), cv2.LINE_8, _SHIFT)
        ref = cv2.resize(ref, (w, h), interpolation=cv2.INTER_AREA)
        out = small.copy()
        raster.paint_band(out.view(np.uint32)[..., 0], polys, npts, cols.view(np.uint32)[:, 0], ss, _SHIFT, whole)
        assert np.array_equal(out, ref), t
