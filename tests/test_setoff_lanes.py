"""The AEB shield's set-off rule (``setoff_speed``, av_gym/shields/aeb_improved.py) predicts every car standing in the
box along its lanes, setting off from 0.5 m/s at ``setoff_accel``; the conflict model gives a car its lane hypotheses
only at >= 0.5 m/s. Compared across a rounding, ``hypot(0.5 cos h, 0.5 sin h)`` came out one ulp under 0.5 for ~1.4 %
of headings, and such a car was predicted on a straight line instead (a heading one ulp apart between the per-env
stack and the batch then split their decisions). The set-off rule now marks its cars as lane-following
(``ConflictModel.predict``'s ``follow``), so the heading's last bit no longer picks the hypotheses."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.shields import conflicts
from av_gym.shields.conflicts import ConflictModel
from conftest import conf

BOX_LANE = ("ir3", "il0", 0)  # the left turn from the east through the box
T = 0.1 * np.arange(1, 31)  # s: the set-off rule's 3 s
T.flags.writeable = False  # as the shield hands its time grids to the kernels: their specialization, not a second


def _speed(h: float) -> float:
    """The set-off rule's start speed (m/s) of a car with heading ``h`` rad, as the conflict model computes it."""
    direction = np.stack([np.cos(np.array([h])), np.sin(np.array([h]))], 1)
    v = 0.5 * direction
    return float(np.hypot(v[:, 0], v[:, 1])[0])


def _headings_across_the_rounding(h0: float) -> tuple[float, float]:
    """Two headings near ``h0`` (rad), a few ulps apart, whose 0.5 m/s start is under 0.5 and >= 0.5 respectively."""
    under = over = None
    h = h0
    for _ in range(200_000):
        h = float(np.nextafter(h, 10.0))
        if _speed(h) < 0.5:
            under = under if under is not None else h
        else:
            over = over if over is not None else h
        if under is not None and over is not None:
            return under, over
    raise AssertionError("no heading rounds under 0.5 near the lane's")


def _standing_car(network, s: float, h: float) -> np.ndarray:
    """A car standing on :data:`BOX_LANE` at ``s`` m along it with heading ``h`` rad (the shield's object row)."""
    x, y = network.get_lane(BOX_LANE).position(s, 0.0)
    return np.array([[x, y, 0.0, 0.0, h, 5.0, 2.0]])


@pytest.fixture(scope="module")
def shield():
    """The per-env AEB shield (improved variant, the ``aeb`` preset) of the left turn, after a reset."""
    from av_gym.make import make_env
    from av_gym.shields import find_shield

    env = make_env(conf("env", "left_turn"), None, conf("shield", "aeb"))
    env.reset(seed=0)
    yield find_shield(env)
    env.close()


def test_the_rounding_is_real_near_a_box_lane(shield):
    """The premise: headings of a car on the box lane exist whose 0.5 m/s start rounds under 0.5 (the test below
    would not test anything otherwise)."""
    lane = shield.env.unwrapped.road.network.get_lane(BOX_LANE)
    under, over = _headings_across_the_rounding(float(lane.heading_at(5.0)))
    assert _speed(under) < 0.5 <= _speed(over) and abs(under - over) < 1e-9


@pytest.mark.parametrize("kernel", [True, False])
def test_a_car_standing_in_the_box_sets_off_along_its_lanes_whatever_the_last_bit_of_its_heading(shield, kernel,
                                                                                                monkeypatch):
    """The set-off prediction of a car standing in the box at two headings a few ulps apart, one whose 0.5 m/s
    start rounds under 0.5 and one that does not: both on every lane hypothesis, setting off along it at
    ``setoff_accel``, at the same places within 1e-6 m. Before, the first was one straight line (the constant-velocity
    hypothesis). With the compiled choice of hypotheses and with its Python reference."""
    monkeypatch.setattr(conflicts, "CONFLICT_KERNEL", kernel)
    network = shield.env.unwrapped.road.network
    n_hyp = len(shield._conflicts.hypotheses(BOX_LANE))
    assert n_hyp >= 1
    under, over = _headings_across_the_rounding(float(network.get_lane(BOX_LANE).heading_at(5.0)))
    out = []
    for h in (under, over):
        xy, hh, owner, size, rear = shield._setoff_predict(_standing_car(network, 5.0, h), [BOX_LANE], T, None,
                                                           np.array([True]))
        assert xy.shape == (len(T), n_hyp, 2) and list(owner) == [0] * n_hyp, h
        out.append(xy)
    np.testing.assert_allclose(out[0], out[1], atol=1e-6)
    # setting off at 3 m/s² along the lane: 0.5 * 3 + 3 * 3² / 2 = 15 m in 3 s (the straight line at 0.5 m/s: 1.5 m)
    start = _standing_car(network, 5.0, under)[0, 0:2]
    assert np.hypot(*(out[0][-1] - start).T).min() > 12.0


@pytest.mark.parametrize("kernel", [True, False])
def test_follow_marks_only_the_cars_it_names_and_keeps_the_off_lane_test(shield, kernel, monkeypatch):
    """``ConflictModel.predict``'s ``follow``: a marked slow car on its lane gets the lane hypotheses, the same car
    unmarked (or marked but 6 m off its lane) the constant-velocity one; a car at >= 0.5 m/s gets its lanes either
    way."""
    monkeypatch.setattr(conflicts, "CONFLICT_KERNEL", kernel)
    network = shield.env.unwrapped.road.network
    model = ConflictModel(network)
    n_hyp = len(model.hypotheses(BOX_LANE))
    h = float(network.get_lane(BOX_LANE).heading_at(5.0))
    slow = _standing_car(network, 5.0, h)
    slow[0, 2:4] = 0.3 * np.array([np.cos(h), np.sin(h)])
    off = slow.copy()
    off[0, 0:2] += 6.0 * np.array([-np.sin(h), np.cos(h)])
    fast = slow.copy()
    fast[0, 2:4] = 4.0 * np.array([np.cos(h), np.sin(h)])
    for obj, follow, map_hyps in ((slow, [True], n_hyp), (slow, [False], 0), (slow, None, 0), (off, [True], 0),
                                  (fast, [False], n_hyp), (fast, None, n_hyp)):
        mark = None if follow is None else np.array(follow)
        _, _, owner, is_map, _ = model.predict(obj, [BOX_LANE], np.zeros((1, 2)), T, None, mark)
        assert int(is_map.sum()) == map_hyps and len(owner) == max(map_hyps, 1), (follow, obj[0, :4])
