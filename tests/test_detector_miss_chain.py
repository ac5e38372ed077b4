"""The detector's miss chain (av_gym.sensors.detector.miss_chain) and the bound DetectorParams puts on it: refused
exactly where the chain's P(miss | seen) would not be a probability, and where accepted the chain has the stationary
miss rate and mean run of misses it was asked for (Gilbert-Elliott: a two-state Markov chain)."""

from __future__ import annotations

import itertools

import pytest

from av_gym.errors import ConfigError
from av_gym.sensors.detector import DetectorParams, miss_chain

RATES = (0.0, 0.1, 0.3, 0.5, 0.6, 0.75, 0.9)
BURSTS = (None, 1.0, 1.2, 1.5, 2.0, 3.0, 5.0, 9.0)


@pytest.mark.parametrize("rate, burst", list(itertools.product(RATES, BURSTS)))
def test_the_params_refuse_exactly_the_chains_that_are_not_probabilities(rate, burst):
    p, q = miss_chain(rate, burst)
    if p > 1.0:
        with pytest.raises(ConfigError, match=r"miss_rate .* needs .*burst_length >= "):
            DetectorParams(miss_rate=rate, burst_length=burst)
        return
    DetectorParams(miss_rate=rate, burst_length=burst)
    assert 0.0 <= p <= 1.0 and 0.0 < q <= 1.0
    # stationary: P(missed) = p / (p + q); mean run of misses 1 / q frames (independent misses: q = 1 - rate)
    assert p / (p + q) == pytest.approx(rate, abs=1e-12)
    assert 1.0 / q == pytest.approx(1.0 / (1.0 - rate) if burst is None else burst)


def test_the_grid_holds_both_kinds():
    """Both branches above are exercised: some pairs refused (m / (1 - m) > burst), most accepted."""
    refused = [(m, b) for m, b in itertools.product(RATES, BURSTS) if miss_chain(m, b)[0] > 1.0]
    assert (0.9, 3.0) in refused and (0.6, 1.2) in refused and (0.6, 1.5) not in refused
    assert 0 < len(refused) < len(RATES) * len(BURSTS) // 2
