"""Rendering the cameras' images from a scene (:mod:`av_gym.sensors.camera_scene`) and the other vehicles:
projection, the ground pass, the compiled painter (:mod:`av_gym.sensors.raster`) for the vertical things, weather;
:func:`render_views` / :func:`render_view` are the entry points (the geometry: :mod:`av_gym.sensors.camera`)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import gymnasium as gym
import numpy as np

from av_gym.geometry import box_corners
from av_gym.sensors import raster
from av_gym.sensors.base import ego_pose, others_state
from av_gym.sensors.world import CIRCLE_KINDS
from av_gym.sensors.camera_scene import (_SHIFT, ASPHALT, CIRCLE_COLOURS, GRASS, GROUND_HAZE, MARKING, NEAR_PLANE,
                                         NEAR_REUSE, ROAD_STEP, SKY_HORIZON, SKY_TOP, SUN, TREE_TRUNK_FRACTION,
                                         VEHICLE_COLOUR, VEHICLE_HEIGHT, WALL_PIECE, WINDOW_BAND, WINDOW_COLOUR,
                                         WINDOW_INSET, _scenery_state, _vertical_quads, CameraSpec, ground_texture,
                                         GroundTexture, RigScenery, scene_of, StaticScene, Weather)


@lru_cache(maxsize=32)
def _ground_points(spec: CameraSpec) -> tuple[int, np.ndarray]:
    """Where each output pixel's ray meets the ground, in the vehicle frame: ``(r0, pts)`` with ``r0`` the first
    output row that sees ground and ``pts`` (rows r0.., W, 2) float32 ``[forward, right]`` metres from the
    vehicle centre. Rays that miss the ground, or meet it further than ``max_range`` from the camera, point far
    outside any texture (so they sample grass, i.e. the background). One ray per output pixel: the ground is
    sampled bilinearly once per output pixel (not ``supersample``² times): 4x fewer samples, the main cost."""
    hs, ws = spec.height, spec.width
    f = spec.focal
    xn = ((np.arange(ws) - (ws - 1) / 2) / f)[None, :]
    yn = ((np.arange(hs) - (hs - 1) / 2) / f)[:, None]
    ct, st = math.cos(spec.pitch), math.sin(spec.pitch)
    down = st + yn * ct
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(down > 1e-6, spec.mount_height / np.maximum(down, 1e-6), np.inf)
        a, b = t * (ct - yn * st), t * xn  # forward and right of the camera (m)
    a, b = np.broadcast_arrays(a, b)
    hit = np.isfinite(a) & np.isfinite(b) & (a * a + b * b <= spec.max_range ** 2)
    a, b = np.where(hit, a, 0.0), np.where(hit, b, 0.0)
    rows = np.flatnonzero(hit.any(1))
    r0 = int(rows[0]) if len(rows) else hs
    cy, sy = math.cos(spec.yaw), math.sin(spec.yaw)
    fwd = spec.forward_offset + a * cy - b * sy
    right = spec.lateral_offset + a * sy + b * cy
    pts = np.stack([np.where(hit, fwd, 1e6), np.where(hit, right, 1e6)], -1)[r0:]
    return r0, np.ascontiguousarray(pts, dtype=np.float32)


@lru_cache(maxsize=32)
def _ground_palette(spec: CameraSpec) -> np.ndarray:
    """Colour of a ground pixel from its texture byte v and its output row: (rows r0.., 256, 4) uint8 RGBA,
    where row i, column v is the camera's background of that row (hazed grass, area-averaged like the internal
    image) covered by asphalt with coverage ``min(v/128, 1)``, then asphalt blended to the marking colour for v in
    128..255 (bilinear texture samples at edges give partial coverage, as area averaging did)."""
    r0, _ = _ground_points(spec)
    bg = _background(spec)
    if spec.supersample > 1:
        bg = cv2.resize(bg, (spec.width, spec.height), interpolation=cv2.INTER_AREA)
    bg = bg[r0:, 0, :].astype(float)  # (rows, 3), constant along a row
    v = np.arange(256, dtype=float)
    alpha = np.clip(v / 128.0, 0.0, 1.0)[None, :, None]
    t = np.clip((v - 128.0) / 127.0, 0.0, 1.0)[None, :, None]
    paint = np.array(ASPHALT, float) * (1 - t) + np.array(MARKING, float) * t
    palette = np.round(bg[:, None, :] * (1 - alpha) + paint * alpha).astype(np.uint8)
    return np.concatenate([palette, np.full(palette.shape[:2] + (1,), 255, np.uint8)], -1)  # RGBA, alpha 255


@lru_cache(maxsize=32)
def _background_out(spec: CameraSpec) -> np.ndarray:
    """:func:`_background` area-averaged to the output size, (H, W, 4) uint8 RGBA (alpha 255)."""
    bg = _background(spec)
    bg = cv2.resize(bg, (spec.width, spec.height), interpolation=cv2.INTER_AREA) if spec.supersample > 1 else bg
    return cv2.cvtColor(bg, cv2.COLOR_RGB2RGBA)


# ================================================================================================ per-camera caches
@lru_cache(maxsize=32)
def _background(spec: CameraSpec) -> np.ndarray:
    """Sky gradient above the horizon and hazy grass below, at the internal resolution (Hs, Ws, 3) uint8."""
    ss = spec.supersample
    hs, ws = spec.height * ss, spec.width * ss
    rows = (np.arange(hs) - (hs - 1) / 2) / (spec.focal * ss)  # tan of the angle below the optical axis
    below = spec.pitch + np.arctan(rows)  # angle below the horizontal (rad)
    sky_t = np.clip(-below / 0.35, 0.0, 1.0)[:, None] ** 0.7
    sky = SKY_HORIZON + (SKY_TOP - SKY_HORIZON) * sky_t
    dist = spec.mount_height / np.tan(np.maximum(below, 1e-4))
    haze = 0.6 * (1.0 - np.exp(-dist / 250.0))[:, None]  # aerial perspective towards the horizon
    ground = GRASS + (GROUND_HAZE - GRASS) * haze
    col = np.where((below > 0)[:, None], ground, sky)
    return np.repeat(np.round(col).astype(np.uint8)[:, None, :], ws, axis=1)


@lru_cache(maxsize=32)
def _ground_rays(spec: CameraSpec) -> tuple[np.ndarray, np.ndarray]:
    """Per internal pixel: distance (m) to the ground along its ray (inf at and above the horizon), and the
    headlight beam factor in [0, 1] from the ray's direction. Both (Hs, Ws) float32."""
    ss = spec.supersample
    hs, ws = spec.height * ss, spec.width * ss
    f = spec.focal * ss
    xn = ((np.arange(ws) - (ws - 1) / 2) / f)[None, :]
    yn = ((np.arange(hs) - (hs - 1) / 2) / f)[:, None]
    ct, st = math.cos(spec.pitch), math.sin(spec.pitch)
    down = st + yn * ct  # −(up component) of the ray (xn, yn, 1) in world terms
    norm = np.sqrt(xn**2 + yn**2 + 1.0)
    with np.errstate(divide="ignore"):
        dist = np.where(down > 1e-6, spec.mount_height / np.maximum(down, 1e-6) * norm, np.inf)
    elevation = -down / norm  # sine of the ray's elevation above the horizontal
    beam = np.exp(-(xn / 0.45) ** 2) * np.exp(-(np.maximum(elevation, 0.0) / 0.12) ** 2)
    return dist.astype(np.float32), np.broadcast_to(beam, (hs, ws)).astype(np.float32)


