"""What another driver's indicator says about where it will go, accumulated over every reading of it (issue 17,
fourth pass).

The shield's indicator channel (:mod:`av_gym.sensors.turn_signal`'s model) has two kinds of noise: per *driver*
(25 % never indicate, 5 % indicate the wrong side) and per *reading* (10 % of readings miss an indicator that is
on). Read one frame at a time, as the shield did before, a driver indicating right shows "none" one frame in ten
and its straight-on hypothesis comes back each time; the per-reading noise averages out over a few frames, the
per-driver noise does not. So the belief is a discrete Bayes filter (filterpy's ``discrete_bayes.update``) over
the driver's hidden state, the pair (turn, driver kind), which does not change while the car approaches: there is
no predict step, only one update per reading.

- turn ``T``: -1 right, 0 straight, +1 left (:func:`av_gym.shields.conflicts.path_turn`), prior uniform (highway-env
  draws every traffic car's destination uniformly among the three other exits);
- driver kind ``D``: indicates the right side, the wrong side, never; prior from the channel's per-driver rates.

``P(reading | T, D)`` (:func:`reading_likelihood`) is floored at ``floor`` per reading so that a reading the model
calls impossible only weakens a state (a model, not the truth), and the turn marginal is floored again relative
to its largest entry, so that no hypothesis is ever ruled out by the indicator alone below ``floor``.
"""

from __future__ import annotations

import numpy as np
from filterpy.discrete_bayes import update

TURNS = (-1.0, 0.0, 1.0)
"""The order of the turn axis in every array here: right, straight, left."""
KINDS = ("right_side", "wrong_side", "never")


def reading_likelihood(reading: float, miss_rate: float, floor: float) -> np.ndarray:
    """``P(reading | T, D)`` (3 turns × 3 driver kinds) for one indicator reading (+1 left, -1 right, 0 none
    seen), each entry at least ``floor``."""
    lik = np.zeros((3, 3))
    for i, turn in enumerate(TURNS):
        if turn == 0.0:  # going straight: no indicator, whatever the driver
            lik[i, :] = 1.0 if reading == 0.0 else 0.0
            continue
        for j, shows in enumerate((turn, -turn, 0.0)):  # right side, wrong side, never
            if shows == 0.0:
                lik[i, j] = 1.0 if reading == 0.0 else 0.0
            else:
                lik[i, j] = (1.0 - miss_rate) if reading == shows else miss_rate if reading == 0.0 else 0.0
    return np.maximum(lik, floor)


class IntentBelief:
    """One driver's belief over (turn, driver kind), updated with every indicator reading of it."""

    def __init__(self, no_signal_rate: float, wrong_rate: float, floor: float = 0.02) -> None:
        kinds = np.array([(1.0 - no_signal_rate) * (1.0 - wrong_rate), (1.0 - no_signal_rate) * wrong_rate,
                          no_signal_rate])
        self.prior = np.outer(np.full(3, 1.0 / 3.0), kinds)  # P(T, D): turn uniform, kind from the channel
        self.posterior = self.prior.copy()
        self.floor = floor
        self.readings = 0

    def update(self, reading: float, miss_rate: float) -> None:
        lik = reading_likelihood(reading, miss_rate, self.floor)
        self.posterior = update(lik.ravel(), self.posterior.ravel()).reshape(3, 3)
        self.readings += 1

    def turn_likelihood(self) -> np.ndarray:
        """``P(readings | T)`` for T = right, straight, left (:data:`TURNS`), scaled to a largest entry of 1 and
        floored at ``floor``: the weight of each turn against the uniform prior."""
        marginal = self.posterior.sum(axis=1) / self.prior.sum(axis=1)
        return np.maximum(marginal / marginal.max(), self.floor)
