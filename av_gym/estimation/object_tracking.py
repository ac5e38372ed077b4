"""``ObjectTracker``: the multi-object Kalman tracker (:mod:`av_gym.estimation.tracker`) as an estimator wrapper,
turning the detector's noisy, gappy object list (``obs["detector"]``) into confirmed tracks (``obs["tracks"]``).

This is how an agent drives "on perceived objects": it sees tracks, never the simulator's vehicles. (The AEB
shield in perceived mode builds its own detector and tracker, like a car's AEB has its own sensor.)
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.estimation.tracker import MultiObjectTracker
from av_gym.sensors.base import SensorWrapper, ego_pose, find_wrapper, sim_time

FIELDS = ("present", "x", "y", "vx", "vy", "heading", "length", "width")
BOUND = 1e4


class ObjectTracker(SensorWrapper):
    """Adds ``obs["tracks"]``: ``Box(max_tracks, 8)`` rows ``[present, x, y, vx, vy, heading, length, width]``
    (world frame, m, m/s, rad), confirmed tracks nearest the ego first, zero rows unused.

    Parameters (config ``sensors.tracker``): ``max_tracks`` (rows, default 16) and any keyword of
    :class:`~av_gym.estimation.tracker.MultiObjectTracker` (``sigma_acc``, ``min_hits``, ``max_coast``, ...). The
    tracker's measurement noise defaults to the detector's own error model, read from the detector wrapper below.
    Needs a ``detector`` with ``frame: world`` below it in the stack."""

    key = "tracks"

    def __init__(self, env: gym.Env, max_tracks: int = 16, **tracker) -> None:
        if int(max_tracks) < 1:
            raise ValueError(f"sensors.tracker.max_tracks must be >= 1, got {max_tracks}")
        detector = _find_detector(env)
        if detector is None:
            raise ValueError("sensors.tracker needs a detector below it (add `detector:` to the sensors preset)")
        if detector.frame != "world":
            raise ValueError(f"sensors.tracker needs sensors.detector.frame=world, got {detector.frame!r}")
        # The detector's error model is the tracker's R, unless the config says otherwise.
        noise = {"sigma_pos0": detector.sigma_pos0, "sigma_pos_k": detector.sigma_pos_k,
                 "sigma_vel": detector.sigma_vel}
        try:
            self.tracker = MultiObjectTracker(**{**noise, **tracker})
        except TypeError as exc:
            raise ValueError(f"sensors.tracker: {exc}") from None
        except ValueError as exc:
            raise ValueError(f"sensors.{exc}") from None
        self.max_tracks = int(max_tracks)
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