# ================================================================================================ projection
@dataclass
class _Pose:
    """Camera position (m) and yaw (rad) in the world, plus the spec."""

    xy: np.ndarray
    cos: float
    sin: float
    spec: CameraSpec


def _camera_pose(pose: np.ndarray, spec: CameraSpec) -> _Pose:
    x, y, psi = float(pose[0]), float(pose[1]), float(pose[2])
    f, r = np.array([math.cos(psi), math.sin(psi)]), np.array([-math.sin(psi), math.cos(psi)])
    xy = np.array([x, y]) + spec.forward_offset * f + spec.lateral_offset * r
    yaw = psi + spec.yaw
    return _Pose(xy, math.cos(yaw), math.sin(yaw), spec)


def _to_camera(cam: _Pose, xy: np.ndarray, z: np.ndarray | float) -> np.ndarray:
    """World points ``xy`` (..., 2) m at heights ``z`` (...) m → camera frame (..., 3) ``[X, Y, Z]`` m."""
    d0, d1 = xy[..., 0] - cam.xy[0], xy[..., 1] - cam.xy[1]
    a = d0 * cam.cos + d1 * cam.sin  # forward
    b = -d0 * cam.sin + d1 * cam.cos  # right
    u = np.asarray(z, dtype=float) - cam.spec.mount_height  # up, relative to the lens
    ct, st = math.cos(cam.spec.pitch), math.sin(cam.spec.pitch)
    return np.stack(np.broadcast_arrays(b, -(a * st + u * ct), a * ct - u * st), -1)


