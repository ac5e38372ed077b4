"""The AEB shield's compiled footprint test (av_gym/shields/kernels.py ``footprint_hit``, behind
:func:`av_gym.shields.predict.footprint_ttc`) against its numpy reference (``footprint_ttc_numpy``): the same first hit
(slice and other) on random scenes, on boxes exactly touching, with and without the rear rule (the same decisions over
a shielded episode: tests/test_aeb.py); the brake actuator's compiled profile (``brake_profile``)."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.shields.predict import footprint_ttc, footprint_ttc_numpy


def _scene(rng: np.random.Generator, K: int, M: int):
    """An ego path and M others drifting over K slices, most of them first meeting the ego somewhere in the
    horizon (the first hit's slice spread over it), a few overlapping from the start."""
    t = 0.1 * np.arange(1, K + 1)
    ego_xy = np.cumsum(rng.normal(0.0, 0.5, (K, 2)), 0) + [0.0, 0.0]
    ego_h = rng.uniform(-np.pi, np.pi) + np.cumsum(rng.normal(0.0, 0.05, K))
    start = rng.uniform(-30, 30, (1, M, 2)) * rng.uniform(0.1, 1.0, (1, M, 1))
    oxy = start + np.cumsum(rng.normal(0.0, 0.6, (K, M, 2)), 0) - start * t[:, None, None] / t[-1]
    oh = rng.uniform(-4, 4, (1, M)) + np.cumsum(rng.normal(0.0, 0.1, (K, M)), 0)
    return ego_xy, ego_h, oxy, oh, rng.uniform(2.0, 6.0, (M, 2)), t


def test_the_footprint_kernel_finds_the_references_first_hit():
    rng = np.random.default_rng(5)
    slices = set()
    for trial in range(1500):
        K, M = int(rng.integers(1, 81)), int(rng.integers(1, 41))
        ego_xy, ego_h, oxy, oh, size, t = _scene(rng, K, M)
        rear = rng.random(M) < 0.5 if trial % 3 else bool(trial % 2)
        margin = (0.0, 0.3, 0.6)[trial % 3]
        got = footprint_ttc(ego_xy, ego_h, (5.0, 2.0), oxy, oh, size, t, margin, rear)
        want = footprint_ttc_numpy(ego_xy, ego_h, (5.0, 2.0), oxy, oh, size, t, margin, rear)
        assert got == want, trial
        slices.add(got[0])
    assert len(slices) > 30 and np.inf in slices  # first hits all over the horizon, and misses


@pytest.mark.parametrize("gap, hit", [(5.0, True), (5.0 + 1e-12, False), (4.999, True)])
def test_boxes_exactly_touching_overlap_in_both(gap, hit):
    """Touching counts as overlap (geometry.boxes_overlap): two 5 m boxes whose centres are exactly 5 m apart."""
    ego_xy, h = np.zeros((1, 2)), np.zeros(1)
    oxy, oh, size, t = np.array([[[gap, 0.0]]]), np.zeros((1, 1)), np.array([[5.0, 2.0]]), np.array([0.1])
    want = (0.1, 0) if hit else (np.inf, -1)
    assert footprint_ttc(ego_xy, h, (5.0, 2.0), oxy, oh, size, t) == want
    assert footprint_ttc_numpy(ego_xy, h, (5.0, 2.0), oxy, oh, size, t) == want


def test_a_follower_is_skipped_only_with_the_rear_rule():
    """An other 3 m behind the ego, heading the same way (within 45°), overlapping it: a hit unless ignored."""
    ego_xy, h = np.zeros((1, 2)), np.zeros(1)
    oxy, oh, size, t = np.array([[[-3.0, 0.0]]]), np.array([[0.2]]), np.array([[5.0, 2.0]]), np.array([0.1])
    for fn in (footprint_ttc, footprint_ttc_numpy):
        assert fn(ego_xy, h, (5.0, 2.0), oxy, oh, size, t, 0.0, False) == (0.1, 0)
        assert fn(ego_xy, h, (5.0, 2.0), oxy, oh, size, t, 0.0, True) == (np.inf, -1)
        assert fn(ego_xy, h, (5.0, 2.0), oxy, oh + 1.0, size, t, 0.0, True) == (0.1, 0)  # not the same way


@pytest.mark.parametrize("delay, jerk", [(0.15, 30.0), (0.0, 0.0), (0.33, 12.5)])
def test_the_brake_profile_is_the_actuator_applied_tick_by_tick(delay, jerk):
    """BrakeActuator.profile (compiled: kernels.brake_profile), what the shield predicts braking does, equals the
    actuator's per-tick command (BrakeActuator.command, what the per-env shield applies to the ego every tick)
    integrated as highway-env's Vehicle.step does, bit for bit: the delay at the car's own acceleration, the
    jerk-limited ramp, never reversing."""
    from av_gym.shields.actuator import BrakeActuator

    rng = np.random.default_rng(3)
    act = BrakeActuator(delay=delay, jerk=jerk)
    for _ in range(200):
        v0, a_before, dt = float(rng.uniform(0.0, 14.0)), float(rng.uniform(-2.0, 2.0)), 0.05
        xs, vs = act.profile(v0, a_before, 4.0, dt)
        act.engage(0.0)
        x, v = 0.0, v0
        for i in range(len(xs)):
            a = act.command(i * dt, v, dt)
            x += v * dt
            v = max(v + (a_before if a is None else a) * dt, 0.0)
            assert (xs[i], vs[i]) == (x, v)
        act.release()
    assert vs[-1] == 0.0
