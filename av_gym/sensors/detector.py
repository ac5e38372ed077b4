"""Object detector: the vehicle list a perception stack would give, with the error profile of paper 004's setting
(a fast detector whose misses a tracker can fill in, digest 004 §10.2).

Per detector frame (at ``rate_hz``, held in between), for each other vehicle within ``max_range`` and the field of
view:

- **misses**: independent (``burst_length`` = None) or bursty: a two-state Markov chain per vehicle with stationary
  miss probability ``miss_rate`` and mean run length ``burst_length`` frames (Gilbert–Elliott, our choice), plus
  **occlusion**: a vehicle whose bearing interval is at least ``occlusion_fraction`` covered by nearer vehicles is
  not detected;
- **position noise** σ(r) = ``sigma_pos0`` + ``sigma_pos_k``·r (digest 004: 0.3 m + 0.01·r), velocity noise
  ``sigma_vel``, box size noise ``sigma_size``, heading noise ``sigma_heading``;
- **false positives**: Poisson(``clutter_rate``) per frame, uniform in range and field of view (004: λ = 0.2).

Observation ``Box(max_objects, 9)``, rows sorted by range, zero rows unused: ``[present, x, y, vx, vy, heading,
length, width, age]`` — positions and velocities in the world frame (m, m/s; set ``frame="ego"`` for x forward,
y right of the ego), heading rad, size m, ``age`` s since this detector frame was taken.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.geometry import box_corners
from av_gym.params import RATE_MAX_HZ, ROWS_MAX, Params, param
from av_gym.sensors import kernels as _kernels
from av_gym.sensors.base import SensorWrapper, ego_pose, others_state, sim_time

FIELDS = ("present", "x", "y", "vx", "vy", "heading", "length", "width", "age")
BOUND = 1e4
PROBES = np.linspace(0.05, 0.95, 9)
"""Where along a vehicle's bearing interval occlusion is tested (fractions of the interval)."""
KERNELS = {"occlusion", "draws"}
"""Which parts run as numba kernels (:mod:`av_gym.sensors.kernels`, bit-identical to the numpy code here, which
stays as their reference): ``occlusion`` :meth:`Detector._occluded` and :meth:`Detector._view` (ranges, field of
view and occlusion together); ``draws`` the batch's detector's draws, one compiled call per frame
(:func:`~av_gym.sensors.kernels.frame_draws_span`; the per-env detector and the batch's reference draw with
:func:`frame_draws`), dropped at its first use in a process where its draws are not numpy's
(:func:`av_gym.sensors.draws_check.compiled_draws`)."""


@dataclass(frozen=True)
class DetectorParams(Params):
    """Object detector error profile after digest 004 §10.2 (the AEB shield's own detector uses it too)."""

    rate_hz: float = param(10.0, "Hz", gt=0, le=RATE_MAX_HZ,
                           doc="detector frames, held in between: the policy rate, half the 20 Hz simulation (004 "
                               "needed >= 15 fps on real video; the scene here is simpler)")
    max_range: float = param(60.0, "m", gt=0, doc="no vehicle detected farther out")
    fov_deg: float = param(360.0, "deg", gt=0, le=360, doc="surround perception (our choice); 120 = one front "
                                                           "camera as in paper 004")
    miss_rate: float = param(0.1, ge=0, lt=1, doc="stationary probability that a visible vehicle is missed")
    burst_length: float | None = param(None, "frames", ge=1, doc="mean length of a run of misses (Gilbert-Elliott "
                                                                 "chain, our choice); null = independent misses")
    occlusion: bool = param(True, doc="vehicles hidden behind nearer ones are missed")
    occlusion_fraction: float = param(0.8, gt=0, le=1, doc="a vehicle whose bearing interval is this much covered "
                                                           "by nearer vehicles is not detected")
    sigma_pos0: float = param(0.3, "m", ge=0, doc="position noise at zero range (004: 0.3)")
    sigma_pos_k: float = param(0.01, "m/m", ge=0, doc="position noise growth per metre of range (004: 0.01)")
    sigma_vel: float = param(0.5, "m/s", ge=0, doc="velocity noise (our choice)")
    sigma_size: float = param(0.1, "m", ge=0, doc="box length/width noise (our choice)")
    sigma_heading: float = param(0.05, "rad", ge=0, doc="heading noise (our choice)")
    clutter_rate: float = param(0.2, "1/frame", ge=0, le=100, doc="false positives per frame, Poisson (004: 0.2; "
                                                                    "each is drawn in a loop: 1e9 hung)")
    max_objects: int = param(16, ge=1, le=ROWS_MAX, doc="rows in the observation")
    frame: Literal["world", "ego"] = param("world", doc="world, or ego (x forward, y right of the ego)")

    def relations(self) -> list[str]:
        """The miss chain's entry probability P(miss | seen) (:func:`miss_chain`, the one formula the detectors
        use) must be a probability: a stationary ``miss_rate`` m needs runs of at least m / (1 - m) frames."""
        if miss_chain(self.miss_rate, self.burst_length)[0] > 1.0:
            need = self.miss_rate / (1 - self.miss_rate)
            return [f"@miss_rate {self.miss_rate} needs @burst_length >= {need:.2f} frames"]
        return []


