"""Where YIELD waits (BeliefLookaheadParams ``wait_back`` / ``wait_gap``, BeliefPlanner.yield_margin ->
av_gym.wrappers.meta_actions ``margin``): ``margin`` m before the stop line, ``wait_back`` farther, and ``wait_gap``
behind the nearest road user standing ahead on the ego's axis where that comes first; on tracks the planner's
tracks say who stands there, never the simulator's vehicles. Both 0: the stop line alone (MARGIN), as before."""

from __future__ import annotations

import numpy as np
import pytest

from agents.belief import BeliefLookaheadParams, BeliefPlanner
from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
from av_gym.envs.left_turn import ROUTE
from av_gym.estimation.turn_features import EGO_FEATURES, OBJECT_FEATURES, TURN
from av_gym.presets import compose_group
from av_gym.sim.batched import LENGTH
from av_gym.wrappers import GO, MARGIN, YIELD


# ----------------------------------------------------------------------------------------- a scripted road
def _empty_road(n: int, seed: int = 5) -> tuple[BatchedLeftTurnBatch, dict]:
    """``n`` rows of one episode (the same ego, ~37 m before its line at 9 m/s), every other vehicle removed and
    none spawned after (spawn_probability 0)."""
    venv = BatchedLeftTurnBatch({"name": "left_turn", "spawn_probability": 0.0},
                                compose_group("sensors", "turn_truth"), None, n, pool=0)
    obs = venv.play(iter([seed] * n))
    t = venv.engine.traffic
    t.alive &= t.ego
    t.compact()
    return venv, obs


def _stand_over_the_line(venv, rear_past_line: float) -> None:
    """A standing car with no controller (highway-env's plain Vehicle: it stays where it is) on every row's
    approach lane, its rear ``rear_past_line`` m past the stop line (0: its rear on the line, the car held over
    it)."""
    e = venv.engine
    t, lane = e.traffic, e.T.id[ROUTE[0]]
    for b in range(e.B):
        slot = t.add(b, lane, float(e.route_starts[1]) + rear_past_line + LENGTH / 2, 0.0, [lane], plain=True)
        t.settle(np.array([b]), np.array([slot]))
    t.route[t.plain] = -1  # a plain Vehicle has no route (as the engine's own reset leaves it)


def _drive_yield(venv, obs, margin, steps: int = 80) -> dict:
    """Every row YIELDs for ``steps`` env steps (8 s at 10 Hz), its meta-actions from meta_actions with
    ``margin(rows)`` (m per row, or None: the default margin); returns the rows' truth at the end."""
    rows = np.arange(venv.engine.B)
    for _ in range(steps):
        m = margin(rows)
        actions = meta_actions(np.full(len(rows), YIELD), obs["turn"]) if m is None else \
            meta_actions(np.full(len(rows), YIELD), obs["turn"], m)
        obs, _, done, _ = venv.step(actions)
        assert not done.any()
    return venv.engine.truth(rows)


def _gap_to_the_standing_car(venv) -> np.ndarray:
    """Per row: the ego's front bumper to the rear bumper of the row's plain car (m, along the ego's axis)."""
    t = venv.engine.traffic
    rows = np.arange(venv.engine.B)
    e, o = venv.engine.ego_slot(rows), np.argmax(t.plain, axis=1)
    h = t.h[rows, e]
    ahead = np.cos(h) * (t.x[rows, o] - t.x[rows, e]) + np.sin(h) * (t.y[rows, o] - t.y[rows, e])
    return ahead - LENGTH


def test_yield_stops_its_margin_before_the_line():
    """An ego driven by meta_actions alone on an empty road stands still ``margin`` m before its line, less than
    0.8 m beyond (the set-points' steps: 9, 4.5, 0 m/s); a larger margin stops it earlier by the difference; the
    default margin is MARGIN (0.5 m)."""
    venv, obs = _empty_road(3)
    margins = np.array([np.nan, 2.5, 5.0])  # the first row: meta_actions' default
    end = _drive_yield(venv, obs, lambda rows: None)
    default_stop = -end["stop_line_offset"][0]
    venv, obs = _empty_road(3)
    end = _drive_yield(venv, obs, lambda rows: np.where(np.isnan(margins), MARGIN, margins))
    stop = -end["stop_line_offset"]  # the ego's front before its line (m)
    assert (end["speed"] < 0.3).all(), end["speed"]
    assert MARGIN == 0.5 and default_stop == pytest.approx(stop[0], abs=1e-9)
    want = np.where(np.isnan(margins), MARGIN, margins)
    assert (stop >= want).all() and (stop - want < 0.8).all(), stop - want
    np.testing.assert_allclose(np.diff(stop), np.diff(want), atol=0.3)


