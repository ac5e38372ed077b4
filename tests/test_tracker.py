"""Multi-object Kalman tracker (av_gym/estimation/tracker.py) and the tracking metrics."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.estimation import MultiObjectTracker
from av_gym.metrics.tracking import TrackingScore, match_objects

DT = 0.1


def rows(*objs, age: float = 0.0) -> np.ndarray:
    """Detector rows [present, x, y, vx, vy, heading, length, width, age] for objects (x, y, vx, vy)."""
    out = np.zeros((max(1, len(objs)), 9))
    for i, (x, y, vx, vy) in enumerate(objs):
        out[i] = [1, x, y, vx, vy, np.arctan2(vy, vx), 5.0, 2.0, age]
    return out if objs else np.zeros((0, 9))


def test_birth_confirmation_and_deletion():
    trk = MultiObjectTracker(min_hits=2, max_coast=0.5)
    assert len(trk.step(rows((0, 0, 10, 0)), 0.0)) == 0  # tentative: not output yet
    assert len(trk.step(rows((1, 0, 10, 0)), DT)) == 1  # confirmed on the second consecutive hit
    trk2 = MultiObjectTracker(min_hits=2)
    trk2.step(rows((0, 0, 10, 0)), 0.0)
    trk2.step(rows(), DT)  # a tentative track dies on its first miss
    assert len(trk2.step(rows((2, 0, 10, 0)), 2 * DT)) == 0
    # a confirmed track coasts through misses for max_coast seconds, then is deleted
    t = DT
    for k in range(5):
        t += DT
        assert len(trk.step(rows(), t)) == 1, f"coasting at miss {k + 1}"
    t += DT
    assert len(trk.step(rows(), t)) == 0


def test_hungarian_association_keeps_identities():
    trk = MultiObjectTracker()
    a, b = np.array([0.0, 0.0, 10.0, 0.0]), np.array([0.0, 4.0, 10.0, 0.0])  # side by side, 4 m apart
    ids = None
    for k in range(20):
        t = k * DT
        pa, pb = a[:2] + a[2:] * t, b[:2] + b[2:] * t
        order = [(*pb, *b[2:]), (*pa, *a[2:])] if k % 2 else [(*pa, *a[2:]), (*pb, *b[2:])]  # shuffled rows
        out = trk.step(rows(*order), t)
        if len(out) == 2:
            by_y = dict(zip(np.round(out[:, 1]).astype(int), trk.track_ids()))
            ids = ids or by_y
            assert by_y == ids  # the track near y = 0 keeps its id, as does the one near y = 4
    assert ids is not None and len(set(ids.values())) == 2


def test_rmse_after_the_tracker_is_below_raw_detections():
    rng = np.random.default_rng(0)
    trk = MultiObjectTracker(sigma_pos0=0.5, sigma_pos_k=0.0, sigma_vel=0.5)
    raw, tracked = TrackingScore(), TrackingScore()
    for k in range(150):
        t = k * DT
        truth = np.array([[-40 + 8.0 * t, 2.0], [30 - 6.0 * t, -2.0]])
        vel = np.array([[8.0, 0.0], [-6.0, 0.0]])
        det = [(*(p + rng.normal(0, 0.5, 2)), *(v + rng.normal(0, 0.5, 2))) for p, v in zip(truth, vel)]
        out = trk.step(rows(*det), t)
        raw.add(truth, np.array(det)[:, :2])
        tracked.add(truth, out[:, :2])
    r, s = raw.summary(), tracked.summary()
    assert s["rmse_m"] < 0.8 * r["rmse_m"]
    assert s["recall"] > 0.98 and s["precision"] > 0.98


def test_tracker_fills_a_burst_of_misses():
    trk = MultiObjectTracker()
    v = np.array([12.0, 0.0])
    for k in range(40):
        t = k * DT
        p = np.array([-50.0, 2.0]) + v * t
        detected = not 15 <= k < 25  # a 1 s burst of misses
        out = trk.step(rows((*p, *v)) if detected else rows(), t)
        if k >= 1:
            assert len(out) == 1, f"frame {k}"
            assert np.linalg.norm(out[0, :2] - p) < 0.5


def test_held_detector_frames_are_not_fused_twice():
    trk = MultiObjectTracker()
    trk.step(rows((0, 0, 10, 0)), 0.0)
    trk.step(rows((1, 0, 10, 0)), 0.1)
    n = trk._tracks[0].n_updates
    trk.step(rows((1, 0, 10, 0), age=0.05), 0.15)  # the same frame, 0.05 s old
    assert trk._tracks[0].n_updates == n
    assert trk.tracks()[0, 0] == pytest.approx(1.5, abs=0.2)  # but predicted forward to now


def test_tracking_metrics_on_a_hand_made_frame():
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    est = np.array([[0.3, 0.4], [10.0, 0.0], [50.0, 0.0]])  # one 0.5 m off, one exact, one clutter
    ti, ei = match_objects(truth, est, gate=2.0)
    assert sorted(zip(ti, ei)) == [(0, 0), (1, 1)]
    sc = TrackingScore()
    sc.add(truth, est, missed=np.array([False, False, True]))
    s = sc.summary()
    assert (s["tp"], s["fp"], s["fn"]) == (2, 1, 1)
    assert s["recall"] == pytest.approx(2 / 3) and s["precision"] == pytest.approx(2 / 3)
    assert s["rmse_m"] == pytest.approx(np.sqrt(0.25 / 2)) and s["recovered_miss_rate"] == 0.0


def test_tracker_raises_recall_on_the_detector_with_bursty_misses():
    from eval.tracking import run

    raw, trk, _ = run(0.3, 5.0, episodes=2, seed=1000, detector_overrides={}, tracker_cfg={})
    assert trk["recall"] > raw["recall"] + 0.1 and trk["rmse_m"] < raw["rmse_m"]


def test_bad_tracker_parameter_is_named():
    with pytest.raises(ValueError, match=r"^sigma_acc must be a number > 0, got 0.0"):
        MultiObjectTracker(sigma_acc=0.0)
