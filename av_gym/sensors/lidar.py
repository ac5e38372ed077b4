"""A ray-cast LiDAR point cloud: a roof-mounted scanner that sees other vehicles and the roadside world.

Not highway-env's ``LidarObservation`` (16 world-aligned sectors of the nearest *vehicle*, useless for scan
matching, digest 002 §6.2): this casts ``beams`` azimuths × ``len(elevations_deg)`` channels against

- other vehicles: oriented boxes from :func:`others_state`, ``vehicle_height`` m tall;
- the roadside world of :func:`roadside_world`: vertical walls over 2-D segments (guard rails, building fronts)
  and vertical cylinders (poles, sign posts, trees), each with its own height.

Objects are first culled by range and by the angular span of their bounding circle, then only the (beam, object)
pairs that can intersect are solved. The numpy code here is the reference; by default the same culling and formulas
run as numba kernels (:mod:`av_gym.sensors.kernels`, switch ``KERNELS``; bit-identical), and a 720-beam scan costs
about 0.2 ms (numpy: about 1 ms) at the left turn (benchmarks/sensor_kernels.py).

Frames
------
- World: highway-env's, x right and y *down* on the screen, heading measured from +x towards +y. With z pointing
  up out of the ground this frame is left-handed.
- Sensor (what :meth:`Lidar.points` returns): right-handed, origin at the sensor (``mount_x`` m ahead of the
  vehicle centre, ``mount_height`` m above the ground), **x forward, y left, z up**, as kiss-icp and ROS (REP 103)
  expect. A world offset (dx, dy) from the sensor maps to x = dx·cosψ + dy·sinψ, y = dx·sinψ − dy·cosψ: the sign
  flip of y is the change of handedness.
- Azimuth φ is measured in the sensor frame from +x towards +y (counter-clockwise seen from above), so a beam at
  azimuth φ points along the world heading ψ − φ.

Scan model
----------
- Observation ``obs["lidar"]``: ``Box(0, max_range, (E, B), float32)`` slant ranges (m) along each beam, channel
  (elevation) major, beam ``k`` at azimuth ``-fov/2 + offset + k·fov/B``. Beams without a return (nothing hit
  within ``max_range``, a dropout, or a hit closer than ``min_range``) read exactly ``max_range``; so do valid
  returns that noise pushes to or past it. Never NaN or inf.
- A single 0° channel (the default) is a **planar 2-D scan** (digest 002 §6.2: points ``[r cos φ, r sin φ, 0]``)
  that sees every object whatever its height: a horizontal beam at the thesis's 1.7 m mount would otherwise fly
  over the 1.5 m cars and 0.8 m guard rails and see only poles, trees and buildings. With several channels
  (``planar=False``, the default for them) a beam at elevation e hits an object at horizontal range r only if
  z = mount_height + r·tan(e) lies within [0, object height]; downward beams can also hit an object's top face.
- There are **no ground returns**: each elevation ring on a flat ground is a sensor-centred circle, identical from
  scan to scan, which pulls scan matching towards zero motion (digest 002 §6.2 step 3, prototype observation).
  A downward beam that reaches the ground is simply absorbed (no return).
- The ego itself is not in the scene (a real sensor's self-hits are what ``min_range`` removes).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.geometry import box_corners
from av_gym.params import RATE_MAX_HZ, Params, param
from av_gym.sensors import kernels as _kernels
from av_gym.sensors.base import SensorWrapper, ego_pose, others_state, sim_time
from av_gym.sensors.world import roadside_world

TWO_PI = 2.0 * np.pi
KERNELS = {"cast", "points"}
"""Which parts run as numba kernels (:mod:`av_gym.sensors.kernels`, bit-identical to the numpy code here, which
stays as their reference): ``cast`` the ray cast of :func:`_cast` and the other vehicles' boxes, ``points`` the
noisy returns, observation and point cloud of a scan (:func:`_scan_points`)."""
LABEL_STATIC, LABEL_VEHICLE = 0, 1
"""Per-point labels of :meth:`Lidar.labels`: the roadside world, or another vehicle."""


# --------------------------------------------------------------------------------------------------- ray casting
def _candidate_pairs(origin: np.ndarray, slack: float, centers: np.ndarray, radii: np.ndarray,
                     angles: np.ndarray, max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """(object index, beam index) pairs whose ray may hit the object, each ``(P,)`` int.

    An object is kept if its bounding circle (``centers`` (M, 2), ``radii`` (M,) m), inflated by ``slack`` m (how
    far the per-beam origins stray from ``origin``), starts within ``max_range``; then it is paired only with the
    beams inside the angular span of that circle as seen from ``origin``. This is what makes a scan cheap: a 2 m
    guard-rail chord 20 m away covers ~6 of 720 beams instead of all of them.
    """
    d_vec = centers - origin
    dist = np.hypot(d_vec[:, 0], d_vec[:, 1])
    r = radii + slack
    keep = np.flatnonzero(dist - r < max_range)
    if keep.size == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    dist, r, d_vec = dist[keep], r[keep], d_vec[keep]
    with np.errstate(divide="ignore", invalid="ignore"):
        half = np.where(dist > r, np.arcsin(np.clip(r / dist, 0.0, 1.0)), np.pi)  # origin inside: every beam
    centre_angle = np.arctan2(d_vec[:, 1], d_vec[:, 0])

    n_beams = len(angles)
    order = np.argsort(np.mod(angles, TWO_PI), kind="stable")
    sorted_angles = np.mod(angles, TWO_PI)[order]
    doubled = np.concatenate([sorted_angles, sorted_angles + TWO_PI])  # spans may wrap past 2π once
    lo = np.mod(centre_angle - half, TWO_PI)
    i0 = np.searchsorted(doubled, lo, side="left")
    i1 = np.searchsorted(doubled, lo + 2.0 * half, side="right")
    counts = np.minimum(i1 - i0, n_beams)
    total = int(counts.sum())
    obj = np.repeat(keep, counts)
    first = np.repeat(i0 - (np.cumsum(counts) - counts), counts)  # i0 of the pair's object minus its offset
    beam = order[(first + np.arange(total)) % n_beams]
    return obj, beam


def _hit_ranges(t_in: np.ndarray, t_out: np.ndarray, height: np.ndarray, tan_e: np.ndarray,
                mount_height: float) -> np.ndarray:
    """Horizontal distance (m) at which each ray first meets an object, ``inf`` if it misses: ``(E, P)``.

    ``[t_in, t_out]`` (P,) is where the ray's ground track crosses the object's footprint (equal for a wall);
    ``height`` (P,) the object's height; ``tan_e`` (E,) the channels' elevation slopes. The ray is inside the
    object's vertical band [0, height] for r in [lo, hi], with hi capped where it reaches the ground (absorbed:
    no ground returns). It hits at the first r in both intervals.
    """
    tan_e = tan_e[:, None]
    h = float(mount_height)
    with np.errstate(divide="ignore", invalid="ignore"):
        r_top = (height[None, :] - h) / tan_e  # where z = height
        r_ground = -h / tan_e  # where z = 0
        lo = np.where(tan_e > 0, -np.inf, np.where(tan_e < 0, r_top, -np.inf))
        hi = np.where(tan_e > 0, r_top, np.where(tan_e < 0, r_ground, np.inf))
    # A level beam is in the band everywhere or nowhere.
    level_ok = (h >= 0.0) & (h <= height)[None, :]
    hi = np.where((tan_e == 0) & ~level_ok, -np.inf, hi)
    start = np.maximum(np.maximum(t_in[None, :], lo), 0.0)
    end = np.minimum(t_out[None, :], hi)
    return np.where(start <= end, start, np.inf)


def _ray_segments(o: np.ndarray, u: np.ndarray, seg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray (origins ``o`` (P, 2), unit directions ``u`` (P, 2)) against segments ``seg`` (P, 4): t (P,), inf = miss."""
    a, v = seg[:, 0:2], seg[:, 2:4] - seg[:, 0:2]
    w = a - o
    denom = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[:, 0] * v[:, 1] - w[:, 1] * v[:, 0]) / denom
        s = (w[:, 0] * u[:, 1] - w[:, 1] * u[:, 0]) / denom
    ok = (denom != 0) & (t >= 0) & (s >= 0) & (s <= 1)
    t = np.where(ok, t, np.inf)
    return t, t


