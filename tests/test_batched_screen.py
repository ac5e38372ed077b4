"""The batch shield's screen (``BatchedShield._screen``: the rows whose own decision ends quiet or in a warning,
decided for all rows at once) and its all-rows helpers, against the per-row code they stand for: ``locate_rows``
(av_gym/shields/locate_rows.py) against ``LanePath.locate`` point by point, ``BrakeActuator.stopping_bounds`` against
``stopping_bound``, and the whole state of every row's shield with the screen off and on, step by step."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from av_gym.shields.locate_rows import locate_rows

VALIDATION = 1_000_000


# ----------------------------------------------------------------------------------------------- locate_rows
def _stadium():
    """A closed loop of two straight lanes and two half circles (m): 60 x 40."""
    from highway_env.road.lane import CircularLane, StraightLane

    from av_gym.envs.lane_path import LanePath

    return LanePath([StraightLane([0.0, 0.0], [60.0, 0.0]),
                     CircularLane([60.0, 20.0], 20.0, -np.pi / 2, np.pi / 2, clockwise=True),
                     StraightLane([60.0, 40.0], [0.0, 40.0]),
                     CircularLane([0.0, 20.0], 20.0, np.pi / 2, 3 * np.pi / 2, clockwise=True)], closed=True)


def _left_turn_route():
    from av_gym.envs.lane_path import LanePath
    from av_gym.envs.left_turn import ROUTE, UnprotectedLeftTurnEnv

    env = UnprotectedLeftTurnEnv()
    env.reset(seed=3)
    net = env.unwrapped.road.network
    return LanePath([net.get_lane(i) for i in ROUTE])


@pytest.mark.parametrize("which", ["left_turn", "closed"])
def test_locate_rows_is_locate_point_by_point(which):
    """``locate_rows`` (one compiled call for many points) gives each point what ``locate`` gives it from
    the same hint, bit for bit (lane, s, lateral offset): points near and far from the path, every hint, walks
    forward and backward, off either end of an open route and round a closed loop. Fails with a hint ignored, the
    walk's direction or stop rule changed, a loop not wrapped, or an arc's angle not numpy's."""
    path = _left_turn_route() if which == "left_turn" else _stadium()
    rng = np.random.default_rng(7)
    n = len(path.lanes)
    ends = np.array([lane.position(s, 0.0) for lane in path.lanes for s in (0.0, lane.length)])
    lo, hi = ends.min(axis=0) - 30.0, ends.max(axis=0) + 30.0
    # points in the box, and points on or near the lanes' centrelines (where a car drives)
    on = [path.lanes[k].position(s, lat) for k, s, lat in zip(rng.integers(0, n, 300).tolist(),
                                                              rng.uniform(-5.0, 45.0, 300).tolist(),
                                                              rng.normal(0.0, 1.5, 300).tolist())]
    xy = np.vstack([rng.uniform(lo, hi, (500, 2)), np.array(on)])
    hint = rng.integers(0, n, len(xy))
    k, s, lat = locate_rows(path, xy[:, 0], xy[:, 1], hint)
    walked = {"forward": 0, "backward": 0, "stayed": 0}
    for i in range(len(xy)):
        want = path.locate(xy[i], int(hint[i]))
        got = (int(k[i]), float(s[i]), float(lat[i]))
        assert got[0] == want[0] and struct.pack("dd", *got[1:]) == struct.pack("dd", *want[1:]), (i, got, want)
        d = want[0] - int(hint[i])
        d = (d + n // 2) % n - n // 2 if path.closed else d  # round a loop: the shorter way
        walked["stayed" if d == 0 else "forward" if d > 0 else "backward"] += 1
    assert min(walked.values()) > 30, walked
    empty = locate_rows(path, np.zeros(0), np.zeros(0), np.zeros(0, int))
    assert [len(a) for a in empty] == [0, 0, 0]


def test_stopping_bounds_are_stopping_bound_per_state():
    """``BrakeActuator.stopping_bounds`` (all rows at once) is ``stopping_bound`` of each state bit for bit, over
    random speeds (standing, negative, fast) and accelerations, with and without a jerk ramp. Fails with the
    acceleration's clip at 0 dropped, another term's order, or the growth changed."""
    from av_gym.shields.actuator import BrakeActuator

    rng = np.random.default_rng(3)
    v = np.concatenate([rng.uniform(-1.0, 20.0, 400), [0.0, -0.0, 1e-9]])
    a = np.concatenate([rng.uniform(-8.0, 4.0, 400), [0.0, -0.0, -1e-9]])
    for jerk in (0.0, 30.0, 7.5):
        act = BrakeActuator(jerk=jerk, delay=float(rng.uniform(0.0, 0.4)), decel=float(rng.uniform(4.0, 9.0)))
        got = act.stopping_bounds(v, a, 0.05)
        want = np.array([act.stopping_bound(float(x), float(y), 0.05) for x, y in zip(v, a)])
        assert got.tobytes() == want.tobytes(), jerk


# ----------------------------------------------------------------------------------------------- screen off / on
def _value(x, depth: int = 0):
    """A comparable picture of a shield attribute: arrays by dtype, shape and bytes, floats by their bits (NaN
    equal to NaN), containers element by element, other objects by their own attributes (two levels deep)."""
    if isinstance(x, np.ndarray):
        return ("array", x.dtype.str, x.shape, x.tobytes())
    if isinstance(x, (float, np.floating)):
        return ("float", struct.pack("d", float(x)))
    if x is None or isinstance(x, (bool, int, str, np.integer, np.bool_)):
        return x
    if isinstance(x, (list, tuple)):
        return (type(x).__name__, tuple(_value(v, depth) for v in x))
    if isinstance(x, dict):
        return ("dict", tuple((_value(k, depth), _value(v, depth)) for k, v in x.items()))
    if depth >= 2 or not hasattr(x, "__dict__"):
        return ("object", type(x).__name__)
    return (type(x).__name__, tuple((k, _value(v, depth + 1)) for k, v in sorted(vars(x).items())))


# the row's view of the batch (each batch its own object, its arrays the batch's: compared through the batch), and
# the objects shared by every shield of the process (the route tables, the conflict model's network)
NOT_STATE = {"env", "route", "driven", "_conflicts"}


def shield_state(shield, engine, row: int) -> dict:
    """Every attribute of a row's shield (``vars``) but :data:`NOT_STATE`, as :func:`_value` pictures it; its road
    users' keys (vehicle ids, unique in the process: two batches' differ) as the engine slots of those vehicles now
    (-1: gone), the same in two batches of the same episodes."""
    out = {k: _value(v) for k, v in vars(shield).items() if k not in NOT_STATE}
    vid = engine.traffic.vid[row].tolist()
    out["_keys"] = [vid.index(k) if k in vid else -1 for k in getattr(shield, "_keys", [])]
    return out


def _side_by_side(monkeypatch, seeds: list[int], n_envs: int, action_of, steps: int = 400) -> dict:
    """The batch with the screen off and on, the same seeds and actions (``action_of(step, n)`` -> (n,)), stepped
    alternately; after every step every row's shield state must be the same in both (:func:`shield_state`), and
    the applied actions too. Returns what the screen decided and what the rows decided themselves."""
    from av_gym.batched import shield as batched_shield
    from tests.test_batched_shield import _venv

    off, on = _venv(n_envs), _venv(n_envs)
    seen = {"quiet": 0, "warn": 0, "own": 0, "setoff_brake": 0, "targets": 0}
    screen = batched_shield.BatchedShield._screen

    def counted(self, rows, actions):
        got = screen(self, rows, actions)
        if batched_shield.SCREEN and got is not None:
            for n, r in enumerate(rows.tolist()):
                if got[n]:
                    seen["warn" if np.isfinite(self.shields[r].target_xy).all() else "quiet"] += 1
                else:
                    seen["own"] += 1
        return got

    setoff_stop = type(on.shield.shields[0])._setoff_stop

    def setoff_counted(self, sc, setoff, t):
        got = setoff_stop(self, sc, setoff, t)
        seen["setoff_brake"] += int(got is not None and batched_shield.SCREEN)
        return got

    monkeypatch.setattr(batched_shield.BatchedShield, "_screen", counted)
    monkeypatch.setattr(type(on.shield.shields[0]), "_setoff_stop", setoff_counted)
    for venv in (off, on):
        venv.play(iter(seeds))
    for step in range(steps):
        if off.idle.all() and on.idle.all():
            break
        a = action_of(step, n_envs)
        monkeypatch.setattr(batched_shield, "SCREEN", False)
        off.step(a)
        monkeypatch.setattr(batched_shield, "SCREEN", True)
        on.step(a)
        assert np.array_equal(off.idle, on.idle) and np.array_equal(off.shield.override, on.shield.override), step
        for r in range(n_envs):
            a_state, b_state = shield_state(off.shield.shields[r], off.engine, r), \
                shield_state(on.shield.shields[r], on.engine, r)
            differ = sorted(k for k in a_state.keys() | b_state.keys() if a_state.get(k) != b_state.get(k))
            assert not differ, f"step {step} row {r}: the screen leaves {differ} unlike the row's own decision"
            seen["targets"] += int(np.isfinite(on.shield.shields[r].target_xy).all())
    assert off.idle.all() and on.idle.all()
    return seen


def test_the_screen_moves_every_shields_state_as_its_own_decisions_do(monkeypatch):
    """With the screen off (every row's own ``_decide``) and on, the same seeds and actions (FASTER / SLOWER /
    IDLE at random), every row's shield has the same full state after every step (``vars``: route lane hint,
    road users' lanes and keys, decision time, the target's position, latch, actuator, channel, ...; arrays by
    value), over quiet and warning decisions decided by the screen and the others by their rows. Fails with the
    screen forgetting to move the route lane hint, the decision time or the target's position (SCREEN_CHECK
    cannot see that: each screened row's own ``_decide`` then moves them itself)."""
    rng = np.random.default_rng(5)
    seen = _side_by_side(monkeypatch, [VALIDATION], 1, lambda step, n: rng.integers(0, 3, n))
    assert seen["quiet"] > 50 and seen["warn"] > 20 and seen["own"] > 5 and seen["targets"] > 20, seen


@pytest.mark.slow  # ~7 CPU-s: three envs, two batches
def test_the_screen_moves_every_shields_state_on_three_envs_at_once(monkeypatch):
    """The same with three envs in each batch (rows decided by the screen beside rows deciding themselves in one
    step, a row's slices of the batch's buffers) over three episodes."""
    rng = np.random.default_rng(5)
    seen = _side_by_side(monkeypatch, [VALIDATION + k for k in range(3)], 3, lambda step, n: rng.integers(0, 3, n))
    assert seen["quiet"] > 200 and seen["warn"] > 40 and seen["own"] > 50 and seen["targets"] > 100, seen


# ----------------------------------------------------------------------------------------------- the stage and set-off
def _screened_counts(monkeypatch, shield: dict, seeds: list[int], action_of, classify) -> dict:
    """``seeds`` on a batch of ``len(seeds)`` envs under ``shield`` with SCREEN_CHECK (each screened row's own
    ``_decide`` runs too and must agree), actions ``action_of(step, n)``; ``classify(want)`` names each screened
    decision's class (None: not counted). Returns the count per class, and ``setoff_screened`` (quiet rows at the
    trigger point the screen decided: no road user the set-off rule predicts, or none of its hypotheses met),
    ``setoff_predicted`` (of those, the rule's prediction made for all rows at once), ``setoff_met_none`` (rows
    screened through that prediction: served, none of its hypotheses met) and ``setoff_brakes`` (the set-off rule's
    brakes, decided by their rows)."""
    from av_gym.batched import shield as batched_shield
    from av_gym.shields.setoff_rows import setoff_slow
    from tests.test_batched_shield import _venv

    monkeypatch.setattr(batched_shield, "SCREEN_CHECK", True)
    seen = {"setoff_screened": 0, "setoff_predicted": 0, "setoff_met_none": 0, "setoff_brakes": 0}
    check, setoff, predict = batched_shield._check_screened, batched_shield.BatchedShield._screen_setoff, \
        batched_shield.predict_rows_following

    def counted(sh, want, route_k, now):
        check(sh, want, route_k, now)
        name = classify(want)
        if name is not None:
            seen[name] = seen.get(name, 0) + 1

    def setoff_counted(self, g, which, flat, first):
        got = setoff(self, g, which, flat, first)
        seen["setoff_screened"] += int(got.sum())
        if got.any():  # of them, the rows with a road user the rule predicts: decided through its prediction
            row_of = np.repeat(np.arange(len(which)), np.diff(flat.row_off))
            slow = setoff_slow(flat.others, self.in_box[flat.lane], flat.recent, self.p.setoff_speed)
            n_slow = np.bincount(row_of[slow & which[row_of]], minlength=len(which))
            seen["setoff_met_none"] += int((got & (n_slow > 0)).sum())
        return got

    def predict_counted(model, others, row_off, *args):
        got = predict(model, others, row_off, *args)
        seen["setoff_predicted"] += int((got[1] >= 0).sum()) if got is not None else 0
        return got

    monkeypatch.setattr(batched_shield, "_check_screened", counted)
    monkeypatch.setattr(batched_shield.BatchedShield, "_screen_setoff", setoff_counted)
    monkeypatch.setattr(batched_shield, "predict_rows_following", predict_counted)
    venv = _venv(len(seeds), shield=shield)
    row_shield = type(venv.shield.shields[0])
    stop = row_shield._setoff_stop

    def stop_counted(self, sc, found, t):
        got = stop(self, sc, found, t)
        seen["setoff_brakes"] += int(got is not None)
        return got

    monkeypatch.setattr(row_shield, "_setoff_stop", stop_counted)
    venv.play(iter(seeds))
    for step in range(400):
        if venv.idle.all():
            break
        venv.step(action_of(step, len(seeds)))
    assert venv.idle.all()
    return seen


def _short_window(warn_k: int = 24) -> tuple[dict, float]:
    """The ``aeb`` preset with the turn window cut to 10 m before the stop line (most of the approach outside it)
    and ``warn_ttc`` exactly the prediction's time ``warn_k`` (s): a TTC can equal it."""
    from av_gym.batched.shield import check_batched_shield
    from av_gym.presets import compose_group
    from av_gym.shields.aeb_improved import long_times

    shield = dict(compose_group("shield", "aeb"), activation_distance=10.0)
    shield["warn_ttc"] = float(long_times(check_batched_shield(shield))[warn_k])
    return shield, shield["warn_ttc"]


def _actions_of_row(row: int, width: int = 12):
    """Random FASTER / SLOWER / IDLE per step as row ``row`` of a batch of ``width`` drew them (the search that found
    these seeds played 12 seeds at once, default_rng(5)): the same episode on a batch of one."""
    rng = np.random.default_rng(5)
    return lambda step, n: rng.integers(0, 3, width)[row: row + 1]


def test_outside_the_turn_window_the_screened_stage_is_the_rows_own_on_both_sides_of_warn_ttc(monkeypatch):
    """Outside the turn window a conflict later than ``ttc_brake`` is a warning only at TTC <= ``warn_ttc``, else
    MONITOR with that TTC (_warn_or_brake): with the window cut short (10 m) and ``warn_ttc`` exactly one of the
    prediction's times, every screened decision is its row's own (SCREEN_CHECK), and the screened decisions outside
    the window have TTCs under, at and over ``warn_ttc`` (seed 1,000,008). Fails with the screen's stage rule
    dropped (a warning for every conflict) or its ``<=`` as ``<``."""
    shield, warn = _short_window()

    def side(want):
        if want[4] or not np.isfinite(want[1]):
            return None
        return "under" if want[1] < warn else "at" if want[1] == warn else "over"

    seen = _screened_counts(monkeypatch, shield, [VALIDATION + 8], _actions_of_row(8), side)
    assert seen.get("under", 0) > 0 and seen.get("at", 0) > 0 and seen.get("over", 0) > 0, seen


def test_the_screen_decides_the_trigger_points_quiet_rows_whose_setoff_rule_finds_nothing(monkeypatch):
    """At the stop-line trigger point with no conflict the row's set-off rule predicts the standing road users in
    the box that moved lately setting off: the screen decides the rows where it finds none or meets none of their
    hypotheses (their prediction for all such rows at once), and leaves its brakes to their rows; with SCREEN_CHECK
    every screened row is its row's own decision (seed 1,000,003, the short window of the test above: set-off
    brakes, and rows the rule predicts without braking). Fails with a set-off brake screened as MONITOR (the TTC's
    horizon or margin changed, another decision's hypotheses read) or the rule's prediction changed."""
    shield, _ = _short_window()
    seen = _screened_counts(monkeypatch, shield, [VALIDATION + 3], _actions_of_row(3), lambda want: None)
    assert seen["setoff_screened"] > 10 and seen["setoff_predicted"] > seen["setoff_brakes"] > 0, seen
    assert seen["setoff_met_none"] > 0, seen  # some rows decided through the all-rows prediction, not only the
    # rows without a road user the rule predicts