def _in_frustum(pc: np.ndarray, spec: CameraSpec) -> np.ndarray:
    """Polygons (N, n, 3) not entirely outside one frustum plane (near plane and the four sides) → (N,) bool."""
    X, Y, Z = pc[..., 0], pc[..., 1], pc[..., 2]
    tx = (spec.width / 2 + 1) / spec.focal  # one pixel of margin
    ty = (spec.height / 2 + 1) / spec.focal
    out = ((Z < NEAR_PLANE).all(1) | (X > tx * Z).all(1) | (-X > tx * Z).all(1)
           | (Y > ty * Z).all(1) | (-Y > ty * Z).all(1))
    return ~out


def _clip_near(poly: np.ndarray) -> np.ndarray:
    """Sutherland–Hodgman clip of one polygon (n, 3) against ``Z >= NEAR_PLANE`` → (m, 3), m may be 0."""
    out = []
    n = len(poly)
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        p_in, q_in = p[2] >= NEAR_PLANE, q[2] >= NEAR_PLANE
        if p_in:
            out.append(p)
        if p_in != q_in:
            out.append(p + (NEAR_PLANE - p[2]) / (q[2] - p[2]) * (q - p))
    return np.array(out).reshape(-1, 3)


def _to_pixels(pc: np.ndarray, spec: CameraSpec) -> np.ndarray:
    """Camera-frame points (..., 3) with Z >= near → int32 internal-resolution pixels (..., 2), ``_SHIFT`` bits."""
    ss = spec.supersample
    f = spec.focal * ss
    cx, cy = (spec.width * ss - 1) / 2, (spec.height * ss - 1) / 2
    uv = np.stack([cx + f * pc[..., 0] / pc[..., 2], cy + f * pc[..., 1] / pc[..., 2]], -1)
    return np.round(uv * (1 << _SHIFT)).astype(np.int32)


def _project(pc: np.ndarray, spec: CameraSpec) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], np.ndarray]:
    """Split culled polygons (N, n, 3) into those wholly in front of the near plane, projected together
    ((A, n, 2) int32, their indices), and straddlers, clipped then projected (list of (m, 1, 2), their indices)."""
    front = (pc[..., 2] >= NEAR_PLANE).all(1)
    whole = np.flatnonzero(front)
    cut_idx, cut = [], []
    for i in np.flatnonzero(~front):
        c = _clip_near(pc[i])
        if len(c) >= 3:
            cut.append(_to_pixels(c, spec).reshape(-1, 1, 2))
            cut_idx.append(i)
    return _to_pixels(pc[whole], spec), whole, cut, np.array(cut_idx, dtype=int)


def _draw_ground(img: np.ndarray, cam: _Pose, quads: np.ndarray, groups: np.ndarray, colour: tuple) -> None:
    """Fill ground quads (N, 4, 2) with one colour. Quads of one group never overlap, so each group goes to a
    single ``fillPoly`` call (whose even-odd rule would punch holes where polygons overlap)."""
    if not len(quads):
        return
    pc = _to_camera(cam, quads, 0.0)
    keep = _in_frustum(pc, cam.spec)
    pc, groups = pc[keep], groups[keep]
    whole, whole_i, cut, _ = _project(pc, cam.spec)
    g = groups[whole_i]
    bounds = np.concatenate([[0], np.flatnonzero(np.diff(g)) + 1, [len(g)]])
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        if hi > lo:
            cv2.fillPoly(img, whole[lo:hi], colour, cv2.LINE_8, _SHIFT)
    for poly in cut:
        cv2.fillPoly(img, [poly], colour, cv2.LINE_8, _SHIFT)


