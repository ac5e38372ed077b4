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
                                                                   "heading", "acc", "lane"}),
                                         ("intent", {"intent"}), ("crash,velocity", {"crash", "velocity"}),
                                         ("all,intent,crash", {"users", "prior", "position", "velocity", "heading",
                                                               "acc", "lane", "intent", "crash"}),
                                         ("all,crash,-velocity", {"users", "prior", "position", "heading", "acc",
                                                                  "lane", "crash"}),
                                         ("all,-lane", {"users", "prior", "position", "velocity", "heading", "acc"}),
                                         ("all,crash,-users,users_extra", {"users_extra", "prior", "position",
                                                                           "velocity", "heading", "acc", "lane",
                                                                           "crash"}),
                                         ("all,crash,-heading", {"users", "prior", "position", "velocity", "acc",
                                                                 "crash"})])
def test_the_parts_named(ablate, spec, parts):
    assert ablate.parts_of(spec) == parts


def test_a_bad_part_is_one_error_line(ablate, capsys):
    with pytest.raises(SystemExit) as out:
        ablate.parts_of("speed")
    err = capsys.readouterr().err.strip()
    assert out.value.code == 2 and len(err.splitlines()) == 1 and "--truth" in err and "velocity" in err
    for spec in ("all,-speed", "crash,-velocity", "velocity,-velocity"):  # a part out of what is not in
        with pytest.raises(SystemExit) as out:
            ablate.parts_of(spec)
        err = capsys.readouterr().err.strip()
        assert out.value.code == 2 and len(err.splitlines()) == 1 and "--truth" in err
    with pytest.raises(SystemExit) as out:
        ablate.parts_of("all,-speed")
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
    # each half of ``users`` alone: the cars without a road user added, or the road users of no car removed (a
    # false track put 60 m from the ego, where no car is); both together are ``users``
    def read_with_a_false_track():
        planner.read(engine, rows, obs["intent"][rows])
        t = planner.tracks.engine.traffic
        j = int(np.flatnonzero(~t.alive[rows[0]] & ~t.ego[rows[0]])[0])
        e = int(np.flatnonzero(t.ego[rows[0]])[0])
        t.alive[rows[0], j], t.x[rows[0], j], t.y[rows[0], j] = True, t.x[rows[0], e] + 60.0, t.y[rows[0], e] + 60.0
        assert np.hypot(s.x[rows[0]] - t.x[rows[0], j], s.y[rows[0]] - t.y[rows[0], j])[s.alive[rows[0]]].min() > 10
        return copy.deepcopy(t)

    halves = {}
    for parts in ("none", "users_missing", "users_extra", "users_missing,users_extra", "users"):
        own = read_with_a_false_track()
        ablate.with_truth(planner, engine, rows, ablate.parts_of(parts), 3.0)
        halves[parts] = copy.deepcopy(planner.tracks.engine.traffic)
    for name in ("alive", "x", "y", "v"):
        np.testing.assert_array_equal(getattr(halves["users"], name), getattr(halves["users_missing,users_extra"],
                                                                                name))
    added = removed = 0
    for r in rows:
        was = set(np.flatnonzero(own.alive[r] & ~own.ego[r]))
        assert set(np.flatnonzero(halves["none"].alive[r] & ~halves["none"].ego[r])) == was
        t = halves["users_missing"]  # every car has its road user; every road user the tracks had stays
        now = np.flatnonzero(t.alive[r] & ~t.ego[r])
        assert was <= set(now)
        for i in np.flatnonzero(s.alive[r] & ~s.ego[r]):
            assert np.hypot(t.x[r, now] - s.x[r, i], t.y[r, now] - s.y[r, i]).min() <= 3.0
        added += len(now) - len(was)
        t = halves["users_extra"]  # only the road users of a car remain, none added
        now = set(np.flatnonzero(t.alive[r] & ~t.ego[r]))
        assert now <= was and now <= set(np.flatnonzero(halves["users"].alive[r]))
        removed += len(was - now)
    assert added > 0 and removed > 0, (added, removed)


def _readers(track_vids, car_vids, alive=None):
    """A one-row planner stand-in (its counts and its futures' start holding road users ``track_vids``) and a
    simulator engine stand-in holding cars ``car_vids`` (slot 0 the ego in both)."""
    n = len(track_vids)
    te = SimpleNamespace(vid=np.array([track_vids]), alive=np.ones((1, n), bool) if alive is None else alive)
    planner = SimpleNamespace(counts=[{}], tracks=SimpleNamespace(engine=SimpleNamespace(traffic=te)))
    return planner, SimpleNamespace(traffic=SimpleNamespace(vid=np.array([car_vids])))