def test_meta_actions_take_one_margin_or_one_per_row():
    """A scalar margin is every row's; a row's own margin moves only its set-point (SLOWER where the approach speed
    sqrt(2 b (d - margin)) falls under 9 m/s: b = 3 m/s², d = 20 m, so past margin 6.5 m), and GO ignores it."""
    ego = np.zeros((4, len(EGO_FEATURES)))
    ego[:, EGO_FEATURES.index("set_point")] = 9.0
    ego[:, EGO_FEATURES.index("to_stop_line")] = 20.0
    turn = TURN.encode(ego, np.zeros((4, TURN.max_objects, len(OBJECT_FEATURES))))
    yield_ = np.full(4, YIELD)
    np.testing.assert_array_equal(meta_actions(yield_, turn, 6.0), meta_actions(yield_, turn, np.full(4, 6.0)))
    np.testing.assert_array_equal(meta_actions(yield_, turn, np.array([0.5, 6.0, 7.0, 19.0])), [1, 1, 0, 0])
    np.testing.assert_array_equal(meta_actions(np.full(4, GO), turn, np.array([0.5, 6.0, 7.0, 19.0])), [1] * 4)


def test_with_wait_gap_the_ego_stands_behind_a_car_held_over_its_line():
    """A car standing with its rear on the stop line in front of a YIELDing ego (benchmarks/belief_tracks_waiting.py's
    "in front" hits): without ``wait_gap`` the ego's set-point follows the line alone and its front ends within 1 m
    of the car; with ``wait_gap`` 3 it stands at least 2.5 m behind it; ``wait_back`` 1.5 alone (2 m before the
    line) does not reach 2.5 m."""
    venv, obs = _empty_road(3)
    _stand_over_the_line(venv, 0.0)
    planners = [BeliefPlanner(BeliefLookaheadParams(samples=4, **kw), n_rows=3)
                for kw in ({}, {"wait_gap": 3.0}, {"wait_back": 1.5})]
    end = _drive_yield(venv, obs, lambda rows: np.array([p.yield_margin(venv.engine, [r])[0]
                                                         for p, r in zip(planners, rows)]))
    gap = _gap_to_the_standing_car(venv)
    assert (end["speed"] < 0.3).all() and not venv.engine.traffic.crashed.any()
    assert 0.0 < gap[0] < 1.0, gap
    assert gap[1] >= 2.5, gap
    assert 1.5 < gap[2] < 2.5, gap


# ----------------------------------------------------------------------------------------- yield_margin
class _Road:
    """An engine as yield_margin reads it: one row per ego (slot 0) with other road users at (ahead, lateral)
    of the ego's axis and a heading each, the ego ``d_stop`` m before its line, heading ``h`` rad."""

    def __init__(self, users: list[list[tuple]], d_stop: list[float], h: float = 0.7, x0: float = 3.0,
                 y0: float = -40.0) -> None:
        n, N = len(users), 1 + max(len(u) for u in users)
        self.traffic = type("T", (), {})()
        t = self.traffic
        t.x, t.y, t.h = np.zeros((n, N)), np.zeros((n, N)), np.full((n, N), h)
        t.alive, t.ego = np.zeros((n, N), bool), np.zeros((n, N), bool)
        t.x[:, 0], t.y[:, 0], t.alive[:, 0], t.ego[:, 0] = x0, y0, True, True
        c, s = np.cos(h), np.sin(h)
        for r, row in enumerate(users):
            for j, (ahead, lateral, heading, *alive) in enumerate(row, start=1):
                t.x[r, j], t.y[r, j] = x0 + c * ahead - s * lateral, y0 + s * ahead + c * lateral
                t.h[r, j], t.alive[r, j] = heading, alive[0] if alive else True
        self.d_stop = np.array(d_stop, float)

    def ego_slot(self, rows) -> np.ndarray:
        return np.zeros(len(rows), int)

    def truth(self, rows) -> dict:
        return {"stop_line_offset": -self.d_stop[np.asarray(rows)]}