def _ray_circles(o: np.ndarray, u: np.ndarray, circ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray against discs ``circ`` (P, 3) ``[x, y, radius]``: entry and exit t (P,), inf when missed."""
    w = circ[:, 0:2] - o
    b = w[:, 0] * u[:, 0] + w[:, 1] * u[:, 1]
    c = w[:, 0] ** 2 + w[:, 1] ** 2 - circ[:, 2] ** 2
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    t_in, t_out = b - root, b + root
    ok = (disc >= 0) & (t_out >= 0)
    return np.where(ok, t_in, np.inf), np.where(ok, t_out, -np.inf)


def _ray_boxes(o: np.ndarray, u: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray against oriented rectangles ``corners`` (P, 4, 2) (any consistent corner order): slab method in the
    box frame. Entry and exit t (P,); entry > exit when missed."""
    center = corners.mean(axis=1)
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 3] - corners[:, 0]  # two adjacent edges
    t_in = np.full(len(o), -np.inf)
    t_out = np.full(len(o), np.inf)
    for edge in (e1, e2):
        length = np.linalg.norm(edge, axis=1)
        axis = edge / length[:, None]
        half = 0.5 * length
        p = np.einsum("ij,ij->i", o - center, axis)
        d = np.einsum("ij,ij->i", u, axis)
        d = np.where(np.abs(d) < 1e-12, 1e-12, d)  # parallel to the slab: ±huge, which the min/max handle
        t1, t2 = (-half - p) / d, (half - p) / d
        t_in = np.maximum(t_in, np.minimum(t1, t2))
        t_out = np.minimum(t_out, np.maximum(t1, t2))
    return t_in, t_out


