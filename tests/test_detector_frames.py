"""The detector's frame arithmetic that the per-env detector runs on its one frame and the batch's detector on all its
envs' frames at once (av_gym/sensors/detector.py ``assemble_frames``, av_gym/sensors/kernels.py
``detector_view_rows``): F frames in one call give each frame what it gets alone, bit for bit (each step is the
same element-wise arithmetic; the sort is stable, by frame then range). The whole stacks are compared in
tests/test_batched_perception.py (detections bit for bit). The batch's compiled draws are the per-env detector's
numpy draws, and the first-use check (av_gym/sensors/draws_check.py) that falls back to those where they are not."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.sensors.detector import PROBES, DetectorParams, assemble_frames, contiguous_columns
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
    # contiguous columns, as the detectors pass them (one compiled specialization: detector.contiguous_columns)
    ex, ey, epsi = contiguous_columns(ego, (0, 1, 2))
    x, y, length, width = contiguous_columns(o, (0, 1, 5, 6))
    for occlusion in (True, False):
        args = (60.0, np.radians(60.0), occlusion, PROBES, 0.8)
        r, view, hidden = detector_view_rows(ex, ey, epsi, off, x, y, c, s, length, width, *args)
        for i in range(len(ego)):
            a, b = off[i], off[i + 1]
            one = detector_view(ex[i], ey[i], epsi[i], x[a:b], y[a:b], c[a:b], s[a:b], length[a:b], width[a:b],
                                *args)
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


def _measure_twice(detector, seeds: list[int]) -> np.ndarray:
    """Two detector frames (t = 0 and 0.1 s) of ``detector`` for envs reset to ``seeds``: random road users of a
    small pool of ids around each ego (so a miss chain steps), every second one ahead; the (2, B, max_objects, 9)
    observations."""
    rng = np.random.default_rng(9)
    detector.reset(np.arange(len(seeds)), seeds)
    out = []
    for t in (0.0, 0.1):
        counts = rng.integers(2, 8, len(seeds))
        f = _frames(rng, counts.tolist(), [0] * len(seeds))
        vids = np.concatenate([100 * (r + 1) + np.arange(c) for r, c in enumerate(counts)]).astype(np.int64)
        out.append(detector.measure(np.arange(len(seeds)), np.full(len(seeds), t), f["ego"], f["others"], vids,
                                    f["off"]))
    return np.stack(out)


def test_the_compiled_draws_pass_their_check_here_and_the_batch_draws_with_them(monkeypatch):
    """draws_check.compiled_draws, on its first call of the process, runs the compiled draws against numpy's
    (draws_differ: None here) and the batch's detector then draws with the kernel, no warning, "draws" kept; the
    check's frames call the kernel with the batch's argument types (one compiled specialization for both)."""
    import warnings

    from av_gym.batched.perception import BatchedDetector
    from av_gym.sensors import detector, draws_check, kernels

    monkeypatch.setattr(draws_check, "_RESULT", [])  # as in a fresh process
    monkeypatch.setattr(detector, "KERNELS", set(detector.KERNELS))
    used = []
    compiled = BatchedDetector._draws_compiled
    monkeypatch.setattr(BatchedDetector, "_draws_compiled", lambda self, *a: used.append(1) or compiled(self, *a))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a failed check's warning would raise here
        obs = _measure_twice(BatchedDetector(3, DetectorParams(clutter_rate=12.0)), [5, 6, 7])
    assert draws_check._RESULT == [None] and "draws" in detector.KERNELS and len(used) == 2
    assert (obs[..., 0] > 0).sum() > 20  # detections and clutter drawn
    assert len(kernels.frame_draws_span.signatures) == 1


def _one_ulp_on_first_normal(kernel):
    def wrong(*args):
        out = kernel(*args)
        if out[0] > args[18]:  # a detection drawn in this call: its first normal one float up
            args[17][args[18], 0] = np.nextafter(args[17][args[18], 0], np.inf)
        return out
    return wrong


def _one_ulp_on_a_bearing(kernel):
    def wrong(*args):
        out = kernel(*args)
        if out[2] < 0 and out[1] > args[21]:  # clutter drawn in this call: its first bearing one float up
            args[19][args[21], 1] = np.nextafter(args[19][args[21], 1], np.inf)
        return out
    return wrong


def _extra_uniform_from_mean_10(kernel):
    def wrong(*args):
        if args[12] >= 10.0:  # a sampler that takes one more uniform where numpy switches to PTRS
            args[0].random()
        return kernel(*args)
    return wrong


def _extra_uniform_at_the_end(kernel):
    from av_gym.sensors import draws_check

    def wrong(*args):
        out = kernel(*args)
        if args[14] == draws_check.FRAMES - 1:  # every draw returned right, the generator moved on further
            args[0].random()
        return out
    return wrong


def _raises(kernel):
    def wrong(*args):
        raise RuntimeError("cannot compile\nthis kernel")  # as a numba whose typing refuses it
    return wrong


@pytest.mark.parametrize("perturb, reason", [
    (_raises, "the kernel raised RuntimeError: cannot compile"),
    (_one_ulp_on_first_normal, "frame 0: the standard normals"),
    (_one_ulp_on_a_bearing, "frame 3: the clutter's uniform(-half_fov, half_fov)"),
    (_extra_uniform_from_mean_10, "frame 5: "),
    (_extra_uniform_at_the_end, "the generators' states after all draws"),
])
def test_a_compiled_draw_that_differs_fails_the_check_and_the_batch_draws_with_numpy(monkeypatch, perturb, reason):
    """With the compiled draws perturbed (one float one step off, one uniform too many: what another numba's or
    numpy's sampler could do; or a kernel that raises, as on a numba that cannot compile it), the check names the
    first draw that differs; compiled_draws is False, drops "draws" from the detector's KERNELS, warns once in one
    line (the numpy and numba versions, the draw), and the batch's detector draws with numpy (detector.frame_draws,
    never the kernel): its frames equal those of the unperturbed compiled draws, which equal the per-env detector's
    (test_the_compiled_draws_are_the_per_frame_draws_of_each_envs_generator; whole episodes in
    test_a_fallen_back_batch_detects_as_the_per_env_stack)."""
    import warnings

    from av_gym.batched.perception import BatchedDetector
    from av_gym.sensors import detector, draws_check, kernels

    want = _measure_twice(BatchedDetector(3, DetectorParams(clutter_rate=12.0)), [5, 6, 7])
    monkeypatch.setattr(draws_check, "_RESULT", [])
    monkeypatch.setattr(detector, "KERNELS", set(detector.KERNELS))
    monkeypatch.setattr(kernels, "frame_draws_span", perturb(kernels.frame_draws_span))
    monkeypatch.setattr(BatchedDetector, "_draws_compiled", lambda *a: pytest.fail("the kernel drew"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = _measure_twice(BatchedDetector(3, DetectorParams(clutter_rate=12.0)), [5, 6, 7])
        assert not draws_check.compiled_draws()  # decided once: no second check, no second warning
    assert draws_check._RESULT[0].startswith(reason) and "draws" not in detector.KERNELS
    assert [str(w.message).count("\n") for w in caught] == [0] and caught[0].category is RuntimeWarning
    assert f"numpy {np.__version__}, numba " in str(caught[0].message) and reason in str(caught[0].message)
    np.testing.assert_array_equal(got, want)


def _truncating_ptrs(rng, lam):
    """numba 0.68's own ``Generator.poisson`` from lam 10: numpy's PTRS with the candidate truncated by int(), where
    numpy floors it (a candidate in (-1, 0) becomes 0 and may be accepted where numpy draws again)."""
    import math

    from av_gym.sensors.kernels import _loggam

    slam, loglam = math.sqrt(lam), math.log(lam)
    b = 0.931 + 2.53 * slam
    a = -0.059 + 0.02483 * b
    invalpha, vr = 1.1239 + 1.1328 / (b - 3.4), 0.9277 - 3.6224 / (b - 2)
    while True:
        u, v = rng.random() - 0.5, rng.random()
        us = 0.5 - abs(u)
        k = int((2 * a / us + b) * u + lam + 0.43)
        if us >= 0.07 and v <= vr:
            return k
        if k < 0 or (us < 0.013 and v > us):
            continue
        if math.log(v) + math.log(invalpha) - math.log(a / (us * us) + b) <= -lam + k * loglam - _loggam(k + 1.0):
            return k


def test_a_poisson_sampler_that_truncates_fails_the_check(monkeypatch):
    """PTRS's rare branch (about one draw in 3e4-1e5 at mean 10) is beyond the check's frames; its own Poisson
    draws at mean 10 on draws_check.POISSON_SEEDS reach it: with the sampler numba 0.68 ships (truncating) in place of
    kernels.poisson the check fails there, drops "draws" and warns."""
    import warnings

    from av_gym.sensors import detector, draws_check, kernels

    monkeypatch.setattr(draws_check, "_RESULT", [])
    monkeypatch.setattr(detector, "KERNELS", set(detector.KERNELS))
    monkeypatch.setattr(kernels, "poisson", _truncating_ptrs)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert not draws_check.compiled_draws()
    assert draws_check._RESULT[0].startswith("the Poisson count at mean 10 (generator 16, draw ")
    assert "draws" not in detector.KERNELS and len(caught) == 1


def test_a_fallen_back_batch_detects_as_the_per_env_stack(monkeypatch):
    """With the compiled draws perturbed (the check fails, the batch draws with numpy), two envs on one batch give
    the per-env stack's detections (make_env's Detector on each env's own generator) on every step of their first
    20, heavy clutter (12 per frame: PTRS counts) and bursty misses included."""
    import warnings

    from av_gym.batched.perception import BatchedDetector
    from av_gym.batched.vec_env import BatchedLeftTurnBatch
    from av_gym.sensors import detector, draws_check, kernels
    from tests.test_batched_perception import ENV, _actions, _sensors, per_env

    monkeypatch.setattr(draws_check, "_RESULT", [])
    monkeypatch.setattr(detector, "KERNELS", set(detector.KERNELS))
    monkeypatch.setattr(kernels, "frame_draws_span", _one_ulp_on_first_normal(kernels.frame_draws_span))
    monkeypatch.setattr(BatchedDetector, "_draws_compiled", lambda *a: pytest.fail("the kernel drew"))
    sensors, seeds, steps = _sensors(clutter_rate=12.0, miss_rate=0.3, burst_length=3.0), [3, 4], 20
    venv = BatchedLeftTurnBatch(ENV, {**sensors, "observe": ["detector"]}, None, len(seeds), pool=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = [venv.play(iter(seeds))["detector"].copy()]
        for a in np.stack([_actions(s) for s in seeds], axis=1)[:steps]:
            obs, _, ended, _ = venv.step(a)
            assert not ended.any()
            got.append(obs["detector"].copy())
    assert draws_check._RESULT[0] is not None and len(caught) == 1
    assert (np.stack(got)[..., 0] > 0).sum() > 200  # rows present: detections and clutter
    for i, seed in enumerate(seeds):
        want = [o["detector"] for o, _ in per_env(seed, sensors, steps)]
        assert len(want) == steps + 1
        np.testing.assert_array_equal(np.stack(want), np.stack(got)[:, i], err_msg=str(seed))