def _margin(users, d_stop, **options) -> np.ndarray:
    road = _Road(users, d_stop)
    return BeliefPlanner(BeliefLookaheadParams(samples=4, **options), n_rows=len(users)).yield_margin(
        road, np.arange(len(users)))


def test_wait_gap_stops_the_ego_its_gap_behind_a_road_user_ahead_on_its_axis():
    """The ego 20 m before its line (front to line); a road user whose centre is 10 m ahead (its rear 5 m ahead of
    the ego's front): YIELD stops 3 m behind its rear, 2 m ahead of the ego's front (margin 18 m). The nearest of
    two counts, any heading counts (a wreck turned across, one facing the ego), a road user 1.9 m off the axis
    counts; one 2.1 m off it (the next lane's is 4 m), behind the ego, 30 m or more ahead, not alive, or one
    whose rear leaves more than ``wait_gap`` before the line does not move the margin."""
    d = 20.0
    rows = [[(10.0, 0.0, 0.7)],  # on the axis, the ego's way
            [(16.0, 0.0, 0.7), (10.0, 0.0, 0.7)],  # the nearer of two (in the later slot)
            [(10.0, 0.3, 0.7 + np.pi / 2)],  # turned across
            [(10.0, -1.9, 0.7 + np.pi)],  # facing the ego, 1.9 m off its axis
            [(10.0, 2.1, 0.7)], [(10.0, -2.1, 0.7)],  # beside the axis
            [(-10.0, 0.0, 0.7)],  # behind
            [(30.5, 0.0, 0.7)],  # out of reach (the ego 30 m out: in reach its rear would move the margin)
            [(10.0, 0.0, 0.7, False)],  # a slot holding nobody
            [(28.0, 0.0, 0.7)]]  # its rear 23 m on, 3 m past the line: the line's stop comes first
    m = _margin(rows, [d] * 7 + [30.0] + [d] * 2, wait_gap=3.0)
    stop = d - (10.0 - LENGTH - 3.0)  # the ego's front 2 m on, 3 m short of the rear at 5 m
    np.testing.assert_allclose(m, [stop] * 4 + [MARGIN] * 6, atol=1e-9)
    # the stop follows the road user (its rear 1 m ahead of the ego's front: stop 2 m back from where it stands)
    np.testing.assert_allclose(_margin([[(6.0, 0.0, 0.7)]], [d], wait_gap=3.0), [d + 2.0], atol=1e-9)


def test_wait_back_adds_to_the_line_and_both_off_is_the_line_alone():
    """``wait_back`` moves the line's stop that far back (MARGIN + 1.5 m), with or without a road user beyond
    reach; with a road user ahead the farther of the two stops wins. Both 0 (the kind's defaults): MARGIN
    exactly, a road user standing right in front or not."""
    d = 20.0
    # wait_gap 3 alone: a stop 18 m before the line, none, 1 m before it (the rear 22 m on, 2 m past the line)
    rows = [[(10.0, 0.0, 0.7)], [(30.5, 0.0, 0.7)], [(27.0, 0.0, 0.7)]]
    np.testing.assert_allclose(_margin(rows, [d] * 3, wait_gap=3.0), [18.0, MARGIN, 1.0], atol=1e-9)
    np.testing.assert_allclose(_margin(rows, [d] * 3, wait_back=1.5), [MARGIN + 1.5] * 3, atol=0)
    np.testing.assert_allclose(_margin(rows, [d] * 3, wait_back=1.5, wait_gap=3.0),
                               [18.0, MARGIN + 1.5, MARGIN + 1.5], atol=1e-9)
    np.testing.assert_array_equal(_margin(rows, [d] * 3), [MARGIN] * 3)
    assert BeliefLookaheadParams().wait_gap == 0 and BeliefLookaheadParams().wait_back == 0


