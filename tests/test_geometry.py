"""Oriented boxes and constant-velocity TTC, on hand-worked cases."""

import numpy as np
import pytest

from av_gym.geometry import box_corners, boxes_overlap, constant_velocity_ttc


def car(x, y, vx, vy, heading, length=5.0, width=2.0):
    return np.array([x, y, vx, vy, heading, length, width])


def test_corners_of_a_rotated_box():
    c = box_corners(np.array([1.0, 2.0]), np.pi / 2, 4.0, 2.0)
    np.testing.assert_allclose(sorted(map(tuple, np.round(c, 9))), sorted([(0, 4), (2, 4), (0, 0), (2, 0)]), atol=1e-9)


def test_overlap_separation_and_rotation():
    a = box_corners(np.zeros(2), 0.0, 5.0, 2.0)
    assert boxes_overlap(a, box_corners(np.array([4.9, 0.0]), 0.0, 5.0, 2.0))
    assert not boxes_overlap(a, box_corners(np.array([5.1, 0.0]), 0.0, 5.0, 2.0))
    # A crossing car rotated 90°: its half-length is along y, so 3.5 m beside a 1 m half-width box still misses.
    assert not boxes_overlap(a, box_corners(np.array([0.0, 3.6]), np.pi / 2, 5.0, 2.0))
    assert boxes_overlap(a, box_corners(np.array([0.0, 3.4]), np.pi / 2, 5.0, 2.0))
    # Diagonal boxes whose bounding boxes overlap but which do not (needs the rotated axes of SAT).
    assert not boxes_overlap(box_corners(np.zeros(2), np.pi / 4, 4.0, 0.2),
                             box_corners(np.array([1.6, -1.6]), np.pi / 4, 4.0, 0.2))


def test_head_on_ttc():
    # Gap between bumpers 20 - 5 = 15 m, closing at 10 m/s → 1.5 s.
    ttc = constant_velocity_ttc(car(0, 0, 5, 0, 0), car(20, 0, -5, 0, np.pi)[None], horizon=5.0, dt=0.05)
    assert ttc == pytest.approx(1.5, abs=0.05)


def test_ttc_infinite_when_paths_do_not_meet_and_zero_when_overlapping():
    assert constant_velocity_ttc(car(0, 0, 5, 0, 0), car(0, 10, 5, 0, 0)[None]) == float("inf")
    assert constant_velocity_ttc(car(0, 0, 5, 0, 0), np.zeros((0, 7))) == float("inf")
    assert constant_velocity_ttc(car(0, 0, 0, 0, 0), car(1, 0, 0, 0, 0)[None]) == 0.0


def test_crossing_ttc():
    # Ego drives +x from x=-20; other drives +y from y=-20 at the same speed: both reach the origin at t=2 s,
    # the boxes touch a little earlier.
    ttc = constant_velocity_ttc(car(-20, 0, 10, 0, 0), car(0, -20, 0, 10, np.pi / 2)[None], dt=0.01)
    assert 1.6 < ttc < 2.0
