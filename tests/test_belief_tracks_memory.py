"""The planner on tracks' memory of the cars whose track the tracker dropped (``recall``; agents/track_memory.py):
remembered at the last state, predicted on, dropped by a track or detection near it, a look that sees nothing, or
``recall`` s; and in the futures' start as a road user."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest

from agents.track_memory import MEMORY_GATE, TrackMemory

RATE = 10.0  # Hz, the detector's frames


class _Tracker:
    """The arrays TrackMemory reads of a BatchedTracker, one row: ``set`` its tracks ``[(id, x, y, vx, vy)]``."""

    def __init__(self) -> None:
        self.n, self.fused_at = np.zeros(1, int), np.zeros(1)
        self._set([], 0.0)

    def _set(self, tracks: list, t: float) -> None:
        K = max(len(tracks), 1)
        self.x = np.zeros((1, K, 7))
        self.id, self.heading, self.t_update = np.full((1, K), -1), np.zeros((1, K)), np.full((1, K), t)
        for k, (i, x, y, vx, vy) in enumerate(tracks):
            self.x[0, k] = [x, y, vx, vy, np.arctan2(vy, vx), 5.0, 2.0]
            self.id[0, k], self.heading[0, k] = i, np.arctan2(vy, vx)
        self.n[0], self.fused_at[0] = len(tracks), t

    def tracks(self, rows):
        return self.x[rows], np.arange(self.x.shape[1])[None] < self.n[rows][:, None]


def _reading(mem: TrackMemory, trk: _Tracker, t: float, tracks: list, detections: list = (),
             ego=(0.0, 0.0, 0.0)) -> tuple:
    """One fused frame at ``t`` s: the tracker holds ``tracks``, the detector saw ``detections`` [(x, y)]; the
    memory's users after it."""
    trk._set(tracks, t)
    det = np.zeros((1, 4, 9))
    for j, (x, y) in enumerate(detections):
        det[0, j, :3] = 1.0, x, y
    p = SimpleNamespace(tracker=trk, last_detections=det)
    rows, now = np.array([0]), np.array([t])
    mem.update(p, rows, np.array([ego]), now)
    return mem.users(rows, now, trk.fused_at)


def _memory(recall: float = 3.0, max_range: float = 50.0) -> TrackMemory:
    return TrackMemory(1, recall, max_range, np.pi, occlusion=True, rate_hz=RATE)


def test_a_dropped_track_is_remembered_and_predicted_on_out_of_view():
    """A car 80 m out (beyond the 50 m range) whose track vanished stays a road user at its constant-velocity place
    for ``recall`` s, with its id, detected heading and the frames since its last detection; then it is forgotten."""
    mem, trk = _memory(recall=1.0), _Tracker()
    _reading(mem, trk, 0.0, [(7, 80.0, 0.0, -10.0, 0.0)])
    pos, ids, alive, seen = _reading(mem, trk, 0.1, [])
    assert alive[0].sum() == 1
    k = int(np.flatnonzero(alive[0])[0])
    np.testing.assert_allclose(pos[0, k, :2], [79.0, 0.0])  # predicted 0.1 s on at -10 m/s
    assert ids[0, k] == 7 and np.isclose(seen[0, k, 0], np.pi) and seen[0, k, 1] == 1
    for t in np.arange(0.2, 1.05, 0.1):
        pos, ids, alive, _ = _reading(mem, trk, float(t), [])
        assert alive[0].sum() == 1, t
    np.testing.assert_allclose(pos[0, k, :2], [70.0, 0.0], atol=1e-9)
    _, _, alive, _ = _reading(mem, trk, 1.2, [])
    assert not alive.any()  # more than recall s since its track died


def test_reset_forgets_the_remembered_cars_and_the_last_reading():
    """A new episode (``reset``): a car remembered out of view is forgotten, and a track of the last reading that the
    new episode's first reading lacks is not taken for a dropped one."""
    mem, trk = _memory(recall=3.0), _Tracker()
    _reading(mem, trk, 0.0, [(7, 80.0, 0.0, -10.0, 0.0), (8, 90.0, 0.0, -10.0, 0.0)])
    _, _, alive, _ = _reading(mem, trk, 0.1, [(8, 89.0, 0.0, -10.0, 0.0)])
    assert alive[0].sum() == 1  # 7 remembered (80 m out: beyond the 50 m range)
    mem.reset([0])
    _, _, alive, _ = _reading(mem, trk, 0.0, [])  # the new episode's clock starts again
    assert not alive.any()


def test_a_look_that_sees_nothing_forgets_it_and_the_frame_it_died_in_does_not():
    """A car 20 m out, in plain view: its track vanished in this frame (the miss that deleted it) and it is kept;
    the next frame, in view again with no detection there, forgets it."""
    mem, trk = _memory(), _Tracker()
    _reading(mem, trk, 0.0, [(3, 20.0, 0.0, 0.0, 0.0)])
    _, _, alive, _ = _reading(mem, trk, 0.1, [])
    assert alive[0].sum() == 1
    _, _, alive, _ = _reading(mem, trk, 0.2, [])
    assert not alive.any()


