"""Episode metrics (lane keeping, left turn) and aggregation statistics."""

from av_gym.metrics.lane_keeping import LANE_UNITS, lane_keeping_summary
from av_gym.metrics.left_turn import STOP_SPEED, left_turn_summary
from av_gym.metrics.stats import aggregate, format_ci, is_binary, markdown_table, mean_ci, wilson_ci

__all__ = [
    "LANE_UNITS",
    "STOP_SPEED",
    "aggregate",
    "format_ci",
    "is_binary",
    "lane_keeping_summary",
    "left_turn_summary",
    "markdown_table",
    "mean_ci",
    "wilson_ci",
]