def _vertical_items(scene: StaticScene, others: np.ndarray, cam: _Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every vertical quad the camera may see: ((N, 4, 3) world ``[x, y, z]``, (N, 3) RGB, (N,) sort distance m)."""
    quads, colours, keys = [scene.walls], [scene.wall_colour], [np.linalg.norm(scene.wall_centre - cam.xy, axis=1)]
    if len(scene.posts):
        c, r, h = scene.posts[:, :2], scene.posts[:, 2], scene.post_height
        ray = c - cam.xy
        dist = np.maximum(np.linalg.norm(ray, axis=1), 1e-6)
        perp = np.stack([-ray[:, 1], ray[:, 0]], 1) / dist[:, None] * r[:, None]  # faces the camera
        a, b = c - perp, c + perp
        tree = scene.post_kind == CIRCLE_KINDS.index("tree")
        z_top = np.where(tree, h * TREE_TRUNK_FRACTION, h)
        kind_colour = np.array([CIRCLE_COLOURS[k][0] for k in CIRCLE_KINDS], float)
        quads.append(_vertical_quads(a, b, np.zeros_like(h), z_top))
        colours.append(kind_colour[scene.post_kind])
        keys.append(dist)
        if tree.any():  # crowns, drawn after their trunks (same key, later in the stable sort)
            quads.append(_vertical_quads(a[tree], b[tree], z_top[tree], h[tree]))
            colours.append(np.tile(np.array(CIRCLE_COLOURS["tree"][1], float), (int(tree.sum()), 1)))
            keys.append(dist[tree])
    if len(others):
        q, col, k = _vehicle_faces(others, cam)
        quads.append(q)
        colours.append(col)
        keys.append(k)
    return np.concatenate(quads), np.concatenate(colours), np.concatenate(keys)


def _vehicle_faces(others: np.ndarray, cam: _Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-facing faces of the other vehicles' boxes: ((F, 4, 3), (F, 3) RGB, (F,) distance m). Back faces are
    dropped, so the faces of one box never overlap on screen and need no ordering among themselves."""
    corners = box_corners(others[:, 0:2], others[:, 4], others[:, 5], others[:, 6])  # (N, 4, 2)
    centre = others[:, None, 0:2]
    a, b = corners, np.roll(corners, -1, axis=1)  # side i runs corner i → i+1
    mid = (a + b) / 2
    edge = b - a
    normal = np.stack([-edge[..., 1], edge[..., 0]], -1)
    normal *= np.sign(np.einsum("nik,nik->ni", normal, mid - centre))[..., None]  # outward
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-9)
    visible = np.einsum("nik,nik->ni", normal, cam.xy - mid) > 0
    shade = 0.62 + 0.38 * np.clip(normal @ SUN, 0.0, 1.0)
    n = len(others)
    zeros, tops = np.zeros(n * 4), np.full(n * 4, VEHICLE_HEIGHT)
    sides = _vertical_quads(a.reshape(-1, 2), b.reshape(-1, 2), zeros, tops).reshape(n, 4, 4, 3)
    dist = np.linalg.norm(others[:, 0:2] - cam.xy, axis=1)
    # Windows: a dark band inset in every visible side, listed after the sides so the stable far-to-near sort
    # draws each over its own side (equal keys keep their order).
    wa, wb = a + WINDOW_INSET * edge, b - WINDOW_INSET * edge
    windows = _vertical_quads(wa.reshape(-1, 2), wb.reshape(-1, 2), np.full(n * 4, WINDOW_BAND[0]),
                              np.full(n * 4, WINDOW_BAND[1])).reshape(n, 4, 4, 3)
    side_keys = np.repeat(dist, 4)[visible.ravel()]
    quads = [sides[visible], windows[visible]]
    colours = [VEHICLE_COLOUR * shade[visible][:, None], WINDOW_COLOUR * shade[visible][:, None]]
    keys = [side_keys, side_keys]
    if cam.spec.mount_height > VEHICLE_HEIGHT:  # roofs are seen only from above
        quads.append(np.concatenate([corners, np.full((n, 4, 1), VEHICLE_HEIGHT)], -1))
        colours.append(np.tile(np.minimum(VEHICLE_COLOUR * 1.1, 255), (n, 1)))
        keys.append(dist)
    return np.concatenate(quads), np.concatenate(colours), np.concatenate(keys)