def test_behind_a_detected_car_it_is_kept():
    """The same car hidden behind a track the detector updated in this frame (between it and the ego) stays."""
    mem, trk = _memory(), _Tracker()
    _reading(mem, trk, 0.0, [(3, 20.0, 0.0, 0.0, 0.0), (4, 10.0, 0.0, 0.0, 0.0)])
    _reading(mem, trk, 0.1, [(4, 10.0, 0.0, 0.0, 0.0)])
    _, _, alive, _ = _reading(mem, trk, 0.2, [(4, 10.0, 0.0, 0.0, 0.0)])
    assert alive[0].sum() == 1
    # the occluder moved out of the line of sight: the look sees nothing there
    _, _, alive, _ = _reading(mem, trk, 0.3, [(4, 10.0, 8.0, 0.0, 0.0)])
    assert not alive.any()


def test_a_new_track_or_a_detection_near_it_takes_its_place():
    """Out of view (so no look forgets it), a new track within MEMORY_GATE of its predicted place is the same car
    (forgotten); a track farther off is another car (kept); a detection near it forgets it too."""
    for near in (True, False):
        mem, trk = _memory(max_range=10.0), _Tracker()
        _reading(mem, trk, 0.0, [(3, 30.0, 0.0, 0.0, 0.0)])
        off = 0.5 * MEMORY_GATE if near else 2.0 * MEMORY_GATE
        _, _, alive, _ = _reading(mem, trk, 0.1, [(9, 30.0, off, 0.0, 0.0)])
        assert alive[0].sum() == (0 if near else 1), near
    mem, trk = _memory(max_range=10.0), _Tracker()
    _reading(mem, trk, 0.0, [(3, 30.0, 0.0, 0.0, 0.0)])
    _, _, alive, _ = _reading(mem, trk, 0.1, [], detections=[(30.5, 0.5)])
    assert not alive.any()


def test_the_remembered_car_is_a_road_user_of_the_futures_start():
    """On the batch, with ``recall`` 3 s: a row whose one confirmed track vanishes keeps a road user at its place in
    the futures' start (marked remembered); with the kind's default (0) the row has only the ego."""
    import dataclasses

    from agents.belief import BeliefLookaheadParams
    from agents.track_prior import TrackBelief
    from tests.test_belief_tracks import _batch, _only_track

    base = BeliefLookaheadParams(samples=4, unseen=0.0, tentative="road_user")
    venv, planner, obs, rows = _batch([420_001], 10, base)
    r = int(rows[0])
    e = venv.engine
    out = {}
    for recall in (0.0, 3.0):
        p = copy.deepcopy(planner, {id(venv.perception): venv.perception, id(e): e,
                                    id(planner.tracks.engine): None})
        p.params = dataclasses.replace(base, recall=recall)
        p.tracks = TrackBelief(p.params, venv.perception, 1)
        s = e.ego_slot([r])[0]
        x, y = float(e.traffic.x[r, s]) - 30.0, float(e.traffic.y[r, s])  # 30 m off the ego
        _only_track(venv, r, (x, y, 5.0, 0.0))
        p.read(e, rows, obs["intent"][rows])
        e.ticks[r] += 1  # one engine tick on; no detector frame fused since (no look)
        _only_track(venv, r, None)
        try:
            p.read(e, rows, obs["intent"][rows])
        finally:
            e.ticks[r] -= 1
        t = p.tracks.engine.traffic
        users = np.flatnonzero(t.alive[r] & ~t.ego[r])
        out[recall] = [(float(t.x[r, j]), float(t.y[r, j]), bool(p.tracks.remembered[r, j])) for j in users]
    assert out[0.0] == []
    assert len(out[3.0]) == 1 and out[3.0][0][2]
    dt = 1.0 / e.config["simulation_frequency"]
    np.testing.assert_allclose(out[3.0][0][:2], [x + 5.0 * dt, y], atol=1e-6)  # one tick on at 5 m/s


