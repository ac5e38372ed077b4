"""``ObjectTracker``: the multi-object Kalman tracker (:mod:`av_gym.estimation.tracker`) as an estimator wrapper,
turning the detector's noisy, gappy object list (``obs["detector"]``) into confirmed tracks (``obs["tracks"]``).

This is how an agent drives "on perceived objects": it sees tracks, never the simulator's vehicles. (The AEB
shield in perceived mode builds its own detector and tracker, like a car's AEB has its own sensor.)
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.errors import ConfigError
from av_gym.estimation.tracker import MultiObjectTracker, TrackerParams, TrackingModel
from av_gym.params import ROWS_MAX, ParamError, param
from av_gym.sensors.base import SensorWrapper, ego_pose, find_wrapper, sim_time

FIELDS = ("present", "x", "y", "vx", "vy", "heading", "length", "width")
BOUND = 1e4


@dataclass(frozen=True)
class ObjectTrackerParams(TrackingModel):
    """:class:`ObjectTracker`'s parameters: the tracker's model (:class:`~av_gym.estimation.tracker.TrackingModel`),
    the rows of the observation, and the measurement noise, which defaults to the detector's own error model."""

    max_tracks: int = param(16, ge=1, le=ROWS_MAX, doc="rows of obs['tracks']")
    sigma_pos0: float | None = param(None, "m", gt=0, doc="position noise at zero range; null = the detector's")
    sigma_pos_k: float | None = param(None, "m/m", ge=0, doc="position noise growth per metre of range; null = the "
                                                             "detector's")
    sigma_vel: float | None = param(None, "m/s", gt=0, doc="velocity noise; null = the detector's")


def tracker_params(p: ObjectTrackerParams, detector) -> TrackerParams:
    """The tracker's parameters for ``p`` over a detector with :class:`~av_gym.sensors.detector.DetectorParams`
    ``detector``: the detector's error model is the tracker's R, unless ``p`` sets it (the per-env
    :class:`ObjectTracker` and the batch's tracker both build theirs here)."""
    noise = {name: getattr(detector, name) if getattr(p, name) is None else getattr(p, name)
             for name in ("sigma_pos0", "sigma_pos_k", "sigma_vel")}
    model = {name: getattr(p, name) for name in TrackingModel.field_names()}
    try:
        return TrackerParams(**model, **noise)
    except ParamError as exc:
        raise ParamError(f"{exc} (the detector's, the tracker's measurement noise unless set here)") from None


class ObjectTracker(SensorWrapper):
    """Adds ``obs["tracks"]``: ``Box(max_tracks, 8)`` rows ``[present, x, y, vx, vy, heading, length, width]``
    (world frame, m, m/s, rad), confirmed tracks nearest the ego first, zero rows unused. Parameters:
    :class:`ObjectTrackerParams`. Needs a ``detector`` with ``frame: world`` below it in the stack."""

    key = "tracks"
    Params = ObjectTrackerParams

    def __init__(self, env: gym.Env, params: ObjectTrackerParams | None = None, **overrides) -> None:
        p = self.params = ObjectTrackerParams.build(params, **overrides)
        detector = _find_detector(env)
        if detector is None:
            raise ConfigError("sensors.tracker needs a detector below it (add `detector:` to the sensors preset)")
        if detector.frame != "world":
            raise ConfigError(f"sensors.tracker needs sensors.detector.frame=world, got {detector.frame!r}")
        self.tracker = MultiObjectTracker(tracker_params(p, detector.params))
        self.max_tracks = int(p.max_tracks)
        super().__init__(env)
        self._last = np.zeros((self.max_tracks, len(FIELDS)), dtype=np.float32)

    def sensor_space(self) -> spaces.Box:
        return spaces.Box(-BOUND, BOUND, shape=(self.max_tracks, len(FIELDS)), dtype=np.float32)

    def on_reset(self) -> None:
        self.tracker.reset()

    def observation(self, observation: dict) -> dict:
        ego_xy = ego_pose(self.env)[:2]  # range for the range-dependent R; the ego knows where its sensor is
        tracks = self.tracker.step(observation["detector"], sim_time(self.env), ego_xy)
        rows = np.zeros((self.max_tracks, len(FIELDS)), dtype=np.float32)
        if len(tracks):
            tracks = tracks[np.isfinite(tracks).all(axis=1)]  # a diverged filter never reaches the agent
            order = np.argsort(np.hypot(tracks[:, 0] - ego_xy[0], tracks[:, 1] - ego_xy[1]))[: self.max_tracks]
            rows[: len(order), 0] = 1.0
            rows[: len(order), 1:] = np.clip(tracks[order], -BOUND, BOUND)
        self._last = rows
        return {**observation, self.key: rows}

    def measure(self) -> np.ndarray:
        return self._last.copy()


def _find_detector(env: gym.Env):
    from av_gym.sensors.detector import Detector

    return find_wrapper(env, Detector)