def _render_one_raster(scene: StaticScene, others: np.ndarray, pose: np.ndarray, spec: CameraSpec,
                weather: Weather) -> np.ndarray:
    """Clean image (H, W, 3) uint8 RGB of ``scene`` and ``others`` from ego ``pose`` [x, y, heading], the
    original way: every road polygon projected and filled (the reference :func:`_render_rig` is checked against)."""
    cam = _camera_pose(pose, spec)
    img = _background(spec).copy()
    _draw_ground(img, cam, scene.road, scene.road_group, ASPHALT)
    _draw_ground(img, cam, scene.marks, scene.mark_group, MARKING)

    depth = _ground_rays(spec)[0].copy() if weather.needs_depth else None
    quads, colours, keys = _vertical_items(scene, others, cam)
    if len(quads):
        idx = np.flatnonzero(keys <= spec.max_range)
        pc = _to_camera(cam, quads[idx][..., :2], quads[idx][..., 2])
        visible = _in_frustum(pc, spec)
        idx, pc = idx[visible], pc[visible]
        order = np.argsort(-keys[idx], kind="stable")  # far to near
        idx, pc = idx[order], pc[order]
        whole, whole_i, cut, cut_i = _project(pc, spec)
        polys: list[tuple[int, np.ndarray]] = [(int(i), p) for i, p in zip(whole_i, whole)]
        polys += [(int(i), p) for i, p in zip(cut_i, cut)]
        polys.sort(key=lambda t: t[0])  # back into far-to-near order
        col = np.round(np.clip(colours[idx], 0, 255)).astype(int).tolist()
        dist = keys[idx]
        for i, p in polys:
            cv2.fillConvexPoly(img, p, col[i], cv2.LINE_8, _SHIFT)
            if depth is not None:
                cv2.fillConvexPoly(depth, p, float(dist[i]), cv2.LINE_8, _SHIFT)

    out_size = (spec.width, spec.height)
    if depth is None:
        return cv2.resize(img, out_size, interpolation=cv2.INTER_AREA) if spec.supersample > 1 else img
    return _apply_weather(img, depth, spec, weather)


_VEHICLE_LOOK = np.array([VEHICLE_HEIGHT, *VEHICLE_COLOUR, *WINDOW_COLOUR, WINDOW_INSET, *WINDOW_BAND, *SUN])


@dataclass(frozen=True)
class RigView:
    """Where a rig looks from and how far, what :func:`raster.rig_quads` culls the scene by."""

    pose: np.ndarray  # the ego's [x, y, heading] (m, rad)
    forward_offset: float  # m, the base camera's lens ahead of the vehicle centre
    mount_height: float  # m
    pitch: float  # rad down
    tan_half_fov: float  # tan of half the horizontal FOV, one pixel of margin
    reach: float  # m, farthest any camera draws
    windshield: bool  # the cameras differ only in lateral offset (side planes cull too)
    lateral_lo: float  # m, the cameras' lateral offsets span lo..hi
    lateral_hi: float
    near: float = NEAR_PLANE  # m, near clipping plane


def rig_quads(scenery: RigScenery, view: RigView, others: np.ndarray) -> tuple:
    """:func:`raster.rig_quads` (compiled, so it takes flat arrays) for ``scenery`` seen from ``view``, the other
    vehicles ``others`` (n, 7+) drawn with the module's vehicle look."""
    return raster.rig_quads(
        scenery.ends, scenery.centre, scenery.radius, scenery.z0, scenery.z1, scenery.colour, scenery.nw,
        view.pose, view.forward_offset, view.mount_height, view.pitch, view.tan_half_fov, view.reach,
        view.windshield, view.lateral_lo, view.lateral_hi, view.near,
        np.ascontiguousarray(others, float) if len(others) else np.zeros((0, 7)), _VEHICLE_LOOK)


