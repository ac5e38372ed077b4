"""The ``Localizer`` wrapper: estimates the ego pose from GNSS, IMU and LiDAR and adds ``obs["ego_estimate"]``,
with the cross-track and heading errors computed from the *estimate* against the lane map, so controllers can
drive on estimated rather than true state.

Modes (``mode``; digest 002's experiments E1–E5, §3.4):

- ``gnss``: the naive baseline, no filter: the last valid GNSS fix as it is (no latency compensation), heading
  from the GNSS Doppler velocity (held below ``init_min_speed``).
- ``gnss_imu``: :class:`~av_gym.estimation.ekf.LocalizationEKF` with IMU prediction and GNSS position and velocity
  updates (thesis E4).
- ``lidar``: kiss-icp odometry only (thesis E3): chained scan-to-scan increments from a pose initialised from the
  first GNSS fix; no IMU, no GNSS afterwards.
- ``fused``: the EKF with IMU prediction, GNSS updates and LiDAR-odometry increment updates (thesis E5); the EKF's
  predicted motion is fed back to kiss-icp as its motion prior (digest 002 §6.3 pitfall 5, §6.5 "closes the loop of
  Fig.5-6"). With ``map_matching`` also an absolute LiDAR pose from scan-to-map matching against the HD map
  (:class:`~av_gym.estimation.lidar_odometry.MapMatcher`): the only measurement that can observe the GNSS
  multipath bias, and what gets the estimate to lane-keeping accuracy.

Observation ``ego_estimate``: ``Box(9,)`` float32, fields :data:`FIELDS`::

    [cte (m, + right of centre), heading_error (rad, + = heading right of the lane), x, y (m, world),
     heading (rad), speed (m/s), valid (1/0), position_std (m), path_s (m along the lap or route)]

Never NaN: before the first GNSS fix everything is 0 with ``valid`` 0; a diverged filter is re-initialised from
the next GNSS fix (``info["localization"]["reinit"]``) and, until then, the last good estimate is held with
``valid`` 0. ``info["localization"]`` reports every update, rejection, failure and re-initialisation of the step
(runtimes are kept on the pipeline, ``Localizer.pipeline.runtimes``, so that ``info`` stays deterministic for a seed).
Divergence is detected three ways, each re-initialising from GNSS with ``reinit_reason`` saying which: the filter
unhealthy (non-finite, not PSD, position std above ``max_position_std``) after a prediction or an update; every
GNSS fix gated out for ``reinit_after_s``; a numerical exception anywhere in the step (``fault``, ``fault_count``:
a singular matrix, a library error). Non-finite IMU samples are skipped (``imu_skipped``). In ``lidar`` mode a
failed kiss-icp registration (an exception, too few points, a jump away from the prior) breaks the chain of
increments, so the pose restarts from GNSS too; in ``fused`` mode the odometry restarts its local map and the EKF
carries on with the IMU and GNSS.

The lane map is the scenario's own: ``env.unwrapped.track`` (lap) or ``env.unwrapped.route`` (left turn),
located with the estimator's own lane hint, never the simulator's. The HD map for map matching is the roadside
world's geometry (av_gym/sensors/world.py) with each object displaced by a seeded survey error (``map_sigma``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.errors import ConfigError
from av_gym.estimation.ekf import BW, GX, GY, EKFNoise, LocalizationEKF, PSI, PX, PY, V, wrap
from av_gym.estimation.lidar_odometry import (LidarOdometry, MapMatcher, MapMatcherParams, OdometryInputError,
                                              OdometryParams, planar_delta, sensor_delta)
from av_gym.params import Params, param
from av_gym.sensors.base import SensorWrapper, sensor_rng, sim_time

MODES = ("gnss", "gnss_imu", "lidar", "fused")  # LocalizerParams.mode
NEEDS = {"gnss": ("gnss",), "gnss_imu": ("gnss", "imu"), "lidar": ("gnss", "lidar"), "fused": ("gnss", "imu", "lidar")}
FIELDS = ("cte", "heading_error", "x", "y", "heading", "speed", "valid", "position_std", "path_s")
CTE, HEADING_ERROR, X, Y, HEADING, SPEED, VALID, POSITION_STD, PATH_S = range(len(FIELDS))
BOUND = 1e5


def find_wrapper(env: gym.Env, key: str):
    """The wrapper in ``env``'s stack that adds observation ``key`` (None if there is none)."""
    e = env
    while isinstance(e, gym.Wrapper):
        if getattr(e, "key", None) == key:
            return e
        e = e.env
    return None


