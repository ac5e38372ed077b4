"""``stopped_alone`` (agents/track_prior.py ``alone``): a track standing inside the junction is held in place in the
futures (as a crashed car is) only where another road user stands within the radius; alone, it is a driver the
futures' regulation and IDM release (the car held for the ego that pulled away: docs/dagger.md, "Where the target
stands")."""

from __future__ import annotations

import copy

import numpy as np

from agents.belief import BeliefLookaheadParams
from agents.track_prior import alone
from av_gym.batched.perception import tracks_observation
from tests.test_belief_tracks import _batch


def test_alone_is_no_other_road_user_of_the_row_within_the_radius():
    """Centre to centre, the road user itself and the slots that hold nobody not counted, row by row."""
    pos = np.zeros((2, 3, 2))
    pos[0, :, 0] = [0.0, 3.9, 20.0]  # the first row: a pair 3.9 m apart and one far off
    pos[1, :, 0] = [0.0, 3.9, 7.0]  # the second: that pair, its second slot nobody; a third 7 m from the first
    users = np.array([[True, True, True], [True, False, True]])
    np.testing.assert_array_equal(alone(pos, users, 4.0), [[False, False, True], [True, False, True]])
    np.testing.assert_array_equal(alone(pos, users, 7.5), [[False, False, True], [False, False, False]])


def _tracks(venv, r: int, tracks: list[tuple]) -> None:
    """The tracker of row ``r`` holds the confirmed tracks ``(x, y, vx, vy)`` (m, m/s) and no other."""
    trk, p = venv.perception.tracker, venv.perception
    now = venv.engine.ticks[r] / venv.engine.config["simulation_frequency"]
    trk.n[r] = len(tracks)
    for i, track in enumerate(tracks):
        trk.x[r, i] = np.array(track, float)[:, None]
        trk.P[r, i] = np.eye(4) * 0.1
        trk.t[r, i] = trk.t_update[r, i] = now
        trk.length[r, i], trk.width[r, i], trk.heading[r, i] = 5.0, 2.0, np.arctan2(track[3], track[2])
        trk.hits[r, i], trk.confirmed[r, i], trk.id[r, i] = 5, True, 7 + i
    e = venv.engine
    s = e.ego_slot([r])
    ego = np.stack([e.traffic.x[r, s], e.traffic.y[r, s]], axis=1)
    p.last_tracks[[r]] = tracks_observation(*trk.tracks([r]), ego, p.max_tracks)


def test_a_track_standing_alone_in_the_junction_drives_one_beside_another_stays():
    """With ``stopped_scope`` off_approach a track standing inside the junction stays put (crashed in the futures);
    with ``stopped_alone`` 6 m it drives there when no other road user is within 6 m, and stays when a second
    standing track is 5.5 m away (a crash's pair, just clear of it). Released, it moves in the futures where it stood
    still before."""
    venv, planner, obs, rows = _batch([420_001], 45, BeliefLookaheadParams(samples=8, unseen=0.0,
                                                                        stopped_scope="off_approach"))
    e = venv.engine
    crashed, moved = {}, {}
    for radius, pair in ((0.0, False), (6.0, False), (6.0, True)):
        for r in rows:
            _tracks(venv, int(r), [(2.0, 2.0, 0.0, 0.3)] + ([(2.0, -3.5, 0.0, 0.3)] if pair else []))
        p = copy.deepcopy(planner, {id(venv.perception): venv.perception, id(e): e, id(planner.tracks.engine): None})
        p.params = BeliefLookaheadParams(samples=8, unseen=0.0, stopped_scope="off_approach", stopped_alone=radius)
        p.tracks.params = p.params
        p.read(e, rows, np.zeros_like(obs["intent"])[rows])
        t = p.tracks.engine.traffic
        users = t.alive[rows] & ~t.ego[rows]
        crashed[radius, pair] = t.crashed[rows][users].tolist()
        f = p.futures(p.tracks.engine, rows[:1], 8)
        p.tracks.fill(f, rows[:1], p.seed, 8)
        first = int(np.flatnonzero(users[0])[0])
        x0, y0 = f.traffic.x[:, first].copy(), f.traffic.y[:, first].copy()
        for _ in range(5):  # 1 s, the ego idling (IDLE)
            f.step(np.full(f.B, 1), active=np.ones(f.B, bool))
        moved[radius, pair] = float(np.hypot(f.traffic.x[:, first] - x0, f.traffic.y[:, first] - y0).max())
    assert crashed[0.0, False] == [True] * len(rows)
    assert crashed[6.0, False] == [False] * len(rows)
    assert crashed[6.0, True] == [True] * (2 * len(rows))
    # standing: its 0.3 m/s braked away (a crashed car's -v); released: IDM pulls it away (or the regulation holds it)
    assert moved[0.0, False] < 0.3 and moved[6.0, True] < 0.3, moved
    assert moved[6.0, False] > 0.5, moved


def test_stopped_release_makes_a_standing_track_a_driver_in_its_share_of_the_futures():
    """``stopped_release``: a track standing inside the junction (held by the standing rule) is a driver in about
    that share of the futures, drawn per future (0: in none; 1: in all), and released it moves; the same
    decision's futures draw the same ones again. One standing on an exit lane stays in every future."""
    venv, planner, obs, rows = _batch([420_001], 45, BeliefLookaheadParams(samples=8, unseen=0.0,
                                                                        stopped_scope="off_approach"))
    e = venv.engine
    driving, moved = {}, {}
    K = 64
    for share in (0.0, 0.25, 1.0):
        _tracks(venv, int(rows[0]), [(2.0, 2.0, 0.0, 0.3), (-2.0, 25.0, 0.0, -0.3)])  # crossing, exit lane
        p = copy.deepcopy(planner, {id(venv.perception): venv.perception, id(e): e, id(planner.tracks.engine): None})
        p.params = BeliefLookaheadParams(samples=8, unseen=0.0, stopped_scope="off_approach", stopped_release=share)
        p.tracks.params = p.params
        p.read(e, rows, np.zeros_like(obs["intent"])[rows])
        t = p.tracks.engine.traffic
        users = np.flatnonzero(t.alive[rows[0]] & ~t.ego[rows[0]])
        kinds = p.tracks.lane_kind[t.lane[rows[0], users]]
        assert sorted(kinds.tolist()) == [1, 2] and t.crashed[rows[0], users].all()  # both held standing at the start
        slot, exit_slot = int(users[kinds == 1][0]), int(users[kinds == 2][0])
        runs = []
        for _ in range(2):
            f = p.futures(p.tracks.engine, rows[:1], K)
            p.tracks.fill(f, rows[:1], p.seed, K)
            runs.append(~f.traffic.crashed[:, slot])
            assert f.traffic.crashed[:, exit_slot].all()
        np.testing.assert_array_equal(runs[0], runs[1])
        driving[share] = runs[0]
        x0, y0 = f.traffic.x[:, slot].copy(), f.traffic.y[:, slot].copy()
        for _ in range(5):  # 1 s, the ego idling
            f.step(np.full(f.B, 1), active=np.ones(f.B, bool))
        moved[share] = np.hypot(f.traffic.x[:, slot] - x0, f.traffic.y[:, slot] - y0)
    assert not driving[0.0].any() and driving[1.0].all()
    assert 8 <= driving[0.25].sum() <= 24, driving[0.25].sum()  # 16 expected of 64
    assert (moved[0.25][~driving[0.25]] < 0.3).all() and (moved[0.25][driving[0.25]] > 0.5).mean() > 0.5