def test_intent_readings_follow_the_car_across_a_reborn_track(ablate):
    """A car (vid 42) read twice "+1" on track 5, then once "0" on its re-born track 9: at the decision track 9
    carries all three of the car's readings; a track of no car keeps its own; a car ``users`` added (road user
    ADDED + 42) carries the car's; restore puts the planner's own per-track counts back."""
    readings = ablate.CarReadings(1)
    planner, sim = _readers([0, 5, 7], [0, 42])
    rows = np.array([0])
    readings.before(planner, rows)
    planner.counts[0][5] = np.array([0, 0, 2])
    planner.counts[0][7] = np.array([1, 0, 0])  # a track of no car
    readings.after(planner, sim, rows, {0: {1: 1}})
    np.testing.assert_array_equal(readings.cars[0][42], [0, 0, 2])
    readings.restore(planner, rows)
    planner.tracks.engine.traffic.vid[0, 1] = 9  # the car's track re-born
    readings.before(planner, rows)
    planner.counts[0][9] = np.array([0, 1, 0])
    readings.after(planner, sim, rows, {0: {1: 1}})
    readings.lend(planner, sim, rows, {0: {1: 1}})
    np.testing.assert_array_equal(planner.counts[0][9], [0, 1, 2])
    np.testing.assert_array_equal(planner.counts[0][7], [1, 0, 0])
    readings.restore(planner, rows)
    np.testing.assert_array_equal(planner.counts[0][9], [0, 1, 0])  # the planner's own again
    # the car from the truth (users) in slot 2, the track of no car gone
    planner.tracks.engine.traffic.vid[0, 2] = ablate.ADDED + 42
    planner.tracks.engine.traffic.alive[0, 1] = False
    readings.lend(planner, sim, rows, {0: {}})
    np.testing.assert_array_equal(planner.counts[0][ablate.ADDED + 42], [0, 1, 2])


@pytest.mark.slow
def test_users_grows_the_spread_with_the_traffic(ablate):
    """A futures' start with no free slot for the cars ``users`` adds (cut to the ego and one track) grows its
    filter covariances with it: with track_spread > 0 the futures draw and every car from the truth starts at its
    place (no error); ``crash`` gives each road user its car's crash flag."""
    venv, planner, obs, rows = _batch([420_001, 420_002], 45, BeliefLookaheadParams(
        samples=4, tentative="road_user", track_heading="detected", ghost=2, merge=2.0, track_spread=1.0))
    engine, s = venv.engine, venv.engine.traffic
    planner.read(engine, rows, obs["intent"][rows])
    tb = planner.tracks
    t = tb.engine.traffic
    for name in t.FIELDS:
        setattr(t, name, getattr(t, name)[:, :2])
    t.N = 2
    tb.tent, tb.ghost, tb.along = tb.tent[:, :2], tb.ghost[:, :2], tb.along[:, :2]
    assert (s.alive[rows] & ~s.ego[rows]).sum(axis=1).max() > 1  # more cars than the slot left
    pairs_of = ablate.all_pairs(planner, engine, rows, 3.0)
    ablate.with_truth(planner, engine, rows, frozenset({"users", "crash"}), 3.0, pairs_of)
    t = tb.engine.traffic
    assert tb.along.shape[1] == t.N > 2
    assert np.isfinite(planner.go_collision(engine, rows)).all()
    flags = 0
    for r in rows:
        car = {int(v): bool(c) for v, c in zip(s.vid[r], s.crashed[r])}
        for i, j in pairs_of[int(r)].items():
            assert t.crashed[r, j] == s.crashed[r, i]
            flags += 1
        for j in np.flatnonzero(t.alive[r] & (t.vid[r] >= ablate.ADDED)):
            assert t.crashed[r, j] == car[int(t.vid[r, j]) - ablate.ADDED]
            flags += 1
    assert flags == (s.alive[rows] & ~s.ego[rows]).sum()  # every car, matched or added


def _frame(t, view, detected=False, kind=0, status="unseen"):
    """A SensorHistory entry: [time s, view (0 out, 1 occluded, 2 in view), detected, track kind, track id, the
    planner's status, range m, lane kind]."""
    return [t, view, detected, kind, 5 if kind else -1, status, 40.0, 0]


