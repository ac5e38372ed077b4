"""``sensors.turn_intent.memory``: each road user's turn belief after every indicator reading on it so far, carried
along the road user from observation to observation (av_gym/estimation/turn_features.py IntentHistory)."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.estimation.driver_intent import DriverIntent
from av_gym.estimation.turn_features import MEMORY_FEATURES, IntentHistory, TurnIntentParams
from av_gym.sensors.turn_signal import TurnSignalsParams

CHANNEL = TurnSignalsParams()


def _drive(history: IntentHistory, dt: float, seconds: float, cars: np.ndarray, readings, order=None, t0=0.0):
    """Observe ``cars`` (k, 4) moving at their velocity every ``dt`` s for ``seconds``; ``readings(t)`` gives each
    car's indicator reading (nan: none in range); ``order(t)`` a permutation of the rows the sensor lists them in.
    Returns the beliefs (k, 3) of the last observation, in the cars' own order."""
    cars = cars.astype(float).copy()
    k = len(cars)
    for i in range(int(round(seconds / dt)) + 1):
        t = t0 + i * dt
        perm = np.arange(k) if order is None else order(i)
        snap = cars[perm]
        r = np.asarray(readings(t), dtype=float)[perm]
        signals = np.zeros((k, 4))
        signals[:, 0], signals[:, 1:3], signals[:, 3] = ~np.isnan(r), snap[:, :2], np.nan_to_num(r)
        out = history.observe([0], np.array([t]), snap[None], np.ones((1, k), bool), snap[None],
                              np.ones((1, k), bool), signals[None])[0]
        cars[:, :2] += cars[:, 2:4] * dt
    belief = np.empty((k, 3))
    belief[perm] = out[:, 2:]
    return belief


def _marginal(counts) -> np.ndarray:
    return DriverIntent(CHANNEL).posterior(np.asarray(counts, float)).reshape(-1, 3, 3).sum(axis=2)


def test_the_belief_is_the_bayes_filter_of_every_reading_on_the_car():
    """A car indicating left, one indicating nothing and one out of the indicator's sight, 2 s at 2 Hz: the first
    two have the Bayes filter's turn marginal after 5 readings each (left; none), the third stays at the prior."""
    cars = np.array([[0.0, 40.0, 0.0, -8.0], [20.0, 0.0, -9.0, 0.0], [-30.0, -5.0, 7.0, 0.0]])
    belief = _drive(IntentHistory(1, TurnIntentParams(memory=True), CHANNEL), 0.5, 2.0, cars,
                    lambda t: [1.0, 0.0, np.nan])
    assert np.allclose(belief[0], _marginal([[0, 0, 5]])[0]) and belief[0, 2] > 0.9
    assert np.allclose(belief[1], _marginal([[0, 5, 0]])[0]) and belief[1].argmax() == 1
    assert np.allclose(belief[2], 1 / 3, atol=1e-6)
    assert len(MEMORY_FEATURES) == 3


def test_a_stack_observed_every_step_counts_the_readings_of_the_decisions():
    """At 10 Hz the per-env stack sees each car 5 times per 0.5 s decision: it still counts one reading per
    ``read_period`` (the batch's), so both stacks give the same belief; with a short period it counts them all."""
    cars = np.array([[0.0, 40.0, 0.0, -8.0], [20.0, 0.0, -9.0, 0.0]])
    flicker = lambda t: [1.0 if round(t * 10) % 3 else 0.0, -1.0]  # noqa: E731 - a missed reading now and then
    slow = _drive(IntentHistory(1, TurnIntentParams(memory=True), CHANNEL), 0.5, 3.0, cars, flicker)
    fast = _drive(IntentHistory(1, TurnIntentParams(memory=True), CHANNEL), 0.1, 3.0, cars, flicker)
    assert np.allclose(slow, fast) and np.allclose(fast[0], _marginal([[0, 3, 4]])[0])  # t = 0, 0.5, ..., 3 s
    every = _drive(IntentHistory(1, TurnIntentParams(memory=True, read_period=0.1), CHANNEL), 0.1, 3.0, cars,
                   flicker)
    assert np.allclose(every[0], _marginal([[0, 11, 20]])[0]) and not np.allclose(every[0], fast[0])


def test_the_belief_follows_the_car_not_its_row():
    """The sensor lists the cars in another order at every observation: each keeps its own readings."""
    cars = np.array([[0.0, 40.0, 0.0, -8.0], [20.0, 0.0, -9.0, 0.0], [-30.0, -5.0, 7.0, 0.0]])
    rng = np.random.default_rng(0)
    perms = [rng.permutation(3) for _ in range(5)]
    belief = _drive(IntentHistory(1, TurnIntentParams(memory=True), CHANNEL), 0.5, 2.0, cars,
                    lambda t: [1.0, -1.0, 0.0], order=lambda i: perms[i])
    assert belief[0].argmax() == 2 and belief[1].argmax() == 0 and belief[2].argmax() == 1
    assert np.allclose(belief, _marginal([[0, 0, 5], [5, 0, 0], [0, 5, 0]]))


def test_a_car_that_jumps_is_another_car_and_a_new_episode_forgets():
    """A car where the one read before would be keeps its readings; one 10 m to the side of it (farther than
    ``gate``) is another car and starts from the prior; so does every car after clear()."""
    car = np.array([[0.0, 40.0, 0.0, -8.0]])
    later = car + [[0.0, -8.0 * 1.5, 0.0, 0.0]]  # where it is at t = 1.5 s
    for shift, kept in ((0.0, True), (10.0, False)):
        history = IntentHistory(1, TurnIntentParams(memory=True), CHANNEL)
        assert _drive(history, 0.5, 1.0, car, lambda t: [1.0])[0, 2] > 0.9
        belief = _drive(history, 0.5, 0.0, later + [[shift, 0.0, 0.0, 0.0]], lambda t: [np.nan], t0=1.5)
        assert (belief[0, 2] > 0.9) if kept else np.allclose(belief, 1 / 3, atol=1e-6)
    history.clear([0])
    assert np.allclose(_drive(history, 0.5, 0.0, later, lambda t: [np.nan], t0=2.0), 1 / 3, atol=1e-6)


@pytest.mark.parametrize("memory,width", [(False, 2), (True, 5)])
def test_the_intent_space_has_the_memory_columns(memory, width):
    import gymnasium as gym

    import av_gym  # noqa: F401 - registers the ids

    env = gym.make("av_gym/UnprotectedLeftTurn-v0", sensors="turn_truth_memory" if memory else "turn_truth")
    obs, _ = env.reset(seed=3)
    assert env.observation_space["intent"].shape[-1] == width and obs["intent"].shape[-1] == width
    assert env.observation_space.contains(obs)
    env.close()
