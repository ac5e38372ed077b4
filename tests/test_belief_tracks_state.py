"""belief_lookahead on tracks: a car backing up (``track_reverse``) and a car's second track farther than ``merge``
whose motion agrees with the first (``merge_far``, ``merge_agree``)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from agents.belief import BeliefLookaheadParams
from agents.track_prior import twins
from av_gym.estimation.turn_features import ACC_SCALE
from tests.test_belief_tracks import _batch, _coasting_track, _decide_on, _twin_tracks


@pytest.fixture(scope="module")
def driven():
    """A two-row batch on turn_perceived after 45 env steps under YIELD, its planner on tracks (4 futures, no unseen
    prior, detected heading)."""
    return _batch([420_001, 420_002], 45, BeliefLookaheadParams(samples=4, unseen=0.0, track_heading="detected"))


def _with(planner, **options):
    """``planner`` with ``options`` replaced in its (and its tracks') parameters."""
    planner.params = planner.tracks.params = dataclasses.replace(planner.params, **options)
    return planner


def test_a_track_backing_up_starts_its_futures_backing_with_track_reverse(driven):
    """A confirmed track whose velocity (1.5 m/s) points against its detected heading: with ``track_reverse`` 1 m/s
    its futures start at -1.5 m/s along that heading, driven (not held standing), and move it back over their first
    ticks; with 0 (off) it stands at 0 m/s and stays; with ``track_reverse`` 2 m/s (faster than it backs: a car
    braking to a halt, the filter's noise) it stands."""
    venv, planner, obs, rows = driven
    for r in rows:
        _coasting_track(venv, int(r), (2.0, 2.0, 0.0, -1.5), 0, heading=np.pi / 2)
    for reverse, v, stands in ((1.0, -1.5, False), (0.0, 0.0, True), (2.0, 0.0, True)):
        _, tracks = _decide_on(venv, _with(planner, track_reverse=reverse), rows, obs)
        t = tracks.engine.traffic
        slot = np.argmax(t.alive[rows] & ~t.ego[rows], axis=1)
        np.testing.assert_allclose(t.v[rows, slot], v, atol=1e-6, err_msg=str(reverse))
        assert t.crashed[rows, slot].tolist() == [stands] * len(rows), reverse
        assert (t.target[rows, slot] >= 0).all()
        f = planner.futures(tracks.engine, rows, 2)
        j = int(slot[0])
        y0 = f.traffic.y[:, j].copy()
        for _ in range(3):  # three engine ticks
            f.traffic.act()
            f.traffic.step(1.0 / float(f.config["simulation_frequency"]))
        dy = f.traffic.y[:, j] - y0
        if stands:
            np.testing.assert_allclose(dy, 0.0, atol=1e-9)
        else:
            assert (dy < -0.05).all(), dy


def test_merge_far_takes_tracks_moving_together_for_one_car():
    """twins: two road users 3 m apart with the same velocity and heading are one car's with ``merge_far`` 3.5 m
    (the one updated last stays); 3 m apart moving in opposite directions, or with velocities 2 m/s apart, or
    4 m apart, are two; ``merge_far`` 0 (off) leaves ``merge`` alone."""
    def pair(second, heading2=np.pi / 2):
        pos = np.array([[[0.0, 0.0, 0.0, 9.0], second]])
        return pos, np.array([[np.pi / 2, heading2]])

    users, missed = np.ones((1, 2), bool), np.array([[1, 0]])
    together, h = pair([0.0, 3.0, 0.0, 9.0])
    np.testing.assert_array_equal(twins(together, users, missed, 2.0, 3.5, 1.0, h), [[True, False]])
    np.testing.assert_array_equal(twins(together, users, missed, 2.0, 0.0, 1.0, h), [[False, False]])
    opposite, h = pair([0.0, 3.0, 0.0, -9.0], -np.pi / 2)
    np.testing.assert_array_equal(twins(opposite, users, missed, 2.0, 3.5, 1.0, h), [[False, False]])
    faster, h = pair([0.0, 3.0, 0.0, 11.0])
    np.testing.assert_array_equal(twins(faster, users, missed, 2.0, 3.5, 1.0, h), [[False, False]])
    far, h = pair([0.0, 4.0, 0.0, 9.0])
    np.testing.assert_array_equal(twins(far, users, missed, 2.0, 3.5, 1.0, h), [[False, False]])
    # two cars standing side by side, their detected headings opposite: not merged
    still = np.array([[[0.0, 0.0, 0.0, 0.0], [3.0, 0.0, 0.0, 0.0]]])
    np.testing.assert_array_equal(twins(still, users, missed, 2.0, 3.5, 1.0, np.array([[np.pi / 2, -np.pi / 2]])),
                                  [[False, False]])


def test_twin_tracks_three_metres_apart_are_one_road_user_with_merge_far(driven):
    """On the batch: two confirmed tracks of one car 3.05 m apart, both 9 m/s north (beyond ``merge`` 2 m): with
    ``merge_far`` 3.5 only the one the detector updated last (id 8) starts the futures; without, both do."""
    venv, planner, obs, rows = driven
    for r in rows:
        _twin_tracks(venv, int(r), (-2.0, -21.95, 0.0, 9.0))
    for far, alive in ((3.5, [8]), (0.0, [7, 8])):
        _, tracks = _decide_on(venv, _with(planner, merge=2.0, merge_far=far), rows, obs)
        t = tracks.engine.traffic
        for r in rows:
            assert sorted(t.vid[r, t.alive[r] & ~t.ego[r]] - 1) == alive, far


def test_track_lag_up_speeds_up_a_car_pulling_away_but_not_a_braking_one(driven):
    """With ``track_lag`` 0.2 and ``track_lag_up`` a described track measured at +3 m/s² starts 0.6 m/s faster than
    its filter's 6 m/s, one measured at -3 m/s² at the filter's 6 m/s (without ``track_lag_up``: 5.4 m/s)."""
    venv, planner, obs, rows = driven
    for r in rows:
        _coasting_track(venv, int(r), (-2.0, -25.0, 0.0, 6.0), 0)
    for acc, up, v in ((3.0, True, 6.6), (-3.0, True, 6.0), (-3.0, False, 5.4)):
        intent = np.zeros_like(obs["intent"])
        intent[:, 0, 0] = acc / ACC_SCALE  # the nearest described track's measured acceleration
        e = venv.engine
        p = copy.deepcopy(_with(planner, track_lag=0.2, track_lag_up=up),
                          {id(venv.perception): venv.perception, id(e): e, id(planner.tracks.engine): None})
        p.read(e, rows, intent[rows])
        t = p.tracks.engine.traffic
        slot = np.argmax(t.alive[rows] & ~t.ego[rows], axis=1)
        np.testing.assert_allclose(t.v[rows, slot], v, rtol=1e-6, err_msg=f"{acc} {up}")
