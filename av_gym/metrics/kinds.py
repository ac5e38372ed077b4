"""What each episode metric is, declared beside the metrics, so its interval can respect it.

Why not guess the kind from the values (all 0/1 → a rate): that calls an all-zero ``min_ttc_s`` a rate and gives
t intervals that leave the metric's range (``min_ttc_s 0.59 [-0.157, 1.34]``). Each metric says:

- ``rate``: 0 or 1 per episode (collision, success): Wilson score interval on the count, inside [0, 1].
- ``count``: a non-negative integer per episode (interventions, lane departures): bootstrap of the mean.
- ``duration``: a non-negative time in s (time to exit, min TTC): bootstrap of the mean.
- ``nonnegative``: any other quantity that cannot be negative (|CTE|, speed, distance, a fraction of time):
  bootstrap of the mean.
- ``signed``: a quantity that can take either sign (return, CTE bias, offsets from a line): Student t.

A bootstrap of the mean (resampled episodes, seeded, :func:`av_gym.metrics.stats.bootstrap_ci`) cannot leave
[min, max] of the episodes, so a quantity that cannot be negative never gets a negative bound, and an all-zero count
gets [0, 0]; a t interval would go below zero whenever the mean is within two standard errors of it.
"""

from __future__ import annotations

from typing import Literal

Kind = Literal["rate", "count", "duration", "nonnegative", "signed"]
KINDS: tuple[str, ...] = ("rate", "count", "duration", "nonnegative", "signed")

# Every metric an episode row carries (av_gym/metrics/left_turn.py, lane_keeping.py, recorder.py): its kind.
METRIC_KINDS: dict[str, Kind] = {
    # left turn (left_turn_summary)
    "collision": "rate",
    "success": "rate",
    "stopped": "rate",
    "time_to_exit_s": "duration",
    "min_ttc_s": "duration",  # capped at 10 s: never negative, never infinite
    "stop_line_offset_at_stop_m": "signed",  # negative = before the line
    "oncoming_gap_at_stop_m": "signed",  # negative = inside the oncoming lane
    "min_oncoming_gap_before_exit_m": "signed",
    "mean_speed_mps": "nonnegative",
    "duration_s": "duration",
    # every scenario (EpisodeMetrics recorder)
    "return": "signed",
    "length": "count",  # policy steps
    "truncated": "rate",
    "override_fraction": "nonnegative",  # share of steps the shield overrode, in [0, 1]
    "intervention": "rate",  # the shield overrode at least once
    "interventions": "count",  # override onsets
    "first_override_s": "duration",
    "sensor_faults": "count",  # non-finite sensor entries replaced (info["sensor_faults"] summed)
    # lane keeping (lane_keeping_summary)
    "cte_mean_abs_m": "nonnegative",
    "cte_rms_m": "nonnegative",
    "cte_std_m": "nonnegative",
    "cte_max_abs_m": "nonnegative",
    "cte_bias_m": "signed",
    "cte_mean_abs_units": "nonnegative",
    "cte_std_units": "nonnegative",
    "cte_max_abs_units": "nonnegative",
    "cte_centred_mae_units": "nonnegative",
    "lap_completed": "rate",
    "lap_fraction": "nonnegative",
    "distance_m": "signed",  # progress along the lap: negative if the car drives backwards
    "lane_departures": "count",
    "time_fraction_out_of_lane": "nonnegative",
    "steering_sign_changes_per_100m": "nonnegative",
}


def kind_of(metric: str) -> Kind:
    """The declared kind of ``metric``; a metric nobody declared is ``signed`` (a t interval: no range is known
    to respect), which :func:`undeclared` lets a test catch."""
    return METRIC_KINDS.get(metric, "signed")


def undeclared(metrics) -> list[str]:
    """The names in ``metrics`` without a declared kind (identifiers such as ``seed`` are not metrics)."""
    return [m for m in metrics if m not in METRIC_KINDS and m not in ("agent", "episode", "seed", "split")]
