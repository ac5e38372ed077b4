"""LiDAR odometry with kiss-icp, guarded against the library's crash cases, plus scan-to-map matching.

Two registrations of the simulated point clouds (:class:`av_gym.sensors.lidar.Lidar`), both at the LiDAR rate:

- :class:`LidarOdometry`: scan-to-local-map odometry with kiss-icp 1.3.0 (digest 002 §6.3), frame-to-frame
  increments for the EKF (digest 002 §6.5, "LiDAR update"). The thesis registered consecutive scans with Open3D
  point-to-plane ICP (digest 002 §2.4, §3.4 E3); kiss-icp is point-to-point ICP against a voxel-hash local map
  with an adaptive threshold and a Geman–McClure kernel (digest 002 §6.3 "What register_frame does").
- :class:`MapMatcher`: 2-D point-to-line ICP of one scan against a prior map of the static roadside world (the
  thesis's point-to-plane cost in the plane, digest 002 §2.4 [SUPPLEMENT], "E = Σ((R p + t − q)·n)²"; matching
  against a geo-referenced map is the thesis's scan-to-map option 1, digest 002 §2.4 "Scan-to-map alternative").
  It gives an *absolute* pose with a covariance from the Gauss–Newton normal matrix, which is what removes the
  GNSS multipath bias that no amount of odometry can observe.

Guards (every case below was run against kiss-icp 1.3.0 in a subprocess; "abort" = SIGABRT from Sophus, the
Python process dies with no exception):

=============================================  ============================  ====================================
input                                          kiss-icp 1.3.0 does           :meth:`LidarOdometry.register` does
=============================================  ============================  ====================================
deskew on, all timestamps equal                abort (0/0 → NaN → SO3::exp)  raises :class:`OdometryInputError`
deskew on, a NaN/inf timestamp                 abort                         raises :class:`OdometryInputError`
deskew on, len(timestamps) != len(points)      IndexError                    raises :class:`OdometryInputError`
motion prior with NaN or non-orthogonal R      abort ("R is not orthogonal")  raises (re-orthonormalises ≤ 1e-3)
points not (N, 3) (e.g. (N, 2))                RuntimeError (pybind cast)    raises :class:`OdometryInputError`
non-finite points                              silently kept                 dropped and counted
empty / fewer than ``min_points``              returns the initial guess     ``ok=False``, library not called
any other exception from ``register_frame``    raises                        ``ok=False``, local map restarted
=============================================  ============================  ====================================

A result whose pose is non-finite, or that jumps more than ``max_deviation`` m from the motion prior, is reported
as a failure (``ok=False``) and the pipeline restarts from an empty local map (kiss-icp keeps no way to undo a
bad map update).

Frames: kiss-icp works in the right-handed sensor frame (x forward, y left, z up). Converting its increments into
highway-env's y-down world convention is the caller's job (:func:`planar_delta`, :func:`sensor_delta`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from av_gym.params import Params, param

KISS_ICP_VERSION = "1.3.0"
"""The version the guards above were verified against (``last_delta`` is public but internal, digest 002 §6.3)."""


class OdometryInputError(ValueError):
    """A scan or motion prior that kiss-icp would crash on (or silently misuse)."""


@dataclass
class OdometryResult:
    """Outcome of one :meth:`LidarOdometry.register` call.

    ``delta``: 4×4 sensor-frame motion from the previous *registered* scan to this one (identity when not ok or on
    the first scan); ``pose``: 4×4 pose in the first scan's sensor frame (restarts are chained in, so it stays
    continuous); ``n_points``: points handed to kiss-icp; ``n_dropped``: non-finite rows removed;
    ``deviation``: m, translation between kiss-icp's result and the initial guess it started from;
    ``runtime_s``: wall time of ``register_frame`` alone; ``first``: this scan started a (new) local map."""

    ok: bool
    reason: str = ""
    delta: np.ndarray = field(default_factory=lambda: np.eye(4))
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    n_points: int = 0
    n_dropped: int = 0
    deviation: float = 0.0
    runtime_s: float = 0.0
    first: bool = False


def _orthonormal(rotation: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(rotation)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


def check_transform(T, name: str = "prior", tol: float = 1e-3) -> np.ndarray:
    """A valid 4×4 rigid transform from ``T`` (rotation re-orthonormalised when within ``tol``), or raise
    :class:`OdometryInputError`: kiss-icp aborts the process on a NaN or non-orthogonal rotation."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise OdometryInputError(f"{name} must be a 4x4 transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise OdometryInputError(f"{name} has non-finite entries (kiss-icp would abort the process)")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise OdometryInputError(f"{name} bottom row must be [0, 0, 0, 1], got {T[3].tolist()}")
    rot = T[:3, :3]
    err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if err > tol or np.linalg.det(rot) <= 0:
        raise OdometryInputError(f"{name} rotation is not a rotation (|RᵀR − I| = {err:.2g}, det = "
                                 f"{np.linalg.det(rot):.3g}); kiss-icp would abort the process")
    out = T.copy()
    out[:3, :3] = _orthonormal(rot)
    return out