def _render_rig(scene: StaticScene, others: np.ndarray, pose: np.ndarray, cameras: Mapping[str, CameraSpec],
                weather: Weather, texture: GroundTexture, whole_image: bool = False) -> dict[str, np.ndarray]:
    """Clean images of every camera in ``cameras`` from ego ``pose`` [x, y, heading]: the ground of all cameras
    sampled from ``texture`` in one stacked pass (:func:`_draw_rig_ground`), then the vertical things far to near
    (:func:`_paint`). The vertical quads are built once for the rig in the vehicle frame, culled by bounding circle
    and sorted far to near (:func:`raster.rig_quads`: scenery facing the rig's centre, every vehicle face), then
    projected, culled and clipped per camera (:func:`raster.project_rig`; the windshield rig, whose cameras
    differ only in lateral offset, with the shared-rig formula the numpy renderer had), both compiled: per rig a
    handful of calls instead of ~30 numpy passes and one OpenCV call per quad. ``whole_image`` repaints the whole
    internal image instead of the band the quads cover (the reference the band is tested against).

    Measured and not taken (with OpenCV's painter): merging runs of neighbouring wall pieces into one quad
    where no quad in between overlaps them removed only ~12 of 55-65 wall quads per camera, since the roadside
    walls are chains of short straight segments, and its overlap test cost more than the fills saved."""
    x, y, psi = float(pose[0]), float(pose[1]), float(pose[2])
    cf, sf = math.cos(psi), math.sin(psi)
    specs = list(cameras.values())
    base = specs[0]
    shared = _shared_geometry(cameras)
    lats = np.array([sp.lateral_offset for sp in specs])
    reach = max(spec.max_range for spec in specs)
    view = RigView(pose=np.asarray(pose, float), forward_offset=base.forward_offset, mount_height=base.mount_height,
                   pitch=base.pitch, tan_half_fov=(base.width / 2 + 1) / base.focal, reach=reach,
                   windshield=shared is not None, lateral_lo=float(lats.min()), lateral_hi=float(lats.max()))
    fa, fb, fz, keys, colours, kind, nrm, nm = rig_quads(_scenery_state(scene), view, others)
    smalls = _draw_rig_ground(pose, specs, texture)
    cams = np.array([[sp.forward_offset, sp.lateral_offset, sp.yaw, sp.mount_height, sp.pitch, sp.focal, sp.width,
                      sp.height, sp.supersample, sp.max_range, x + sp.forward_offset * cf - sp.lateral_offset * sf,
                      y + sp.forward_offset * sf + sp.lateral_offset * cf, sp.mount_height > VEHICLE_HEIGHT]
                     for sp in specs], float)
    polys, npts = raster.project_rig(fa, fb, fz, keys, kind, nrm, nm, cams, NEAR_PLANE, _SHIFT, shared is not None)
    colours = np.ascontiguousarray(colours.astype(np.uint8)).view(np.uint32)[:, 0]  # RGBA packed as the images
    return {name: _paint(sm, polys[k], npts[k], colours, keys, spec, weather, whole_image)
            for k, (name, sm, spec) in enumerate(zip(cameras, smalls, specs))}


def _shared_geometry(cameras: Mapping[str, CameraSpec]) -> CameraSpec | None:
    """The rig's common spec when its cameras differ only in lateral offset (the windshield rig), else None."""
    return _shared_spec(tuple(cameras.values()))


@lru_cache(maxsize=32)
def _shared_spec(specs: tuple[CameraSpec, ...]) -> CameraSpec | None:
    base = replace(specs[0], lateral_offset=0.0)
    if base.yaw == 0 and all(replace(sp, lateral_offset=0.0) == base for sp in specs):
        return base
    return None


