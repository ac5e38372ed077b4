"""The set-off rule for many decisions at once (av_gym/shields/setoff_rows.py: which road users it predicts, their
set-off start, and their prediction on flat buffers) against the per-decision code it stands for
(:meth:`ImprovedAEB._setoff_predict`), bit for bit on random road users."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

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



def _capped_counts(monkeypatch, horizon: float) -> dict:
    """Seed 1,000,003 under the short-window shield (tests/test_batched_screen.py) with ``setoff_horizon`` =
    ``horizon`` s and SCREEN_CHECK (each row the screen decides also decides itself, and both must agree): the TTCs
    of the set-off rule's brakes (the row's own ImprovedAEB._setoff_stop), and its calls whose prediction meets the
    ego only beyond the cap (no brake, the TTC over the whole horizon finite), all and those made while checking a
    row the screen decided; with _screened_counts' counts."""
    from av_gym.batched import shield as batched_shield
    from av_gym.shields.aeb_improved import ImprovedAEB
    from tests.test_batched_screen import VALIDATION, _actions_of_row, _screened_counts, _short_window

    shield, _ = _short_window()
    shield["setoff_horizon"] = horizon
    seen = {"brake_ttcs": [], "capped": 0, "capped_screened": 0}
    checking = []
    check, stop = batched_shield._check_screened, ImprovedAEB._setoff_stop

    def check_marked(sh, want, route_k, now):
        checking.append(True)
        try:
            check(sh, want, route_k, now)
        finally:
            checking.pop()

    def stop_seen(self, sc, setoff, t):
        got = stop(self, sc, setoff, t)
        whole, _ = self._ttc_of(sc, sc.ds_cruise, sc.n, self.p.margin, *setoff[:2], *setoff[3:])
        if got is not None:
            seen["brake_ttcs"].append(float(got[1]))
        elif np.isfinite(whole):
            seen["capped"] += 1
            seen["capped_screened"] += int(bool(checking))
        return got

    monkeypatch.setattr(batched_shield, "_check_screened", check_marked)
    monkeypatch.setattr(ImprovedAEB, "_setoff_stop", stop_seen)
    counts = _screened_counts(monkeypatch, shield, [VALIDATION + 3], _actions_of_row(3), lambda want: None)
    return {**seen, **counts}


@pytest.mark.slow  # ~4 CPU-s: one shielded episode with every screened decision checked
def test_the_setoff_horizon_caps_the_rule_alike_in_the_screen_and_the_rows_own_decision(monkeypatch):
    """``setoff_horizon`` (2 s here, the aeb preset's 3 s never binds on this episode): the set-off rule counts a
    conflict with a setting-off car only within it. On seed 1,000,003 (short window) the rule brakes at TTC <= 2 s,
    and at a decision whose prediction meets the ego only later (within the whole horizon, beyond 2 s) the row's own
    decision does not brake and the batch's screen (its n_set = min(n_slices, setoff_horizon / step)) decides the
    row quiet too (SCREEN_CHECK: the same decision). Fails with the cap dropped from ImprovedAEB._setoff_stop (a
    brake beyond 2 s, or the screen's MONITOR unlike the row's brake) or from the screen (no row it decides is
    capped: it leaves them to their rows)."""
    seen = _capped_counts(monkeypatch, 2.0)
    assert seen["brake_ttcs"] and max(seen["brake_ttcs"]) <= 2.0, seen
    assert seen["capped_screened"] > 0 and seen["setoff_brakes"] > 0, seen
