"""Each model once: the turn-signal channel, the intent features (acceleration, the signal read on an
object) and the turn features' closest approach have one implementation, vectorised over a leading batch axis,
that the per-env wrappers call with a batch of one and the batched left turn with every env at once. Here: the
callers use those functions (not copies), a batch gives row for row what a batch of one gives on >= 10,000 random
inputs, and the shield's Bayes filter reads the likelihood of the very channel that draws the readings."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from av_gym.batched import left_turn as batched
from av_gym.estimation import turn_features
from av_gym.estimation.turn_features import T_MAX, acceleration, path_conflict, signals_at
from av_gym.params import ParamError
from av_gym.sensors import turn_signal
from av_gym.sensors.turn_signal import (DRIVER_DRAWS, LEFT, NONE, RIGHT, TurnSignalsParams, channel_likelihood,
                                        draws_needed, driver_kinds, first_sighting, read_channel, reported)
from av_gym.shields import aeb_improved as aeb
from av_gym.shields import intent

N = 10_000  # random inputs per model


def _calls(function, name: str) -> bool:
    """``function``'s code calls ``name`` (a global of its module)."""
    return name in inspect.getsource(function) and name in function.__code__.co_names


def test_the_stacks_call_the_one_implementation():
    # the per-env sensor, the batched stack and the shield draw the indicator channel through the same functions
    assert batched.read_channel is turn_signal.read_channel and _calls(batched.BatchedIntent.signals, "read_channel")
    assert _calls(turn_signal.TurnSignals.measure, "read_channel")
    assert aeb.first_sighting is turn_signal.first_sighting and aeb.reported is turn_signal.reported
    assert _calls(aeb.ImprovedAEB._intent, "first_sighting") and _calls(aeb.ImprovedAEB._intent, "reported")
    assert batched.turn_signal is turn_signal.turn_signal and _calls(turn_signal.intended_signal, "turn_signal")
    # the shield's belief: the channel's own likelihood and driver-kind prior
    assert _calls(intent.reading_likelihood, "channel_likelihood") and _calls(intent.DriverIntent.__init__,
                                                                              "driver_kinds")
    # intent features and the closest approach: TurnIntent / TurnFeatures and the batch call the same functions
    for name in ("acceleration", "signals_at", "path_conflict"):
        assert getattr(batched, name) is getattr(turn_features, name)
    assert _calls(turn_features.TurnIntent._acceleration, "acceleration")
    assert _calls(turn_features.TurnIntent.observation, "signals_at")
    assert _calls(turn_features.TurnFeatures._path_conflict, "path_conflict")
    assert _calls(batched.BatchedIntent.intent, "acceleration") and _calls(batched.BatchedIntent.intent, "signals_at")
    assert _calls(batched.BatchedLeftTurn._path_conflict, "path_conflict")


def test_indicator_channel_batch_equals_batches_of_one():
    """read_channel on 10,000 envs at once (the batched stack) = env by env (the per-env sensor), draws included."""
    rng = np.random.default_rng(0)
    p = TurnSignalsParams(no_signal_rate=0.3, wrong_rate=0.2, miss_rate=0.25)
    n, k = N, 6
    in_range = rng.uniform(size=(n, k)) < 0.7
    new = in_range & (rng.uniform(size=(n, k)) < 0.5)
    intended = rng.choice([LEFT, NONE, RIGHT], size=(n, k))
    indicates, wrong = rng.uniform(size=(n, k)) < 0.7, rng.uniform(size=(n, k)) < 0.2
    widths = draws_needed(in_range, new).sum(axis=1)
    u = rng.uniform(size=int(widths.sum()))
    signal, ind, wr = read_channel(u, in_range, new, intended, indicates, wrong, p)
    start = np.concatenate([[0], np.cumsum(widths)])
    for r in range(n):
        one = read_channel(u[start[r]:start[r + 1]], in_range[r:r + 1], new[r:r + 1], intended[r:r + 1],
                           indicates[r:r + 1], wrong[r:r + 1], p)
        assert np.array_equal(one[0][0], signal[r]) and np.array_equal(one[1][0], ind[r]) and \
            np.array_equal(one[2][0], wr[r])
    # and each reading is the scalar model: a driver's first-sighting draws, then its seen? draw
    r = int(np.flatnonzero(new.any(axis=1))[0])
    j = int(np.flatnonzero(new[r])[0])
    offset = start[r] + draws_needed(in_range[r, :j], new[r, :j]).sum()
    first = first_sighting(u[offset:offset + DRIVER_DRAWS], p)
    assert (ind[r, j], wr[r, j]) == (bool(first[0]), bool(first[1]))
    assert signal[r, j] == reported(intended[r, j], first[0], first[1], u[offset + DRIVER_DRAWS], p)