@pytest.mark.parametrize("unseen", [0.0, 1.0])
def test_a_tentative_road_user_is_packed_into_the_futures_start_and_stays(unseen: float):
    """A tentative track standing in the ego's path inside the junction (a road user with ``tentative:
    road_user``), read after the 16 described slots, is packed into slot 1 of the futures' start, as the same car
    confirmed is, and every future of GO collides with it, as with the car confirmed. Left in its slot after the
    described block (before the packing), the futures' first step trimmed it away (Traffic.trim keeps the slots up
    to the most road users a row holds) and GO looked safe (0 of 16 colliding). Also with the unseen prior on (the
    preset's, the kind's default 1.0), whose drivers join at each future's live count."""
    from agents.belief import BeliefLookaheadParams
    from tests.test_belief_tracks import _batch, _only_track

    out = {}
    for confirmed in (False, True):
        params = BeliefLookaheadParams(samples=16, unseen=unseen, tentative="road_user")
        venv, planner, obs, rows = _batch([420_001, 420_002], 45, params)
        for r in rows:
            _only_track(venv, int(r), (2.0, 5.0, 0.0, -0.2))  # 10 m ahead of the ego, standing
        venv.perception.tracker.confirmed[rows, 0] = confirmed
        planner.read(venv.engine, rows, obs["intent"][rows])
        tb = planner.tracks
        for r in rows:
            assert np.flatnonzero(tb.engine.traffic.alive[r]).tolist() == [0, 1]  # the ego, then the car
            assert tb.tent[r].tolist() == [False, not confirmed] + [False] * (tb.engine.traffic.N - 2)
        out[confirmed] = planner.go_collision(venv.engine, rows)
    np.testing.assert_array_equal(out[True], [1.0, 1.0])
    np.testing.assert_array_equal(out[False], [1.0, 1.0])


def test_a_road_user_an_edit_moved_behind_a_gap_stays_in_the_futures():
    """A tool that edits the futures' start after the read (the ablation's truth parts, the confirm trace's road
    user left out) may leave a gap: the confirmed car standing in the ego's path moved from slot 1 to a late slot
    still collides in every future of GO (the futures are packed before the unseen drivers join); left behind the
    gap, the first step's trim dropped it and GO looked safe."""
    from agents.belief import BeliefLookaheadParams
    from av_gym.sim.batched import Traffic
    from tests.test_belief_tracks import _batch, _only_track

    venv, planner, obs, rows = _batch([420_001, 420_002], 45, BeliefLookaheadParams(samples=16, unseen=0.0))
    for r in rows:
        _only_track(venv, int(r), (2.0, 5.0, 0.0, -0.2))  # 10 m ahead of the ego, standing
    planner.read(venv.engine, rows, obs["intent"][rows])
    t = planner.tracks.engine.traffic
    late = t.N - 1
    assert late > 4 and not t.alive[rows, late].any()
    for name in Traffic.FIELDS:
        getattr(t, name)[rows, late] = getattr(t, name)[rows, 1]
    t.alive[rows, 1] = False
    np.testing.assert_array_equal(planner.go_collision(venv.engine, rows), [1.0, 1.0])


def test_decisions_with_recall_do_not_read_the_hidden_traffic():
    """Near the stop line, the one confirmed track of each row (a car standing in the ego's path, at a simulator
    vehicle's place) vanishes: with ``recall`` the planner keeps it and every future of GO collides;
    without, none does. The same tracks, observations and ego then give the same GO collision probabilities, bit for
    bit, after the simulator's vehicles (none with a track now) were removed or moved and every hidden draw
    re-drawn (tests/test_belief_tracks.py's check): the memory reads the tracker, never the cars."""
    import dataclasses

    from agents.belief import BeliefLookaheadParams
    from tests.test_belief import rerandomise
    from tests.test_belief_tracks import _batch, _hide_changes, _only_track

    params = BeliefLookaheadParams(samples=16, unseen=0.0, tentative="road_user", track_heading="detected",
                                   ghost=2, merge=2.0, recall=3.0)
    venv, planner, obs, rows = _batch([420_001, 420_002], 45, params)
    e = venv.engine
    t = e.traffic
    car = (2.0, 5.0, 0.0, -0.2)
    for r in rows:
        _only_track(venv, int(r), car)
        # a simulator vehicle there (the memory must not find it)
        j = int(np.flatnonzero(t.alive[r] & ~t.ego[r])[0])
        t.x[r, j], t.y[r, j], t.h[r, j], t.v[r, j] = car[0], car[1], -np.pi / 2, 0.2
    planner.read(e, rows, obs["intent"][rows])
    e.ticks[rows] += 1  # one engine tick on, no detector frame fused since: the track gone, no look yet
    for r in rows:
        _only_track(venv, int(r), None)
    shared = {id(venv.perception): venv.perception, id(e): e, id(planner.tracks.engine): None}
    again, without = copy.deepcopy(planner, dict(shared)), copy.deepcopy(planner, dict(shared))
    without.params = dataclasses.replace(params, recall=0.0)
    without.tracks.memory = None
    planner.read(e, rows, obs["intent"][rows])
    p_before = planner.go_collision(e, rows)
    assert planner.tracks.remembered[rows].any(axis=1).all()
    without.read(e, rows, obs["intent"][rows])
    np.testing.assert_array_equal(p_before, [1.0, 1.0])
    np.testing.assert_array_equal(without.go_collision(e, rows), [0.0, 0.0])
    assert _hide_changes(e, rows, venv.perception.detector.max_range, venv.perception.last_tracks[rows]) > 0
    rerandomise(e, rows, seed=11)
    again.read(e, rows, obs["intent"][rows])
    np.testing.assert_array_equal(p_before, again.go_collision(e, rows))
