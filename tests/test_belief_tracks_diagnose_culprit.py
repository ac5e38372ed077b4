"""benchmarks/belief_tracks_diagnose.py ``_snapshot`` (the "culprit" of a collision after a GO) is keyed by the
simulator's car: when two tracks share their nearest car (a twin, a ghost), the nearest track speaks for it, so the
error reported is that track's (the last one read overwrote it: seed 1,953,064 reported a 79 m error)."""

from __future__ import annotations

import importlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest


@pytest.fixture
def diagnose(monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent.parent / "benchmarks"))
    return importlib.import_module("belief_tracks_diagnose")


def _traffic(n: int, **fields) -> SimpleNamespace:
    """One row of ``n`` vehicles; unnamed state fields zero (m, rad, m/s, m/s^2)."""
    base = {k: np.zeros((1, n)) for k in ("h", "v", "acc", "target")}
    base |= {"lane": np.zeros((1, n), int), "crashed": np.zeros((1, n), bool), "yielding": np.zeros((1, n), bool),
             "vid": np.arange(100, 100 + n)[None], "route": np.full((1, n, 3), -1)}
    return SimpleNamespace(**(base | fields))


def test_two_tracks_on_one_car_report_the_nearest(diagnose, monkeypatch):
    # track 1 is 0.5 m from car 2, track 3 (a twin) 79 m from it; read nearest first, so the last-read one is far
    monkeypatch.setattr(diagnose, "nearest_cars", lambda te, engine, r: {1: (2, 0.5), 3: (2, 79.0), 0: (1, 2.0)})
    monkeypatch.setattr(diagnose, "_swapped", lambda *a: 0.0)
    tracks = SimpleNamespace(engine=SimpleNamespace(traffic=_traffic(4, v=np.array([[0.0, 8.0, 0.0, 3.0]]))),
                             tent=np.zeros((1, 4), bool))
    planner = SimpleNamespace(tracks=tracks, turn_probabilities=lambda rows, vids: np.zeros((1, 4, 3)),
                              _origin=np.zeros(4, int), _dest=np.zeros(4, int))
    engine = SimpleNamespace(traffic=_traffic(3))
    snap = diagnose._snapshot(planner, engine, 0, 0)
    assert sorted(snap) == [101, 102]  # keyed by the car's vid
    car = snap[102]
    assert (car["pos_err_m"], car["track_slot"], car["v_track"], car["tracks_on_car"]) == (0.5, 1, 8.0, 2)
    assert (snap[101]["track_slot"], snap[101]["tracks_on_car"]) == (0, 1)


def test_nearest_track_per_car_whatever_the_order(diagnose):
    for matched in ({5: (0, 79.0), 6: (0, 0.5)}, {6: (0, 0.5), 5: (0, 79.0)}):
        assert diagnose.nearest_track_per_car(matched) == {0: (6, 0.5, 2)}
