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
from av_gym.estimation import driver_intent as intent
from av_gym.shields import aeb_improved as aeb

N = 10_000  # random inputs per model


def _calls(function, name: str) -> bool:
    """``function``'s code calls ``name`` (a global of its module)."""
    function = inspect.unwrap(function)  # a sensor's __init__ is wrapped to record its arguments
    return name in inspect.getsource(function) and name in function.__code__.co_names


def test_the_stacks_call_the_one_implementation():
    # the per-env sensor, the batched stack and the shield read the indicator channel through the same functions,
    # and keep its per-driver draws in the same table
    assert batched.read_signals is turn_signal.read_signals and _calls(batched.BatchedIntent.signals, "read_signals")
    assert _calls(turn_signal.TurnSignals.measure, "read_signals") and _calls(turn_signal.read_signals, "read_channel")
    assert aeb.first_sighting is turn_signal.first_sighting and aeb.reported is turn_signal.reported
    assert _calls(aeb.ImprovedAEB._intent, "first_sighting") and _calls(aeb.ImprovedAEB._intent, "reported")
    assert batched.DriverDraws is aeb.DriverDraws is turn_signal.DriverDraws
    assert batched.turn_signal is turn_signal.turn_signal and _calls(turn_signal.intended_signal, "turn_signal")
    # the shield's belief: the channel's own likelihood and driver-kind prior
    assert _calls(intent.reading_likelihood, "channel_likelihood") and _calls(intent.DriverIntent.__init__,
                                                                              "driver_kinds")
    # the turn features (encoding included) and the intent features with their history: TurnFeatures /
    # TurnIntent and the batch call the same function and class
    assert batched.turn_features is turn_features.turn_features
    assert _calls(turn_features.TurnFeatures.features, "turn_features") and _calls(batched.BatchedLeftTurn.observe,
                                                                                   "turn_features")
    assert _calls(turn_features.turn_features, "path_conflict") and _calls(turn_features.turn_features, "TurnEncoding")
    assert batched.IntentHistory is turn_features.IntentHistory
    assert _calls(turn_features.TurnIntent.__init__, "IntentHistory") and _calls(batched.BatchedIntent.__init__,
                                                                                "IntentHistory")
    assert _calls(turn_features.IntentHistory.observe, "acceleration") and \
        _calls(turn_features.IntentHistory.observe, "signals_at")
    # no scale of the encoding written anywhere else: the readers decode (meta-actions, the gap-acceptance rule)
    from agents import go_yield
    from av_gym import wrappers
    from av_gym.batched import vec_env

    assert vec_env.meta_actions is wrappers.meta_actions and _calls(wrappers.meta_action, "meta_actions")
    assert _calls(wrappers.meta_actions, "TURN") and _calls(go_yield.GapAcceptance.choice, "TURN")
    for module in (batched, vec_env, wrappers, go_yield):
        source = inspect.getsource(module)
        assert not any(f"{c} / {k}" in source or f"{k} * " in source for c in ("x", "]") for k in ("10.0", "30.0"))
        assert "SET_POINTS = " not in source or module is wrappers


def test_encoding_decodes_what_it_encodes():
    """TurnEncoding.decode inverts encode for every feature inside [-1, 1] (both layouts, float32 rounding)."""
    rng = np.random.default_rng(3)
    for enc in (turn_features.TURN, turn_features.TurnEncoding(max_objects=3, time_scale=7.0)):
        scales = np.concatenate([enc.ego_scales, np.tile(list(turn_features.OBJECT_SCALES.values()),
                                                            enc.max_objects)])
        raw = rng.uniform(-0.99, 0.99, size=(50, enc.width)) * scales
        m, k = enc.max_objects, len(turn_features.EGO_FEATURES)
        turn = enc.encode(raw[:, :k], raw[:, k:].reshape(50, m, -1))
        assert turn.shape == (50, enc.width) and turn.dtype == np.float32
        for j, name in enumerate(turn_features.EGO_FEATURES):
            assert np.allclose(enc.decode(turn.astype(float), name), raw[:, j], rtol=1e-6, atol=1e-6 * scales[j])
        for j, name in enumerate(turn_features.OBJECT_FEATURES):
            col = raw[:, k + j::len(turn_features.OBJECT_FEATURES)]
            assert np.allclose(enc.decode(turn.astype(float), name), col, rtol=1e-6, atol=1e-4)


def test_meta_action_is_meta_actions_on_a_batch_of_one():
    from av_gym.wrappers import ACTION_SETS, GO, YIELD, meta_action, meta_actions

    rng = np.random.default_rng(4)
    turn = rng.uniform(-1.0, 1.0, size=(2000, turn_features.TURN.width)).astype(np.float32)
    turn[:, 1] = rng.choice([0.0, 0.45, 0.9], size=2000)  # set-points on and off the grid
    choice = rng.choice([YIELD, GO], size=2000)
    batch = meta_actions(choice, turn)
    assert set(np.unique(batch)) == {0, 1, 2}
    assert [meta_action(c, t) for c, t in zip(choice, turn)] == batch.tolist()
    go_yield = ACTION_SETS["go_yield"]
    assert np.array_equal(go_yield.act(choice, {"turn": turn}), batch)
    assert go_yield.act_one(int(choice[0]), {"turn": turn[0]}) == batch[0]


