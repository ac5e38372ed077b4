"""The detector's frame arithmetic that the per-env detector runs on its one frame and the batch's detector on all its
envs' frames at once (av_gym/sensors/detector.py ``assemble_frames``, av_gym/sensors/kernels.py
``detector_view_rows``): F frames in one call give each frame what it gets alone, bit for bit (each step is the
same element-wise arithmetic; the sort is stable, by frame then range). The whole stacks are compared in
tests/test_batched_perception.py (detections bit for bit)."""

from __future__ import annotations

import numpy as np

from av_gym.sensors.detector import PROBES, DetectorParams, assemble_frames
from av_gym.sensors.kernels import detector_view, detector_view_rows


def _frames(rng: np.random.Generator, counts: list[int], clutters: list[int]) -> dict:
    """Random frames: per frame its ego, road users (k, 7), a random subset detected, and its clutter draws."""
    ego = np.column_stack([rng.uniform(-50, 50, len(counts)), rng.uniform(-50, 50, len(counts)),
                           rng.uniform(-np.pi, np.pi, len(counts))])
    off = np.concatenate([[0], np.cumsum(counts)])
    others = np.column_stack([rng.uniform(-80, 80, (off[-1], 2)), rng.normal(0, 5, (off[-1], 2)),
                              rng.uniform(-np.pi, np.pi, off[-1]), np.full(off[-1], 5.0), np.full(off[-1], 2.0)])
    src = np.flatnonzero(rng.random(off[-1]) < 0.8)
    frame_of = np.searchsorted(off, src, side="right") - 1
    return {"ego": ego, "off": off, "others": others, "src": src, "frame_of": frame_of,
            "ranges": rng.uniform(0, 60, len(src)), "draws": rng.standard_normal((len(src), 7)),
            "clutter_frame": np.repeat(np.arange(len(clutters)), clutters),
            "clutter": rng.random((sum(clutters), 3))}


def test_many_frames_are_assembled_as_each_frame_alone():
    p = DetectorParams(clutter_rate=2.0, max_objects=5)
    f = _frames(np.random.default_rng(3), counts=[4, 0, 9, 1, 6], clutters=[1, 2, 0, 3, 0])
    rows, kept, n = assemble_frames(p, 60.0, 5, f["ego"], f["others"], f["src"], f["frame_of"], f["ranges"],
                                    f["draws"], f["clutter_frame"], f["clutter"])
    total = np.bincount(f["frame_of"], minlength=5) + np.bincount(f["clutter_frame"], minlength=5)
    assert n.tolist() == np.minimum(total, 5).tolist() and total.max() > 5  # a frame cut at max_objects
    for i in range(len(f["ego"])):
        mine, theirs = f["frame_of"] == i, f["clutter_frame"] == i
        one = assemble_frames(p, 60.0, 5, f["ego"][i:i + 1], f["others"], f["src"][mine],
                              np.zeros(int(mine.sum()), int), f["ranges"][mine], f["draws"][mine],
                              np.zeros(int(theirs.sum()), int), f["clutter"][theirs])
        np.testing.assert_array_equal(rows[i], one[0][0])
        np.testing.assert_array_equal(kept[i], one[1][0])
        assert n[i] == one[2][0]
        d = np.hypot(*(rows[i, : n[i], 1:3] - f["ego"][i, :2]).T)
        assert np.all(np.diff(d) >= 0)  # nearest first
        assert np.all(rows[i, n[i]:] == 0) and np.all(kept[i, n[i]:] == -1)


def test_a_tie_in_range_keeps_the_detections_first_then_their_order():
    """Two road users and a false positive at exactly 30 m from the ego (no position noise; the clutter at range
    60 sqrt(0.25), bearing 0) and a nearer road user: nearest first, then at equal range the detections before the
    clutter, each in its order (the per-env detector's stable sort of its detections then its clutter). Fails with
    a sort that is not stable or that puts clutter first."""
    p = DetectorParams(sigma_pos0=0.0, sigma_pos_k=0.0)
    others = np.array([[0.0, 30.0, 1, 0, 0, 5, 2], [-30.0, 0.0, 0, 1, 0, 5, 2], [5.0, 0.0, 0, 0, 1, 5, 2]])
    for src in ([0, 1, 2], [1, 0, 2]):  # the detections in either order: the rule, not one input's luck
        src = np.array(src)
        ego = np.zeros((1, 3))
        ranges = np.hypot(others[src, 0], others[src, 1])
        rows, kept, n = assemble_frames(p, 60.0, 4, ego, others, src, np.zeros(3, int), ranges, np.zeros((3, 7)),
                                        np.zeros(1, int), np.array([[0.25, 0.0, 0.0]]))
        ties = [i for i in src.tolist() if i != 2]
        assert n.tolist() == [4] and kept[0].tolist() == [2, *ties, -1]
        np.testing.assert_array_equal(rows[0, :, 1:3], np.vstack([others[[2, *ties], :2], [[30.0, 0.0]]]))