@dataclass(frozen=True)
class OdometryParams(Params):
    """The kiss-icp odometry settings a config may change (the localizer's ``odometry`` section); the range filter
    comes from the LiDAR."""

    voxel_size: float | None = param(None, "m", gt=0, doc="null = kiss-icp's loader default max_range / 100 (1 m "
                                                          "at 100 m; digest 002 §6.3). 0.5 and 0.75 m were tried on "
                                                          "two laps and were no better")
    min_points: int = param(30, ge=3, doc="scans with fewer valid points are not registered (our choice)")
    max_deviation: float = param(3.0, "m", gt=0, doc="a result further than this from the motion prior is a "
                                                    "failure and restarts the map (our choice: 3 lane widths' worth "
                                                    "of scan at 10 Hz would need 30 m/s of prior error)")
    deskew: bool | None = param(None, doc="undo motion distortion from per-point times (digest 002 §6.4); null = "
                                          "the LiDAR's deskew_poses (it casts every beam from the scan pose "
                                          "otherwise)")


class LidarOdometry:
    """kiss-icp scan-to-map odometry behind input validation.

    Parameters (keyword only; source in brackets):
        max_range, min_range: m, kiss-icp's range filter; match the sensor's. Defaults 100 / 0.5 [the LiDAR's,
            LidarParams].
        voxel_size, min_points, max_deviation: see :class:`OdometryParams` (build the kiss-icp config with
            ``load_config``: a bare ``KISSConfig`` crashes, digest 002 §6.3).
        deskew: undo motion distortion from per-point times [digest 002 §6.4]. Default False: the simulated LiDAR
            casts every beam from the scan pose unless ``deskew_poses`` is on.
        max_threads: kiss-icp registration threads. Default 1: deterministic sums and polite on shared cores.
    """

    def __init__(self, *, max_range: float = 100.0, min_range: float = 0.5,
                 voxel_size: float | None = OdometryParams.voxel_size, deskew: bool = False,
                 min_points: int = OdometryParams.min_points, max_deviation: float = OdometryParams.max_deviation,
                 max_threads: int = 1) -> None:
        if not 0 <= min_range < max_range < np.inf:
            raise ValueError(f"odometry needs 0 <= min_range < max_range < inf, got {min_range}, {max_range}")
        OdometryParams(voxel_size=voxel_size, min_points=min_points, max_deviation=max_deviation)  # the checks
        self.max_range, self.min_range = float(max_range), float(min_range)
        self.voxel_size = voxel_size
        self.deskew = bool(deskew)
        self.min_points = int(min_points)
        self.max_deviation = float(max_deviation)
        self.max_threads = int(max_threads)
        self.runtimes: list[float] = []
        self.reset()

    # ------------------------------------------------------------------------------------------------ state
    def _new_pipeline(self):
        from kiss_icp.config import load_config
        from kiss_icp.kiss_icp import KissICP

        cfg = load_config(None)  # the loader sets mapping.voxel_size = max_range / 100 (digest 002 §6.3 pitfall 1)
        cfg.data.max_range, cfg.data.min_range, cfg.data.deskew = self.max_range, self.min_range, self.deskew
        if self.voxel_size is not None:
            cfg.mapping.voxel_size = float(self.voxel_size)
        cfg.registration.max_num_threads = self.max_threads
        return KissICP(cfg)

    def reset(self) -> None:
        """Forget everything: the next scan starts a new local map at the identity."""
        self._kiss = self._new_pipeline()
        self._deviations: list[np.ndarray] = []  # what the current pipeline's adaptive threshold was fed
        self._origin = np.eye(4)  # pose of the current pipeline's first frame in the first scan's frame
        self._pose = np.eye(4)
        self._registered = 0  # scans registered by the current pipeline
        self.restarts = 0

    # kiss-icp's pipeline holds native (pybind11) objects that neither pickle nor deep-copy, which made every stack
    # with a localizer impossible to copy (async vector envs pickle their envs' results, lookahead
    # copies envs). Its whole state is public or can be rebuilt: the last pose and delta, the local map's points,
    # and the adaptive threshold, which is a function of the model deviations it was fed (replayed in order).
    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        kiss = state.pop("_kiss")
        state["_kiss_state"] = {"last_pose": kiss.last_pose.copy(), "last_delta": kiss.last_delta.copy(),
                                "map": kiss.local_map.point_cloud().copy()}
        return state

    def __setstate__(self, state: dict) -> None:
        kiss_state = state.pop("_kiss_state")
        self.__dict__.update(state)
        kiss = self._kiss = self._new_pipeline()
        kiss.last_pose, kiss.last_delta = kiss_state["last_pose"], kiss_state["last_delta"]
        if len(kiss_state["map"]):
            kiss.local_map.add_points(kiss_state["map"])
        for deviation in self._deviations:
            kiss.adaptive_threshold.update_model_deviation(deviation)

    @property
    def scans_in_map(self) -> int:
        """Scans registered into the current local map (0 right after a reset or restart)."""
        return self._registered

    @property
    def pose(self) -> np.ndarray:
        """4×4 pose of the last registered scan in the first scan's sensor frame."""
        return self._pose.copy()

    def _restart(self) -> None:
        self._origin = self._pose.copy()
        self._kiss = self._new_pipeline()
        self._deviations = []
        self._registered = 0
        self.restarts += 1

    # ------------------------------------------------------------------------------------------------ validation
    def validate(self, points, timestamps=None) -> tuple[np.ndarray, np.ndarray, int]:
        """Points ``(M, 3)`` float64 kept (finite, inside the range band), their timestamps (empty unless deskew),
        and the number of non-finite rows dropped. Raises :class:`OdometryInputError` on malformed input."""
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise OdometryInputError(f"points must be an (N, 3) array, got shape {pts.shape}")
        if pts.dtype.kind not in "fiu":
            raise OdometryInputError(f"points must be real numbers, got dtype {pts.dtype}")
        pts = pts.astype(np.float64, copy=False)
        finite = np.all(np.isfinite(pts), axis=1)
        n_dropped = int((~finite).sum())
        rng = np.linalg.norm(np.where(finite[:, None], pts, 0.0), axis=1)
        keep = finite & (rng > self.min_range) & (rng < self.max_range)

        ts = np.zeros(0)
        if self.deskew and timestamps is not None and np.size(timestamps) > 0:
            t = np.asarray(timestamps)
            if t.ndim != 1 or len(t) != len(pts):
                raise OdometryInputError(f"timestamps must be ({len(pts)},) to match the points, got shape {t.shape}")
            if t.dtype.kind not in "fiu":
                raise OdometryInputError(f"timestamps must be real numbers, got dtype {t.dtype}")
            t = t.astype(np.float64)
            if not np.all(np.isfinite(t[finite])):
                raise OdometryInputError("timestamps contain NaN or inf; with deskew on kiss-icp would abort the "
                                         "process")
            ts = t[keep]
            if ts.size and float(ts.max() - ts.min()) <= 1e-12:
                raise OdometryInputError("all timestamps are equal; with deskew on kiss-icp normalises by "
                                         "max - min = 0 and aborts the process (digest 002 §6.3 pitfall 2). Pass "
                                         "real per-point times, an empty array, or turn deskew off")
        return np.ascontiguousarray(pts[keep]), ts, n_dropped

    # ------------------------------------------------------------------------------------------------ registration
    def register(self, points, timestamps=None, prior=None) -> OdometryResult:
        """Register one scan.

        Args:
            points: ``(N, 3)`` sensor-frame points (x forward, y left, z up), m.
            timestamps: ``(N,)`` per-point times, any monotone scale (used only when ``deskew``); empty or None =
                no deskew for this scan.
            prior: 4×4 predicted sensor motion since the previous *registered* scan (e.g. from the IMU/EKF), the
                motion prior digest 002 §6.3 pitfall 5 calls for on feature-poor roads; None = kiss-icp's own
                constant-velocity guess.

        Raises :class:`OdometryInputError` for input that would crash kiss-icp; returns ``ok=False`` for a scan
        that cannot be registered (too few points, diverged)."""
        pts, ts, n_dropped = self.validate(points, timestamps)
        prior = None if prior is None else check_transform(prior, "prior")
        if len(pts) < self.min_points:
            return OdometryResult(False, f"too few points ({len(pts)} < {self.min_points})", pose=self.pose,
                                  n_points=len(pts), n_dropped=n_dropped)
        kiss = self._kiss
        if prior is not None and self._registered > 0:
            kiss.last_delta = prior  # initial guess = last_pose @ last_delta (digest 002 §6.3 step 4)
        guess = kiss.last_pose @ kiss.last_delta
        prev = kiss.last_pose.copy()
        t0 = time.perf_counter()
        try:
            kiss.register_frame(pts, ts)
        except Exception as exc:  # noqa: BLE001 - whatever the library raises, the scan is lost, not the process
            self._restart()
            first_line = str(exc).splitlines()[0] if str(exc) else ""
            return OdometryResult(False, f"kiss-icp raised {type(exc).__name__}: {first_line}; local map restarted",
                                  pose=self.pose, n_points=len(pts), n_dropped=n_dropped)
        runtime = time.perf_counter() - t0
        self.runtimes.append(runtime)
        new = kiss.last_pose
        self._deviations.append(np.linalg.inv(guess) @ new)  # = register_frame's own model_deviation
        first = self._registered == 0
        if not np.all(np.isfinite(new)):
            self._restart()
            return OdometryResult(False, "non-finite pose from kiss-icp; local map restarted", pose=self.pose,
                                  n_points=len(pts), n_dropped=n_dropped, runtime_s=runtime)
        deviation = float(np.linalg.norm((np.linalg.inv(guess) @ new)[:3, 3]))
        if not first and deviation > self.max_deviation:
            self._restart()
            return OdometryResult(False, f"diverged ({deviation:.2f} m from the prior); local map restarted",
                                  pose=self.pose, n_points=len(pts), n_dropped=n_dropped, deviation=deviation,
                                  runtime_s=runtime)
        self._registered += 1
        delta = np.eye(4) if first else np.linalg.inv(prev) @ new
        self._pose = self._origin @ new
        return OdometryResult(True, "", delta=delta, pose=self.pose, n_points=len(pts), n_dropped=n_dropped,
                              deviation=0.0 if first else deviation, runtime_s=runtime, first=first)