@pytest.mark.parametrize("memory", [False, True])
def test_intent_history_batch_equals_batches_of_one(memory):
    """IntentHistory over 20 envs = 20 histories of one, step by step, envs reset at different times (with memory:
    the turn beliefs too)."""
    rng = np.random.default_rng(5)
    p = turn_features.TurnIntentParams(memory=memory)
    n, m, k = 20, 4, 6
    many = turn_features.IntentHistory(n, p)
    ones = [turn_features.IntentHistory(1, p) for _ in range(n)]
    now = np.zeros(n)
    snap = rng.normal(0.0, 20.0, size=(n, k, 4))
    for step in range(30):
        reset = rng.uniform(size=n) < 0.05
        many.clear(np.flatnonzero(reset))
        now = np.where(reset, 0.0, now + 0.1)
        snap[..., :2] += 0.1 * snap[..., 2:4]
        snap[..., 2:4] += rng.normal(0.0, 0.5, size=(n, k, 2))
        valid = rng.uniform(size=(n, k)) < 0.9
        order = np.argsort(rng.uniform(size=(n, k)), axis=1)[:, :m]
        objects = np.take_along_axis(snap, order[..., None], axis=1)
        described = rng.uniform(size=(n, m)) < 0.8
        signals = np.concatenate([np.ones((n, 3, 1)), snap[:, :3, :2], rng.choice([-1.0, 0.0, 1.0], size=(n, 3, 1))],
                                 axis=2)
        out = many.observe(np.arange(n), now, objects, described, snap, valid, signals)
        for r in range(n):
            if reset[r]:
                ones[r].clear([0])
            one = ones[r].observe([0], now[r:r + 1], objects[r:r + 1], described[r:r + 1], snap[r:r + 1],
                                  valid[r:r + 1], signals[r:r + 1])
            assert np.array_equal(one[0, :, :2], out[r, :, :2])
            # the beliefs come out of a matrix product (the Bayes filter in log space), whose BLAS kernel may sum
            # a batch of rows and a single row in another order: equal to float32 rounding, not to the last bit
            np.testing.assert_allclose(one[0, :, 2:], out[r, :, 2:], rtol=0, atol=1e-6)
        assert (out[..., 0] != 0).mean() > 0.2 or step < 2
    if memory:  # the beliefs moved off the prior for some objects and left the others
        read = np.abs(out[..., 2:] - 1 / 3).max(axis=-1) > 0.05
        assert 0.1 < read.mean() < 0.9


def test_driver_draws_by_key_and_by_row_are_one_table():
    from av_gym.sensors.turn_signal import DriverDraws

    draws = DriverDraws()
    keys = [object() for _ in range(5)]
    rows = draws.rows(keys)
    assert rows.tolist() == [0, 1, 2, 3, 4] and draws.rows(keys[::-1]).tolist() == [4, 3, 2, 1, 0]
    known, _, _ = draws.get(rows)
    assert not known.any()
    draws.keep(rows[:2], np.array([True, False]), np.array([False, True]))
    known, indicates, wrong = draws.get(np.array([1, 0, 700]))  # a batch's vehicle id beyond the table grows it
    assert known.tolist() == [True, True, False] and indicates.tolist() == [False, True, False]
    assert wrong.tolist() == [True, False, False]
    draws.clear()
    assert not draws.get(rows)[0].any() and draws.rows(keys[2:3]).tolist() == [0]


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
    n, m, s = 1_000, 4, 3  # the per-row loop is ~0.3 ms a row: 1,000 rows still exercise both branches (asserted)
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
    """BatchedIntent's and the engine's defaults are the sensors' Params (not a constructor signature), checked the
    same way."""
    engine = batched.BatchedLeftTurn(1, {"duration": 5})
    assert engine.features == turn_features.TurnFeaturesParams()
    assert engine.n_features == turn_features.TurnEncoding.of(engine.features).width
    assert batched.BatchedLeftTurn(1, {"duration": 5}, max_objects=3).n_features == 5 + 12 * 3
    with pytest.raises(ParamError, match="max_objects"):
        batched.BatchedLeftTurn(1, {"duration": 5}, max_objects=0)
    bi = batched.BatchedIntent(engine, {}, {})
    assert bi.sig == TurnSignalsParams()
    assert (bi.history, bi.gate, bi.signal_gate) == (turn_features.TurnIntentParams().history,
                                                      turn_features.TurnIntentParams().gate,
                                                      turn_features.TurnIntentParams().signal_gate)
    assert batched.BatchedIntent(engine, {"miss_rate": 0.5}, {}).sig.miss_rate == 0.5
    with pytest.raises(ParamError, match="sensors.turn_signals.miss_rate"):
        batched.BatchedIntent(engine, {"miss_rate": 2.0}, {})
