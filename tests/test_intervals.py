"""Intervals that respect each metric's declared kind (av_gym/metrics/kinds.py): never outside its range."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binomtest

from av_gym.metrics import METRIC_KINDS, aggregate, interval, wilson_ci
from av_gym.metrics.kinds import undeclared


def test_an_all_zero_count_gets_zero_zero():
    """interventions 0.00 [0.00, 0.28] came from treating an all-zero count as a rate: a count of zeros is 0."""
    assert interval(np.zeros(30), "count") == (0.0, 0.0, 0.0)
    (row,) = aggregate([{"agent": "a", "interventions": 0.0} for _ in range(30)])
    assert (row["interventions"], row["interventions_lo"], row["interventions_hi"]) == (0.0, 0.0, 0.0)


def test_a_positive_duration_near_zero_never_gets_a_negative_bound():
    """min_ttc_s 0.59 [-0.157, 1.34] was a t interval; the bootstrap stays in [min, max] of the episodes."""
    rng = np.random.default_rng(3)
    x = np.where(rng.random(12) < 0.8, 0.0, rng.exponential(3.0, 12))  # mostly 0 s, a few long: skewed
    mean, half = x.mean(), 2.2 * x.std(ddof=1) / np.sqrt(x.size)
    assert mean - half < 0  # a t interval would leave the range here
    m, lo, hi = interval(x, "duration")
    assert 0.0 <= lo <= m <= hi <= x.max() and m == pytest.approx(mean)
    assert hi > lo  # a real interval, not a point


def test_the_bootstrap_is_seeded():
    x = np.random.default_rng(1).exponential(1.0, 200)
    assert interval(x, "nonnegative") == interval(x, "nonnegative")


@pytest.mark.parametrize("k,n", [(0, 1), (0, 20), (1, 20), (19, 20), (20, 20), (19, 1000), (500, 1000)])
def test_rate_bounds_are_wilson_and_inside_zero_one(k, n):
    x = np.r_[np.ones(k), np.zeros(n - k)]
    p, lo, hi = interval(x, "rate")
    ref = binomtest(k, n).proportion_ci(method="wilson")
    assert (lo, hi) == pytest.approx((ref.low, ref.high), abs=1e-12) and (p, lo, hi) == wilson_ci(k, n)
    assert 0.0 <= lo <= p <= hi <= 1.0


def test_a_rate_that_is_not_zero_or_one_is_refused():
    with pytest.raises(ValueError, match="0 or 1"):
        interval([0.0, 0.5, 1.0], "rate")
    with pytest.raises(ValueError, match="cannot be negative"):
        interval([1.0, -0.5], "count")


def test_signed_quantities_get_student_t():
    m, lo, hi = interval([-1.0, 1.0, 3.0], "signed")
    assert m == 1.0 and hi - m == pytest.approx(m - lo) and lo < -1.0  # may cross zero: it has either sign


def test_every_metric_an_episode_row_carries_has_a_declared_kind(turn_cfg, lane_cfg):
    """A new metric without a kind would get a t interval with no range to respect."""
    from av_gym.make import make_env

    for cfg in (turn_cfg, lane_cfg):
        env = make_env(cfg, {"name": "truth"}, None)
        env.reset(seed=0)
        done = False
        while not done:
            *_, term, trunc, info = env.step(env.action_space.sample())
            done = term or trunc
        env.close()
        assert undeclared(info["episode_metrics"]) == []
    assert set(METRIC_KINDS.values()) <= {"rate", "count", "duration", "nonnegative", "signed"}