def test_the_stop_is_measured_as_meta_actions_reads_the_line():
    """The ego 40 m before its line (it starts up to ~40 m out) and a road user with its rear 10 m ahead: obs["turn"]
    clips the distance to the line at 30 m, so the margin is counted from there and YIELD's approach speed stays
    sqrt(2 b (10 - 3)) (set-point 4.5 m/s), not 0 (a margin counted from 40 m asked for a stop 10 m short)."""
    m = _margin([[(15.0, 0.0, 0.7)]], [40.0], wait_gap=3.0)
    ego = np.zeros((1, len(EGO_FEATURES)))
    ego[0, EGO_FEATURES.index("set_point")] = 4.5
    ego[0, EGO_FEATURES.index("to_stop_line")] = 40.0
    turn = TURN.encode(ego, np.zeros((1, TURN.max_objects, len(OBJECT_FEATURES))))
    seen = float(TURN.decode(turn.astype(float), "to_stop_line")[0])
    assert seen == pytest.approx(30.0) and seen - m[0] == pytest.approx(10.0 - 3.0, abs=1e-5)
    assert meta_actions(np.array([YIELD]), turn, m)[0] == 1  # IDLE: 4.5 m/s held


# ----------------------------------------------------------------------------------------- on tracks
def test_on_tracks_the_margin_reads_the_tracks_not_the_simulators_vehicles():
    """On turn_perceived the road user ahead is the tracker's: a confirmed track standing 12 m ahead on the ego's
    axis moves the margin; with no track, a real car put at the same place (which the tracker does not hold)
    does not, while the planner on truth, which reads the vehicles, stops behind it (so the test can fail)."""
    from tests.test_belief_tracks import _batch, _only_track

    params = BeliefLookaheadParams(samples=4, wait_gap=3.0)
    venv, planner, obs, rows = _batch([420_001], 12, params)
    e = venv.engine
    r = int(rows[0])
    t, s = e.traffic, int(e.ego_slot([r])[0])
    ex, ey, h = t.x[r, s], t.y[r, s], t.h[r, s]
    d = -float(e.truth([r])["stop_line_offset"][0])
    assert 8.0 < d < 30.0, d  # the ego still on its way to the line
    spot = (ex + 12.0 * np.cos(h), ey + 12.0 * np.sin(h))
    stop = d - (12.0 - LENGTH - 3.0)
    intent = np.zeros_like(obs["intent"])[rows]

    _only_track(venv, r, (*spot, 0.0, 0.0))
    planner.read(e, rows, intent)
    assert planner.yield_margin(e, rows)[0] == pytest.approx(stop, abs=0.3)

    _only_track(venv, r, None)
    other = int(np.flatnonzero(t.alive[r] & ~t.ego[r])[0])  # a real car, put where the track stood
    t.x[r, other], t.y[r, other], t.h[r, other], t.v[r, other] = *spot, h, 0.0
    planner.read(e, rows, intent)
    assert planner.yield_margin(e, rows)[0] == MARGIN
    truth = BeliefPlanner(params, n_rows=e.B)
    assert truth.yield_margin(e, rows)[0] == pytest.approx(stop, abs=1e-6)


@pytest.mark.slow  # 3.5 s at load ~3.5 (three per-env stacks)
def test_the_batch_evaluation_waits_where_the_per_env_agent_does():
    """eval.batched's decider (the batch evaluation of belief_lookahead on tracks) gives the per-env agent's
    meta-actions step by step with ``wait_gap`` 3 and ``wait_back`` 1.5 on, each side driving its own episodes with
    its own actions; and the margin moves some of them (the same steps with the line's margin alone differ)."""
    from agents.belief import BeliefLookahead
    from av_gym.make import make_env
    from eval.batched import _Decider

    seeds, sensors = [400_100, 400_101, 400_102], compose_group("sensors", "turn_perceived")
    params = BeliefLookaheadParams(samples=4, wait_gap=3.0, wait_back=1.5)
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, sensors, None, len(seeds), pool=0)
    bobs = venv.play(iter(seeds))
    decider = _Decider(BeliefLookahead(None, params), venv.engine, venv.perception)
    decider.reset(np.arange(len(seeds)))
    envs = [make_env({"name": "left_turn"}, sensors, None) for _ in seeds]
    obs = [e.reset(seed=s)[0] for e, s in zip(envs, seeds)]
    agents = [BeliefLookahead(e, params) for e in envs]
    moved = 0
    for k in range(30):
        live = ~venv.idle
        assert live.all(), k
        out = decider.act(bobs, live)
        per_env = [a.act(o) for a, o in zip(agents, obs)]
        assert out.tolist() == per_env, k
        moved += int((out != meta_actions(decider.choice, bobs["turn"])).sum())
        bobs, _, _, _ = venv.step(out)
        obs = [e.step(a)[0] for e, a in zip(envs, per_env)]
    for e in envs:
        e.close()
    assert moved > 0, "wait_gap / wait_back must change some YIELD meta-action"