def miss_chain(miss_rate: float, burst_length: float | None) -> tuple[float, float]:
    """The two-state miss chain's (P(miss | seen), P(seen | missed)) for a stationary miss rate and a mean run of
    ``burst_length`` missed frames (None: independent misses, P(miss | missed) = miss_rate)."""
    q = 1.0 - miss_rate if burst_length is None else 1.0 / burst_length
    return (q * miss_rate / (1.0 - miss_rate) if miss_rate > 0 else 0.0), q


def contiguous_columns(rows: np.ndarray, cols: tuple[int, ...]) -> list[np.ndarray]:
    """Columns of ``rows`` (n, k) as contiguous 1-D copies (the same values): a column slice is strided ('A' layout
    to numba) unless n <= 1 (then numpy flags it contiguous, 'C'), so slices would compile the detector's kernels
    twice, once per layout, depending on how many road users a frame has."""
    return [np.ascontiguousarray(rows[:, c]) for c in cols]


def draw_detections(rng: np.random.Generator, chain: dict, keys, in_view: np.ndarray, occluded: np.ndarray,
                    miss_rate: float, p: float, q: float) -> tuple[list[int], list[np.ndarray]]:
    """One frame's random draws for the vehicles in view, in the order the detector makes them: each vehicle's
    miss-chain step (``chain[keys[i]]``: missed last frame or not; P(miss | seen) = ``p``, P(seen | missed) = ``q``;
    a first sight starts in the chain's stationary distribution), then seven standard normals per detection.
    rng.normal(0, σ) is 0 + σ·z with z = rng.standard_normal(): one call for a detection's seven draws gives the same
    numbers, in the same order, as seven normal() calls (the caller scales them). Shared by the per-env
    :class:`Detector` and the batch's detector, so that both draw the same numbers from the same generator.

    Returns the indices of the vehicles detected and their (7,) draws."""
    ids, draws = [], []
    for i in np.flatnonzero(in_view).tolist():
        key = keys[i]
        state = chain.get(key)
        if state is None:
            missing = rng.random() < miss_rate
        elif state:
            missing = rng.random() >= q
        else:
            missing = rng.random() < p
        chain[key] = missing
        if missing or occluded[i]:
            continue
        draws.append(rng.standard_normal(7))
        ids.append(i)
    return ids, draws


class FrameDrawer(Protocol):
    """What :func:`frame_draws` reads of a detector (the per-env :class:`Detector` or the batch's
    ``BatchedDetector``): its parameters, its stationary miss rate, its miss chain's P(miss | seen) ``p`` and
    P(seen | missed) ``q`` (:func:`miss_chain`) and half its field of view (rad)."""

    params: DetectorParams
    miss_rate: float
    p: float
    q: float
    half_fov: float