def _per_object(height: float | np.ndarray, n: int) -> np.ndarray:
    """One height per object, ``(n,)`` float (a scalar repeated, or an array broadcast), contiguous and writable
    (a read-only array would compile a second specialization of the compiled cast)."""
    height = np.asarray(height, dtype=float)
    return np.full(n, float(height)) if height.ndim == 0 else np.array(np.broadcast_to(height, (n,)))


def _cast_kernel(origin_xy: np.ndarray, angles: np.ndarray, tan_e: np.ndarray, cos_e: np.ndarray, mount_height: float,
                 segments: np.ndarray, seg_height: np.ndarray, circles: np.ndarray, circ_height: np.ndarray,
                 boxes_corners: np.ndarray, box_height: np.ndarray, max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_cast` by :func:`av_gym.sensors.kernels.cast`, on inputs already in shape: float arrays, shapes
    C-contiguous, one height per object; ``tan_e``, ``cos_e`` of the channels' elevations. The culling origin, its
    slack and the sorted beam angles are :func:`_cast`'s / :func:`_candidate_pairs`'."""
    per_beam = origin_xy.ndim == 2
    ref = origin_xy.mean(axis=0) if per_beam else origin_xy
    slack = float(np.max(np.linalg.norm(origin_xy - ref, axis=1))) if per_beam else 0.0
    sorted_mod = np.mod(angles, TWO_PI)
    order = np.argsort(sorted_mod, kind="stable")
    sorted_mod = sorted_mod[order]
    return _kernels.cast(np.ascontiguousarray(origin_xy if per_beam else origin_xy[None]), float(ref[0]),
                         float(ref[1]), slack, np.cos(angles), np.sin(angles), order,
                         np.concatenate([sorted_mod, sorted_mod + TWO_PI]), tan_e, cos_e, float(mount_height),
                         segments, seg_height, circles, circ_height, boxes_corners, box_height, float(max_range))


def _cast(origin_xy: np.ndarray, angles: np.ndarray, elevations: np.ndarray, mount_height: float,
          segments: np.ndarray, seg_height: np.ndarray, circles: np.ndarray, circ_height: np.ndarray,
          boxes_corners: np.ndarray, box_height: float | np.ndarray, max_range: float
          ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cast_rays` plus a ``(E, B)`` bool "the return is a vehicle" mask."""
    angles = np.asarray(angles, dtype=float).reshape(-1)
    elevations = np.asarray(elevations, dtype=float).reshape(-1)
    n_beams, n_ch = len(angles), len(elevations)
    origin_xy = np.asarray(origin_xy, dtype=float)
    per_beam = origin_xy.ndim == 2
    ref = origin_xy.mean(axis=0) if per_beam else origin_xy
    slack = float(np.max(np.linalg.norm(origin_xy - ref, axis=1))) if per_beam else 0.0

    segments = np.asarray(segments, dtype=float).reshape(-1, 4)
    circles = np.asarray(circles, dtype=float).reshape(-1, 3)
    boxes_corners = np.asarray(boxes_corners, dtype=float).reshape(-1, 4, 2)
    seg_height = _per_object(seg_height, len(segments))
    circ_height = _per_object(circ_height, len(circles))
    box_height = _per_object(box_height, len(boxes_corners))
    if "cast" in KERNELS:  # the same culling, pairs and formulas in one compiled loop (av_gym/sensors/kernels.py)
        return _cast_kernel(origin_xy, angles, np.tan(elevations), np.cos(elevations), mount_height,
                            np.ascontiguousarray(segments), seg_height, np.ascontiguousarray(circles), circ_height,
                            np.ascontiguousarray(boxes_corners), box_height, max_range)

    # One bounding circle per object, all kinds together, so candidates are generated in a single pass.
    seg_mid = 0.5 * (segments[:, 0:2] + segments[:, 2:4])
    seg_rad = 0.5 * np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    box_mid = boxes_corners.mean(axis=1)
    box_rad = np.linalg.norm(boxes_corners - box_mid[:, None, :], axis=2).max(axis=1, initial=0.0)
    centers = np.concatenate([seg_mid, circles[:, 0:2], box_mid])
    radii = np.concatenate([seg_rad, circles[:, 2], box_rad])
    n_seg, n_circ = len(segments), len(circles)

    best = np.full(n_ch * n_beams, np.inf)
    best_static = np.full(n_ch * n_beams, np.inf)
    if len(centers):
        obj, beam = _candidate_pairs(ref, slack, centers, radii, angles, max_range)
        u = np.stack([np.cos(angles[beam]), np.sin(angles[beam])], axis=1)
        o = origin_xy[beam] if per_beam else np.broadcast_to(origin_xy, u.shape)
        starts = np.array([0, n_seg, n_seg + n_circ, len(centers)])  # obj is sorted: segments, circles, boxes
        cut = np.searchsorted(obj, starts)
        tan_e = np.tan(elevations)
        flat = np.arange(n_ch)[:, None] * n_beams + beam[None, :]  # (E, P) index into the (E·B) result
        kinds = ((_ray_segments, segments, seg_height), (_ray_circles, circles, circ_height),
                 (_ray_boxes, boxes_corners, box_height))
        for kind, (intersect, shapes, heights) in enumerate(kinds):
            sl = slice(cut[kind], cut[kind + 1])
            if sl.stop <= sl.start:
                continue
            idx = obj[sl] - starts[kind]
            t_in, t_out = intersect(o[sl], u[sl], shapes[idx])
            r = _hit_ranges(t_in, t_out, heights[idx], tan_e, mount_height).ravel()  # (E·P',) horizontal m
            np.minimum.at(best, flat[:, sl].ravel(), r)
            if kind < 2:  # segments and circles are the static world
                np.minimum.at(best_static, flat[:, sl].ravel(), r)
    best = best.reshape(n_ch, n_beams)
    is_vehicle = best < best_static.reshape(n_ch, n_beams)
    slant = best / np.cos(elevations)[:, None]  # the range a LiDAR measures is along the beam
    ranges = np.where(slant < max_range, slant, max_range)
    return ranges, is_vehicle & (slant < max_range)


def cast_rays(origin_xy: np.ndarray, angles: np.ndarray, elevations: np.ndarray, mount_height: float,
              segments: np.ndarray, seg_height: np.ndarray, circles: np.ndarray, circ_height: np.ndarray,
              boxes_corners: np.ndarray, box_height: float | np.ndarray, max_range: float) -> np.ndarray:
    """Noise-free ranges of a multi-channel 2.5-D ray cast, ``(E, B)`` m.

    Args:
        origin_xy: sensor position (2,) m, or one per beam (B, 2) (a moving sensor over a sweep).
        angles: beam directions (B,) rad in the caller's plane frame (for the world: highway-env headings).
        elevations: channel elevations (E,) rad, + = up, |e| < π/2.
        mount_height: sensor height above the ground (m).
        segments: walls (M, 4) ``[x0, y0, x1, y1]`` m; ``seg_height`` (M,) m.
        circles: vertical cylinders (K, 3) ``[x, y, radius]`` m; ``circ_height`` (K,) m.
        boxes_corners: vehicles (N, 4, 2) m, as from :func:`av_gym.geometry.box_corners`; ``box_height`` m,
            scalar or (N,).
        max_range: m; rays that hit nothing closer (along the beam) read exactly ``max_range``.

    Returns:
        ``(E, B)`` slant range along each beam to the first surface, where a ray at elevation e meets an object at
        horizontal range r only if ``mount_height + r·tan(e)`` is within [0, height] (heights may be ``inf``).
        Objects stand on the ground (z = 0); the ground itself returns nothing.
    """
    return _cast(origin_xy, angles, elevations, mount_height, segments, seg_height, circles, circ_height,
                 boxes_corners, box_height, max_range)[0]


# Rays per scan: every ray is cast against every box and kept per point (several float arrays of this length per
# scan). An Ouster OS-128 at 2048 columns gives 262,144 = 2**18; 1e8 beams asked for GiBs.
RAYS_MAX = 2**18
BEAMS_MAX = 2**15  # one channel: 0.011° steps, finer than any spinning LiDAR's azimuth resolution


# --------------------------------------------------------------------------------------------------- the wrapper
@dataclass(frozen=True)
class LidarParams(Params):
    """Roof-mounted ray-cast LiDAR (thesis 002: σ 0.02 m, 100 m, 1.7 m mount, 10 Hz; digest 000 §5.4)."""

    beams: int = param(720, ge=1, le=BEAMS_MAX, doc="azimuth samples per channel over fov_deg; 720 = 0.5° (our "
                                                    "choice; digest 002 §6.2 suggests 720-1080)")
    fov_deg: float = param(360.0, "deg", gt=0, le=360, doc="horizontal field of view, centred forward (thesis 002: "
                                                           "roof-mounted 360° Ouster)")
    min_range: float = param(0.5, "m", ge=0, doc="closer hits are no return: a real sensor's blind zone, which "
                                                 "also hides self-hits (our choice)")
    max_range: float = param(100.0, "m", gt=0, doc="beams with no return read this value (thesis 002: Ouster)")
    range_sigma: float = param(0.02, "m", ge=0, doc="Gaussian noise along each beam (thesis 002)")
    dropout: float = param(0.01, ge=0, le=1, doc="probability that a beam returns nothing (digest 000: 1-3 % in "
                                                 "clear weather)")
    azimuth_jitter: bool = param(True, doc="one random azimuth offset in [0, fov/beams) per scan, so consecutive "
                                           "scans do not sample the same bearings (identical sampling of a "
                                           "corridor makes ICP stick at zero motion; digest 000/002)")
    elevations_deg: tuple[float, ...] = param((0.0,), "deg", gt=-89, lt=89, doc="channel elevations, + = up; one "
                                              "0° channel = a planar 2-D scan that sees every object (our choice; "
                                              "the thesis's CARLA LiDAR has 32-64 channels over -30°...+10°)")
    planar: bool | None = param(None, doc="ignore object heights (every beam sees every object, z = 0 in the "
                                          "cloud, the 2-D scan of digest 002 §6.2); null = planar exactly when "
                                          "elevations_deg == [0]")
    mount_x: float = param(0.0, "m", doc="ahead of the vehicle centre (our choice)")
    mount_height: float = param(1.7, "m", ge=0, doc="above the ground (thesis 002)")
    vehicle_height: float = param(1.5, "m", gt=0, doc="height of the other vehicles' boxes (a passenger car)")
    rate_hz: float = param(10.0, "Hz", gt=0, le=RATE_MAX_HZ, doc="scan rate; scans are taken at observations (at most the policy "
                                                 "rate), the last one held in between (thesis 002)")
    sweep_time: float = param(0.1, "s", gt=0, doc="one rotation, for per-point times and deskew_poses (one "
                                                  "rotation per 10 Hz scan)")
    deskew_poses: bool = param(False, doc="cast each beam from the sensor pose at its firing time (the sweep ends "
                                          "at the scan time): the motion distortion of a real spinning LiDAR "
                                          "(digest 002 §6.2 step 4 / §6.4). Without it run kiss-icp with "
                                          "deskew=False, or its constant-velocity deskew adds a distortion that "
                                          "is not there")

    def relations(self) -> list[str]:
        if not self.min_range < self.max_range:
            return [f"@min_range must be < @max_range, got {self.min_range:g} and {self.max_range:g}"]
        if not self.elevations_deg:
            return ["@elevations_deg must be a non-empty list"]
        if self.beams * len(self.elevations_deg) > RAYS_MAX:
            return [f"@beams x len(@elevations_deg) must be at most {RAYS_MAX} rays per scan, got "
                    f"{self.beams} x {len(self.elevations_deg)}"]
        if self.planar and any(e != 0.0 for e in self.elevations_deg):
            return [f"@planar needs every elevation to be 0°, got @elevations_deg {list(self.elevations_deg)}"]
        return []


class Lidar(SensorWrapper):
    """Roof-mounted ray-cast LiDAR; adds ``obs["lidar"]`` (ranges) and keeps the last scan's point cloud.
    Parameters: :class:`LidarParams`.

    Example: ranges (m) per channel and beam, and the returns as points in the sensor frame (x forward, y left,
    z up):

        >>> import gymnasium as gym
        >>> import av_gym
        >>> from av_gym.sensors.lidar import Lidar
        >>> env = Lidar(gym.make("av_gym/UnprotectedLeftTurn-v0"), beams=360)
        >>> obs, info = env.reset(seed=0)
        >>> obs["lidar"].shape  # (len(elevations_deg), beams)
        (1, 360)
        >>> points, times = env.points()  # (N, 3) m, and when in the sweep each beam fired, in [0, 1)
        >>> points.shape[1], bool(((0 <= times) & (times < 1)).all())
        (3, True)
    """

    key = "lidar"
    Params = LidarParams

    def __init__(self, env: gym.Env, params: LidarParams | None = None, **overrides) -> None:
        p = self.params = LidarParams.build(params, **overrides)
        self.beams = int(p.beams)
        self.fov = float(np.radians(p.fov_deg))
        self.min_range, self.max_range = float(p.min_range), float(p.max_range)
        self.range_sigma, self.dropout = float(p.range_sigma), float(p.dropout)
        self.azimuth_jitter = bool(p.azimuth_jitter)
        self.elevations = np.radians(np.asarray(p.elevations_deg, dtype=float).reshape(-1))
        self.planar = bool(p.planar) if p.planar is not None else bool(len(self.elevations) == 1
                                                                        and self.elevations[0] == 0.0)
        self.mount_x, self.mount_height = float(p.mount_x), float(p.mount_height)
        self.vehicle_height = float(p.vehicle_height)
        self.rate_hz, self.sweep_time = float(p.rate_hz), float(p.sweep_time)
        self.deskew_poses = bool(p.deskew_poses)
        self._sin_e, self._cos_e = np.sin(self.elevations), np.cos(self.elevations)
        self._tan_e = np.tan(self.elevations)
        self._beam_index = np.arange(self.beams)
        self._world_arrays: tuple | None = None  # (world, its kernel inputs), see _world_inputs
        super().__init__(env)
        self._clear_scan()

    # ----------------------------------------------------------------------------------------------- gym API
    def sensor_space(self) -> spaces.Box:
        return spaces.Box(0.0, self.max_range, (len(self.elevations), self.beams), np.float32)

    def on_reset(self) -> None:
        self._clear_scan()
        self._next_scan = 0.0
        self._pose_log: list[tuple[float, float, float, float]] = []
        if self.deskew_poses:
            listeners = self.env.unwrapped.tick_listeners
            if self._record_pose not in listeners:
                listeners.append(self._record_pose)
            self._record_pose(self.env.unwrapped)

    def invalidate(self, raw: np.ndarray, clean: np.ndarray) -> np.ndarray:
        """A beam that read NaN/inf (see ``SensorWrapper._guarded``) reads ``max_range``, the scan's own mark of a
        beam with no valid return, not 0 (an obstacle touching the sensor) nor a clipped bound."""
        return np.where(np.isfinite(raw), clean, np.float32(self.max_range)).astype(np.float32)

    def measure(self) -> np.ndarray:
        t = sim_time(self.env)
        if self._obs is None or t >= self._next_scan - 1e-9:
            self._scan(t)
            while self._next_scan <= t + 1e-9:  # hold the last scan until the next one is due
                self._next_scan += 1.0 / self.rate_hz
        return self._obs.copy()

    # ----------------------------------------------------------------------------------------------- scans
    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """The last scan's valid returns: points ``(N, 3)`` float64 m in the sensor frame (x forward, y left,
        z up, right-handed; origin at the sensor) and per-point times ``(N,)`` in [0, 1), the fraction of the
        sweep at which each beam fired (by azimuth, counter-clockwise from the rear). Ready for
        ``KissICP.register_frame(points, timestamps)``."""
        return self._points.copy(), self._times.copy()

    def labels(self) -> np.ndarray:
        """Per-point labels ``(N,)`` int for :meth:`points`: 0 = static world, 1 = vehicle."""
        return self._labels.copy()

    def scan_pose(self) -> np.ndarray:
        """True sensor pose ``[x, y, heading]`` (m, m, rad; highway-env world frame) at the last scan (the end of
        its sweep)."""
        return self._pose.copy()

    @property
    def scan_time(self) -> float:
        """Simulation time (s) of the last scan (end of its sweep); per-point times are
        ``scan_time - (1 - timestamp) * sweep_time``."""
        return self._scan_time

    @property
    def scan_index(self) -> int:
        """Number of scans taken this episode minus one: changes exactly when a new scan replaces the held one."""
        return self._scan_index

    def _clear_scan(self) -> None:
        self._obs: np.ndarray | None = None
        self._points = np.zeros((0, 3))
        self._times = np.zeros(0)
        self._labels = np.zeros(0, dtype=int)
        self._pose = np.zeros(3)
        self._scan_time = 0.0
        self._scan_index = -1

    def _record_pose(self, env) -> None:
        ego = env.vehicle
        self._pose_log.append((sim_time(env), float(ego.position[0]), float(ego.position[1]), float(ego.heading)))
        del self._pose_log[:-64]  # a few sweeps' worth is all interpolation needs

    def _sensor_pose_at(self, times: np.ndarray) -> np.ndarray:
        """Sensor ``[x, y, heading]`` interpolated at ``times`` (s) from the tick log → (len(times), 3)."""
        log = np.array(self._pose_log)
        heading = np.unwrap(log[:, 3])
        psi = np.interp(times, log[:, 0], heading)
        x = np.interp(times, log[:, 0], log[:, 1]) + self.mount_x * np.cos(psi)
        y = np.interp(times, log[:, 0], log[:, 2]) + self.mount_x * np.sin(psi)
        return np.stack([x, y, psi], axis=1)

    def _world_inputs(self, world, seg_h, circ_h) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The static world as the ray-cast kernel takes it (contiguous shapes, one height per object), built once
        per episode's world."""
        cached = self._world_arrays
        if cached is None or cached[0] is not world:
            segments = np.ascontiguousarray(world.segments, dtype=float).reshape(-1, 4)
            circles = np.ascontiguousarray(world.circles, dtype=float).reshape(-1, 3)
            cached = self._world_arrays = (world, (segments, _per_object(seg_h, len(segments)), circles,
                                                   _per_object(circ_h, len(circles))))
        return cached[1]

    def _scan(self, t: float) -> None:
        n_ch, n_beams = len(self.elevations), self.beams
        rng = self.rng
        # Draw every random number for the whole scan up front, whatever is hit, so the stream (and hence a
        # twin sensor with different noise settings) stays aligned scan by scan.
        step = self.fov / n_beams
        offset = rng.uniform(0.0, step) if self.azimuth_jitter else 0.0
        noise = rng.standard_normal((n_ch, n_beams))
        dropped = rng.random((n_ch, n_beams)) < self.dropout

        phi = -0.5 * self.fov + offset + step * self._beam_index  # sensor azimuth, + = left
        # firing time within the sweep, in [0, 1) (np.clip's values at a third of its cost)
        frac = np.minimum(np.maximum((phi + np.pi) / TWO_PI, 0.0), np.nextafter(1.0, 0.0))
        if self.deskew_poses:
            poses = self._sensor_pose_at(t - (1.0 - frac) * self.sweep_time)
            origin, world_angles = poses[:, 0:2], poses[:, 2] - phi
            pose = self._sensor_pose_at(np.array([t]))[0]
        else:
            x, y, psi, _ = ego_pose(self.env)
            pose = np.array([x + self.mount_x * np.cos(psi), y + self.mount_x * np.sin(psi), psi])
            origin, world_angles = pose[0:2], psi - phi

        world = roadside_world(self.env)
        if self.planar:  # a 2-D scan plane cuts every object, whatever its height
            seg_h, circ_h, box_h = np.inf, np.inf, np.inf
        else:
            seg_h, circ_h, box_h = world.segment_height, world.circle_height, self.vehicle_height
        if "cast" in KERNELS:
            unwrapped = self.env.unwrapped  # the columns of others_state() that a box needs (not the velocities)
            ego = unwrapped.vehicle
            bx, by, bh, length, width = np.array([(v.position[0], v.position[1], v.heading, v.LENGTH, v.WIDTH)
                                                  for v in unwrapped.road.vehicles if v is not ego],
                                                 dtype=float).reshape(-1, 5).T
            boxes = _kernels.box_corners(bx, by, np.cos(bh), np.sin(bh), length, width)
            segments, seg_h, circles, circ_h = self._world_inputs(world, seg_h, circ_h)
            ranges, is_vehicle = _cast_kernel(np.asarray(origin, dtype=float), world_angles, self._tan_e, self._cos_e,
                                              self.mount_height, segments, seg_h, circles, circ_h, boxes,
                                              np.full(len(boxes), box_h), self.max_range)
        else:
            others = others_state(self.env)
            boxes = box_corners(others[:, 0:2], others[:, 4], others[:, 5], others[:, 6])
            ranges, is_vehicle = _cast(origin, world_angles, self.elevations, self.mount_height, world.segments,
                                       seg_h, world.circles, circ_h, boxes, box_h, self.max_range)

        returns = _kernels.scan_points if "points" in KERNELS else _scan_points
        self._obs, self._points, self._times, self._labels = returns(
            ranges, is_vehicle, noise, dropped, self.range_sigma, self.min_range, self.max_range, np.cos(phi),
            np.sin(phi), frac, self._sin_e, self._cos_e, self.planar, LABEL_STATIC, LABEL_VEHICLE)
        self._pose = pose
        self._scan_time = t
        self._scan_index += 1