# ---------------------------------------------------------------------------------------------- frame helpers
def _se2(x: float, y: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3], T[1, 3] = x, y
    return T


def sensor_delta(dx: float, dy_right: float, dpsi: float, mount_x: float = 0.0) -> np.ndarray:
    """4×4 right-handed *sensor*-frame motion for a vehicle motion given in highway-env's convention.

    ``dx`` forward and ``dy_right`` to the right (m) in the previous vehicle frame, ``dpsi`` heading change (rad,
    + = right turn, highway-env's). The handedness flip (y right → y left, clockwise → counter-clockwise) is
    av_gym/sensors/lidar.py's; the sensor sits ``mount_x`` m ahead of the vehicle reference point, so the sensor
    motion is the vehicle motion conjugated by that mount: M⁻¹ T M."""
    vehicle = _se2(dx, -dy_right, -dpsi)
    mount = _se2(mount_x, 0.0, 0.0)
    return np.linalg.inv(mount) @ vehicle @ mount


def planar_delta(delta: np.ndarray, mount_x: float = 0.0) -> tuple[float, float, float]:
    """Inverse of :func:`sensor_delta`: (dx forward, dy to the right, dpsi + = right turn) of the vehicle reference
    point from a 4×4 sensor-frame motion (its out-of-plane part, zero on planar scans, is ignored)."""
    mount = _se2(mount_x, 0.0, 0.0)
    vehicle = mount @ np.asarray(delta, dtype=float) @ np.linalg.inv(mount)
    yaw = float(np.arctan2(vehicle[1, 0], vehicle[0, 0]))
    return float(vehicle[0, 3]), float(-vehicle[1, 3]), -yaw


