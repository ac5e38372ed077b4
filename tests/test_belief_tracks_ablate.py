"""benchmarks/belief_tracks_ablate.py: the planner on tracks with one sensed part the simulator's (a measurement)."""

from __future__ import annotations

import copy
import importlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from agents.belief import BeliefLookaheadParams
from tests.test_belief_tracks import _batch


@pytest.fixture()
def ablate(monkeypatch):
    """The script as it imports its neighbours (its folder on sys.path)."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent.parent / "benchmarks"))
    return importlib.import_module("belief_tracks_ablate")


def _road(xs):
    """A one-row engine stand-in whose traffic holds the ego at the origin then cars at ``xs`` (m, on y = 0)."""
    x = np.array([[0.0, *xs]])
    n = x.shape[1]
    ego = np.zeros((1, n), bool)
    ego[0, 0] = True
    return SimpleNamespace(traffic=SimpleNamespace(x=x, y=np.zeros((1, n)), alive=np.ones((1, n), bool), ego=ego))


def test_each_car_takes_its_nearest_track_one_track_per_car(ablate):
    """Cars at 10 and 11 m, tracks at 10.5, 11.2 and 30 m: the nearest pair (11 m, 11.2 m) first, the car at 10 m the
    remaining track at 10.5 m; the track at 30 m is nobody's; a car with no track within the radius has none."""
    sim, tracks = _road([10.0, 11.0, 50.0]), _road([10.5, 11.2, 30.0])
    pairs = ablate.match_users(tracks, sim, 0, 3.0, np.zeros(4, bool))
    assert pairs == {2: 2, 1: 1}
    # a track the planner left out (a ghost) is still a car's
    tracks.traffic.alive[0, 1] = False
    left_out = np.array([False, True, False, False])
    assert ablate.match_users(tracks, sim, 0, 3.0, left_out) == {2: 2, 1: 1}
    assert ablate.match_users(tracks, sim, 0, 3.0, np.zeros(4, bool)) == {2: 2}


@pytest.mark.parametrize("spec, parts", [("velocity", {"velocity"}), ("users,prior", {"users", "prior"}),
                                         ("none", set()), ("all", {"users", "prior", "position", "velocity",
                                                                   "heading", "acc", "lane"})])
def test_the_parts_named(ablate, spec, parts):
    assert ablate.parts_of(spec) == parts


def test_a_bad_part_is_one_error_line(ablate, capsys):
    with pytest.raises(SystemExit) as out:
        ablate.parts_of("speed")
    err = capsys.readouterr().err.strip()
    assert out.value.code == 2 and len(err.splitlines()) == 1 and "--truth" in err and "velocity" in err


@pytest.mark.slow
def test_with_truth_gives_the_futures_start_the_simulators_cars(ablate):
    """After a read, ``users`` describes every simulator car (a road user within the match radius of each, the
    unmatched tracks gone), ``position`` puts each matched track on its car, and ``none`` changes nothing."""
    venv, planner, obs, rows = _batch([420_001, 420_002], 45, BeliefLookaheadParams(
        samples=4, tentative="road_user", track_heading="detected", ghost=2, merge=2.0))
    engine, s = venv.engine, venv.engine.traffic
    planner.read(engine, rows, obs["intent"][rows])
    before = copy.deepcopy(planner.tracks.engine.traffic)
    ablate.with_truth(planner, engine, rows, frozenset(), 3.0)
    np.testing.assert_array_equal(planner.tracks.engine.traffic.x, before.x)
    cars = 0
    for parts, tol in ((frozenset({"users"}), 3.0), (frozenset({"users", "position"}), 1e-9)):
        planner.read(engine, rows, obs["intent"][rows])
        ablate.with_truth(planner, engine, rows, parts, 3.0)
        t = planner.tracks.engine.traffic
        for r in rows:
            users = np.flatnonzero(t.alive[r] & ~t.ego[r])
            for i in np.flatnonzero(s.alive[r] & ~s.ego[r]):
                assert np.hypot(t.x[r, users] - s.x[r, i], t.y[r, users] - s.y[r, i]).min() <= tol
                cars += 1
            assert len(users) == (s.alive[r] & ~s.ego[r]).sum()  # one road user per car, no other
    assert cars > 0