def lane_map(env: gym.Env):
    """The scenario's lane path: the lap (``track``) or the left-turn ``route``."""
    u = env.unwrapped
    path = getattr(u, "track", None) if u.scenario == "lane_keeping" else getattr(u, "route", None)
    if path is None:
        raise ValueError(f"scenario {u.scenario!r} has no lane map for the localizer")
    return path


class LaneLocator:
    """CTE and heading error of an estimated pose on a :class:`~av_gym.envs.lane_path.LanePath`, with its own
    lane hint (a global search on the first call or after a jump)."""

    def __init__(self, path) -> None:
        self.path = path
        self.hint: int | None = None

    def _global(self, position: np.ndarray) -> int:
        best, best_k = np.inf, 0
        for k, lane in enumerate(self.path.lanes):
            s, lat = lane.local_coordinates(position)
            d = abs(lat) + max(0.0, -s) + max(0.0, s - lane.length)
            if d < best:
                best, best_k = d, k
        return best_k

    def locate(self, position: np.ndarray, heading: float) -> tuple[float, float, float]:
        """(cte m + right, heading error rad, path s m)."""
        if self.hint is None:
            self.hint = self._global(position)
        k, s, lat = self.path.locate(position, self.hint)
        if abs(lat) > 10.0:  # lost (e.g. after a re-initialisation): search every lane again
            k = self._global(position)
            s, lat = self.path.lanes[k].local_coordinates(position)
        self.hint = k
        lane = self.path.lanes[k]
        heading_error = float(wrap(heading - lane.heading_at(float(np.clip(s, 0.0, lane.length)))))
        return float(lat), heading_error, float(self.path.path_s(k, s))


@dataclass(frozen=True)
class LocalizerParams(Params):
    """The localizer (digest 002 §6.3 kiss-icp, §6.5 EKF; our tuning on seeds 0-2, never the evaluation seeds)."""

    mode: Literal["gnss", "gnss_imu", "lidar", "fused"] = param(
        "fused", doc="gnss (raw fixes, no filter) | gnss_imu (EKF) | lidar (kiss-icp odometry only) | fused")
    map_matching: bool = param(True, doc="fused only: LiDAR scan-to-map pose updates against the HD map (the "
                                         "roadside world's geometry); without it nothing observes the GNSS "
                                         "multipath bias (~0.5 m). What reaches lane-keeping accuracy")
    map_sigma: float = param(0.05, "m", ge=0, doc="survey error of the HD map, per object (HD-map grade; our "
                                                  "choice)")
    gnss_latency: float | None = param(None, "s", ge=0, doc="receiver latency; null = the GNSS sensor's configured "
                                                            "one (a datasheet value)")
    rear_axle: float | None = param(None, "m", ge=0, doc="from the reference point to the non-holonomic axle; null = "
                                                         "half the ego's length (highway-env's kinematic bicycle)")
    noise: EKFNoise = param(EKFNoise(), doc="the filter's noise model")
    odometry: OdometryParams = param(OdometryParams(), doc="kiss-icp odometry settings")
    map_matcher: MapMatcherParams = param(MapMatcherParams(), doc="scan-to-map matching settings")
    odometry_update: Literal["relative_pose", "velocity"] = param(
        "relative_pose", doc="relative_pose (one update per odom_window scans against a cloned pose, stochastic "
                             "cloning) | velocity (digest 002 §6.5's per-scan body velocity and yaw rate)")
    odom_window: int = param(10, "scans", ge=1, doc="scans per relative-pose odometry update (1 s at 10 Hz)")
    reinit_after_s: float = param(2.0, "s", gt=0, doc="consecutive gated-out GNSS fixes for this long: the filter "
                                                      "is declared diverged and re-initialised from GNSS")
    max_position_std: float = param(50.0, "m", gt=0, doc="a larger position std also counts as divergence")
    init_min_speed: float = param(1.0, "m/s", ge=0, doc="slower than this the initial heading comes from the lane "
                                                        "map, not the GNSS velocity")
    search_above_std: float = param(0.3, "m", ge=0, doc="above this position std a correlative search precedes map "
                                                        "matching")
    relocalize_after: int = param(10, "scans", ge=1, doc="refused map matches before a forced search and, if the "
                                                         "match is good and still refused, a re-localisation")
    ambiguity_margin: float = param(0.05, ge=0, le=1, doc="acquisition refuses a map fit when another peak >= 1 m "
                                                          "away has a map fraction within this of the best")

    def relations(self) -> list[str]:
        if self.map_matching and self.mode != "fused":
            return [f"@map_matching needs mode fused, got mode {self.mode!r}"]
        return []