def test_channel_draws_match_the_likelihood_the_shield_filters_with():
    """Readings drawn by first_sighting/reported have the frequencies channel_likelihood x driver_kinds give."""
    rng = np.random.default_rng(1)
    p = TurnSignalsParams(no_signal_rate=0.25, wrong_rate=0.1, miss_rate=0.2)
    n = 200_000
    for turn in (RIGHT, NONE, LEFT):
        indicates, wrong = first_sighting(rng.uniform(size=(n, DRIVER_DRAWS)), p)
        readings = reported(np.full(n, turn), indicates, wrong, rng.uniform(size=n), p)
        expected = np.array([channel_likelihood(r, p.miss_rate)[int(turn) + 1] @ driver_kinds(p)
                             for r in (RIGHT, NONE, LEFT)])
        observed = np.array([(readings == r).mean() for r in (RIGHT, NONE, LEFT)])
        assert np.allclose(observed, expected, atol=0.005), (turn, observed, expected)


def test_intent_and_turn_features_batch_equals_batches_of_one():
    rng = np.random.default_rng(2)
    n, m, s = N, 4, 3
    objects = rng.normal(0.0, 20.0, size=(n, m, 4))
    dt = rng.uniform(0.1, 0.5, size=n)
    then = objects[:, rng.permutation(m)].copy()  # the same objects dt ago, some moved, some not matched
    then[..., :2] -= then[..., 2:4] * dt[:, None, None]
    then += rng.normal(0.0, 1.0, size=then.shape)
    valid = rng.uniform(size=then.shape[:2]) < 0.8
    signals = np.concatenate([rng.uniform(size=(n, s, 1)) < 0.7, objects[:, :s, :2] +
                              rng.normal(0.0, 2.0, size=(n, s, 2)), rng.choice([-1.0, 0.0, 1.0], size=(n, s, 1))],
                             axis=2).astype(np.float32)
    path = np.column_stack([np.linspace(-10.0, 10.0, 15), np.linspace(0.0, 20.0, 15) ** 1.2])
    path_s = np.arange(15) * 2.0
    acc = acceleration(objects, then, valid, dt, 2.0)
    sig = signals_at(objects, signals, 3.0)
    t_star, miss, ps = path_conflict(objects[..., :2], objects[..., 2:4], path, path_s)
    assert (np.abs(acc) > 0).mean() > 0.2 and (sig != 0).mean() > 0.1  # the inputs exercise both branches
    for r in range(n):
        v = valid[r]
        one = acceleration(objects[r], then[r][v], np.ones(v.sum(), bool), np.asarray(dt[r]), 2.0) if v.any() \
            else np.zeros(m)
        assert np.array_equal(one, acc[r])
        seen = signals[r][signals[r][:, 0] > 0]  # the per-env form: only the seen readings
        assert np.array_equal(signals_at(objects[r], seen, 3.0), sig[r])
        one = path_conflict(objects[r, :, :2], objects[r, :, 2:4], path, path_s)
        assert all(np.array_equal(a, b[r]) for a, b in zip(one, (t_star, miss, ps)))
    assert (t_star >= 0).all() and (t_star <= T_MAX).all()


def test_batched_intent_reads_the_sensor_params():
    """BatchedIntent's defaults are the sensors' Params (not a constructor signature), checked the same way."""
    engine = batched.BatchedLeftTurn(1, {"duration": 5})
    bi = batched.BatchedIntent(engine, {}, {})
    assert bi.sig == TurnSignalsParams()
    assert (bi.history, bi.gate, bi.signal_gate) == (turn_features.TurnIntentParams().history,
                                                      turn_features.TurnIntentParams().gate,
                                                      turn_features.TurnIntentParams().signal_gate)
    assert batched.BatchedIntent(engine, {"miss_rate": 0.5}, {}).sig.miss_rate == 0.5
    with pytest.raises(ParamError, match="sensors.turn_signals.miss_rate"):
        batched.BatchedIntent(engine, {"miss_rate": 2.0}, {})
