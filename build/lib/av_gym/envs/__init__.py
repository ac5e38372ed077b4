"""Scenario environments (highway-env based). Importing :mod:`av_gym` registers them with Gymnasium."""

from av_gym.envs.lane_keeping import LaneKeepingLapEnv
from av_gym.envs.left_turn import UnprotectedLeftTurnEnv

__all__ = ["LaneKeepingLapEnv", "UnprotectedLeftTurnEnv"]
