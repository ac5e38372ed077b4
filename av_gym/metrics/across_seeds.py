"""A method's result over training seeds: the mean and the interquartile mean (IQM) over its seeds, each with a
stratified-bootstrap interval over seeds and episodes.

The field's protocol for reporting learned policies (Agarwal et al., "Deep RL at the Edge of the Statistical
Precipice", the rliable library; Henderson et al. on seed variance) treats one trained policy as one draw from the
training procedure: a claim about the method is a statistic over several training seeds, with an interval that
counts both sources of chance, which training seed was drawn and which episodes it was scored on. Here each seed's
score is its mean over its episodes; the interval resamples the seeds (with replacement) and, within each drawn
seed, its episodes (with replacement): two-level (stratified) resampling, percentile interval, from a generator
seeded with :data:`av_gym.metrics.stats.BOOTSTRAP_SEED`, :data:`av_gym.metrics.stats.BOOTSTRAP_RESAMPLES`
resamples, so the same episodes always give the same bounds.

For a rate (0/1 per episode) the interval is never narrower than the Wilson interval of all the seeds' episodes
pooled: where every episode ends alike (PilotNet completes 20 of 20 laps on each of 5 seeds) no resample differs
and the percentile interval is the point [1, 1], a certainty 100 laps cannot give (Wilson: [0.963, 1]); the
episodes' chance is at least what a pooled binomial says, whatever the seeds add to it."""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats as _st

from av_gym.metrics.stats import BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED, wilson_ci

__all__ = ["iqm", "across_seeds", "IQM_CUT"]

IQM_CUT = 0.25  # rliable's IQM: scipy.stats.trim_mean with a quarter cut from each end
_NAN = float("nan")


def iqm(scores: ArrayLike, axis: int | None = None) -> np.ndarray | float:
    """The interquartile mean of ``scores`` (one per run), rliable's definition: ``scipy.stats.trim_mean`` cutting
    ``floor(0.25 n)`` values from each end (with 3 runs nothing is cut, with 5 the best and the worst are)."""
    out = _st.trim_mean(np.asarray(scores, dtype=float), IQM_CUT, axis=axis)
    return float(out) if np.ndim(out) == 0 else out


def _resampled_seed_scores(per_seed: list[np.ndarray], resamples: int, rng: np.random.Generator) -> np.ndarray:
    """``(resamples, k)`` seed scores: each row draws k of the k seeds with replacement, then for every drawn seed
    its own episodes with replacement (a seed drawn twice gets two independent episode resamples)."""
    k = len(per_seed)
    drawn = rng.integers(0, k, size=(resamples, k))
    scores = np.empty((resamples, k))
    for s, episodes in enumerate(per_seed):  # one seed at a time: memory is resamples x its episodes at most
        where = np.nonzero(drawn == s)
        picks = rng.integers(0, episodes.size, size=(where[0].size, episodes.size))
        scores[where] = episodes[picks].mean(axis=1)
    return scores


def across_seeds(per_seed: Sequence[ArrayLike], confidence: float = 0.95, resamples: int = BOOTSTRAP_RESAMPLES,
                 seed: int = BOOTSTRAP_SEED, rate: bool = False) -> dict[str, tuple[float, float, float]]:
    """``{"mean": (value, lo, hi), "iqm": (value, lo, hi)}`` of a metric over training seeds.

    ``per_seed`` holds one array per training seed: that seed's per-episode values of the metric (in the metric's
    own unit; NaNs, episodes where it is undefined, are dropped). The value is the mean (or IQM) over seeds of
    each seed's mean over its episodes; ``lo, hi`` the percentile interval of the same statistic over
    ``resamples`` stratified resamples (seeds, then episodes within each seed). A seed with no defined episode
    leaves the metric undefined (NaNs); fewer than two seeds is a ValueError: one seed is a single policy.
    ``rate``: the values are 0/1 outcomes, and each interval is widened to hold the pooled episodes' Wilson
    interval (the module docstring)."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    arrays = [np.asarray(x, dtype=float).ravel() for x in per_seed]
    if len(arrays) < 2:
        raise ValueError(f"an across-seed statistic needs at least 2 training seeds, got {len(arrays)}")
    arrays = [a[~np.isnan(a)] for a in arrays]
    if any(a.size == 0 for a in arrays):
        return {"mean": (_NAN, _NAN, _NAN), "iqm": (_NAN, _NAN, _NAN)}
    point = np.array([a.mean() for a in arrays])
    scores = _resampled_seed_scores(arrays, resamples, np.random.default_rng(seed))
    tail = 100.0 * (1.0 - confidence) / 2.0
    pooled = np.concatenate(arrays)
    floor = wilson_ci(int(round(pooled.sum())), pooled.size, confidence)[1:] if rate else (np.inf, -np.inf)
    out = {}
    for name, value, dist in (("mean", float(point.mean()), scores.mean(axis=1)),
                              ("iqm", iqm(point), iqm(scores, axis=1))):
        lo, hi = np.percentile(dist, [tail, 100.0 - tail])
        out[name] = (value, float(min(lo, floor[0])), float(max(hi, floor[1])))
    return out