def test_the_view_of_many_frames_is_each_frames_own():
    rng = np.random.default_rng(5)
    f = _frames(rng, counts=[3, 0, 7, 1, 12], clutters=[0] * 5)
    o, ego, off = f["others"], f["ego"], f["off"]
    c, s = np.cos(o[:, 4]), np.sin(o[:, 4])
    for occlusion in (True, False):
        args = (60.0, np.radians(60.0), occlusion, PROBES, 0.8)
        r, view, hidden = detector_view_rows(ego[:, 0], ego[:, 1], ego[:, 2], off, o[:, 0], o[:, 1], c, s, o[:, 5],
                                             o[:, 6], *args)
        for i in range(len(ego)):
            a, b = off[i], off[i + 1]
            one = detector_view(ego[i, 0], ego[i, 1], ego[i, 2], o[a:b, 0], o[a:b, 1], c[a:b], s[a:b], o[a:b, 5],
                                o[a:b, 6], *args)
            for got, want in zip((r[a:b], view[a:b], hidden[a:b]), one):
                np.testing.assert_array_equal(got, want)
        assert view.any() and not view.all()
        assert hidden.any() == occlusion


def _draw_twins(params, seeds: list[int]):
    """Two batch detectors of the same parameters, their envs reset to the same episode seeds."""
    from av_gym.batched.perception import BatchedDetector

    twins = [BatchedDetector(len(seeds), params) for _ in range(2)]
    for d in twins:
        d.reset(np.arange(len(seeds)), seeds)
    return twins


def test_the_compiled_draws_are_the_per_frame_draws_of_each_envs_generator(monkeypatch):
    """BatchedDetector._draws_compiled (one compiled call per frame, kernels.frame_draws_span, miss chains in arrays
    by vehicle id) against _draws (detector.frame_draws per frame, the per-env detector's code and dict chains): over
    40 rounds of random frames of random envs (road users from a small pool of ids, so chains run on over frames,
    bursty misses, occlusion, heavy clutter that overflows the clutter buffer, drawn on in Python), the same
    detections, draws, clutter, bit for bit, and each env's generator left in the same state; then new episodes in
    half the envs reusing the same vehicle ids (their chains start afresh, as a new dict). Fails with a chain state
    read across episodes or envs, a branch's probability swapped, or a draw out of order."""
    from av_gym.batched.perception import BatchedDetector

    monkeypatch.setattr(BatchedDetector, "_clutter_room", lambda self, frames: 2)  # the Python overflow path too
    p = DetectorParams(miss_rate=0.3, burst_length=3.0, clutter_rate=1.5, fov_deg=120.0)
    B = 6
    ref, new = _draw_twins(p, [11, 12, 13, 14, 15, 16])
    rng = np.random.default_rng(7)
    drawn, overflows = 0, 0
    for step in range(40):
        if step == 20:  # new episodes in half the envs: the same vehicle ids meet fresh chains
            for d in (ref, new):
                d.reset(np.array([0, 2, 4]), [21, 22, 23])
        rows = np.flatnonzero(rng.random(B) < 0.7)
        counts = rng.integers(0, 7, len(rows))
        off = np.concatenate([[0], np.cumsum(counts)])
        vids = np.concatenate([100 * (r + 1) + rng.choice(8, c, replace=False) for r, c in zip(rows, counts)] or
                              [np.zeros(0, np.int64)]).astype(np.int64)
        in_view, hidden = rng.random(off[-1]) < 0.8, rng.random(off[-1]) < 0.2
        want = ref._draws(rows, vids, in_view, hidden, off)
        got = new._draws_compiled(rows, vids, in_view, hidden, off)
        for a, b in zip(want, got):
            assert a.shape == b.shape and a.astype(float).tobytes() == b.astype(float).tobytes(), step
        drawn += len(want[0])
        overflows += int(len(want[4]) > 2)
    for r in range(B):
        assert ref.rngs[r].bit_generator.state == new.rngs[r].bit_generator.state, r
    assert drawn > 50 and overflows > 3
