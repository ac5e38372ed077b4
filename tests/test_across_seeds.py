"""A method over training seeds: rliable's IQM and the stratified bootstrap over seeds and episodes."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.metrics.across_seeds import across_seeds, iqm
from av_gym.metrics.stats import wilson_ci


def test_iqm_is_the_mean_of_the_middle_half():
    """rliable's IQM: floor(n/4) runs cut from each end, the rest averaged."""
    assert iqm([1.0, 2.0, 3.0, 4.0, 100.0]) == pytest.approx(3.0)  # 5 runs: best and worst cut
    assert iqm([7.0, 0.0, 5.0, 1.0, 6.0, 2.0, 4.0, 3.0]) == pytest.approx(3.5)  # 8 runs: 2 cut each end
    assert iqm([0.1, 0.2, 0.9]) == pytest.approx(0.4)  # 3 runs: floor(0.75) = 0, nothing cut
    assert np.allclose(iqm([[1.0, 2.0, 3.0, 4.0, 100.0], [0.0, 0.0, 1.0, 1.0, 1.0]], axis=1), [3.0, 2 / 3])


def _seeds(rates: list[float], episodes: int, seed: int = 7) -> list[np.ndarray]:
    """Per training seed, ``episodes`` 0/1 outcomes with that seed's rate (a seeded generator)."""
    rng = np.random.default_rng(seed)
    return [(rng.random(episodes) < p).astype(float) for p in rates]


def test_the_interval_covers_the_mean_and_iqm_and_the_values_are_over_seeds():
    per_seed = _seeds([0.70, 0.75, 0.80, 0.78, 0.60], 1000)
    out = across_seeds(per_seed)
    scores = [a.mean() for a in per_seed]
    assert out["mean"][0] == pytest.approx(np.mean(scores))
    assert out["iqm"][0] == pytest.approx(np.mean(sorted(scores)[1:4]))
    for value, lo, hi in out.values():
        assert lo < value < hi
    assert across_seeds(per_seed) == out  # seeded: the same episodes give the same bounds


def test_the_interval_shrinks_with_more_seeds():
    rng = np.random.default_rng(3)
    rates = list(np.clip(rng.normal(0.75, 0.05, size=20), 0, 1))
    few, many = across_seeds(_seeds(rates[:3], 500)), across_seeds(_seeds(rates, 500))
    for stat in ("mean", "iqm"):
        assert many[stat][2] - many[stat][1] < 0.6 * (few[stat][2] - few[stat][1]), (stat, few, many)


def test_the_interval_counts_the_spread_between_seeds_not_only_episodes():
    """Two seeds far apart (0.2 and 0.8): pooling their episodes would give a Wilson interval of +-0.03; over
    seeds the method is one of two very different policies, and the interval says so."""
    per_seed = _seeds([0.2, 0.8], 1000)
    _, lo, hi = across_seeds(per_seed)["mean"]
    _, w_lo, w_hi = wilson_ci(int(sum(a.sum() for a in per_seed)), 2000)
    assert hi - lo > 0.4 > 5 * (w_hi - w_lo)
    assert lo < 0.3 and hi > 0.7


def test_episodes_within_a_seed_are_resampled_too():
    """Seeds with the same rate: the interval is the episodes' chance alone, not a point."""
    per_seed = [np.r_[np.ones(50), np.zeros(50)] for _ in range(4)]
    value, lo, hi = across_seeds(per_seed)["mean"]
    assert value == 0.5 and 0.03 < 0.5 - lo < 0.08 and 0.03 < hi - 0.5 < 0.08


def test_one_seed_is_refused_and_a_seed_without_values_is_undefined():
    with pytest.raises(ValueError, match="at least 2 training seeds"):
        across_seeds([np.ones(10)])
    out = across_seeds([np.ones(10), np.full(10, np.nan)])
    assert all(np.isnan(v) for v in out["mean"])


def test_a_rate_where_every_episode_ends_alike_keeps_the_episodes_chance():
    """5 seeds completing 20 of 20 laps each: no resample differs, and the percentile interval alone was the point
    [1, 1]; a rate's interval holds at least the pooled episodes' Wilson interval (100 of 100: [0.963, 1])."""
    per_seed = [np.ones(20) for _ in range(5)]
    assert across_seeds(per_seed)["mean"] == (1.0, 1.0, 1.0)  # a mean of anything: no spread to see
    _, w_lo, w_hi = wilson_ci(100, 100)
    for value, lo, hi in across_seeds(per_seed, rate=True).values():
        assert (value, lo, hi) == (1.0, pytest.approx(w_lo), w_hi) and 0.96 < lo < 0.97
    spread = _seeds([0.2, 0.8], 1000)  # where the seeds disagree the bootstrap is wider and is kept
    assert across_seeds(spread, rate=True) == across_seeds(spread)
