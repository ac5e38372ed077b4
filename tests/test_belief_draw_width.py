"""A futures' start of more slots than ``SLOTS`` is refused (agents.track_prior.draw_width): widening the draw
streams to its slot count would change every road user's draws with the slot count, so the batch and a one-row
view of an env would no longer draw alike."""

from __future__ import annotations

import pytest

from agents.belief import BeliefLookaheadParams
from agents.track_prior import SLOTS
from tests.test_belief_tracks import _batch, _only_track


def _read_start(spread: float) -> tuple:
    """A batch's planner on tracks after reading one confirmed track per row, and the futures' start it built."""
    venv, planner, obs, rows = _batch([420_001, 420_002], 45, BeliefLookaheadParams(
        samples=4, unseen=0.0, track_spread=spread))
    for r in rows:
        _only_track(venv, int(r), (-2.0, -25.0, 0.0, 9.0))
    planner.read(venv.engine, rows, obs["intent"][rows])
    return planner, planner.tracks.current(venv.engine), rows


def test_the_futures_of_a_start_of_more_than_slots_road_users_are_refused():
    """BeliefPlanner.futures: a start of SLOTS slots plays; one of SLOTS + 1 raises, naming SLOTS and the bound."""
    planner, start, rows = _read_start(0.0)
    start.traffic.grow(SLOTS - start.traffic.N)
    assert planner.futures(start, rows).traffic.N == SLOTS
    start.traffic.grow(1)
    with pytest.raises(ValueError, match=r"holds 65 slots, more than SLOTS = 64 .*at most 42"):
        planner.futures(start, rows)


def test_the_spread_of_a_start_of_more_than_slots_road_users_is_refused():
    """TrackBelief's track_spread draws (fill): a start grown to SLOTS + 1 slots after its futures were forked
    raises, naming SLOTS."""
    planner, start, rows = _read_start(1.0)
    f = planner.futures(start, rows)
    start.traffic.grow(SLOTS + 1 - start.traffic.N)
    with pytest.raises(ValueError, match=r"holds 65 slots, more than SLOTS = 64"):
        planner.tracks.fill(f, rows, planner.seed, planner.K)