def _scan_points(ranges: np.ndarray, is_vehicle: np.ndarray, noise: np.ndarray, dropped: np.ndarray,
                 range_sigma: float, min_range: float, max_range: float, cos_phi: np.ndarray, sin_phi: np.ndarray,
                 frac: np.ndarray, sin_e: np.ndarray, cos_e: np.ndarray, planar: bool, label_static: int,
                 label_vehicle: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The noisy returns of a scan: the observation ``(E, B)`` float32, and the valid returns' points ``(N, 3)``
    (sensor frame), per-point times ``(N,)`` and labels ``(N,)``, channel-major with beams in firing order.
    ``ranges``/``is_vehicle`` from :func:`_cast`; ``noise``, ``dropped`` the scan's draws; ``cos_phi``,
    ``sin_phi``, ``frac`` (B,) per beam; ``sin_e``, ``cos_e`` (E,) per channel."""
    hit = ranges < max_range
    measured = ranges + range_sigma * noise
    valid = hit & ~dropped & (measured >= min_range) & (measured < max_range)
    obs = np.where(valid, measured, max_range).astype(np.float32)

    ch, k = np.nonzero(valid)  # channel-major, beams in firing order within a channel
    r = measured[ch, k]
    z = np.zeros_like(r) if planar else r * sin_e[ch]
    horiz = r if planar else r * cos_e[ch]
    points = np.stack([horiz * cos_phi[k], horiz * sin_phi[k], z], axis=1)
    labels = np.where(is_vehicle[ch, k], label_vehicle, label_static).astype(int)
    return obs, points, frac[k], labels


def sensor_to_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Sensor-frame points ``(N, 3)`` (x forward, y left, z up) → highway-env world ``(N, 2)`` (x right, y down)
    given the sensor ``pose`` ``[x, y, heading]``. Inverse of the frame change described in the module docstring."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    fx, ly = points[:, 0], points[:, 1]
    return np.stack([pose[0] + fx * c + ly * s, pose[1] + fx * s - ly * c], axis=1)


__all__ = ["Lidar", "cast_rays", "sensor_to_world", "LABEL_STATIC", "LABEL_VEHICLE"]