def _sections_as_mappings(overrides: dict) -> dict:
    """Nested sections given as instances (``noise=EKFNoise(...)``) as their fields, for ``Params.build``."""
    return {k: v.as_dict() if isinstance(v, Params) else v for k, v in overrides.items()}


class LocalizationPipeline:
    """The estimator behind :class:`Localizer`, usable on its own (eval/localization.py runs several on one
    episode). Call :meth:`reset` after ``env.reset`` and :meth:`step` after every ``env.step`` with the observation
    dict (it needs ``gnss``, and ``imu``/LiDAR as the mode requires; points come from the LiDAR wrapper in the
    stack)."""

    def __init__(self, params: LocalizerParams | None = None, **overrides) -> None:
        p = self.params = LocalizerParams.build(params, **_sections_as_mappings(overrides))
        self.odometry_update, self.odom_window = p.odometry_update, int(p.odom_window)
        self.search_above_std, self.relocalize_after = float(p.search_above_std), int(p.relocalize_after)
        self.ambiguity_margin = float(p.ambiguity_margin)
        self.mode, self.map_matching, self.map_sigma = p.mode, bool(p.map_matching), float(p.map_sigma)
        self.gnss_latency, self.rear_axle = p.gnss_latency, p.rear_axle
        self.noise = p.noise
        self.odometry_params = p.odometry.as_dict()
        self.matcher_params = p.map_matcher
        self.reinit_after_s, self.max_position_std = float(p.reinit_after_s), float(p.max_position_std)
        self.init_min_speed = float(p.init_min_speed)
        self.last = np.zeros(len(FIELDS), dtype=np.float32)
        self.runtimes: dict[str, list[float]] = {"step": [], "map": []}
        """Wall-clock seconds per :meth:`step` and per map match, over the pipeline's life (kiss-icp's own per-scan
        times are ``self.odometry.runtimes``). Not in ``info``: it must be deterministic for a seed."""

    # ------------------------------------------------------------------------------------------------ binding
    def bind(self, env: gym.Env) -> None:
        """Find the sensors this mode needs in ``env``'s stack and read their fixed parameters."""
        self.env = env
        self.gnss = find_wrapper(env, "gnss")
        self.imu = find_wrapper(env, "imu")
        self.lidar = find_wrapper(env, "lidar")
        missing = [k for k in NEEDS[self.mode] if find_wrapper(env, k) is None]
        if missing:
            raise ConfigError(f"sensors.localizer.mode={self.mode} needs the sensors {list(NEEDS[self.mode])}; the "
                              f"preset lacks {missing}")
        u = env.unwrapped
        self.dt = 1.0 / float(u.config["simulation_frequency"])
        self.latency = float(self.gnss.latency if self.gnss_latency is None else self.gnss_latency)

    # ------------------------------------------------------------------------------------------------ episode
    def reset(self, env: gym.Env, obs: dict, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
        self.bind(env)
        u = env.unwrapped
        self.locator = LaneLocator(lane_map(env))
        lr = float(u.vehicle.LENGTH) / 2.0 if self.rear_axle is None else float(self.rear_axle)
        self.ekf = LocalizationEKF(self.noise, rear_axle=lr) if self.mode in ("gnss_imu", "fused") else None
        self.lr = lr
        self.reinit_count = 0
        self.fault_count = 0  # numerical failures caught in step() (each one re-initialises from GNSS)
        self._rejected_since: float | None = None
        self._last_good = np.zeros(len(FIELDS), dtype=np.float32)
        self.raw: np.ndarray | None = None  # gnss mode: [x, y, heading, speed]
        self.raw_valid = False
        self.lidar_pose: np.ndarray | None = None  # lidar mode: [x, y, heading] at the last registered scan
        self.lidar_speed = 0.0
        self.odometry: LidarOdometry | None = None
        self.matcher: MapMatcher | None = None
        self.mount_x = 0.0
        if self.mode in ("lidar", "fused"):
            lid = self.lidar
            p = dict(self.odometry_params)
            deskew = p.pop("deskew", None)
            self.odometry = LidarOdometry(max_range=lid.max_range, min_range=lid.min_range,
                                          deskew=bool(lid.deskew_poses if deskew is None else deskew), **p)
            self.mount_x = float(lid.mount_x)
            self._scan_seen = -1
        if self.map_matching:
            from av_gym.sensors.world import roadside_world

            world = roadside_world(env)
            segs = world.segments.copy()
            circ = world.circles.copy()
            if self.map_sigma > 0:  # survey error: each object displaced as a whole
                segs += np.repeat(rng.normal(0.0, self.map_sigma, (len(segs), 2)), 2, axis=0).reshape(-1, 4)
                circ[:, :2] += rng.normal(0.0, self.map_sigma, (len(circ), 2))
            self.matcher = MapMatcher(segs, circ, self.matcher_params)
        self._reset_interval()
        self._window = (np.zeros(3), 0, 0.0)  # odometry window: [dx, dy, dpsi] chained, scans, metres
        self._map_misses = 0
        self.t = sim_time(env)
        return self._finish(obs, self._info(), first=True)

    def _reset_interval(self) -> None:
        """Start a new LiDAR interval: dead reckoning (vehicle frame) and gyro sum since the last registered scan."""
        self._dr = np.zeros(3)  # dx forward, dy right, dpsi
        self._gyro_sum, self._gyro_n = 0.0, 0
        self._interval_start = None

    def _info(self) -> dict:
        return {"mode": self.mode + ("+map" if self.map_matching else ""), "valid": False, "reinit": False,
                "reinit_reason": "", "reinit_count": 0, "gnss_used": False, "gnss_rejected": False, "gnss_nis": 0.0,
                "lidar_scan": False, "lidar_used": False, "lidar_failed": "", "lidar_nis": 0.0, "map_used": False,
                "map_failed": "", "map_nis": 0.0, "map_searched": False, "map_relocalized": False,
                "fault": "", "fault_count": self.fault_count, "imu_skipped": 0}

    # ------------------------------------------------------------------------------------------------ helpers
    def _gnss_fix(self, obs: dict) -> tuple[bool, np.ndarray, float]:
        """(usable fresh fix?, [x, y, vx, vy], delay s)."""
        g = np.asarray(obs["gnss"], dtype=float)
        usable = bool(g[4] > 0.5 and g[5] > 0.5 and np.all(np.isfinite(g[:4])) and np.isfinite(g[6]))
        return usable, g[:4], self.latency + float(g[6])

    def _initial_heading(self, fix: np.ndarray, position: np.ndarray) -> tuple[float, float]:
        """Heading (rad) and speed (m/s) from the GNSS velocity, or the lane direction when nearly stopped."""
        speed = float(np.hypot(fix[2], fix[3]))
        if speed >= self.init_min_speed:
            return float(np.arctan2(fix[3], fix[2])), speed
        k = self.locator._global(position)
        lane = self.locator.path.lanes[k]
        s, _ = lane.local_coordinates(position)
        return float(lane.heading_at(float(np.clip(s, 0.0, lane.length)))), speed

    def _init_ekf(self, fix: np.ndarray, delay: float) -> None:
        heading, speed = self._initial_heading(fix, fix[:2])
        # The fix is ``delay`` s old: move it forward along the GNSS velocity.
        pos = fix[:2] + delay * fix[2:4]
        self.ekf.initialize(pos, heading, speed, heading_sigma=0.05 if speed >= self.init_min_speed else 0.2)
        self._window = (np.zeros(3), 0, 0.0)  # initialize() cloned the pose: a new odometry window starts
        self._rejected_since = None

    def _reinit(self, info: dict, reason: str) -> None:
        if self.ekf is not None:
            self.ekf.initialized = False
        info["reinit_reason"] = reason
        self.reinit_count += 1

    # ------------------------------------------------------------------------------------------------ step
    def step(self, obs: dict) -> tuple[np.ndarray, dict]:
        t0 = time.perf_counter()
        info = self._info()
        t = sim_time(self.env)
        dt_step, self.t = t - self.t, t
        try:
            if self.mode == "gnss":
                self._step_gnss(obs)
            elif self.mode == "lidar":
                self._step_lidar(obs, info, dt_step)
            else:
                self._step_ekf(obs, info)
                if self.ekf.initialized and not self.ekf.is_healthy(self.max_position_std):
                    self._reinit(info, "filter unhealthy after an update (non-finite, not PSD or position std too "
                                       "large)")
        except (ArithmeticError, ValueError, RuntimeError) as exc:
            # A numerical failure anywhere in the estimator (a singular matrix, a library error) must not end the
            # episode: the estimate restarts from the next GNSS fix, as after a divergence, and info says why.
            self.fault_count += 1
            info["fault"] = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
            info["fault_count"] = self.fault_count
            self._restart_from_gnss(info, f"fault ({info['fault']})")
        self.runtimes["step"].append(time.perf_counter() - t0)
        return self._finish(obs, info)

    def _restart_from_gnss(self, info: dict, reason: str) -> None:
        """Forget the estimate: the next usable GNSS fix starts it again (every mode)."""
        if self.mode == "gnss":
            self.raw = None
            info["reinit_reason"] = reason
            self.reinit_count += 1
        elif self.mode == "lidar":
            self._reinit_lidar(info, reason)
        else:
            self._reinit(info, reason)

    def _step_gnss(self, obs: dict) -> None:
        usable, fix, _ = self._gnss_fix(obs)
        self.raw_valid = bool(np.asarray(obs["gnss"])[5] > 0.5)  # a held fix during an outage is not valid
        if usable:
            speed = float(np.hypot(fix[2], fix[3]))
            if speed >= self.init_min_speed:
                heading = float(np.arctan2(fix[3], fix[2]))
            elif self.raw is not None:
                heading = float(self.raw[2])
            else:
                heading = self._initial_heading(fix, fix[:2])[0]
            self.raw = np.array([fix[0], fix[1], heading, speed])

    # --- lidar only
    def _step_lidar(self, obs: dict, info: dict, dt_step: float) -> None:
        if self.lidar_pose is None:
            usable, fix, delay = self._gnss_fix(obs)
            if usable:
                info["reinit"] = self.reinit_count > 0
                heading, speed = self._initial_heading(fix, fix[:2])
                self.lidar_pose = np.array([*(fix[:2] + delay * fix[2:4]), heading])
                self.lidar_speed = speed
                self._prime = sensor_delta(speed / self.lidar.rate_hz, 0.0, 0.0, self.mount_x)
                self.odometry.reset()
                self._register(info, prior=None)  # first frame of the map at the initial pose
                self._interval_start = self.lidar.scan_time
            return
        if self.lidar.scan_index == self._scan_seen:
            return
        prior = self._prime if self.odometry.scans_in_map == 1 else None  # kiss-icp starts at zero velocity
        res = self._register(info, prior)
        if res is None or not res.ok:
            # The chain of increments is broken (the car moved during the lost scan): start again from GNSS.
            self._reinit_lidar(info, f"LiDAR odometry failed ({info['lidar_failed']})")
            return
        if res.first:
            return
        dx, dy, dpsi = planar_delta(res.delta, self.mount_x)
        x, y, psi = self.lidar_pose
        c, s = np.cos(psi), np.sin(psi)
        self.lidar_pose = np.array([x + dx * c - dy * s, y + dx * s + dy * c, wrap(psi + dpsi)])
        interval = max(self.lidar.scan_time - self._interval_start, 1e-6)
        self.lidar_speed = float(np.hypot(dx, dy) / interval)
        self._interval_start = self.lidar.scan_time
        info["lidar_used"] = True

    def _reinit_lidar(self, info: dict, reason: str) -> None:
        self.lidar_pose = None
        info["reinit_reason"] = reason
        self.reinit_count += 1

    def _register(self, info: dict, prior):
        """Register the LiDAR's current scan; never raises (failures go to info)."""
        lid = self.lidar
        self._scan_seen = lid.scan_index
        info["lidar_scan"] = True
        pts, times = lid.points()
        try:
            res = self.odometry.register(pts, times, prior=prior)
        except OdometryInputError as exc:
            info["lidar_failed"] = f"input: {exc}"
            return None
        if not res.ok:
            info["lidar_failed"] = res.reason
        return res

    # --- EKF modes
    def _step_ekf(self, obs: dict, info: dict) -> None:
        ekf = self.ekf
        usable, fix, delay = self._gnss_fix(obs)
        if ekf.initialized:
            for a_long, _a_lat, gyro in np.asarray(obs["imu"], dtype=float):
                if not (np.isfinite(a_long) and np.isfinite(gyro)):  # a bad sample is skipped, not integrated
                    info["imu_skipped"] += 1
                    continue
                self._predict(float(a_long), float(gyro))
            if not ekf.is_healthy(self.max_position_std):
                self._reinit(info, "filter unhealthy (non-finite, not PSD or position std too large)")
        if not ekf.initialized:
            if usable:
                self._init_ekf(fix, delay)
                if self.reinit_count:
                    info["reinit"] = True
                self._restart_lidar(info)
            return
        if usable:
            up = ekf.update_gnss_position(fix[:2], delay)
            info["gnss_nis"] = up.nis
            if up.accepted:
                ekf.update_gnss_velocity(fix[2:4], delay)
                info["gnss_used"] = True
                self._rejected_since = None
            else:
                info["gnss_rejected"] = True
                if self._rejected_since is None:
                    self._rejected_since = self.t
                elif self.t - self._rejected_since >= self.reinit_after_s:
                    # Every fix for reinit_after_s has been an outlier: the filter, not GNSS, is wrong.
                    self._reinit(info, f"GNSS rejected for {self.t - self._rejected_since:.1f} s")
                    self._init_ekf(fix, delay)
                    info["reinit"] = True
                    self._restart_lidar(info)
                    return
        if self.mode == "fused" and self.lidar.scan_index != self._scan_seen:
            self._lidar_update(info)

    def _restart_lidar(self, info: dict) -> None:
        """After a (re)initialisation from GNSS, odometry restarts from the current scan (fused mode only)."""
        if self.mode == "fused":
            self.odometry.reset()
            self._register(info, prior=None)
            self._reset_interval()
            self._interval_start = self.lidar.scan_time

    def _predict(self, a_long: float, gyro: float) -> None:
        ekf, dt = self.ekf, self.dt
        x = ekf.kf.x
        w = gyro - x[BW]
        dx, dy, dpsi = self._dr
        v, lr = x[V], self.lr
        c, s = np.cos(dpsi), np.sin(dpsi)
        self._dr = np.array([dx + (v * c - lr * w * s) * dt, dy + (v * s + lr * w * c) * dt, dpsi + w * dt])
        self._gyro_sum += gyro
        self._gyro_n += 1
        ekf.predict(a_long, gyro, dt)

    def _lidar_update(self, info: dict) -> None:
        ekf = self.ekf
        prior = sensor_delta(*self._dr, mount_x=self.mount_x)
        res = self._register(info, prior)
        if res is not None and res.ok:
            if res.first:  # a restarted local map: the odometry chain is broken, start a new window here
                ekf.clone()
                self._window = (np.zeros(3), 0, 0.0)
            elif self.odometry_update == "relative_pose":
                self._window_update(res, info)
            else:
                self._velocity_update(res, info)
            self._reset_interval()
            self._interval_start = self.lidar.scan_time
        if self.matcher is not None:
            self._map_update(info)

    def _map_update(self, info: dict) -> None:
        """Scan-to-map pose update.

        Tracking (position std ≤ ``search_above_std``): ICP from the filter's pose. Acquisition (start-up, or after
        ``relocalize_after`` refused scans): a correlative search gives the best few peaks, ICP refines each, and
        the best fit is used only if no other peak ≥ 1 m away fits almost as well (a corridor's along-track
        ambiguity: then this scan is skipped and the next one, further down the road, tried). A good fit (≥ 70 % of
        the scan on the map) that the gate still refuses after refused scans means the filter is confidently wrong:
        its pose covariance is inflated (re-localisation, reported) and the match applied."""
        t0 = time.perf_counter()
        ekf, matcher = self.ekf, self.matcher
        pts, _ = self.lidar.points()
        body = MapMatcher.scan_to_body(pts, self.mount_x)
        x = ekf.kf.x
        guess = x[[PX, PY, PSI]]
        std = ekf.position_std()
        psi_std = float(np.sqrt(max(ekf.kf.P[PSI, PSI], 0.0)))
        stuck = self._map_misses >= self.relocalize_after and self._map_misses % self.relocalize_after == 0
        if std > self.search_above_std or stuck:
            info["map_searched"] = True
            half_xy = 3.0 if stuck else float(np.clip(3.0 * std, 1.0, 4.0))
            peaks = matcher.search(body, guess, half_xy, float(np.clip(3.0 * psi_std, 0.01, 0.06)), peaks=4)
            fits = sorted((m for m in (matcher.match(body, p) for p, _ in peaks) if m.ok),
                          key=lambda m: -m.fraction)
            m = fits[0] if fits else matcher.match(body, peaks[0][0])
            rivals = [f for f in fits[1:] if np.hypot(*(f.pose[:2] - m.pose[:2])) >= 1.0
                      and f.fraction >= m.fraction - self.ambiguity_margin]
            if m.ok and rivals:
                info["map_failed"] = (f"ambiguous ({len(rivals) + 1} fits within {self.ambiguity_margin:.2f} of "
                                      f"{100 * m.fraction:.0f} % on the map, ≥ 1 m apart)")
                m = None
        else:
            m = matcher.match(body, guess)
        if m is not None and m.ok:
            up = ekf.update_pose(m.pose, m.cov)
            if not up.accepted and stuck and m.fraction >= 0.7:
                ekf.inflate_pose(1.0, 0.05)
                up = ekf.update_pose(m.pose, m.cov)
                info["map_relocalized"] = up.accepted
            info["map_nis"] = up.nis
            info["map_used"] = up.accepted
            if not up.accepted:
                info["map_failed"] = f"gated (NIS {up.nis:.1f} > {up.threshold:.1f})"
        elif m is not None:
            info["map_failed"] = m.reason
        self._map_misses = 0 if info["map_used"] else self._map_misses + 1
        self.runtimes["map"].append(time.perf_counter() - t0)
        self._check_gnss_bias(info)

    def _check_gnss_bias(self, info: dict) -> None:
        """With map matching the filter estimates the GNSS multipath bias g; an estimate far outside its model
        (gᵀ g / σ_g² above the χ²₂ gate) means GNSS and the map disagree by more than multipath explains, i.e. the
        map matching locked onto a wrong place (e.g. along a repetitive corridor). Re-initialise from GNSS: the
        acquisition search then starts again."""
        x, sg = self.ekf.kf.x, self.noise.gnss_bias_sigma
        if sg <= 0:
            return
        nis = float(x[GX] ** 2 + x[GY] ** 2) / sg**2
        if nis > self.ekf._threshold(2):
            self._reinit(info, f"GNSS bias estimate implausible (|g| = {np.hypot(x[GX], x[GY]):.2f} m): map lock "
                               "suspected")

    def _window_update(self, res, info: dict) -> None:
        """Chain the scan's increment into the window; every ``odom_window`` scans, one relative-pose update
        against the clone, then clone again."""
        dx, dy, dpsi = planar_delta(res.delta, self.mount_x)
        acc, n, dist = self._window
        c, s = np.cos(acc[2]), np.sin(acc[2])
        acc = np.array([acc[0] + c * dx - s * dy, acc[1] + s * dx + c * dy, acc[2] + dpsi])
        n, dist = n + 1, dist + float(np.hypot(dx, dy))
        if n < self.odom_window:
            self._window = (acc, n, dist)
            return
        up = self.ekf.update_relative_pose(acc, distance=dist)
        info["lidar_nis"] = up.nis
        info["lidar_used"] = up.accepted
        if not up.accepted:
            info["lidar_failed"] = f"gated (NIS {up.nis:.1f} > {up.threshold:.1f})"
        self.ekf.clone()
        self._window = (np.zeros(3), 0, 0.0)

    def _velocity_update(self, res, info: dict) -> None:
        """Digest 002 §6.5's per-scan body-frame velocity and yaw-rate pseudo-measurement."""
        interval = self.lidar.scan_time - self._interval_start
        if interval <= 0 or not self._gyro_n:
            return
        dx, dy, dpsi = planar_delta(res.delta, self.mount_x)
        c, s = np.cos(-dpsi / 2), np.sin(-dpsi / 2)  # velocity at mid-interval, not the chord
        z = np.array([(c * dx - s * dy) / interval, (s * dx + c * dy) / interval, dpsi / interval])
        up = self.ekf.update_odometry(z, self._gyro_sum / self._gyro_n)
        info["lidar_nis"] = up.nis
        info["lidar_used"] = up.accepted
        if not up.accepted:
            info["lidar_failed"] = f"gated (NIS {up.nis:.1f} > {up.threshold:.1f})"

    # ------------------------------------------------------------------------------------------------ output
    def estimate(self) -> tuple[np.ndarray | None, float, float]:
        """([x, y, heading], speed, position std) of the current estimate, or (None, 0, 0) before one exists."""
        if self.mode == "gnss":
            if self.raw is None:
                return None, 0.0, 0.0
            return self.raw[:3].copy(), float(self.raw[3]), float(np.hypot(self.noise.gnss_sigma,
                                                                             self.noise.gnss_bias_sigma))
        if self.mode == "lidar":
            if self.lidar_pose is None:
                return None, 0.0, 0.0
            return self.lidar_pose.copy(), self.lidar_speed, 0.0
        if not self.ekf.initialized:
            return None, 0.0, 0.0
        x = self.ekf.kf.x
        speed = float(np.hypot(x[V], self.lr * self.ekf.yaw_rate))
        return x[[PX, PY, PSI]].copy(), speed, self.ekf.position_std()

    def _finish(self, obs: dict, info: dict, first: bool = False) -> tuple[np.ndarray, dict]:
        if first and self.mode != "lidar":
            self._first_fix(obs, info)
        elif first:
            self._step_lidar(obs, info, 0.0)
        pose, speed, std = self.estimate()
        info["reinit_count"] = self.reinit_count
        if pose is None or not (np.all(np.isfinite(pose)) and np.isfinite(speed) and np.isfinite(std)):
            out = self._last_good.copy()
            out[VALID] = 0.0
        else:
            cte, heading_error, path_s = self.locator.locate(pose[:2], float(pose[2]))
            valid = 1.0 if self.mode != "gnss" or self.raw_valid else 0.0
            out = np.array([cte, heading_error, pose[0], pose[1], wrap(pose[2]), speed, valid, std, path_s])
            out = np.clip(np.nan_to_num(out, nan=0.0, posinf=BOUND, neginf=-BOUND), -BOUND, BOUND)
            out = out.astype(np.float32)
            self._last_good = out.copy()
            info["valid"] = bool(valid)
        self.last = out
        return out.copy(), info

    def _first_fix(self, obs: dict, info: dict) -> None:
        if self.mode == "gnss":
            self._step_gnss(obs)
            return
        usable, fix, delay = self._gnss_fix(obs)
        if usable:
            self._init_ekf(fix, delay)
            if self.mode == "fused":
                self.odometry.reset()
                self._register(info, prior=None)
                self._interval_start = self.lidar.scan_time


class Localizer(SensorWrapper):
    """Adds ``obs["ego_estimate"]`` (see the module docstring) and ``info["localization"]``; parameters:
    :class:`LocalizerParams`. A GNSS-bias estimate outside its own model (χ²₂ gate) with map matching on
    re-initialises the filter (a wrong map lock); see :meth:`LocalizationPipeline._check_gnss_bias`."""

    key = "ego_estimate"
    Params = LocalizerParams

    def __init__(self, env: gym.Env, params: LocalizerParams | None = None, **overrides) -> None:
        p = self.params = LocalizerParams.build(params, **_sections_as_mappings(overrides))
        self.pipeline = LocalizationPipeline(p)
        super().__init__(env)
        self.pipeline.bind(env)  # fail at construction if the preset lacks a sensor this mode needs

    def sensor_space(self) -> spaces.Box:
        low = np.full(len(FIELDS), -BOUND, dtype=np.float32)
        high = np.full(len(FIELDS), BOUND, dtype=np.float32)
        low[VALID], high[VALID] = 0.0, 1.0
        low[POSITION_STD] = 0.0
        return spaces.Box(low, high, dtype=np.float32)

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.rng = sensor_rng(self.env, self.key)
        est, linfo = self.pipeline.reset(self.env, obs, self.rng)
        return {**obs, self.key: est}, {**info, "localization": linfo}

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        est, linfo = self.pipeline.step(obs)
        return {**obs, self.key: est}, reward, terminated, truncated, {**info, "localization": linfo}

    def measure(self) -> np.ndarray:
        return self.pipeline.last.copy()


__all__ = ["FIELDS", "MODES", "LaneLocator", "LocalizationPipeline", "Localizer", "find_wrapper", "lane_map",
           "CTE", "HEADING_ERROR", "X", "Y", "HEADING", "SPEED", "VALID", "POSITION_STD", "PATH_S"]
