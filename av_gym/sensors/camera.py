"""Three windshield cameras (left, centre, right): pinhole perspective renders of the road, its markings, the
roadside world and the other vehicles, for PilotNet behaviour cloning (digest 001 §2, §8.5a).

Geometry
--------
Each camera sits on the windshield at ``forward_offset`` ahead of the vehicle's reference point (its centre in
highway-env), ``lateral_offset`` across it (+ = driver's right, highway-env's lateral sign) and ``mount_height``
above the ground, looks along the vehicle heading (plus an optional ``yaw_deg``) and is pitched down by
``pitch_deg``. The rig puts the side cameras at ``lateral_offset = ∓d`` with ``d =`` :data:`WINDSHIELD_HALF_WIDTH`
= 0.6 m (our choice: the half-width of a car's windshield; digest 001 §8.5 suggests 0.8–1.0 m, which would sit
outside the glass of highway-env's 2 m-wide car).

World point ``(x, y, z)`` (highway-env frame: x right, y down on screen, z up, metres) → vehicle-aligned
``a`` (forward), ``b`` (right), ``u = z − mount_height`` (up) → camera frame (OpenCV convention: X right, Y down,
Z along the optical axis) ``X = b``, ``Y = −(a·sinθ + u·cosθ)``, ``Z = a·cosθ − u·sinθ`` (θ = pitch) → pixels
``col = cx + f·X/Z``, ``row = cy + f·Y/Z`` with ``f = (W/2)/tan(hfov/2)`` (square pixels). Polygons are clipped
against the near plane ``Z = NEAR_PLANE`` (Sutherland–Hodgman) before the division, so geometry beside or behind
the camera never folds over the image.

Drawing (painter's algorithm): sky gradient and grass (precomputed per camera) → asphalt of every lane →
lane markings (edge lines for ``CONTINUOUS`` sides, 3 m dashes every 9 m for ``STRIPED`` sides, nothing for
``NONE``) → vertical things far to near: roadside walls (guard rails, building fronts) as ground-to-height quads,
cylinders (poles, sign posts, trees) as camera-facing rectangles ``2r`` wide, other vehicles as
:data:`VEHICLE_HEIGHT`-tall boxes with back faces culled. Scenery shapes are exactly :mod:`av_gym.sensors.world`'s,
so the camera and the LiDAR see the same world. Rendering is done at ``supersample``× the output size and
averaged down with ``cv2.resize(INTER_AREA)`` (anti-aliasing).

Conditions and noise
--------------------
Deterministic conditions (:class:`Weather`, applied by :func:`render_view`): fog as an airlight blend
``I' = I·t + A·(1 − t)`` (digest 000 §5.7) with per-pixel transmission ``t = exp(−3.912·d/V)`` (Koschmieder's law,
visibility ``V``, distance ``d`` from a depth buffer; our choice), and night (darken by an ambient factor plus
headlight pools, then a gamma; digest 000 §5.7 ranges). Random sensor noise (:class:`CameraNoise`, drawn from the
wrapper's ``self.rng``): per-episode brightness/contrast and per-camera gain, optional Gaussian blur, per-frame
Gaussian pixel noise.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Literal
from functools import lru_cache

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces
from highway_env.road.lane import AbstractLane, LineType

from av_gym.geometry import box_corners
from av_gym.params import RATE_MAX_HZ, Params, param
from av_gym.sensors import raster
from av_gym.sensors.base import SensorWrapper, ego_pose, others_state, sim_time
from av_gym.sensors.world import CIRCLE_KINDS, SEGMENT_KINDS, geometry_key, roadside_world

CAMERA_NAMES = ("left", "centre", "right")
WINDSHIELD_HALF_WIDTH = 0.6  # m, side-camera offset d (our choice, see module docstring)
VEHICLE_HEIGHT = 1.5  # m, box height of other vehicles (a typical saloon car; highway-env is 2-D)
NEAR_PLANE = 0.3  # m, polygons are clipped at this camera depth
ROAD_STEP = 2.0  # m, asphalt and edge-line sampling along each lane (chord error 2 cm on a 25 m radius)
MARKING_WIDTH = 0.20  # m, painted line width (our choice; 0.15-0.30 m is usual)
DASH_LENGTH, DASH_PERIOD = 3.0, 9.0  # m, striped lines: 3 m dash, 6 m gap (our choice, a common urban pattern)
WALL_PIECE = 3.0  # m, long walls are split into pieces this long so far-to-near sorting stays right
NEAR_REUSE = 5.0  # m the ego may move before the texture renderer culls the roadside scenery again
TEXTURE_RES = 0.04  # m per texel of the top-down ground texture (a 0.20 m marking is 5 texels wide)
NOISE_BANK_SIZE = 1 << 21  # standard normals drawn once per process for the pixel noise (Cameras._pixel_noise)
NOISE_BANK_SEED = 18  # the bank's generator seed: the same bank in every process
_SHIFT = 3  # fractional bits of the int32 pixel coordinates handed to OpenCV (sub-pixel polygon edges)

# Palette (RGB, our choice). Kept within ~[20, 230] so moderate pixel noise is rarely clipped.
SKY_TOP = np.array([95, 145, 215], float)
SKY_HORIZON = np.array([190, 210, 228], float)
GRASS = np.array([78, 118, 58], float)
GROUND_HAZE = np.array([150, 165, 160], float)
ASPHALT = (88, 88, 92)
MARKING = (228, 228, 220)
VEHICLE_COLOUR = np.array([200, 30, 30], float)  # red: no scenery colour is red-dominant
WINDOW_COLOUR = np.array([45, 52, 64], float)
WINDOW_BAND = (0.85, 1.35)  # m, window glass heights on vehicle boxes (looks; the box stays the shape)
WINDOW_INSET = 0.12  # fraction of each side left as body at either end of the window band
SEGMENT_COLOURS = {"guard_rail": [[170, 172, 178]],
                   "building": [[176, 162, 138], [150, 150, 156], [168, 140, 116], [196, 186, 160], [128, 132, 140]]}
CIRCLE_COLOURS = {"pole": [[70, 70, 74]], "sign_post": [[120, 122, 130]], "tree": [[96, 72, 48], [46, 96, 42]]}
TREE_TRUNK_FRACTION = 0.35  # trees: lower part drawn as trunk (brown), the rest as crown (green); same silhouette
SUN = np.array([0.45, -0.89])  # unit horizontal direction towards the sun (world x, y), for face shading


# ================================================================================================ specifications
@dataclass(frozen=True)
class CameraSpec:
    """One pinhole camera: image size (px), horizontal field of view, mount pose on the ego and render range.

    ``height``/``width`` px (default 66×200, PilotNet's input); ``hfov_deg`` horizontal FOV (deg; 70° makes a 4 m
    lane fill about a third of the bottom row); ``mount_height`` m above ground; ``pitch_deg`` down (deg; digest
    001 §8.5 says 5–10°); ``lateral_offset`` m (+ = right); ``forward_offset`` m ahead of the vehicle centre
    (windshield of a 5 m car); ``yaw_deg`` extra yaw (+ = right, deg); ``max_range`` m, ground and objects further
    than this are not drawn; ``supersample`` internal resolution factor (anti-aliasing)."""

    height: int = 66
    width: int = 200
    hfov_deg: float = 70.0
    mount_height: float = 1.4
    pitch_deg: float = 8.0
    lateral_offset: float = 0.0
    forward_offset: float = 0.5
    yaw_deg: float = 0.0
    max_range: float = 80.0
    supersample: int = 2

    def __post_init__(self) -> None:
        if self.height < 2 or self.width < 2:
            raise ValueError(f"camera image must be at least 2x2 px, got {self.height}x{self.width}")
        if not 1.0 <= self.hfov_deg <= 170.0:
            raise ValueError(f"hfov_deg must be in [1, 170], got {self.hfov_deg}")
        if not (self.mount_height > 0 and self.max_range > NEAR_PLANE):
            raise ValueError("mount_height must be > 0 and max_range > the near plane")
        if not (isinstance(self.supersample, int) and 1 <= self.supersample <= 8):
            raise ValueError(f"supersample must be an int in [1, 8], got {self.supersample!r}")

    @property
    def hfov(self) -> float:
        """Horizontal field of view (rad)."""
        return math.radians(self.hfov_deg)

    @property
    def pitch(self) -> float:
        """Downward pitch (rad)."""
        return math.radians(self.pitch_deg)

    @property
    def yaw(self) -> float:
        """Yaw relative to the vehicle heading (rad, + = right)."""
        return math.radians(self.yaw_deg)

    @property
    def focal(self) -> float:
        """Focal length in output pixels."""
        return (self.width / 2) / math.tan(self.hfov / 2)

    @property
    def horizon_row(self) -> float:
        """Image row (output px, 0 = top, pixel centres at integers) of the horizon."""
        return (self.height - 1) / 2 - self.focal * math.tan(self.pitch)


def camera_rig(base: CameraSpec | None = None, d: float = WINDSHIELD_HALF_WIDTH) -> dict[str, CameraSpec]:
    """Left, centre and right cameras: ``base`` moved to lateral offsets −d, 0, +d (m)."""
    base = base or CameraSpec()
    return {name: replace(base, lateral_offset=base.lateral_offset + k * d)
            for name, k in zip(CAMERA_NAMES, (-1.0, 0.0, 1.0))}


@dataclass(frozen=True)
class Weather(Params):
    """Deterministic viewing conditions applied by :func:`render_view` (a section of :class:`CamerasParams`)."""

    fog_visibility: float | None = param(None, "m", gt=0, doc="meteorological visibility V, null = clear; "
                                         "transmission t = exp(-3.912 d / V) (Koschmieder; our choice of a "
                                         "distance-dependent t: at 120 m, t = 0.72 / 0.52 / 0.27 at 10 / 20 / 40 "
                                         "m, around digest 000's suggested global t = 0.4-0.8)")
    fog_airlight: float = param(200.0, "8-bit", ge=0, le=255, doc="airlight grey level A (our choice)")
    night: bool = param(False, doc="darken and gamma")
    night_ambient: float = param(0.4, ge=0, le=1, doc="night brightness factor (digest 000: x0.3-0.5)")
    night_gamma: float = param(1.8, gt=0, doc="night gamma (digest 000: 1.5-2.2)")
    headlights: bool = param(True, doc="at night, low-beam pools ahead of the ego (our choice: about ±25° wide, "
                                       "falling off as 1/(1 + (d/20 m)²))")

    @property
    def needs_depth(self) -> bool:
        return self.fog_visibility is not None or self.night


@dataclass(frozen=True)
class CameraNoise(Params):
    """Random sensor noise, all drawn from the wrapper's generator (a section of :class:`CamerasParams`). Applied
    in this order: exposure (brightness, contrast, camera_gain), blur, pixel noise, clip to [0, 255], round."""

    pixel_std: float = param(3.0, "8-bit", ge=0, doc="per-frame Gaussian pixel noise by day, independent per pixel "
                                                     "and channel (digest 000: 2-8)")
    night_pixel_std: float = param(12.0, "8-bit", ge=0, doc="pixel noise at night (digest 000: 8-20)")
    brightness: float = param(15.0, "8-bit", ge=0, doc="per-episode offset, uniform in ±this (our choice)")
    contrast: float = param(0.15, ge=0, lt=1, doc="per-episode gain about mid-grey 128, uniform in 1 ± this (our "
                                                  "choice)")
    camera_gain: float = param(0.10, ge=0, lt=1, doc="per-episode, per-camera gain, uniform in 1 ± this (digest "
                                                     "000: inter-camera exposure mismatch ±10 %)")
    blur_sigma: float = param(0.0, "px", ge=0, doc="Gaussian blur σ in output pixels; 0 = off (our choice)")


@dataclass
class StaticScene:
    """The episode's static geometry in world coordinates (m), flattened into arrays for vectorised culling.

    ``road`` (Q, 4, 2) asphalt quads and ``road_group`` (Q,) lane index; ``marks`` (M, 4, 2) painted quads and
    ``mark_group`` (M,) lane-side index; ``walls`` (P, 4, 3) vertical quads ``[x, y, z]`` with ``wall_colour``
    (P, 3) RGB and ``wall_group`` (P,) the roadside segment each piece belongs to; ``posts`` (K, 3) ``[x, y, radius]``, ``post_height`` (K,), ``post_kind`` (K,) index into
    :data:`CIRCLE_KINDS`. ``*_centre`` (·, 2) are centroids for range culling and depth sorting."""

    road: np.ndarray
    road_group: np.ndarray
    marks: np.ndarray
    mark_group: np.ndarray
    walls: np.ndarray
    wall_colour: np.ndarray
    posts: np.ndarray
    post_height: np.ndarray
    post_kind: np.ndarray
    wall_group: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.road_centre = self.road.mean(1) if len(self.road) else np.zeros((0, 2))
        self.mark_centre = self.marks.mean(1) if len(self.marks) else np.zeros((0, 2))
        self.wall_centre = self.walls[:, :2, :2].mean(1) if len(self.walls) else np.zeros((0, 2))
        if self.wall_group is None:
            self.wall_group = np.arange(len(self.walls))

    def near(self, xy: np.ndarray, radius: float, ground: bool = True) -> StaticScene:
        """The part of the scene whose pieces are within ``radius`` m of ``xy`` (shared by a rig's cameras);
        ``ground=False`` leaves out the asphalt and markings (the texture renderer does not need them)."""
        def keep(centre: np.ndarray) -> np.ndarray:
            return np.einsum("ij,ij->i", centre - xy, centre - xy) <= radius * radius

        if ground:
            r, m = keep(self.road_centre), keep(self.mark_centre)
        else:
            r, m = np.zeros(len(self.road), bool), np.zeros(len(self.marks), bool)
        w = keep(self.wall_centre)
        p = keep(self.posts[:, :2]) if len(self.posts) else np.zeros(0, bool)
        return StaticScene(self.road[r], self.road_group[r], self.marks[m], self.mark_group[m], self.walls[w],
                           self.wall_colour[w], self.posts[p], self.post_height[p], self.post_kind[p],
                           self.wall_group[w])


def _lane_points(lane: AbstractLane, s: np.ndarray, lat: float) -> np.ndarray:
    return np.array([lane.position(float(si), lat) for si in s], dtype=float)


def _strip(lane: AbstractLane, s: np.ndarray, lat0: float, lat1: float) -> np.ndarray:
    """Quads (len(s)−1, 4, 2) covering lateral band [lat0, lat1] between consecutive stations ``s``."""
    p0, p1 = _lane_points(lane, s, lat0), _lane_points(lane, s, lat1)
    return np.stack([p0[:-1], p0[1:], p1[1:], p1[:-1]], 1)


def build_scene(env: gym.Env) -> StaticScene:
    """Asphalt, markings and roadside scenery of ``env``'s current episode (see :class:`StaticScene`)."""
    unwrapped = env.unwrapped
    road, road_g, marks, mark_g = _road_quads(unwrapped.road.network)
    world = roadside_world(env)
    walls, colours, wall_g = [], [], []
    for i, ((x0, y0, x1, y1), h, k) in enumerate(zip(world.segments, world.segment_height, world.segment_kind)):
        p0, p1 = np.array([x0, y0]), np.array([x1, y1])
        length = float(np.linalg.norm(p1 - p0))
        if length < 1e-6:
            continue
        n = max(1, int(np.ceil(length / WALL_PIECE)))
        pts = p0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (p1 - p0)
        normal = np.array([-(y1 - y0), x1 - x0]) / length
        palette = SEGMENT_COLOURS[SEGMENT_KINDS[k]]
        colour = np.array(palette[i % len(palette)], float) * (0.65 + 0.35 * abs(normal @ SUN))
        for a, b in zip(pts[:-1], pts[1:]):
            walls.append([[*a, 0.0], [*b, 0.0], [*b, h], [*a, h]])
            colours.append(colour)
            wall_g.append(i)

    return StaticScene(road, road_g, marks, mark_g, np.array(walls, float).reshape(-1, 4, 3),
                       np.array(colours, float).reshape(-1, 3), world.circles.reshape(-1, 3).astype(float),
                       world.circle_height.astype(float), world.circle_kind.astype(int), np.array(wall_g, int))


_ROADS: dict[tuple, tuple] = {}  # road quads per road geometry (a layout), shared by every episode on it


def _road_quads(network) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Asphalt quads (Q, 4, 2) with their lane index (Q,), marking quads (M, 4, 2) with their lane-side index (M,)
    of a road network. highway-env builds a new network every episode, but its geometry is the layout's: the quads
    are kept per geometry (:func:`av_gym.sensors.world.geometry_key` and each lane's line types; ~10 ms per
    episode of ``lane.position`` calls otherwise)."""
    lanes = network.lanes_list()
    key = geometry_key(lanes, tuple(tuple(int(t) for t in lane.line_types) for lane in lanes))
    cached = _ROADS.get(key)
    if cached is not None:
        return cached
    road, road_g, marks, mark_g = [], [], [], []
    for g, lane in enumerate(lanes):
        w = float(lane.width_at(0.0))
        s = np.linspace(0.0, lane.length, max(1, int(np.ceil(lane.length / ROAD_STEP))) + 1)
        q = _strip(lane, s, -w / 2, w / 2)
        road.append(q)
        road_g.append(np.full(len(q), g))
        for side, line_type in enumerate(lane.line_types):  # side 0 = left (lat −w/2), 1 = right (lat +w/2)
            lat = (side - 0.5) * w
            if line_type in (LineType.CONTINUOUS, LineType.CONTINUOUS_LINE):
                q = _strip(lane, s, lat - MARKING_WIDTH / 2, lat + MARKING_WIDTH / 2)
            elif line_type == LineType.STRIPED:
                pieces = []
                for a in np.arange(0.0, lane.length, DASH_PERIOD):
                    b = min(a + DASH_LENGTH, lane.length)
                    ds = np.linspace(a, b, max(1, int(np.ceil((b - a) / 1.5))) + 1)  # ≤1.5 m chords on tight arcs
                    pieces.append(_strip(lane, ds, lat - MARKING_WIDTH / 2, lat + MARKING_WIDTH / 2))
                q = np.concatenate(pieces) if pieces else np.zeros((0, 4, 2))
            else:
                continue
            marks.append(q)
            mark_g.append(np.full(len(q), 2 * g + side))

    def cat(parts: list, shape: tuple) -> np.ndarray:
        return np.concatenate(parts).astype(float) if parts else np.zeros(shape)

    out = (cat(road, (0, 4, 2)), cat(road_g, (0,)).astype(int), cat(marks, (0, 4, 2)), cat(mark_g, (0,)).astype(int))
    for a in out:
        a.flags.writeable = False  # shared by every episode on this layout
    if len(_ROADS) >= 8:
        _ROADS.pop(next(iter(_ROADS)))
    _ROADS[key] = out
    return out


def scene_of(env: gym.Env) -> StaticScene:
    """This episode's :class:`StaticScene`, built once per episode and cached on the unwrapped env."""
    unwrapped = env.unwrapped
    key = (id(unwrapped.road), getattr(unwrapped, "episode_seed", None))
    cached = getattr(unwrapped, "_camera_scene", None)
    if cached is None or cached[0] != key:
        unwrapped._camera_scene = (key, build_scene(unwrapped))
    return unwrapped._camera_scene[1]


# ================================================================================================ ground texture
@dataclass(frozen=True)
class GroundTexture:
    """Top-down picture of the map's ground (asphalt and markings), one byte per ``res`` × ``res`` m texel:
    0 = grass (nothing painted), 128 = asphalt, 255 = marking; texel ``(row, col)`` has its centre at world
    ``(x0 + col·res, y0 + row·res)``. Intermediate values come from bilinear sampling at edges and are mapped to
    colours by :data:`_GROUND_LUT` (grass → asphalt → marking), the grass showing the camera's own hazed
    background."""

    texels: np.ndarray
    x0: float
    y0: float
    res: float


_TEXTURES: dict[bytes, GroundTexture] = {}  # one per road geometry (a layout), shared by every episode on it


def ground_texture(scene: StaticScene, res: float = TEXTURE_RES) -> GroundTexture:
    """The :class:`GroundTexture` of ``scene``'s asphalt and markings (built once per road geometry, ~20 MB for a
    lap layout at 4 cm). Drawn with the same polygons as the raster renderer, so both show the same road."""
    import hashlib

    cached = getattr(scene, "_texture", None)
    if cached is not None and cached.res == res:
        return cached
    key = hashlib.blake2b(scene.road.tobytes() + scene.marks.tobytes() + np.float64(res).tobytes(),
                          digest_size=16).digest()
    tex = _TEXTURES.get(key)
    if tex is None:
        pts = np.concatenate([scene.road.reshape(-1, 2), scene.marks.reshape(-1, 2)])
        lo = np.floor(pts.min(0)) - 1.0 if len(pts) else np.zeros(2)
        hi = np.ceil(pts.max(0)) + 1.0 if len(pts) else np.ones(2)
        w, h = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
        texels = np.zeros((h, w), np.uint8)
        for quads, groups, value in ((scene.road, scene.road_group, 128), (scene.marks, scene.mark_group, 255)):
            if not len(quads):
                continue
            px = np.round((quads - lo) / res * (1 << _SHIFT)).astype(np.int32)
            # one fillPoly per group (quads of a group never overlap; the even-odd rule would punch holes)
            bounds = np.concatenate([[0], np.flatnonzero(np.diff(groups)) + 1, [len(groups)]])
            for a, b in zip(bounds[:-1], bounds[1:]):
                cv2.fillPoly(texels, px[a:b], value, cv2.LINE_8, _SHIFT)
        if len(_TEXTURES) >= 4:
            _TEXTURES.pop(next(iter(_TEXTURES)))
        tex = _TEXTURES[key] = GroundTexture(texels, float(lo[0]), float(lo[1]), float(res))
    scene._texture = tex
    return tex


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


def _scenery_state(scene: StaticScene) -> dict:
    """The roadside vertical things of ``scene`` as :func:`raster.rig_quads` takes them, built once per scene:
    wall pieces' ends, every item's bounding circle, bottom and top heights (m) and RGBA colour; walls first, then
    poles and trunks, then tree crowns (after their trunks: same key, later in the stable far-to-near sort)."""
    st = getattr(scene, "_rig_scenery", None)
    if st is None:
        tree = scene.post_kind == CIRCLE_KINDS.index("tree")
        h = scene.post_height
        z_top = np.where(tree, h * TREE_TRUNK_FRACTION, h)
        kind_colour = np.array([CIRCLE_COLOURS[k][0] for k in CIRCLE_KINDS], float)
        crown = np.flatnonzero(tree)
        item = np.concatenate([np.arange(len(h)), crown]).astype(int)  # which post each cylinder quad stands on
        nw = len(scene.walls)
        colour = np.concatenate([scene.wall_colour.reshape(-1, 3), kind_colour[scene.post_kind].reshape(-1, 3),
                                 np.tile(np.array(CIRCLE_COLOURS["tree"][1], float), (len(crown), 1))])
        colour = np.round(np.clip(colour, 0, 255)).astype(np.int64)
        w = scene.walls.reshape(-1, 4, 3)
        st = scene._rig_scenery = dict(
            nw=nw, ends=np.concatenate([w[:, 0, :2], w[:, 1, :2]], 1),  # (P, 4): A and B of each wall piece
            centre=np.concatenate([scene.wall_centre.reshape(-1, 2), scene.posts[item, :2].reshape(-1, 2)]),
            radius=np.concatenate([np.hypot(*(w[:, 1, :2] - w[:, 0, :2]).T) / 2, scene.posts[item, 2]]),
            z0=np.concatenate([w[:, 0, 2], np.zeros(len(h)), z_top[crown]]),
            z1=np.concatenate([w[:, 2, 2], z_top, h[crown]]),
            colour=np.concatenate([colour, np.full((len(colour), 1), 255)], 1))
    return st


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


def _vertical_quads(a: np.ndarray, b: np.ndarray, z0: np.ndarray, z1: np.ndarray) -> np.ndarray:
    """Quads (N, 4, 3) standing on ground segments a→b (N, 2) from height z0 to z1 (N,)."""
    return np.stack([np.column_stack([a, z0]), np.column_stack([b, z0]),
                     np.column_stack([b, z1]), np.column_stack([a, z1])], 1)


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

    Measured and not taken (second pass, OpenCV painter): merging runs of neighbouring wall pieces into one quad
    where no quad in between overlaps them removed only ~12 of 55-65 wall quads per camera, since the roadside
    walls are chains of short straight segments, and its overlap test cost more than the fills saved."""
    x, y, psi = float(pose[0]), float(pose[1]), float(pose[2])
    cf, sf = math.cos(psi), math.sin(psi)
    specs = list(cameras.values())
    base = specs[0]
    shared = _shared_geometry(cameras)
    lats = np.array([sp.lateral_offset for sp in specs])
    reach = max(spec.max_range for spec in specs)
    st = _scenery_state(scene)
    lo, hi = float(lats.min()), float(lats.max())
    fa, fb, fz, keys, colours, kind, nrm, nm = raster.rig_quads(
        st["ends"], st["centre"], st["radius"], st["z0"], st["z1"], st["colour"], st["nw"],
        np.asarray(pose, float), base.forward_offset, base.mount_height, base.pitch,
        (base.width / 2 + 1) / base.focal, reach, shared is not None, lo, hi, NEAR_PLANE,
        np.ascontiguousarray(others, float) if len(others) else np.zeros((0, 7)), _VEHICLE_LOOK)
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
    kept as the reference for ``docs/cameras/compare_renderers.py`` and the tests). Returns name → (H, W, 3)
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


@lru_cache(maxsize=1)
def _noise_bank() -> np.ndarray:
    """:data:`NOISE_BANK_SIZE` float32 standard normals from a generator seeded with :data:`NOISE_BANK_SEED`."""
    return np.random.default_rng(NOISE_BANK_SEED).standard_normal(NOISE_BANK_SIZE, dtype=np.float32)


# Pixels rendered per camera and frame (height x width x supersample²): the renderer holds a few float arrays of this
# size per camera; 2**23 (e.g. 1024 x 2048 at supersample 2) is ~0.2 GB per camera, where 10000 x 10000 asked for
# 8.9 GiB (issue 31). PilotNet's input is 66 x 200.
RENDER_PIXELS_MAX = 2**23


# ================================================================================================ the wrapper
@dataclass(frozen=True)
class CamerasParams(Params):
    """Three windshield cameras, left/centre/right (digest 001 §2, §8.5; 000 §5.7); see :class:`CameraSpec`."""

    height: int = param(66, "px", ge=2, le=2160, doc="image height (PilotNet input, paper 001 Table 1); <= 4K")
    width: int = param(200, "px", ge=2, le=3840, doc="image width (PilotNet input); <= 4K")
    hfov_deg: float = param(70.0, "deg", ge=1, le=170, doc="horizontal field of view (our choice: a 4 m lane "
                                                           "fills about a third of the bottom row)")
    mount_height: float = param(1.4, "m", gt=0, doc="lens height above the ground")
    pitch_deg: float = param(8.0, "deg", gt=-90, lt=90, doc="downward pitch (digest 001 §8.5: 5-10°)")
    lateral_offset: float = param(WINDSHIELD_HALF_WIDTH, "m", doc="side cameras at ±this across the windshield "
                                                                  "(half a windshield; 001 suggests 0.8-1.0)")
    forward_offset: float = param(0.5, "m", doc="ahead of the vehicle centre (the windshield of a 5 m car)")
    max_range: float = param(80.0, "m", gt=0, doc="nothing is drawn beyond")
    supersample: int = param(2, ge=1, le=8, doc="render at this factor, shrink with area averaging "
                                                "(anti-aliasing)")
    rate_hz: float | None = param(None, "Hz", gt=0, le=RATE_MAX_HZ, doc="capture rate; null = every policy step; lower values hold "
                                                        "the last frame")
    noise: CameraNoise | None = param(CameraNoise(), doc="sensor noise; null = clean renders (bit-identical to "
                                                         "render_views)")
    fog_visibility: float | None = param(None, "m", gt=0, doc="fog visibility (null = clear); see Weather")
    night: bool = param(False, doc="night-time rendering; see Weather")
    weather: Weather | None = param(None, doc="a full Weather section; overrides fog_visibility and night")
    views: tuple[Literal["left", "centre", "right"], ...] = param(
        CAMERA_NAMES, doc="the cameras rendered (camera_centre: [centre]). The per-episode exposure is drawn for "
                          "all three whatever the subset, so a subset's camera has the same exposure as in the rig")

    def relations(self) -> list[str]:
        if not self.views:
            return [f"@views must be a non-empty subset of {list(CAMERA_NAMES)}, got []"]
        rendered = self.height * self.width * self.supersample**2
        if rendered > RENDER_PIXELS_MAX:
            return [f"@height x @width x @supersample² must be at most {RENDER_PIXELS_MAX} rendered pixels per "
                    f"camera, got {self.height} x {self.width} x {self.supersample}² = {rendered}"]
        return []


class Cameras(SensorWrapper):
    """Adds ``obs["cameras"] = {"left", "centre", "right"}``: three (H, W, 3) uint8 RGB windshield images (or the
    subset named by ``views``); parameters: :class:`CamerasParams`. From Python, ``noise`` may also be ``True``
    (the defaults) or ``False`` (clean renders), and ``noise``/``weather`` instances.

    Building one sets OpenCV to one thread for the process (``cv2.setNumThreads(1)``): its thread pool splits each
    66×200 remap and colour conversion across cores, which bought 0.05 ms of a 3.2 ms left-turn `full` step for
    0.8 ms more CPU on 2 idle cores (session 27; ``python benchmarks/sensor_cost.py``), and an RL run steps one
    environment per core anyway."""

    key = "cameras"
    Params = CamerasParams

    def __init__(self, env: gym.Env, params: CamerasParams | None = None, **overrides) -> None:
        if isinstance(overrides.get("noise"), bool):
            overrides["noise"] = CameraNoise().as_dict() if overrides["noise"] else None
        for key in ("noise", "weather"):  # sections given as instances: checked as their fields
            if isinstance(overrides.get(key), Params):
                overrides[key] = overrides[key].as_dict()
        p = self.params = CamerasParams.build(params, **overrides)
        base = CameraSpec(height=int(p.height), width=int(p.width), hfov_deg=float(p.hfov_deg),
                          mount_height=float(p.mount_height), pitch_deg=float(p.pitch_deg),
                          forward_offset=float(p.forward_offset), max_range=float(p.max_range),
                          supersample=int(p.supersample))
        rig = camera_rig(base, float(p.lateral_offset))
        self.specs = {name: rig[name] for name in CAMERA_NAMES if name in p.views}
        self.weather = p.weather or Weather(fog_visibility=p.fog_visibility, night=bool(p.night))
        self.noise: CameraNoise | None = p.noise
        self.rate_hz = p.rate_hz
        cv2.setNumThreads(1)
        super().__init__(env)
        self._exposure = {name: (1.0, 0.0) for name in CAMERA_NAMES}  # name → (gain, offset)
        self._held: dict[str, np.ndarray] | None = None
        self._next_capture = 0.0

    def sensor_space(self) -> spaces.Dict:
        return spaces.Dict({name: spaces.Box(0, 255, (spec.height, spec.width, 3), np.uint8)
                            for name, spec in self.specs.items()})

    def on_reset(self) -> None:
        self._held, self._next_capture = None, 0.0
        n = self.noise
        if n is None:
            return
        # Per-episode exposure: I' = ((I − 128)·contrast + 128 + brightness)·gain_k = I·g + o per camera.
        brightness = self.rng.uniform(-n.brightness, n.brightness)
        contrast = self.rng.uniform(1 - n.contrast, 1 + n.contrast)
        gains = self.rng.uniform(1 - n.camera_gain, 1 + n.camera_gain, size=len(CAMERA_NAMES))
        self._exposure = {name: (float(contrast * g), float((128.0 * (1 - contrast) + brightness) * g))
                          for name, g in zip(CAMERA_NAMES, gains)}

    def _noisy(self, name: str, clean: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
        """Exposure, blur and pixel noise on one clean frame; ``noise`` (H, W, 3) float32 standard normals (see
        :meth:`_pixel_noise`), None without pixel noise."""
        n = self.noise
        gain, offset = self._exposure[name]
        sigma = n.night_pixel_std if self.weather.night else n.pixel_std
        im = clean.astype(np.float32)
        if n.blur_sigma > 0:
            im = cv2.GaussianBlur(im * np.float32(gain) + np.float32(offset), (0, 0), n.blur_sigma)
            gain, offset = 1.0, 0.0
        # exposure, pixel noise, rounding and clipping to [0, 255] in one OpenCV pass (saturate_cast rounds to
        # nearest)
        return cv2.addWeighted(im, float(gain), im if noise is None else noise, float(sigma) if noise is not None
                               else 0.0, float(offset), dtype=cv2.CV_8U)

    def _pixel_noise(self) -> dict[str, np.ndarray] | None:
        """This frame's standard normals, name → (H, W, 3) float32, or None when the pixel noise is off.

        Drawing 40k Gaussians per 66x200 camera cost as much as rendering it (~0.15-0.4 ms), so they come from a
        bank of :data:`NOISE_BANK_SIZE` standard normals drawn once per process from a generator seeded with
        :data:`NOISE_BANK_SEED`: each frame the wrapper's generator draws one uniform offset and the rig's cameras
        take consecutive windows of the bank from there. Within a frame every value is a distinct draw, so each
        pixel, channel and camera is independent N(0, 1) as before. Across frames the offsets are independent,
        so a pixel's noise in two frames is the same value only if the offsets coincide (probability 1/2^21) and
        its correlation between frames is ~0 (tested); but two frames whose offsets are closer than the rig's
        pixel count (about 2·119k/2^21 ≈ 11 % of frame pairs for the 3 x 66x200 rig) share part of their noise
        pattern shifted by the offset difference, and an episode's noise patterns are windows of one fixed 8 MB
        bank. Images too large for the bank (over half of it) draw their normals directly."""
        n = self.noise
        if (n.night_pixel_std if self.weather.night else n.pixel_std) <= 0:
            return None
        sizes = [spec.height * spec.width * 3 for spec in self.specs.values()]
        total = sum(sizes)
        if total > NOISE_BANK_SIZE // 2:
            return {name: self.rng.standard_normal((spec.height, spec.width, 3), dtype=np.float32)
                    for name, spec in self.specs.items()}
        start = int(self.rng.integers(0, NOISE_BANK_SIZE - total + 1))
        bank, out = _noise_bank(), {}
        for (name, spec), size in zip(self.specs.items(), sizes):
            out[name] = bank[start:start + size].reshape(spec.height, spec.width, 3)
            start += size
        return out

    def measure(self) -> dict[str, np.ndarray]:
        t = sim_time(self.env)
        if self.rate_hz is not None and self._held is not None and t < self._next_capture - 1e-9:
            return {name: img.copy() for name, img in self._held.items()}  # frame hold between captures
        if self.rate_hz is not None:
            period = 1.0 / self.rate_hz
            while self._next_capture <= t + 1e-9:
                self._next_capture += period
        frames = render_views(self.env, self.specs, weather=self.weather)
        if self.noise is not None:
            noise = self._pixel_noise()
            frames = {name: self._noisy(name, frames[name], None if noise is None else noise[name])
                      for name in self.specs}
        self._held = frames
        return {name: img.copy() for name, img in frames.items()} if self.rate_hz is not None else frames


__all__ = ["CAMERA_NAMES", "WINDSHIELD_HALF_WIDTH", "VEHICLE_HEIGHT", "CameraSpec", "Weather", "CameraNoise",
           "Cameras", "CamerasParams", "StaticScene", "build_scene", "scene_of", "camera_rig", "render_view",
           "render_views"]