def test_a_nan_distance_to_the_line_falls_back_to_the_lines_margin():
    """A non-finite ``stop_line_offset`` (NaN) leaves the margin at the line's (MARGIN + ``wait_back``), a road user
    ahead or not, never NaN: meta_actions reads a NaN margin as room to speed up (FASTER), so YIELD would
    accelerate."""
    rows = [[(10.0, 0.0, 0.7)], [(30.5, 0.0, 0.7)]]  # one in reach, one beyond it
    np.testing.assert_array_equal(_margin(rows, [np.nan] * 2, wait_gap=3.0), [MARGIN] * 2)
    m = _margin(rows, [np.nan] * 2, wait_gap=3.0, wait_back=1.5)
    np.testing.assert_array_equal(m, [MARGIN + 1.5] * 2)
    ego = np.zeros((2, len(EGO_FEATURES)))
    # 5 m before the line at 4.5 m/s: sqrt(2 b (5 - 2)) = 4.2 m/s is under 4.5 (SLOWER); NaN read as the top (FASTER)
    ego[:, EGO_FEATURES.index("set_point")] = 4.5
    ego[:, EGO_FEATURES.index("to_stop_line")] = 5.0
    turn = TURN.encode(ego, np.zeros((2, TURN.max_objects, len(OBJECT_FEATURES))))
    assert meta_actions(np.full(2, YIELD), turn, np.full(2, np.nan))[0] == 2  # why NaN must not get through
    np.testing.assert_array_equal(meta_actions(np.full(2, YIELD), turn, m), [0, 0])  # SLOWER


class _Moving(_Road):
    """:class:`_Road` with the ego at ``speed`` m/s (committed() reads it)."""

    def __init__(self, users, d_stop, speed: float) -> None:
        super().__init__(users, d_stop)
        self.speed = np.full(len(users), float(speed))

    def truth(self, rows) -> dict:
        return {**super().truth(rows), "speed": self.speed[np.asarray(rows)]}


def test_commit_stop_judges_the_stop_where_yield_stops():
    """``commit: stop`` makes a held GO final where the ego can no longer stop where YIELD would stop it: 10 m
    before the line at 6.5 m/s it can still stop at the line (sqrt(2·3·9.5) = 7.5 m/s), not 5.5 m before it
    (``wait_back`` 5: 5.2 m/s) nor 3 m behind a car whose rear is 5 m ahead (``wait_gap`` 3: stop 8 m before the
    line, 3.5 m/s). Without wait_back / wait_gap (every shipped preset; belief_tracks runs commit: never, which
    never asks committed()) the line's MARGIN, as before."""
    users = [[(30.5, 0.0, 0.7)], [(30.5, 0.0, 0.7)], [(10.0, 0.0, 0.7)]]
    road = _Moving(users, [10.0] * 3, 6.5)
    rows, held, step = np.arange(3), np.full(3, GO), np.zeros(3, int)
    for options, want in (({}, [False] * 3), ({"wait_back": 5.0}, [True] * 3),
                          ({"wait_gap": 3.0}, [False, False, True])):
        planner = BeliefPlanner(BeliefLookaheadParams(samples=4, commit="stop", **options), n_rows=3)
        due, final = planner.live(road, rows, held, step)
        np.testing.assert_array_equal(final, want, err_msg=str(options))
        assert (due == ~final).all()
    assert BeliefPlanner.committed(road, rows, held).tolist() == [False] * 3  # the default: the line's MARGIN
    assert BeliefLookaheadParams().commit == "never"