def _draw_rig_ground(pose: np.ndarray, specs: list[CameraSpec], tex: GroundTexture) -> list[np.ndarray]:
    """Sky, grass, road and markings of every camera at the output size, (H, W, 4) uint8 RGBA each (views of one
    stacked buffer). The pixel rays are fixed in the car frame, so one affine map (``cv2.transform``, from the
    ego pose) takes the ground points of all cameras (:func:`_rig_ground`) to texels; one ``cv2.remap`` samples
    the texture there (bilinear) and :func:`raster.palette_lookup` looks each byte up in its row's palette.
    Cameras of another size than the first are done in their own pass."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    out: list[np.ndarray | None] = [None] * len(specs)
    for size in dict.fromkeys((sp.height, sp.width) for sp in specs):
        ks = [k for k, sp in enumerate(specs) if (sp.height, sp.width) == size]
        pts, palette = _rig_ground(tuple(specs[k] for k in ks))
        k_ = 1.0 / tex.res
        m = np.array([[c * k_, -s * k_, (float(pose[0]) - tex.x0) * k_],
                      [s * k_, c * k_, (float(pose[1]) - tex.y0) * k_]], np.float32)
        v = cv2.remap(tex.texels, cv2.transform(pts, m), None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=0)
        small = raster.palette_lookup(v, palette).view(np.uint8).reshape(v.shape + (4,))
        for j, k in enumerate(ks):
            out[k] = small[j * size[0]:(j + 1) * size[0]]
    return out


@lru_cache(maxsize=8)
def _rig_ground(specs: tuple[CameraSpec, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Ground lookup of cameras of one output size, stacked vertically (K cameras of H×W): ``pts`` (K·H, W, 2)
    float32 vehicle-frame ground points of every output pixel (:func:`_ground_points`; far outside any texture
    where the ray meets no ground within range) and ``palette`` (K·H, 256) RGBA viewed as uint32
    (:func:`_ground_palette` below the first ground row, the row's background for every byte above it, so a sky
    pixel looks up its sky colour)."""
    pts_all, pal_all = [], []
    for spec in specs:
        r0, pts = _ground_points(spec)
        full = np.full((spec.height, spec.width, 2), 1e6, np.float32)
        full[r0:] = pts
        pal = np.repeat(_background_out(spec)[:, :1], 256, axis=1)  # a background row is one colour
        pal[r0:] = _ground_palette(spec)
        pts_all.append(full)
        pal_all.append(pal)
    pts, palette = np.concatenate(pts_all), np.concatenate(pal_all)
    return np.ascontiguousarray(pts), np.ascontiguousarray(palette).view(np.uint32)[..., 0]


def _paint(small: np.ndarray, polys: np.ndarray, npts: np.ndarray, colours: np.ndarray, dist: np.ndarray,
           spec: CameraSpec, weather: Weather, whole: bool = False) -> np.ndarray:
    """The vertical things over one camera's ground image ``small`` (H, W, 4) RGBA at the output size; returns
    the (H, W, 3) RGB frame. ``polys`` (N, MAX_VERTS, 2) / ``npts`` (N,): this camera's internal-pixel polygons,
    far to near (:func:`raster.project_rig`); ``colours`` (N, 4) uint8 RGBA; ``dist`` (N,) m, for the depth buffer.

    Painter's algorithm at ``supersample``x, then area-averaged down, compiled (:func:`raster.paint_band`): only
    the band the quads cover is enlarged, painted and shrunk (the ground outside it is final already); ``whole``
    repaints the whole image (the reference the band is tested against). With fog or night the whole image is
    painted, with a depth buffer beside it."""
    if weather.needs_depth:
        img = _enlarge(small, spec.supersample)
        depth = _ground_rays(spec)[0].copy()
        raster.paint_depth(_as_pixels(img), depth, polys, npts, colours, dist, _SHIFT)
        return _apply_weather(cv2.cvtColor(img, cv2.COLOR_RGBA2RGB), depth, spec, weather)
    raster.paint_band(_as_pixels(small), polys, npts, colours, spec.supersample, _SHIFT, whole)
    return cv2.cvtColor(small, cv2.COLOR_RGBA2RGB)


def _as_pixels(img: np.ndarray) -> np.ndarray:
    """An (H, W, 4) uint8 RGBA image viewed as (H, W) uint32, one value per pixel (same memory), as the compiled
    painter fills it."""
    return img.view(np.uint32)[..., 0]