def frame_draws(detector: FrameDrawer, rng: np.random.Generator, chain: dict, keys, in_view: np.ndarray,
                occluded: np.ndarray) -> tuple[list[int], list[np.ndarray], list[tuple[float, float, float]]]:
    """One frame's random draws in the detector's order: :func:`draw_detections` (``detector``'s miss rate and
    chain), then the clutter count (Poisson, ``clutter_rate``) and per false positive its three uniforms (the
    range's square, in [0, 1); the bearing off the heading, rad, within the field of view; the heading, rad).
    Returns the detected vehicles' indices, their (7,) draws and the clutter's draws."""
    ids, draws = draw_detections(rng, chain, keys, in_view, occluded, detector.miss_rate, detector.p, detector.q)
    clutter = [(rng.random(), rng.uniform(-detector.half_fov, detector.half_fov), rng.uniform(-np.pi, np.pi))
               for _ in range(rng.poisson(detector.params.clutter_rate))]
    return ids, draws, clutter


def assemble_frames(p: DetectorParams, max_range: float, max_objects: int, ego: np.ndarray, others: np.ndarray,
                    src: np.ndarray, frame_of: np.ndarray, ranges: np.ndarray, draws: np.ndarray,
                    clutter_frame: np.ndarray, clutter: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows of F detector frames (world frame) from their draws (:func:`frame_draws`): ``ego`` (F, 3) each
    frame's ego ``[x, y, psi]`` (m, rad); the detections ``src`` (m,) rows of ``others`` (k, 7), of frame
    ``frame_of`` (m,), at range ``ranges`` (m,) m, with their draws (m, 7); the false positives of frame
    ``clutter_frame`` (c,) with their uniforms (c, 3). Per frame its detections then its clutter, each in order,
    sorted by range (stable) and cut at ``max_objects``: rows (F, max_objects, 8) ``[present, x, y, vx, vy, heading,
    length, width]`` (headings not wrapped; zero rows unused), each row's index in ``others`` (-1: clutter or
    unused) and the rows per frame (F,). Element by element the same operations whatever the number of frames."""
    scales = np.repeat(np.array([[0.0, 0.0, p.sigma_vel, p.sigma_vel, p.sigma_heading, p.sigma_size,
                                  p.sigma_size]]), len(src), axis=0)
    scales[:, 0] = scales[:, 1] = p.sigma_pos0 + p.sigma_pos_k * ranges
    det = np.empty((len(src) + len(clutter), 8))
    det[: len(src), 0] = 1.0
    det[: len(src), 1:] = others[src] + (0.0 + scales * draws)
    e = ego[clutter_frame]
    r, b = max_range * np.sqrt(clutter[:, 0]), e[:, 2] + clutter[:, 1]  # uniform over the area
    det[len(src):] = np.stack([np.ones(len(r)), e[:, 0] + r * np.cos(b), e[:, 1] + r * np.sin(b), np.zeros(len(r)),
                               np.zeros(len(r)), clutter[:, 2], np.full(len(r), 5.0), np.full(len(r), 2.0)], axis=1)
    frame = np.concatenate([frame_of, clutter_frame]).astype(int)
    rel = det[:, 1:3] - ego[frame, :2]
    order = np.lexsort((np.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1]), frame))  # by frame, then range
    frame = frame[order]
    count = np.bincount(frame, minlength=len(ego))
    rank = np.arange(len(frame)) - (np.cumsum(count) - count)[frame]
    shown = rank < max_objects
    rows, kept = np.zeros((len(ego), max_objects, 8)), np.full((len(ego), max_objects), -1)
    rows[frame[shown], rank[shown]] = det[order[shown]]
    kept[frame[shown], rank[shown]] = np.concatenate([src, np.full(len(clutter), -1)]).astype(int)[order[shown]]
    return rows, kept, np.minimum(count, max_objects)


class Detector(SensorWrapper):
    """Adds ``obs["detector"]``; parameters: :class:`DetectorParams`.

    Example: rows ``[present, x, y, vx, vy, heading, length, width, age]`` nearest first, zero rows unused:

        >>> import gymnasium as gym
        >>> import av_gym
        >>> from av_gym.sensors.detector import Detector
        >>> env = Detector(gym.make("av_gym/UnprotectedLeftTurn-v0"), miss_rate=0.3, max_objects=8)
        >>> obs, info = env.reset(seed=0)
        >>> obs["detector"].shape
        (8, 9)
        >>> set(obs["detector"][:, 0].tolist()) <= {0.0, 1.0}  # the present flag
        True
    """

    key = "detector"
    Params = DetectorParams

    def __init__(self, env: gym.Env, params: DetectorParams | None = None, **overrides) -> None:
        p = self.params = DetectorParams.build(params, **overrides)
        miss_rate, burst_length = p.miss_rate, p.burst_length
        # Two-state chain (detect ↔ miss): leave a miss run with q = 1/L, enter it with p so that P(miss) = m.
        self.p, self.q = miss_chain(miss_rate, burst_length)
        self.rate_hz, self.max_range, self.half_fov = p.rate_hz, p.max_range, np.radians(p.fov_deg) / 2
        self.miss_rate, self.occlusion, self.occlusion_fraction = miss_rate, bool(p.occlusion), p.occlusion_fraction
        self.max_objects, self.frame = int(p.max_objects), p.frame
        super().__init__(env)

    def sensor_space(self) -> spaces.Box:
        low = np.tile(np.array([0] + [-BOUND] * 4 + [-np.pi, 0, 0, 0], dtype=np.float32), (self.max_objects, 1))
        high = np.tile(np.array([1] + [BOUND] * 4 + [np.pi, 20, 10, BOUND], dtype=np.float32), (self.max_objects, 1))
        return spaces.Box(low, high, dtype=np.float32)

    def on_reset(self) -> None:
        # Per-vehicle chain state, keyed by the vehicle object (not id(), which a deep copy of the stack would
        # leave pointing at the original's vehicles, and which a new vehicle could reuse).
        self._missing: dict[object, bool] = {}
        self._next_frame = 0.0
        self._frame_time = 0.0
        self._rows = np.zeros((self.max_objects, len(FIELDS)), dtype=np.float32)
        self.truth_ids = np.full(self.max_objects, -1)  # index into others_state() of each row; -1 = clutter/empty

    # ------------------------------------------------------------------------------------------- model
    def _occluded(self, ego_xy: np.ndarray, others: np.ndarray) -> np.ndarray:
        """Per vehicle: is at least ``occlusion_fraction`` of its bearing interval behind nearer vehicles?"""
        n = len(others)
        if n < 2:
            return np.zeros(n, dtype=bool)
        if "occlusion" in KERNELS:
            x, y, length, width = contiguous_columns(others, (0, 1, 5, 6))
            return _kernels.occluded(float(ego_xy[0]), float(ego_xy[1]), x, y, np.cos(others[:, 4]),
                                     np.sin(others[:, 4]), length, width, PROBES, float(self.occlusion_fraction))
        corners = box_corners(others[:, :2], others[:, 4], others[:, 5], others[:, 6]) - ego_xy  # (N, 4, 2)
        bearings = np.arctan2(corners[..., 1], corners[..., 0])
        centre = np.arctan2(others[:, 1] - ego_xy[1], others[:, 0] - ego_xy[0])
        rel = (bearings - centre[:, None] + np.pi) % (2 * np.pi) - np.pi  # unwrap around each vehicle's centre
        lo, hi = centre + rel.min(1), centre + rel.max(1)
        dist = np.linalg.norm(others[:, :2] - ego_xy, axis=1)
        probes = lo[:, None] + (hi - lo)[:, None] * PROBES[None]  # (N, 9) bearings
        occluded = np.zeros(n, dtype=bool)
        for i in range(n):
            nearer = dist < dist[i]
            if not nearer.any():
                continue
            d = (probes[i][:, None] - (lo[nearer] + hi[nearer])[None] / 2 + np.pi) % (2 * np.pi) - np.pi
            covered = np.any(np.abs(d) <= (hi[nearer] - lo[nearer])[None] / 2, axis=1)
            occluded[i] = covered.mean() >= self.occlusion_fraction
        return occluded

    def _view(self, ego_xy: np.ndarray, psi: float, others: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per other vehicle: range (m), in view (within ``max_range`` and the field of view), occluded."""
        if "occlusion" in KERNELS:  # the three in one compiled pass
            x, y, length, width = contiguous_columns(others, (0, 1, 5, 6))
            return _kernels.detector_view(
                float(ego_xy[0]), float(ego_xy[1]), float(psi), x, y, np.cos(others[:, 4]), np.sin(others[:, 4]),
                length, width, float(self.max_range), float(self.half_fov), bool(self.occlusion), PROBES,
                float(self.occlusion_fraction))
        rel = others[:, :2] - ego_xy
        r = np.sqrt(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1])  # np.linalg.norm(rel, axis=1), faster
        bearing = np.arctan2(rel[:, 1], rel[:, 0]) - psi
        in_view = (r <= self.max_range) & (np.abs((bearing + np.pi) % (2 * np.pi) - np.pi) <= self.half_fov)
        occluded = self._occluded(ego_xy, others) if self.occlusion else np.zeros(len(others), dtype=bool)
        return r, in_view, occluded

    def _world_frame(self, rng: np.random.Generator, chain: dict, keys, x: float, y: float, psi: float,
                     others: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One frame in the world frame from the ego pose ``x, y`` (m), ``psi`` (rad) and ``others`` (k, 7): the
        rows ``[present, x, y, vx, vy, heading, length, width]`` (m, 8) nearest first (at most ``max_objects``;
        headings not yet wrapped) and each row's index in ``others`` (-1: clutter). Draws from ``rng`` and steps
        the miss chain ``chain`` (keyed by ``keys[i]``): :func:`frame_draws` and :func:`assemble_frames`, which the
        batch's detector (av_gym/batched/perception.py) runs for all its envs' frames at once, each env's draws from
        its own generator, so that both draw and compute the same numbers."""
        r, in_view, occluded = self._view(np.array([x, y]), psi, others) if len(others) else (np.zeros(0),) * 3
        ids, draws, clutter = frame_draws(self, rng, chain, keys, in_view, occluded)
        rows, kept, n = assemble_frames(self.params, self.max_range, self.max_objects, np.array([[x, y, psi]]),
                                        others, np.array(ids, dtype=int), np.zeros(len(ids), dtype=int),
                                        np.asarray(r)[ids], np.array(draws).reshape(-1, 7),
                                        np.zeros(len(clutter), dtype=int), np.array(clutter).reshape(-1, 3))
        return rows[0, : n[0]], kept[0, : n[0]]

    def _frame(self) -> None:
        x, y, psi, _ = ego_pose(self.env)
        others = others_state(self.env)
        unwrapped = self.env.unwrapped
        vehicles = [v for v in unwrapped.road.vehicles if v is not unwrapped.vehicle]
        det, ids = self._world_frame(self.rng, self._missing, vehicles, x, y, psi, others)
        if self.frame == "ego":
            c, s = np.cos(psi), np.sin(psi)
            rot = np.array([[c, s], [-s, c]])  # world → ego (x forward, y right in highway-env's y-down frame)
            det[:, 1:3] = (det[:, 1:3] - np.array([x, y])) @ rot.T
            det[:, 3:5] = det[:, 3:5] @ rot.T
            det[:, 5] = det[:, 5] - psi
        det[:, 5] = (det[:, 5] + np.pi) % (2 * np.pi) - np.pi
        self._rows = np.zeros((self.max_objects, len(FIELDS)), dtype=np.float32)
        self._rows[: len(det), :8] = det
        self.truth_ids = np.full(self.max_objects, -1)
        self.truth_ids[: len(ids)] = ids

    def invalidate(self, raw: np.ndarray, clean: np.ndarray) -> np.ndarray:
        """A row that held NaN/inf (see ``SensorWrapper._guarded``) is dropped: all zeros, present = 0, as an unused
        row, rather than a present object with a 0 put in place of the NaN."""
        bad = ~np.all(np.isfinite(raw), axis=-1)
        return np.where(bad[:, None], np.float32(0.0), clean).astype(np.float32)

    def measure(self) -> np.ndarray:
        t = sim_time(self.env)
        if t + 1e-9 >= self._next_frame:
            self._frame()
            self._frame_time = t
            self._next_frame = t + 1.0 / self.rate_hz
        out = self._rows.copy()
        out[:, 8] = np.where(out[:, 0] > 0, t - self._frame_time, 0.0)
        space = self.observation_space[self.key]
        return np.clip(out, space.low, space.high)
