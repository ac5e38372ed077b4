"""State estimation on top of the sensors: the multi-object Kalman tracker (objects from the detector)."""

from av_gym.estimation.tracker import TRACK_FIELDS, MultiObjectTracker, Track, TrackerParams

__all__ = ["TRACK_FIELDS", "MultiObjectTracker", "Track", "TrackerParams"]
