"""The cameras' world (:mod:`av_gym.sensors.camera`'s module docstring has the geometry and the drawing order):
the camera and rig specs, the look (colours, sizes), the conditions (:class:`Weather`), and the scene built once per
map: the road's asphalt and marking quads (:func:`build_scene`), the top-down ground texture they are sampled from
(:func:`ground_texture`) and the roadside scenery arrays the compiled painter culls (:func:`_scenery_state`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import gymnasium as gym
import numpy as np
from highway_env.road.lane import AbstractLane, LineType

from av_gym.params import Params, param
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


@dataclass(frozen=True)
class RigScenery:
    """The roadside vertical things of a scene as the compiled painter takes them (:func:`raster.rig_quads`),
    walls first, then poles and trunks, then tree crowns (after their trunks: same key, later in the stable
    far-to-near sort). ``P`` items, the first ``nw`` walls."""

    nw: int  # wall pieces
    ends: np.ndarray  # (nw, 4) each wall piece's ends A, B (world x, y, m)
    centre: np.ndarray  # (P, 2) bounding circles' centres (m)
    radius: np.ndarray  # (P,) bounding circles' radii (m)
    z0: np.ndarray  # (P,) bottom heights (m)
    z1: np.ndarray  # (P,) top heights (m)
    colour: np.ndarray  # (P, 4) RGBA


def _scenery_state(scene: StaticScene) -> RigScenery:
    """``scene``'s :class:`RigScenery`, built once per scene."""
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
        st = scene._rig_scenery = RigScenery(
            nw=nw, ends=np.concatenate([w[:, 0, :2], w[:, 1, :2]], 1),
            centre=np.concatenate([scene.wall_centre.reshape(-1, 2), scene.posts[item, :2].reshape(-1, 2)]),
            radius=np.concatenate([np.hypot(*(w[:, 1, :2] - w[:, 0, :2]).T) / 2, scene.posts[item, 2]]),
            z0=np.concatenate([w[:, 0, 2], np.zeros(len(h)), z_top[crown]]),
            z1=np.concatenate([w[:, 2, 2], z_top, h[crown]]),
            colour=np.concatenate([colour, np.full((len(colour), 1), 255)], 1))
    return st


def _vertical_quads(a: np.ndarray, b: np.ndarray, z0: np.ndarray, z1: np.ndarray) -> np.ndarray:
    """Quads (N, 4, 3) standing on ground segments a→b (N, 2) from height z0 to z1 (N,)."""
    return np.stack([np.column_stack([a, z0]), np.column_stack([b, z0]),
                     np.column_stack([b, z1]), np.column_stack([a, z1])], 1)