# ---------------------------------------------------------------------------------------------- map matching
@dataclass
class MapMatch:
    """Outcome of :meth:`MapMatcher.match`: the pose ``[x, y, heading]`` (highway-env world frame) of the vehicle,
    its 3×3 covariance, the number of inlier correspondences, and the RMS point-to-map residual (m)."""

    ok: bool
    reason: str = ""
    pose: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cov: np.ndarray = field(default_factory=lambda: np.eye(3))
    inliers: int = 0
    rms: float = 0.0
    fraction: float = 0.0


@dataclass(frozen=True)
class MapMatcherParams(Params):
    """:class:`MapMatcher`'s settings (the localizer's ``map_matcher`` section); our choices unless noted."""

    sample_step: float = param(0.25, "m", gt=0, doc="map primitives are sampled this often for the KD-tree")
    gate: float = param(1.0, "m", gt=0, doc="pairs further apart are dropped (vehicles, unmapped clutter); 0.5 m "
                                            "after the first two iterations")
    max_range: float = param(60.0, "m", gt=0, doc="scan points farther out are not matched")
    kernel: float = param(0.1, "m", gt=0, doc="Geman-McClure kernel scale σ_k (kiss-icp's kernel, digest 002 §6.3)")
    iterations: int = param(8, ge=1, doc="Gauss-Newton iterations")
    min_inliers: int = param(40, ge=1, doc="fewer correspondences: no match")
    sigma_floor: float = param(0.02, "m", gt=0, doc="floor of the weighted RMS residual σ̂ in the covariance")
    inflation: float = param(25.0, gt=0, doc="covariance = inflation·σ̂²(JᵀWJ)⁻¹: 25 = 5² in standard deviation, "
                                             "for the residuals of one scan not being independent (map survey "
                                             "errors are shared by every point on an object)")
    inlier_distance: float = param(0.2, "m", gt=0, doc="a point this close to the map counts as fitting")
    min_fraction: float = param(0.5, ge=0, le=1, doc="a solution with fewer of the scan's points fitting is refused "
                                                     "(a wrong basin, or a scan mostly of unmapped vehicles)")


