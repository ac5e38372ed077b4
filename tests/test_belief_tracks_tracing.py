"""The tracing tools (benchmarks/belief_tracks_diagnose.py, _confirm.py, _lost.py, _truth.py) ask GO's collision
probability exactly as the planner's ``decide()`` does (belief_tracks_truth.decision_p): under
``track_margin_scope`` start a held GO is judged on contact alone, a GO to start with the margin."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest

from agents.belief import BeliefLookaheadParams
from av_gym.wrappers import GO, YIELD
from tests.test_belief_tracks import _batch, _read_copy

# belief_tracks' own options (tests/test_belief_tracks.py: tracked_shipped) at 8 futures, a 0.5 m margin for a GO
# to start only
PARAMS = BeliefLookaheadParams(samples=8, tentative="road_user", track_heading="detected", ghost=2, merge=2.0,
                               track_margin=0.5, track_margin_scope="start")


@pytest.fixture(scope="module")
def margin_start():
    return _batch(list(range(410_000, 410_006)), 30, PARAMS)


def test_the_tracing_tools_p_is_decides_p(margin_start, monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent.parent / "benchmarks"))
    truth, diagnose, lost = (importlib.import_module(f"belief_tracks_{m}") for m in ("truth", "diagnose", "lost"))
    venv, planner, obs, rows = margin_start
    p, engine = _read_copy(venv, planner, obs, rows), venv.engine
    held = np.where(np.arange(len(rows)) % 2, GO, YIELD)
    step = np.full(len(rows), 30)  # a regular decision (repeat 5): every row decides
    assert p.live(engine, rows, held, step)[0].all()
    # decide()'s p: the GO collision shares of the decision's own futures (K of them, no recheck stream)
    seen: dict[int, float] = {}
    own = p.go_collision

    def recorded(engine, rs, K=None, stream=(), margin=None):
        out = own(engine, rs, K, stream, margin)
        if K is None and not stream:
            seen.update(zip(np.asarray(rs).tolist(), out.tolist()))
        return out

    monkeypatch.setattr(p, "go_collision", recorded)
    p.decide(engine, rows, held, step)
    decided = np.array([seen[r] for r in rows.tolist()])
    # the margin matters here: asked of every row alike, a held GO's p is not decide()'s
    wide = own(engine, rows)
    assert (wide != decided)[held == GO].any() and (wide == decided)[held != GO].all(), (wide, decided, held)
    np.testing.assert_array_equal(truth.decision_p(p, engine, rows, held), decided)
    for n, (r, h) in enumerate(zip(rows.tolist(), held.tolist())):  # the counterfactuals with nothing changed
        assert diagnose._swapped(p, engine, r, 0, 0, (), h) == decided[n], (r, h)
        assert lost._p(p, engine, r, h) == decided[n], (r, h)


def test_the_traced_futures_are_the_decisions_own(margin_start, monkeypatch):
    """belief_tracks_diagnose._future_paths plays the decision's own K futures (the same draws, the tracks' fill):
    its futures that collide are go_collision's share, row by row; _predicted reads where they put a road user
    ``elapsed`` s on against a true place."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent.parent / "benchmarks"))
    diagnose = importlib.import_module("belief_tracks_diagnose")
    venv, planner, obs, rows = margin_start
    p, engine = _read_copy(venv, planner, obs, rows), venv.engine
    shares = p.go_collision(engine, rows)
    traced = [diagnose._future_paths(p, engine, int(r)) for r in rows]
    np.testing.assert_array_equal([sum(t["collided"]) / p.K for t in traced], shares)
    assert 0 < shares.max(), shares  # rows whose futures collide: the count is not trivially 0 = 0
    assert all(not w for t in traced for w, c in zip(t["with"], t["collided"]) if not c)  # only a collided one's
    paths = {"dt": 0.1, "places": {7: {0: {3: (1.0, 0.0)}, 1: {3: (4.0, 0.0)}, 2: {2: (9.0, 9.0)}}},
             "collided": [True, False, False], "with": [[7], [], []]}
    got = diagnose._predicted(paths, 7, 0.3, (0.0, 0.0))
    assert got == {"elapsed_s": 0.3, "futures_holding": 2, "nearest_m": 1.0, "median_m": 2.5, "futures_collided": 1,
                   "futures_hit_by_it": 1}
