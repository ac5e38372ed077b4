"""Known-answer tests for av_gym.metrics (lane keeping, left turn, stats)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from av_gym.metrics import (
    LANE_UNITS,
    STOP_SPEED,
    aggregate,
    format_ci,
    lane_keeping_summary,
    left_turn_summary,
    markdown_table,
    mean_ci,
    wilson_ci,
)

# ---------------------------------------------------------------- lane keeping

LANE = 4.0  # m
CAR = 2.0  # m -> a wheel crosses the line once |cte| > 4/2 - 2/2 = 1.0 m


def _lk(cte, steering=None, progress=None, **kw):
    cte = np.asarray(cte, dtype=float)
    n = cte.size
    if steering is None:
        steering = np.zeros(n)
    if progress is None:
        progress = np.linspace(0.0, 10.0, n)
    args = dict(lane_width=LANE, vehicle_width=CAR, lap_length=100.0, lap_completed=False)
    args.update(kw)
    return lane_keeping_summary(cte, steering, progress, **args)


def test_sine_cte_rms_is_amplitude_over_sqrt2():
    # 4 whole periods sampled at 400 points (endpoint excluded): the discrete
    # sum of sin^2 is exactly N/2 and the mean exactly 0; N divisible by 16
    # puts samples on the peaks, so max |cte| = A.
    amp = 0.6
    n = 400
    phase = 2.0 * np.pi * 4.0 * np.arange(n) / n
    s = _lk(amp * np.sin(phase))
    assert s["cte_rms_m"] == pytest.approx(amp / math.sqrt(2.0), rel=1e-12)
    assert s["cte_std_m"] == pytest.approx(amp / math.sqrt(2.0), rel=1e-12)
    assert s["cte_bias_m"] == pytest.approx(0.0, abs=1e-12)
    assert s["cte_max_abs_m"] == pytest.approx(amp, rel=1e-12)
    # Continuous mean |sin| is 2/pi; 100 samples per period are close to it.
    assert s["cte_mean_abs_m"] == pytest.approx(2.0 * amp / math.pi, rel=1e-3)
    # 0.6 m in a 4 m lane is 15 units.
    assert s["cte_max_abs_units"] == pytest.approx(amp / LANE * LANE_UNITS)
    assert s["lane_departures"] == 0.0
    assert s["time_fraction_out_of_lane"] == 0.0


def test_biased_two_point_trace_raw_and_centred_units():
    # cte = [1, 3] m in a 4 m lane -> u = [25, 75]; mean 50, centred MAE 25.
    s = lane_keeping_summary(
        np.array([1.0, 3.0]),
        np.zeros(2),
        np.array([0.0, 1.0]),
        lane_width=LANE,
        vehicle_width=CAR,
        lap_length=100.0,
        lap_completed=True,
    )
    assert s["cte_bias_m"] == pytest.approx(2.0)
    assert s["cte_mean_abs_m"] == pytest.approx(2.0)
    assert s["cte_rms_m"] == pytest.approx(math.sqrt(5.0))
    assert s["cte_std_m"] == pytest.approx(1.0)
    assert s["cte_mean_abs_units"] == pytest.approx(50.0)
    assert s["cte_std_units"] == pytest.approx(25.0)
    assert s["cte_max_abs_units"] == pytest.approx(75.0)
    assert s["cte_centred_mae_units"] == pytest.approx(25.0)
    assert s["lap_completed"] == 1.0
    # 1.0 m sits exactly on the threshold (inside); 3.0 m is out -> one departure.
    assert s["lane_departures"] == 1.0
    assert s["time_fraction_out_of_lane"] == 0.5


def test_step_trace_departures_and_time_out():
    # Threshold 1.0 m; exactly 1.0 is still inside.
    cte = [0.0, 0.5, 1.2, 1.5, 0.8, -1.1, -0.2, 1.0, 1.01]
    # out:   F    F    T    T    F     T     F    F    T   -> 3 entries, 4/9 out
    s = _lk(cte)
    assert s["lane_departures"] == 3.0
    assert s["time_fraction_out_of_lane"] == pytest.approx(4.0 / 9.0)


def test_trace_starting_out_of_lane_counts_one_departure():
    s = _lk([1.5, 0.0, 0.0])
    assert s["lane_departures"] == 1.0
    assert s["time_fraction_out_of_lane"] == pytest.approx(1.0 / 3.0)


def test_steering_sign_changes_per_100m_with_deadband():
    # Non-deadband samples: 0.1, -0.1, -0.2, 0.3, 0.3, -0.3 -> 3 sign changes.
    # The 0.0005 jitter between -0.1 and -0.2 and the exact 0 are ignored.
    steering = [0.1, -0.1, 0.0005, -0.2, 0.3, 0.0, 0.3, -0.3]
    progress = np.linspace(0.0, 50.0, len(steering))
    s = _lk(np.zeros(len(steering)), steering, progress)
    assert s["distance_m"] == pytest.approx(50.0)
    assert s["steering_sign_changes_per_100m"] == pytest.approx(3.0 / 50.0 * 100.0)
    # With no deadband the jitter sample now flips sign twice more
    # (-0.1 -> +0.0005 -> -0.2); exact zeros are still signless and skipped.
    s0 = _lk(np.zeros(len(steering)), steering, progress, steer_deadband=0.0)
    assert s0["steering_sign_changes_per_100m"] == pytest.approx(5.0 / 50.0 * 100.0)


def test_zero_distance_gives_zero_sign_change_rate():
    s = _lk([0.0, 0.0, 0.0], [0.1, -0.1, 0.1], [5.0, 5.0, 5.0])
    assert s["distance_m"] == 0.0
    assert s["steering_sign_changes_per_100m"] == 0.0
    assert s["lap_fraction"] == 0.0


def test_lap_fraction_is_distance_over_lap_and_capped():
    assert _lk([0.0, 0.0], progress=[10.0, 35.0], lap_length=100.0)["lap_fraction"] == pytest.approx(0.25)
    s = _lk([0.0, 0.0], progress=[0.0, 250.0], lap_length=100.0)
    assert s["lap_fraction"] == 1.0
    assert s["distance_m"] == pytest.approx(250.0)


def test_single_sample_trace():
    s = _lk([-0.5], [0.2], [3.0])
    assert s["cte_bias_m"] == -0.5
    assert s["cte_std_m"] == 0.0
    assert s["cte_centred_mae_units"] == 0.0
    assert s["distance_m"] == 0.0
    assert all(isinstance(v, float) for v in s.values())


@pytest.mark.parametrize(
    "cte, steering, progress, kw, name",
    [
        ([], [], [], {}, "cte"),
        ([0.0, 0.0], [0.0], [0.0, 1.0], {}, "length"),
        ([0.0, np.nan], [0.0, 0.0], [0.0, 1.0], {}, "cte"),
        ([0.0, 0.0], [0.0, np.inf], [0.0, 1.0], {}, "steering"),
        ([0.0, 0.0], [0.0, 0.0], [0.0, 1.0], {"lane_width": 0.0}, "lane_width"),
        ([0.0, 0.0], [0.0, 0.0], [0.0, 1.0], {"lane_width": -3.0}, "lane_width"),
        ([0.0, 0.0], [0.0, 0.0], [0.0, 1.0], {"lap_length": 0.0}, "lap_length"),
    ],
)
def test_lane_keeping_validation(cte, steering, progress, kw, name):
    args = dict(lane_width=LANE, vehicle_width=CAR, lap_length=100.0, lap_completed=False)
    args.update(kw)
    with pytest.raises(ValueError, match=name):
        lane_keeping_summary(np.asarray(cte, float), np.asarray(steering, float), np.asarray(progress, float), **args)


# ------------------------------------------------------------------ left turn


def _episode():
    """Approach, creep to a stop behind the line, then turn and exit at t=2.5 s."""
    return dict(
        time=np.array([0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0]),
        speed=np.array([5.0, 2.0, 0.05, 0.0, 3.0, 6.0, 8.0]),
        collision=np.zeros(7, dtype=bool),
        arrived=np.array([0, 0, 0, 0, 0, 1, 1], dtype=bool),
        ttc=np.array([np.inf, 8.0, 20.0, np.inf, 3.5, 12.0, np.inf]),
        stop_line_offset=np.array([-10.0, -4.0, -1.5, -1.5, 2.0, 8.0, 15.0]),
        oncoming_gap=np.array([5.0, 4.0, 3.2, 3.2, 1.0, -0.5, -2.0]),
    )


def test_left_turn_successful_episode():
    s = left_turn_summary(**_episode())
    assert s["collision"] == 0.0
    assert s["success"] == 1.0
    assert s["time_to_exit_s"] == 2.5
    assert s["min_ttc_s"] == 3.5
    assert s["stopped"] == 1.0
    # First step below STOP_SPEED is index 2 (0.05 m/s).
    assert s["stop_line_offset_at_stop_m"] == -1.5
    assert s["oncoming_gap_at_stop_m"] == 3.2
    # Steps 0..4 are before the first arrival; the -0.5 / -2.0 after are not.
    assert s["min_oncoming_gap_before_exit_m"] == 1.0
    assert s["mean_speed_mps"] == pytest.approx(24.05 / 7.0)
    assert s["duration_s"] == 3.0
    assert all(isinstance(v, float) for v in s.values())


def test_left_turn_collision_is_not_success():
    ep = _episode()
    ep["collision"] = np.array([0, 0, 0, 0, 1, 1, 1], dtype=bool)
    s = left_turn_summary(**ep)
    assert s["collision"] == 1.0
    assert s["success"] == 0.0


def test_left_turn_never_arrived_never_stopped_all_inf_ttc():
    ep = _episode()
    ep["arrived"] = np.zeros(7, dtype=bool)
    ep["speed"] = np.full(7, 4.0)
    ep["ttc"] = np.full(7, np.inf)
    s = left_turn_summary(**ep, ttc_cap=7.5)
    assert math.isnan(s["time_to_exit_s"])
    assert s["success"] == 0.0
    assert s["min_ttc_s"] == 7.5
    assert s["stopped"] == 0.0
    assert math.isnan(s["stop_line_offset_at_stop_m"])
    assert math.isnan(s["oncoming_gap_at_stop_m"])
    # Never arrived -> the whole episode counts.
    assert s["min_oncoming_gap_before_exit_m"] == -2.0


def test_left_turn_stop_after_arrival_does_not_count():
    ep = _episode()
    ep["speed"] = np.array([5.0, 5.0, 5.0, 5.0, 5.0, 5.0, STOP_SPEED / 2])
    s = left_turn_summary(**ep)
    assert s["stopped"] == 0.0
    assert math.isnan(s["stop_line_offset_at_stop_m"])


def test_left_turn_speed_exactly_stop_speed_is_not_stopped():
    ep = _episode()
    ep["speed"] = np.full(7, STOP_SPEED)
    assert left_turn_summary(**ep)["stopped"] == 0.0


@pytest.mark.parametrize(
    "key, value, name",
    [
        ("time", np.zeros(6), "same length"),
        ("speed", np.array([0.0, np.nan, 0, 0, 0, 0, 0]), "speed"),
        ("ttc", np.array([np.nan, 1, 1, 1, 1, 1, 1]), "ttc"),
        ("ttc", np.array([-np.inf, 1, 1, 1, 1, 1, 1]), "ttc"),
        ("oncoming_gap", np.array([np.inf, 1, 1, 1, 1, 1, 1]), "oncoming_gap"),
        ("arrived", np.array([0, 2, 0, 0, 0, 0, 0]), "arrived"),
    ],
)
def test_left_turn_validation(key, value, name):
    ep = _episode()
    ep[key] = value
    with pytest.raises(ValueError, match=name):
        left_turn_summary(**ep)


def test_left_turn_empty_raises():
    ep = {k: np.array([]) for k in _episode()}
    with pytest.raises(ValueError, match="time"):
        left_turn_summary(**ep)


# ---------------------------------------------------------------------- stats


def test_mean_ci_known_values():
    # [0, 2]: mean 1, s = sqrt(2), sem = 1, t_{0.975, 1} = 12.706.
    m, h = mean_ci([0.0, 2.0])
    assert m == 1.0
    assert h == pytest.approx(12.7062, abs=1e-4)
    # 1..5: mean 3, s = sqrt(2.5), sem = sqrt(0.5), t_{0.975, 4} = 2.7764.
    m, h = mean_ci([1, 2, 3, 4, 5])
    assert m == 3.0
    assert h == pytest.approx(2.7764451 * math.sqrt(0.5), rel=1e-6)
    # 90% uses t_{0.95, 4} = 2.1318.
    assert mean_ci([1, 2, 3, 4, 5], 0.90)[1] == pytest.approx(2.1318468 * math.sqrt(0.5), rel=1e-6)


def test_mean_ci_edge_cases():
    assert mean_ci([3.0, 3.0, 3.0]) == (3.0, 0.0)
    m, h = mean_ci([7.0])
    assert m == 7.0 and math.isnan(h)
    m, h = mean_ci([])
    assert math.isnan(m) and math.isnan(h)
    m, h = mean_ci([np.nan, np.nan])
    assert math.isnan(m) and math.isnan(h)
    # NaNs are dropped before counting: same answer as [0, 2].
    m, h = mean_ci([0.0, np.nan, 2.0])
    assert m == 1.0 and h == pytest.approx(12.7062, abs=1e-4)
    with pytest.raises(ValueError, match="confidence"):
        mean_ci([1.0, 2.0], confidence=1.5)


def test_wilson_known_values():
    # 5/10 at 95%: the textbook interval is (0.2366, 0.7634).
    p, lo, hi = wilson_ci(5, 10)
    assert p == 0.5
    assert lo == pytest.approx(0.2366, abs=1e-4)
    assert hi == pytest.approx(0.7634, abs=1e-4)
    # 0/n and n/n have closed forms: hi = z^2/(n+z^2), lo = n/(n+z^2).
    z2 = 1.959964**2
    p, lo, hi = wilson_ci(0, 10)
    assert (p, lo) == (0.0, 0.0)
    assert hi == pytest.approx(z2 / (10 + z2), rel=1e-5)
    p, lo, hi = wilson_ci(10, 10)
    assert (p, hi) == (1.0, 1.0)
    assert lo == pytest.approx(10 / (10 + z2), rel=1e-5)


@pytest.mark.parametrize("n", [1, 2, 3, 10, 1000])
def test_wilson_stays_in_unit_interval(n):
    for k in (0, n):
        p, lo, hi = wilson_ci(k, n)
        assert 0.0 <= lo <= p <= hi <= 1.0


def test_wilson_edge_cases():
    assert all(math.isnan(v) for v in wilson_ci(0, 0))
    with pytest.raises(ValueError):
        wilson_ci(3, 2)
    with pytest.raises(ValueError):
        wilson_ci(-1, 2)


def test_aggregate_groups_binary_and_continuous():
    rows = [
        {"agent": "ppo", "seed": 0, "episode": 0, "success": 1.0, "cte": 0.0},
        {"agent": "pid", "seed": 0, "episode": 0, "success": 0.0, "cte": 1.0},
        {"agent": "ppo", "seed": 1, "episode": 1, "success": 0.0, "cte": 2.0},
        {"agent": "ppo", "seed": 2, "episode": 2, "success": 1.0, "cte": float("nan")},
    ]
    out = aggregate(rows)
    assert [r["agent"] for r in out] == ["ppo", "pid"]  # first-appearance order
    ppo, pid = out
    assert set(ppo) == {"agent", "n", "success", "success_lo", "success_hi", "cte", "cte_lo", "cte_hi"}
    assert ppo["n"] == 3 and pid["n"] == 1
    # success is 0/1 everywhere -> Wilson interval for 2 of 3.
    assert (ppo["success"], ppo["success_lo"], ppo["success_hi"]) == pytest.approx(wilson_ci(2, 3))
    # cte: NaN dropped, [0, 2] -> 1 +/- 12.706.
    assert ppo["cte"] == 1.0
    assert ppo["cte_lo"] == pytest.approx(1.0 - 12.7062, abs=1e-4)
    assert ppo["cte_hi"] == pytest.approx(1.0 + 12.7062, abs=1e-4)
    # One pid episode: continuous half-width undefined.
    assert pid["cte"] == 1.0 and math.isnan(pid["cte_lo"]) and math.isnan(pid["cte_hi"])
    assert (pid["success"], pid["success_lo"], pid["success_hi"]) == pytest.approx(wilson_ci(0, 1))


def test_aggregate_explicit_metrics_and_group_key():
    rows = [{"policy": "a", "x": 1.0, "y": 5.0}, {"policy": "a", "x": 3.0, "y": 5.0}]
    out = aggregate(rows, group_key="policy", metrics=["x"])
    assert out == [
        {"policy": "a", "n": 2, "x": 2.0, "x_lo": pytest.approx(2.0 - 12.7062, abs=1e-4),
         "x_hi": pytest.approx(2.0 + 12.7062, abs=1e-4)}
    ]


def test_markdown_table():
    rows = [{"agent": "ppo", "n": 3, "cte": 0.123456}, {"agent": "pid", "n": 1, "cte": float("nan")}]
    assert markdown_table(rows, ["agent", "n", "cte"]) == (
        "| agent | n | cte |\n"
        "| --- | --- | --- |\n"
        "| ppo | 3 | 0.123 |\n"
        "| pid | 1 | \u2013 |"
    )
    assert markdown_table(rows[:1], ["cte"], floatfmt=".1f").splitlines()[-1] == "| 0.1 |"


def test_format_ci():
    assert format_ci(0.38, 0.29, 0.48, binary=True) == "0.38 [0.29, 0.48]"
    assert format_ci(0.5, 0.2366, 0.7634, binary=True) == "0.50 [0.24, 0.76]"
    assert format_ci(1.23456, 0.5, 2.0, binary=False) == "1.23 [0.5, 2]"
    assert format_ci(7.0, float("nan"), float("nan"), binary=False) == "7"
    assert format_ci(float("nan"), float("nan"), float("nan"), binary=True) == "\u2013"
