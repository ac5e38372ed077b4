"""The batch's tracker association (av_gym/batched/perception.py ``BatchedTracker._assign``): the matches of every
env's cost matrix are those of ``scipy.optimize.linear_sum_assignment`` on it, as the per-env tracker takes them
(pairs below ``_BIG``), whether the env's gated pairs compete (the assignment runs) or not (its gated pairs are
taken as they are)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from av_gym.batched.perception import BatchedTracker
from av_gym.estimation.tracker import _BIG, TrackerParams


def _costs(rng: np.random.Generator, n: int, K: int, D: int, density: float):
    """Random gated cost matrices (n, K, D): costs in [0, gate] where gated, ``_BIG`` elsewhere and beyond each
    env's tracks and detections."""
    n_tracks, nz = rng.integers(0, K + 1, n), rng.integers(0, D + 1, n)
    cost = np.where(rng.random((n, K, D)) < density, rng.uniform(0, 13.8, (n, K, D)), _BIG)
    beyond = (np.arange(K)[None, :, None] >= n_tracks[:, None, None]) | (np.arange(D)[None, None] >= nz[:, None, None])
    cost[beyond] = _BIG
    return cost, n_tracks, nz


def _per_env(cost, n_tracks, nz):
    """The per-env tracker's matches, env by env."""
    out = []
    for b in range(len(cost)):
        if n_tracks[b] and nz[b]:
            c = cost[b, : n_tracks[b], : nz[b]]
            i, j = linear_sum_assignment(c)
            out += [(b, k, d) for k, d in zip(i.tolist(), j.tolist()) if c[k, d] < _BIG]
    return out


def test_the_association_of_every_env_is_its_own_assignment():
    tracker = BatchedTracker(1, TrackerParams())
    rng = np.random.default_rng(0)
    competing = alone = 0
    for density in (0.05, 0.15, 0.4):
        cost, n_tracks, nz = _costs(rng, 300, 8, 10, density)
        got = list(zip(*(x.tolist() for x in tracker._assign(cost, n_tracks, nz))))
        assert got == _per_env(cost, n_tracks, nz)
        gated = cost < _BIG
        clash = (gated.sum(axis=2) > 1).any(axis=1) | (gated.sum(axis=1) > 1).any(axis=1)
        competing, alone = competing + int(clash.sum()), alone + int((~clash & gated.any(axis=(1, 2))).sum())
    assert competing > 100 and alone > 100  # both ways taken


def test_the_gated_pairs_go_to_the_assignment_where_a_gated_cost_could_reach_big(monkeypatch):
    """The shortcut (gated pairs taken as they are) rests on every gated cost being below ``_BIG`` (gate < _BIG);
    with a gate at ``_BIG`` every env with tracks and detections goes to ``linear_sum_assignment``, with the
    default gate only those whose gated pairs compete. Fails without the guard on the gate."""
    import av_gym.batched.perception as perception

    calls = []

    def counted(c):
        calls.append(c.shape)
        return linear_sum_assignment(c)

    monkeypatch.setattr(perception, "linear_sum_assignment", counted)
    cost, n_tracks, nz = _costs(np.random.default_rng(1), 200, 6, 6, 0.1)
    both = int(((n_tracks > 0) & (nz > 0)).sum())
    for gate, expect_all in ((13.8, False), (_BIG, True)):
        calls.clear()
        got = list(zip(*(x.tolist() for x in BatchedTracker(1, TrackerParams(gate=gate))._assign(cost, n_tracks, nz))))
        assert got == _per_env(cost, n_tracks, nz)
        assert (len(calls) == both) == expect_all and 0 < len(calls) <= both