def test_why_names_the_cause_a_car_was_missing(ablate):
    """``--why``'s cause from a car's frames: never in view (out of range / occluded), its track died in view
    (tentative or confirmed), out of view now after a confirmed track, held by the tracker but nobody to the planner,
    and the frames since it was last in view and tracked."""
    why = ablate.why_cause
    assert why([])["cause"] == "not on the map"
    assert why([_frame(0.0, 0), _frame(0.1, 0)])["cause"] == "never in view: out of range/fov"
    assert why([_frame(0.0, 0), _frame(0.1, 1)])["cause"] == "never in view: occluded"
    died = [_frame(0.0, 2, True, 1, "tentative"), _frame(0.1, 2, False, 0)]
    got = why(died)
    assert got["cause"] == "in view, tentative died" and got["since_tracked_s"] == 0.1
    assert got["detected_frames"] == 1 and got["in_view_frames"] == 2
    # its tentative track (id 5) still held by the tracker at the decision's frame, off the car: not died
    assert why(died, frozenset({5}))["cause"] == "in view, tentative drifted off"
    assert why(died, frozenset({4}))["cause"] == "in view, tentative died"
    gone = [_frame(0.0, 2, True, 1, "tentative"), _frame(0.1, 1, False, 0)]
    assert why(gone, frozenset({5}))["cause"] == "not in view now (occluded), tentative drifted off"
    coasted = [_frame(0.0, 2, True, 2, "confirmed")] + [_frame(0.1 * k, 1, False, 2, "confirmed") for k in (1, 2)] \
        + [_frame(0.3, 1)]
    got = why(coasted)  # its track (id 5) no longer among the tracker's: deleted
    assert got["cause"] == "not in view now (occluded), confirmed deleted" and got["since_in_view_s"] == 0.3
    assert why(coasted, frozenset({4, 6}))["cause"] == "not in view now (occluded), confirmed deleted"
    # the tracker still holds track 5, more than the match radius off the car
    assert why(coasted, frozenset({5}))["cause"] == "not in view now (occluded), confirmed drifted off"
    history = ablate.SensorHistory(1, ablate.MATCH_M)  # why() hands why_cause the ids of the decision's frame
    history.log[0][9] = coasted
    history.tracks[0][0.3] = frozenset({5})
    assert history.why(0, 9, 0.3)["cause"].endswith("confirmed drifted off")
    history.tracks[0][0.3] = frozenset()
    assert history.why(0, 9, 0.3)["cause"].endswith("confirmed deleted")
    assert why([_frame(0.0, 2, True, 2, "left out")])["cause"] == "held by the tracker, not a road user of the planner"
    # occluded now, its confirmed track (id 5) still within the match radius: held, not drifted off
    held = [_frame(0.0, 2, True, 2, "confirmed"), _frame(0.1, 1, False, 2, "left out")]
    assert why(held, frozenset({5}))["cause"] == \
        "not in view now (occluded), held by the tracker, not a road user of the planner"
    assert why([_frame(0.0, 2, False, 0)])["cause"] == "in view, never tracked"


def test_the_table_pairs_scattered_seeds(ablate, tmp_path):
    """``--table`` on runs of scattered ``--seeds`` (a replay): the arrived episodes come from the seeds each run
    played, not ``seed .. seed + episodes``; a file written before the ``seeds`` field falls back to that range."""
    import json

    def run(path, played, not_arrived, **extra):
        doc = {"truth": [], "collision": 0.0, "success": 0.5, "collided": [], "not_arrived": not_arrived,
               "collisions": [], "seed": min(played), "episodes": len(played), **extra}
        (tmp_path / path).write_text(json.dumps(doc))
        return str(tmp_path / path)

    base = run("base.json", [1_949_010, 1_949_500], [1_949_500], seeds=[1_949_010, 1_949_500])
    other = run("other.json", [1_949_010, 1_949_500], [1_949_010], seeds=[1_949_010, 1_949_500])
    old = run("old.json", [1_949_010, 1_949_011], [1_949_010])
    rows = ablate.table([base, other, old]).splitlines()[2:]
    assert [r.split("|")[5].strip() for r in rows] == ["0 / 0", "1 / 1", "1 / 1"]


def test_the_sensor_history_records_the_detectors_view_per_car(ablate, monkeypatch):
    """``--why``'s recorder (SensorHistory.frame) at a fused frame: each simulator car gets the detector's own view
    of it (0 out of range or field of view, 1 occluded, 2 in view) and range as the detector's ``_views`` gives them
    (patched: a known hidden car), under its vid."""
    from av_gym.batched.perception import others_state

    venv, planner, obs, rows = _batch([420_001], 20, BeliefLookaheadParams(samples=4))
    e = venv.engine
    planner.read(e, rows, obs["intent"][rows])
    venv.perception.tracker.fused_at[rows] = e.ticks[rows] / e.config["simulation_frequency"]  # a frame fused now
    _, vids, off = others_state(e, rows)
    n = int(off[-1])
    assert n >= 3
    code = np.arange(n) % 3  # out of view, occluded (in range and field, hidden), in view
    monkeypatch.setattr(venv.perception.detector, "_views",
                        lambda ego, others, o: (10.0 + np.arange(n), code > 0, code == 1))
    history = ablate.SensorHistory(1, ablate.MATCH_M)
    history.frame(planner, e, rows)
    got = {v: history.log[int(rows[0])][int(v)] for v in vids}
    assert [len(h) for h in got.values()] == [1] * n
    assert [h[0][1] for h in got.values()] == code.tolist()
    assert [h[0][6] for h in got.values()] == (10.0 + np.arange(n)).tolist()
    trk = venv.perception.tracker  # and the tracker's track ids at that frame
    held = trk.id[int(rows[0]), : int(trk.n[int(rows[0])])].tolist()
    assert list(history.tracks[int(rows[0])].values()) == [frozenset(held)]