class MapMatcher:
    """2-D point-to-line / point-to-circle ICP of a planar scan against a prior map of walls and cylinders.

    The map is the roadside world's geometry (``segments`` (M, 4) ``[x0, y0, x1, y1]``, ``circles`` (K, 3)
    ``[x, y, radius]``, highway-env world frame), i.e. an HD map surveyed beforehand. Per iteration each scan point
    is paired with the nearest map primitive (a KD-tree over primitives sampled every ``sample_step`` m, then the
    exact distance to that primitive), pairs further than ``gate`` m are dropped (vehicles and unmapped clutter), and
    one Gauss–Newton step solves the linearised point-to-plane cost (digest 002 §2.4 [SUPPLEMENT]) in (x, y, ψ)::

        r_i = n_iᵀ (p + R(ψ) q_i − m_i),   J_i = [n_iᵀ, n_iᵀ R'(ψ) q_i],   Δ = −(Jᵀ W J)⁻¹ Jᵀ W r

    with Geman–McClure weights w_i = (σ_k²/(σ_k² + r_i²))² (the kernel kiss-icp uses, digest 002 §6.3 step 5).
    The covariance is ``inflation · σ̂² (JᵀWJ)⁻¹`` with σ̂ the weighted RMS residual (floored at ``sigma_floor``):
    along a featureless corridor JᵀWJ is nearly singular in the along-track direction and the covariance says so,
    which is exactly what the EKF needs. ``inflation`` (default 25 = 5² in standard deviation) accounts for the
    residuals of one scan not being independent (map survey errors are shared by every point on an object).
    A solution with fewer than ``min_fraction`` of the scan within ``inlier_distance`` m of the map is refused (a
    wrong basin, or a scan mostly of unmapped vehicles); :meth:`search` finds the right basin from a poor guess.
    """

    Params = MapMatcherParams

    def __init__(self, segments: np.ndarray, circles: np.ndarray, params: MapMatcherParams | None = None,
                 **overrides) -> None:
        p = self.params = MapMatcherParams.build(params, **overrides)
        sample_step = p.sample_step
        self.segments = np.asarray(segments, dtype=float).reshape(-1, 4)
        self.circles = np.asarray(circles, dtype=float).reshape(-1, 3)
        self.gate, self.max_range, self.kernel = float(p.gate), float(p.max_range), float(p.kernel)
        self.iterations, self.min_inliers = int(p.iterations), int(p.min_inliers)
        self.sigma_floor, self.inflation = float(p.sigma_floor), float(p.inflation)
        self.inlier_distance, self.min_fraction = float(p.inlier_distance), float(p.min_fraction)
        samples, ids = [], []
        for i, (x0, y0, x1, y1) in enumerate(self.segments):
            n = max(2, int(np.ceil(np.hypot(x1 - x0, y1 - y0) / sample_step)) + 1)
            u = np.linspace(0.0, 1.0, n)
            samples.append(np.stack([x0 + u * (x1 - x0), y0 + u * (y1 - y0)], axis=1))
            ids.append(np.full(n, i))
        n_seg = len(self.segments)
        for j, (cx, cy, r) in enumerate(self.circles):
            n = max(8, int(np.ceil(2 * np.pi * r / sample_step)))
            a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
            samples.append(np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], axis=1))
            ids.append(np.full(n, n_seg + j))
        self._ids = np.concatenate(ids) if ids else np.zeros(0, dtype=int)
        self._tree = cKDTree(np.concatenate(samples)) if samples else None

    @staticmethod
    def scan_to_body(points: np.ndarray, mount_x: float = 0.0) -> np.ndarray:
        """Sensor-frame points (x forward, y left) → vehicle frame in highway-env's handedness (x forward, y right),
        ``(N, 2)``."""
        pts = np.asarray(points, dtype=float)
        return np.stack([pts[:, 0] + mount_x, -pts[:, 1]], axis=1)

    def _residuals(self, world: np.ndarray, prim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance of each world point to its primitive along the primitive's normal, and that normal."""
        n_seg = len(self.segments)
        res = np.empty(len(world))
        nrm = np.empty((len(world), 2))
        is_seg = prim < n_seg
        if np.any(is_seg):
            seg = self.segments[prim[is_seg]]
            a, d = seg[:, 0:2], seg[:, 2:4] - seg[:, 0:2]
            length2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-12)
            u = np.clip(np.einsum("ij,ij->i", world[is_seg] - a, d) / length2, 0.0, 1.0)
            foot = a + u[:, None] * d
            off = world[is_seg] - foot
            dist = np.linalg.norm(off, axis=1)
            line_n = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.sqrt(length2)[:, None]
            inside = (u > 0.0) & (u < 1.0)
            # On the segment: the line normal (point-to-plane); past an end: the direction to the end point.
            n = np.where(inside[:, None], line_n, off / np.maximum(dist, 1e-9)[:, None])
            nrm[is_seg] = n
            res[is_seg] = np.einsum("ij,ij->i", off, n)
        if np.any(~is_seg):
            c = self.circles[prim[~is_seg] - n_seg]
            off = world[~is_seg] - c[:, 0:2]
            dist = np.maximum(np.linalg.norm(off, axis=1), 1e-9)
            nrm[~is_seg] = off / dist[:, None]
            res[~is_seg] = dist - c[:, 2]
        return res, nrm

    def _prepare(self, points_body) -> np.ndarray:
        q = np.asarray(points_body, dtype=float).reshape(-1, 2)
        q = q[np.all(np.isfinite(q), axis=1)]
        return q[np.hypot(q[:, 0], q[:, 1]) < self.max_range]

    @staticmethod
    def _transform(q: np.ndarray, pose: np.ndarray) -> np.ndarray:
        c, s = np.cos(pose[2]), np.sin(pose[2])
        return pose[:2] + q @ np.array([[c, s], [-s, c]])  # R(ψ) q for each row (x fwd, y right → world)

    def search(self, points_body: np.ndarray, guess: np.ndarray, half_xy: float, half_psi: float,
               step_xy: float = 0.5, n_psi: int = 5, max_points: int = 150, radius: float = 0.3,
               peaks: int = 1, separation: float = 1.0) -> list[tuple[np.ndarray, float]]:
        """Correlative (brute-force) scan matching around ``guess``: every offset on a grid of ``step_xy`` m within
        ±``half_xy`` m and ``n_psi`` headings within ±``half_psi`` rad, scored by Σ max(0, 1 − (d/radius)²) over a
        subsample of the scan (d = distance to the map). Returns up to ``peaks`` candidates ``(pose, score as a
        fraction of the points)``, best first, at least ``separation`` m apart. ICP alone converges to the nearest
        local minimum, which from a GNSS-grade guess (metres off) is often a wrong one (a guard rail matched to the
        next pole); this puts ICP in the right basin, and several peaks expose along-track ambiguity."""
        guess = np.asarray(guess, dtype=float)
        q = self._prepare(points_body)
        if self._tree is None or len(q) == 0:
            return [(guess, 0.0)]
        q = q[:: max(1, len(q) // max_points)]
        offsets = np.arange(-half_xy, half_xy + 1e-9, step_xy)
        psis = np.linspace(-half_psi, half_psi, n_psi) if n_psi > 1 else np.zeros(1)
        dx, dy = np.meshgrid(offsets, offsets, indexing="ij")
        dx, dy = dx.ravel(), dy.ravel()
        poses, scores = [], []
        for dpsi in psis:
            pose = guess + [0.0, 0.0, dpsi]
            base = self._transform(q, pose)  # (P, 2)
            pts = base[None, :, :] + np.stack([dx, dy], axis=1)[:, None, :]  # (C, P, 2)
            d, _ = self._tree.query(pts.reshape(-1, 2), k=1, distance_upper_bound=radius)
            score = np.maximum(0.0, 1.0 - (np.minimum(d, radius) / radius) ** 2).reshape(len(dx), -1).sum(axis=1)
            poses.append(np.stack([pose[0] + dx, pose[1] + dy, np.full(len(dx), pose[2])], axis=1))
            scores.append(score)
        poses, scores = np.concatenate(poses), np.concatenate(scores) / len(q)
        out: list[tuple[np.ndarray, float]] = []
        for i in np.argsort(-scores, kind="stable"):
            if all(np.hypot(*(poses[i, :2] - p[:2])) >= separation for p, _ in out):
                out.append((poses[i], float(scores[i])))
                if len(out) >= peaks:
                    break
        return out

    def match(self, points_body: np.ndarray, guess: np.ndarray) -> MapMatch:
        """Register body-frame points ``(N, 2)`` (x forward, y right; :meth:`scan_to_body`) starting from the
        vehicle pose ``guess`` ``[x, y, heading]``. ``ok`` needs ``min_inliers`` points and a fraction
        ``min_fraction`` of the scan within ``inlier_distance`` of the map at the solution."""
        if self._tree is None:
            return MapMatch(False, "empty map")
        q = self._prepare(points_body)
        guess = np.asarray(guess, dtype=float)
        if q.shape[0] < self.min_inliers or not np.all(np.isfinite(guess)):
            return MapMatch(False, f"too few points ({len(q)})")
        x = guess.copy()
        for it in range(self.iterations):
            c, s = np.cos(x[2]), np.sin(x[2])
            world = self._transform(q, x)
            _, idx = self._tree.query(world, k=1)
            prim = self._ids[idx]
            res, n = self._residuals(world, prim)
            gate = self.gate if it < 2 else min(self.gate, 0.5)
            inl = np.abs(res) < gate
            if inl.sum() < self.min_inliers:
                return MapMatch(False, f"too few map correspondences ({int(inl.sum())} < {self.min_inliers})",
                                pose=x, inliers=int(inl.sum()))
            r, nn, qq = res[inl], n[inl], q[inl]
            dR_q = qq @ np.array([[-s, c], [-c, -s]])  # ∂(R(ψ) q)/∂ψ
            J = np.column_stack([nn[:, 0], nn[:, 1], np.einsum("ij,ij->i", nn, dR_q)])
            w = (self.kernel**2 / (self.kernel**2 + r**2)) ** 2
            H = J.T @ (w[:, None] * J)
            g = J.T @ (w * r)
            try:
                step = -np.linalg.solve(H + 1e-9 * np.eye(3), g)
            except np.linalg.LinAlgError:
                return MapMatch(False, "singular normal matrix", pose=x)
            x = x + step
            if it >= 1 and np.linalg.norm(step[:2]) < 2e-3 and abs(step[2]) < 1e-4:
                break  # 2 mm / 0.1 mrad: far below the covariance it reports
        fraction = float(np.mean(np.abs(res) < self.inlier_distance))
        if fraction < self.min_fraction:
            return MapMatch(False, f"poor fit ({100 * fraction:.0f} % of points within {self.inlier_distance} m "
                                   f"of the map < {100 * self.min_fraction:.0f} %)", pose=x, inliers=int(inl.sum()))
        sigma2 = max(float(np.sum(w * r**2) / max(np.sum(w), 1e-9)), self.sigma_floor**2)
        try:
            cov = self.inflation * sigma2 * np.linalg.inv(H)
        except np.linalg.LinAlgError:
            return MapMatch(False, "singular normal matrix", pose=x)
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(cov))):
            return MapMatch(False, "non-finite result", pose=guess)
        return MapMatch(True, "", pose=x, cov=0.5 * (cov + cov.T), inliers=int(inl.sum()),
                        rms=float(np.sqrt(np.mean(r**2))), fraction=fraction)


__all__ = ["KISS_ICP_VERSION", "LidarOdometry", "MapMatch", "MapMatcher", "OdometryInputError", "OdometryResult",
           "check_transform", "planar_delta", "sensor_delta"]
