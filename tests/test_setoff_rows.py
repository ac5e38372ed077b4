"""The set-off rule for many decisions at once (av_gym/shields/setoff_rows.py: which road users it predicts, their
set-off start, and their prediction on flat buffers) against the per-decision code it stands for
(:meth:`ImprovedAEB._setoff_predict`), bit for bit on random road users."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from tests.test_shield_kernels import fresh_paths  # noqa: F401 -- the fixture: a store no other test simulated into

SIZES = (3, 0, 5, 2, 4, 1)  # road users per decision: one decision without any


def _scene(net, rng: np.random.Generator, setoff_speed: float):
    """Road users of ``len(SIZES)`` decisions on the intersection's lanes (the engine's lane table ``index`` and
    each one's lane id), many in the box, standing, creeping, at exactly ``setoff_speed`` or faster, some moving
    lately (``recent``), some with indicator readings."""
    index = [(a, b, i) for a, to in net.graph.items() for b, ls in to.items() for i in range(len(ls))]
    box = [k for k, li in enumerate(index) if str(li[0]).startswith("ir")]
    M = sum(SIZES)
    # a few of the box's lanes and a few others: each lane's paths' speed bins are simulated once (~15 ms a bin)
    lane = np.where(rng.random(M) < 0.7, rng.choice(box[::4], M), rng.choice(range(0, len(index), 9), M))
    others = np.zeros((M, 7))
    for m, k in enumerate(lane.tolist()):
        ln = net.get_lane(index[k])
        s = rng.uniform(0.0, ln.length)
        h = ln.heading_at(s) + rng.normal(0.0, 0.2)
        speed = rng.choice([0.0, 0.3, rng.uniform(0.0, setoff_speed), setoff_speed, 5.0])
        others[m] = (*ln.position(s, rng.normal(0.0, 0.8)), speed * np.cos(h), speed * np.sin(h), h,
                     rng.uniform(4.0, 5.5), rng.uniform(1.8, 2.2))
    others[rng.random(M) < 0.15, 2:4] = (setoff_speed, 0.0)  # exactly at the threshold: hypot is setoff_speed
    intent = rng.dirichlet(np.ones(3), M)
    intent[rng.random(M) < 0.4] = np.nan
    recent = rng.random(M) < 0.8
    return index, lane, others, intent, recent, np.concatenate([[0], np.cumsum(SIZES)]).astype(np.int64)


def _own(model, p):
    """An object with what ImprovedAEB._setoff_predict reads of its shield: the parameters and the conflict model."""
    from av_gym.shields.aeb_improved import ImprovedAEB

    own = SimpleNamespace(p=p, _conflicts=model)
    own._accel_predict = lambda *a, **k: ImprovedAEB._accel_predict(own, *a, **k)
    return lambda *a: ImprovedAEB._setoff_predict(own, *a)


def test_the_setoff_rule_of_many_decisions_is_each_decisions_own(fresh_paths):  # noqa: F811
    """setoff_slow, setoff_start and predict_rows_following over the road users of several decisions at once give
    each decision exactly its own ImprovedAEB._setoff_predict: none where it predicts none, else the same positions,
    headings, owners (rows of its road users), sizes and rear flags, bit for bit, decisions of different sizes, one
    without road users, with and without indicator readings, road users exactly at ``setoff_speed``. Fails with
    the speed test's ``<`` as ``<=``, the set-off start's speed or acceleration changed, the 3 s acceleration time
    not taken, or a decision reading another's road users."""
    from av_gym.shields.aeb_improved import long_times
    from av_gym.shields.aeb_params import ImprovedParams
    from av_gym.shields.conflicts import ConflictModel
    from av_gym.shields.setoff_rows import box_lanes, predict_rows_following, setoff_slow, setoff_start

    net = fresh_paths
    seen = {"none": 0, "some": 0, "map": 0, "cv": 0, "threshold": 0}
    for trial in range(1):  # ~1.5 s a trial: most of it simulating the speed bins the scene reads
        p = ImprovedParams()
        model, t = ConflictModel(net, min_p=p.hypothesis_min_p), long_times(p)
        index, lane, others, intent, recent, row_off = _scene(net, np.random.default_rng(41 + trial), p.setoff_speed)
        own_setoff = _own(model, p)
        lanes = [index[k] for k in lane.tolist()]
        want = [own_setoff(others[a:b], lanes[a:b], t, intent[a:b], recent[a:b])  # simulates the bins it reads
                for a, b in zip(row_off[:-1].tolist(), row_off[1:].tolist())]
        slow = setoff_slow(others, box_lanes(index)[lane], recent, p.setoff_speed)
        row_of = np.repeat(np.arange(len(SIZES)), SIZES)
        n_slow = np.bincount(row_of[slow], minlength=len(SIZES))
        mod, accels = setoff_start(others[slow], p.setoff_accel)
        slow_off = np.concatenate([[0], np.cumsum(n_slow)]).astype(np.int64)
        h_off, n_h, xy, hh, owner, is_map, _ = predict_rows_following(
            model, mod, slow_off, [lanes[m] for m in np.flatnonzero(slow).tolist()], accels, t, intent[slow], 3.0)
        K = len(t)
        for r, w in enumerate(want):
            if w is None:
                assert n_slow[r] == 0, r
                seen["none"] += 1
                continue
            H, o = int(n_h[r]), int(h_off[r])
            assert n_slow[r] > 0 and H == len(w[2]), r
            got_xy, got_h = xy[2 * K * o: 2 * K * (o + H)].reshape(K, H, 2), hh[K * o: K * (o + H)].reshape(K, H)
            assert got_xy.tobytes() == w[0].tobytes() and got_h.tobytes() == w[1].tobytes(), r
            idx = np.flatnonzero(slow[row_off[r]: row_off[r + 1]])  # the decision's road users it predicts
            assert np.array_equal(idx[owner[o: o + H]], w[2]), r
            assert mod[slow_off[r] + owner[o: o + H], 5:7].tobytes() == w[3].tobytes(), r
            assert np.array_equal(is_map[o: o + H] | p.ignore_rear, w[4]), r
            seen["some"] += 1
            seen["map"] += int(is_map[o: o + H].sum())
            seen["cv"] += int((~is_map[o: o + H]).sum())
        seen["threshold"] += int((np.hypot(others[:, 2], others[:, 3]) == p.setoff_speed).sum())
    assert seen["none"] >= 1 and seen["some"] >= 3 and seen["map"] > 5 and seen["threshold"] > 2, seen