def _enlarge(img: np.ndarray, ss: int) -> np.ndarray:
    """``img`` enlarged ``ss`` times, each pixel an ss×ss block: ``INTER_NEAREST_EXACT``, which for an integer
    factor picks the same source pixels as ``INTER_NEAREST`` and runs ~2x faster here."""
    if ss == 1:
        return img.copy()
    return cv2.resize(img, (img.shape[1] * ss, img.shape[0] * ss), interpolation=cv2.INTER_NEAREST_EXACT)


def _apply_weather(img: np.ndarray, depth: np.ndarray, spec: CameraSpec, weather: Weather) -> np.ndarray:
    """Fog and night on an internal-resolution image, using its depth buffer (m); returns output-size uint8.
    Fog comes first (scattering happens in the scene), night second (it dims the airlight too)."""
    out_size = (spec.width, spec.height)
    resize = (lambda a: cv2.resize(a, out_size, interpolation=cv2.INTER_AREA)) if spec.supersample > 1 \
        else (lambda a: a)
    im = resize(img).astype(np.float32)
    if weather.fog_visibility is not None:
        t = resize(np.exp(-3.912 / weather.fog_visibility * depth).astype(np.float32))[..., None]
        im = im * t + np.float32(weather.fog_airlight) * (1.0 - t)
    if weather.night:
        light = np.full(depth.shape, weather.night_ambient, np.float32)
        if weather.headlights:
            beam = _ground_rays(spec)[1]
            light += (1.0 - weather.night_ambient) * beam / (1.0 + (depth / 20.0) ** 2)
        light = resize(light)[..., None]
        im = 255.0 * np.clip(im * light / 255.0, 0.0, 1.0) ** weather.night_gamma
    return np.clip(np.round(im), 0, 255).astype(np.uint8)


_CLEAR = Weather()  # the default conditions, built once (validating a Params costs ~0.1 ms)


# ================================================================================================ public rendering
def render_views(env: gym.Env, cameras: Mapping[str, CameraSpec], pose: np.ndarray | None = None,
                 weather: Weather | None = None, ground: str = "texture") -> dict[str, np.ndarray]:
    """Clean renders of several cameras from one ego pose, sharing the scene culling.

    ``pose``: ego ``[x, y, heading]`` (m, m, rad); default the true ego pose (pass a displaced pose to render
    what the car would see there, e.g. for behaviour-cloning recovery data). ``ground``: ``"texture"`` (sample the
    top-down ground texture) or ``"raster"`` (project every road polygon: the original, ~10x slower renderer,
    kept as the reference for the renderer comparison (docs/sensors.md) and the tests). Returns name → (H, W, 3)
    uint8 RGB."""
    if ground not in ("texture", "raster"):
        raise ValueError(f"ground must be 'texture' or 'raster', got {ground!r}")
    pose = ego_pose(env)[:3] if pose is None else np.asarray(pose, dtype=float)
    scene = scene_of(env)
    reach = max(s.max_range + abs(s.forward_offset) + abs(s.lateral_offset) for s in cameras.values())
    texture = ground_texture(scene) if ground == "texture" else None
    if texture is None:
        local = scene.near(pose[:2], reach + WALL_PIECE + ROAD_STEP)
    else:  # the texture renderer needs only the vertical scenery: culled again only every NEAR_REUSE m
        cached = getattr(scene, "_near", None)
        if cached is None or cached[1] != reach or np.hypot(*(pose[:2] - cached[0])) > NEAR_REUSE:
            cached = scene._near = (pose[:2].copy(), reach,
                                    scene.near(pose[:2], reach + WALL_PIECE + ROAD_STEP + NEAR_REUSE, ground=False))
        local = cached[2]
    others = others_state(env)
    weather = weather or _CLEAR
    if texture is None:  # the original renderer
        return {name: _render_one_raster(local, others, pose, spec, weather) for name, spec in cameras.items()}
    return _render_rig(local, others, pose, cameras, weather, texture)


def render_view(env: gym.Env, camera: CameraSpec | None = None, pose: np.ndarray | None = None,
                weather: Weather | None = None, ground: str = "texture") -> np.ndarray:
    """Clean (noise-free) render (H, W, 3) uint8 RGB of one camera; see :func:`render_views`."""
    return render_views(env, {"view": camera or CameraSpec()}, pose, weather, ground)["view"]
