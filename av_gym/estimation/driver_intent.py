"""What other drivers' indicators say about where they will go, accumulated over every reading of each.

The shield's indicator channel (:mod:`av_gym.sensors.turn_signal`'s model) has two kinds of noise: per *driver*
(25 % never indicate, 5 % indicate the wrong side) and per *reading* (10 % of readings miss an indicator that is
on). Read one frame at a time, as the shield did before, a driver indicating right shows "none" one frame in ten
and its straight-on hypothesis comes back each time; the per-reading noise averages out over a few frames, the
per-driver noise does not. So each driver's belief is a discrete Bayes filter over its hidden state, the pair
(turn, driver kind), which does not change while the car approaches: no predict step, one update per reading.

- turn ``T``: -1 right, 0 straight, +1 left (:func:`av_gym.shields.conflicts.path_turn`), prior uniform (highway-env
  draws every traffic car's destination uniformly among the three other exits);
- driver kind ``D``: indicates the right side, the wrong side, never; prior from the channel's per-driver rates.

``P(reading | T, D)`` (:func:`reading_likelihood`) is floored at ``floor`` per reading so that a reading the model
calls impossible only weakens a state (a model, not the truth), and the turn marginal is floored again relative
to its largest entry, so that the indicator alone never weighs a turn below ``floor``.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence

import numpy as np

from av_gym.sensors.turn_signal import TurnSignalsParams, channel_likelihood, driver_kinds

TURNS = (-1.0, 0.0, 1.0)
"""The order of the turn axis in every array here: right, straight, left."""


def reading_likelihood(reading: float, miss_rate: float, floor: float) -> np.ndarray:
    """``P(reading | T, D)`` (3 turns × 3 driver kinds) for one indicator reading (+1 left, -1 right, 0 none
    seen): the channel's own likelihood (:func:`av_gym.sensors.turn_signal.channel_likelihood`, beside the model
    that draws the readings), each entry at least ``floor``."""
    return np.maximum(channel_likelihood(reading, miss_rate), floor)


class DriverIntent:
    """Every driver's belief over (turn, driver kind), one per key (the vehicle), updated with each reading.

    The belief after a driver's readings is the discrete Bayes update (filterpy's ``discrete_bayes.update``:
    posterior ∝ likelihood × prior) applied once per reading. The hidden state does not change, so that product
    depends on the readings only through how many of each (-1, 0, +1) there were:
    ``log P(T, D | n) = log P(T, D) + Σ_r n_r log P(r | T, D) + const``, evaluated for every driver of a decision
    in one matrix product (in log space: a driver read 200 times would underflow the product). Why not one
    filterpy call per reading: the shield reads up to ~20 drivers per 0.1 s decision inside a 1 ms budget, and
    ~12 small numpy calls per driver cost more than the rest of the indicator path (docs/shield.md);
    ``tests/test_conflicts.py`` checks the result against filterpy's update reading by reading."""

    def __init__(self, channel: TurnSignalsParams, floor: float = 0.02) -> None:
        # P(T, D): turn uniform, kind from the channel's per-driver rates
        self.prior = np.outer(np.full(3, 1.0 / 3.0), driver_kinds(channel)).ravel()
        self.likelihood = np.stack([reading_likelihood(r, channel.miss_rate, floor).ravel() for r in TURNS])
        self.floor = floor
        with np.errstate(divide="ignore"):  # a kind the channel rules out (rate 0) has log prior -inf
            self._log_prior = np.log(self.prior)
        self._log_lik = np.log(self.likelihood)
        self.clear()

    def clear(self) -> None:
        """Forget every driver (a new episode)."""
        self.counts: dict[Hashable, tuple[int, int, int]] = {}  # driver -> readings (-1, 0, +1) so far

    def update(self, keys: Sequence[Hashable], readings: Sequence[float]) -> None:
        """One reading (+1 / 0 / -1) per driver in ``keys``; a driver first read here starts from the prior."""
        for k, r in zip(keys, readings):
            right, none, left = self.counts.get(k, (0, 0, 0))
            self.counts[k] = (right + (r < 0), none + (r == 0), left + (r > 0))

    def posterior(self, counts: np.ndarray) -> np.ndarray:
        """``P(T, D | readings)`` (N, 9: T-major, 3 turns × 3 kinds) after ``counts`` (N, 3) readings of -1, 0, +1;
        a stack (S, N, 3) of such groups gives (S, N, 9), one (N, 3) @ (3, 9) product per group: each group's
        numbers equal its own call's bit for bit as observed here with numpy 2.4's OpenBLAS 0.3.31 (its Haswell,
        SkylakeX, Zen and Prescott kernels), not promised by numpy (another BLAS may round the last bit apart)."""
        counts = np.asarray(counts, dtype=float)
        log_post = (counts if counts.ndim == 3 else counts.reshape(-1, 3)) @ self._log_lik + self._log_prior
        post = np.exp(log_post - log_post.max(axis=-1, keepdims=True))
        return post / post.sum(axis=-1, keepdims=True)

    def turn_weights(self, keys: Sequence[Hashable]) -> np.ndarray:
        """``P(readings | T)`` (len(keys), 3) for T = right, straight, left (:data:`TURNS`), each row scaled to a
        largest entry of 1 and floored at ``floor``: the weight of each turn against the uniform prior. A driver
        never read gets a NaN row."""
        out = np.full((len(keys), 3), np.nan)
        rows = [i for i, k in enumerate(keys) if k in self.counts]
        if rows:
            out[rows] = self.weights([self.counts[keys[i]] for i in rows])
        return out

    def weights(self, counts) -> np.ndarray:
        """:meth:`turn_weights`' rows for drivers read ``counts`` (N, 3: readings -1, 0, +1; N >= 1) times: (N, 3),
        in one :meth:`posterior` of those N (a matrix product's last bit may depend on N, so callers keep
        :meth:`turn_weights`' grouping: one call per decision with that decision's drivers, or a stack (S, N, 3) of
        S decisions' groups of N, giving (S, N, 3): the same bits as each group's call where the BLAS multiplies a
        stack group by group, observed with OpenBLAS, not promised)."""
        post = self.posterior(counts)
        marginal = post.reshape(*post.shape[:-1], 3, 3).sum(axis=-1)
        marginal /= marginal.max(axis=-1, keepdims=True)  # the T prior is uniform: no division by it needed
        return np.maximum(marginal, self.floor)