def test_the_rows_prediction_leaves_a_decision_with_a_missing_speed_bin_to_its_own(fresh_paths):  # noqa: F811
    """A decision whose set-off hypotheses read a speed bin not simulated yet gets ``n_h`` -1 (its row's own code
    then simulates it), never a prediction from an empty table."""
    from av_gym.shields.aeb_improved import long_times
    from av_gym.shields.aeb_params import ImprovedParams
    from av_gym.shields.conflicts import ConflictModel
    from av_gym.shields.setoff_rows import box_lanes, predict_rows_following, setoff_slow, setoff_start

    p = ImprovedParams()
    model, t = ConflictModel(fresh_paths, min_p=p.hypothesis_min_p), long_times(p)
    index, lane, others, intent, recent, row_off = _scene(fresh_paths, np.random.default_rng(43), p.setoff_speed)
    slow = setoff_slow(others, box_lanes(index)[lane], recent, p.setoff_speed)
    mod, accels = setoff_start(others[slow], p.setoff_accel)
    n_slow = np.bincount(np.repeat(np.arange(len(SIZES)), SIZES)[slow], minlength=len(SIZES))
    buffers = predict_rows_following(model, mod, np.concatenate([[0], np.cumsum(n_slow)]),
                                     [index[k] for k in lane[slow].tolist()], accels, t, intent[slow], 3.0)
    assert (buffers[1][n_slow > 0] == -1).all() and (buffers[1][n_slow == 0] == 0).all(), (buffers[1], n_slow)
