"""Episode metrics (lane keeping, left turn) and aggregation statistics."""

from av_gym.metrics.lane_keeping import LANE_UNITS, lane_keeping_summary
from av_gym.metrics.left_turn import STOP_SPEED, left_turn_summary
from av_gym.metrics.kinds import METRIC_KINDS, kind_of
from av_gym.metrics.stats import aggregate, bootstrap_ci, format_ci, interval, markdown_table, mean_ci, wilson_ci

__all__ = [
    "LANE_UNITS",
    "STOP_SPEED",
    "aggregate",
    "format_ci",
    "METRIC_KINDS",
    "bootstrap_ci",
    "interval",
    "kind_of",
    "lane_keeping_summary",
    "left_turn_summary",
    "markdown_table",
    "mean_ci",
    "wilson_ci",
]
