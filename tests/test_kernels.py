"""The numba kernels (av_gym/sim/kernels.py) against the numpy code they replace in av_gym/sim/batched.py:
on random inputs with ties and boundary cases (duplicate vehicles, boxes exactly touching, centres exactly 5 m
apart), every decision must be the same and every float the same to tests/_numerics.py's portable tolerance (1e-12
relative: numba's libm calls and numpy's own SIMD maths may differ in the last bits, and do on AVX-512 machines);
and a batch run with the kernels equals one without them, every state array at every step.

Each relaxed comparison still fails on a real change: tests/mutations.py changes the IDM kernel's interaction
exponent 2.0 to 2.01, and the collision kernel's separating-axis ``>`` to ``>=`` (touching boxes become crashes), and
checks that these tests fail."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from av_gym.batched.left_turn import BatchedLeftTurn, tables
from av_gym.make import highway_config
from av_gym.sim import batched as sb
from av_gym.sim import kernels

from _numerics import same as _same


def _traffic(rng, B: int, N: int, spread: float) -> sb.Traffic:
    """Random vehicles near the intersection's lanes (or in a ``spread`` m square at the centre if spread > 0), with
    duplicated vehicles (exact ties) and some on a grid with headings multiple of pi/2 (exactly touching boxes)."""
    T = tables()[0]
    t = sb.Traffic(T, B, N=N)
    n = rng.integers(0, N + 1, B)
    t.alive[:] = np.arange(N)[None] < n[:, None]
    k = rng.integers(0, len(T.length), (B, N))
    if spread > 0:
        t.x[:], t.y[:] = rng.uniform(-spread / 2, spread / 2, (2, B, N))
        t.h[:] = rng.uniform(-np.pi, np.pi, (B, N))
    else:
        s = rng.uniform(-9, 1, (B, N)) + rng.uniform(0, 1, (B, N)) * (T.length[k] + 8)
        t.x[:], t.y[:] = T.position(k, s, rng.uniform(-4.5, 4.5, (B, N)))
        t.h[:] = T.heading_at(k, s) + rng.normal(0, 0.2, (B, N))
    grid = rng.random((B, N)) < 0.3  # integer positions, axis-aligned: exact contacts and exact distances
    t.x[grid], t.y[grid] = rng.integers(-3, 4, (2, grid.sum())) * 2.5
    t.h[grid] = rng.integers(-2, 3, grid.sum()) * (np.pi / 2)
    t.v[:] = np.where(rng.random((B, N)) < 0.2, 0.0, rng.uniform(0, 12, (B, N)))
    dup = rng.random((B, N)) < 0.2  # a copy of slot 0 (same position, heading and speed)
    for name in ("x", "y", "h", "v"):
        a = getattr(t, name)
        a[dup] = np.broadcast_to(a[:, :1], a.shape)[dup]
    t.lane[:] = np.where(rng.random((B, N)) < 0.8, k, rng.integers(0, len(T.length), (B, N)))
    return t


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_front_kernel_is_the_numpy_leader_search(monkeypatch, seed):
    rng = np.random.default_rng(seed)
    t = _traffic(rng, 64, 14, spread=0)
    monkeypatch.setattr(sb, "KERNELS", set())
    ref = t._front(t.lane)
    monkeypatch.setattr(sb, "KERNELS", {"front"})
    got = t._front(t.lane)
    assert np.array_equal(got, ref)
    assert (ref >= 0).sum() > 50 and (ref < 0).sum() > 50  # both outcomes occur
    # ties occur and go to the last slot: some leader is a duplicate of slot 0 that has a copy after it
    leaders = ref[ref > 0]
    assert len(leaders) and (t.x[np.nonzero(ref > 0)[0], leaders] == t.x[np.nonzero(ref > 0)[0], 0]).any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_idm_kernel_is_the_numpy_idm(monkeypatch, seed):
    """IDM acceleration with the leader search's fronts (and none), set-points at and around utils.not_zero's
    bound (0, +-0.01, negative, above the lane's limit), standing vehicles, zero gaps (duplicates)."""
    rng = np.random.default_rng(seed)
    t = _traffic(rng, 64, 14, spread=0)
    t.target[:] = rng.choice([0.0, 0.01, -0.01, 0.005, -3.0, 4.5, 9.0, 30.0], t.target.shape)
    t.delta[:] = np.where(rng.random(t.delta.shape) < 0.5, 4.0, rng.uniform(3.5, 4.5, t.delta.shape))
    front = t._front(t.lane)
    front[:, ::5] = -1
    monkeypatch.setattr(sb, "KERNELS", set())
    ref = t._idm_acc(front)
    monkeypatch.setattr(sb, "KERNELS", {"idm"})
    got = t._idm_acc(front)
    assert _same(got, ref)
    d = t.tables.local(t.lane, np.take_along_axis(t.x, np.maximum(front, 0), 1),
                       np.take_along_axis(t.y, np.maximum(front, 0), 1))[0] - t.tables.local(t.lane, t.x, t.y)[0]
    assert ((front >= 0) & (d == 0)).any() and ((front >= 0) & (d != 0)).any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_collision_kernel_is_the_numpy_separating_axes(monkeypatch, seed):
    rng = np.random.default_rng(seed)
    t = _traffic(rng, 96, 10, spread=25.0)
    a, b = t.subset(range(t.B)), t.subset(range(t.B))
    monkeypatch.setattr(sb, "KERNELS", set())
    a._collisions(1 / 15)
    monkeypatch.setattr(sb, "KERNELS", {"collisions"})
    b._collisions(1 / 15)
    for name in ("crashed", "has_impact", "impact_x", "impact_y"):
        assert _same(getattr(a, name), getattr(b, name)), name
    assert 0 < a.crashed.sum() < a.alive.sum() and (a.has_impact & ~a.crashed).any()  # contacts and near misses


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_conflict_kernel_is_the_numpy_regulation_test(seed):
    rng = np.random.default_rng(seed)
    b, N, T = 48, 10, len(sb.REG_TIMES)
    px, py = rng.uniform(-15, 15, (2, b, N, T))
    ph = rng.uniform(-np.pi, np.pi, (b, N, T))
    grid = rng.random((b, N, T)) < 0.3  # centres exactly 5 m apart (the pre-check's bound), aligned boxes
    px[grid], py[grid] = rng.integers(-2, 3, (2, grid.sum())) * 5.0
    ph[grid] = rng.integers(-2, 3, grid.sum()) * (np.pi / 2)
    px[:, 3], py[:, 3], ph[:, 3] = px[:, 1], py[:, 1], ph[:, 1]  # duplicates
    alive = np.arange(N)[None] < rng.integers(0, N + 1, b)[:, None]
    ref = sb._conflicts(px, py, ph, alive)
    got = kernels.conflicts(px, py, ph, alive, sb.LENGTH, sb.WIDTH)
    assert np.array_equal(got, ref)
    assert 0 < ref.sum() < np.triu(alive[:, :, None] & alive[:, None, :], 1).sum()


@pytest.mark.parametrize("seed", [0, 1])
def test_closest_lane_kernel_is_the_numpy_argmin(monkeypatch, seed):
    """Points anywhere near the intersection, on lane ends (where two lanes meet: near-ties) and duplicated."""
    T, rng = tables()[0], np.random.default_rng(seed)
    k = rng.integers(0, len(T.length), 3000)
    s = np.where(rng.random(3000) < 0.3, rng.integers(0, 2, 3000) * T.length[k], rng.uniform(-5, 1, 3000) * T.length[k])
    x, y = T.position(k, s, np.where(rng.random(3000) < 0.5, 0.0, rng.normal(0, 3, 3000)))
    h = T.heading_at(k, s) + np.where(rng.random(3000) < 0.5, 0.0, rng.normal(0, 1, 3000))
    x[::7], y[::7], h[::7] = x[1::7][: len(x[::7])], y[1::7][: len(x[::7])], h[1::7][: len(x[::7])]
    x[-500:], y[-500:] = rng.uniform(-120, 120, (2, 500))
    monkeypatch.setattr(sb, "KERNELS", set())
    ref = T.closest(x, y, h)
    monkeypatch.setattr(sb, "KERNELS", {"closest"})
    got = T.closest(x, y, h)
    assert np.array_equal(got, ref) and len(np.unique(ref)) > len(T.length) // 2
    assert np.array_equal(T.closest(x[:60].reshape(3, 20), y[:60].reshape(3, 20), h[:60].reshape(3, 20)),
                          ref[:60].reshape(3, 20))


@pytest.mark.parametrize("seed", [0, 1])
def test_closest_lane_from_any_hint_is_the_numpy_argmin(monkeypatch, seed):
    """The tick's closest lane starts from the vehicle's previous lane (a hint) and, within kernels.NEAR_GAP of it,
    evaluates only its near lanes: the numpy argmin whatever the hint. Points within centimetres of a lane (the near
    path), on lane ends (ties where lanes meet) and anywhere; hints the true lane, a lane the point left, any lane."""
    T, rng = tables()[0], np.random.default_rng(seed)
    n = 4000
    k = rng.integers(0, len(T.length), n)
    s = np.where(rng.random(n) < 0.3, rng.integers(0, 2, n) * T.length[k], rng.uniform(-0.2, 1.2, n) * T.length[k])
    r = np.where(rng.random(n) < 0.6, rng.normal(0, 0.05, n), rng.normal(0, 2, n))
    x, y = T.position(k, s, r)
    h = T.heading_at(k, s) + np.where(rng.random(n) < 0.6, rng.normal(0, 0.02, n), rng.normal(0, 0.5, n))
    x[-400:], y[-400:] = rng.uniform(-120, 120, (2, 400))
    monkeypatch.setattr(sb, "KERNELS", set())
    ref = T.closest(x, y, h)
    near = T.distance_with_heading(ref, x, y, h) <= kernels.NEAR_GAP
    assert near.mean() > 0.4 and len(np.unique(ref[near])) == len(T.length)  # the near path on every lane
    for hint in (ref, k, rng.integers(0, len(T.length), n), np.full(n, -1)):
        got = kernels.closest(T.arr, x, y, h, np.ascontiguousarray(hint, dtype=np.int64))
        assert np.array_equal(got, ref), np.nonzero(got != ref)[0][:10]


def test_steering_and_slip_by_their_cosines_and_sines_are_the_angle_formulas():
    """Traffic._steering's tan(asin q) = q / sqrt(1 - q²) and Traffic._kinematics' slip angle by its cosine and
    sine from t = tan(steer) / 2 give highway-env's angle formulas (atan(2 tan(asin q)); atan(t), cos(h + β),
    sin(h + β), sin β) to 1e-12, saturated steering (|q| = 1) included; the tick kernel does the same arithmetic
    (the lockstep tests)."""
    rng = np.random.default_rng(4)
    t = _traffic(rng, 64, 12, 0.0)
    t.tlane[:] = t.lane
    t.v[:] = np.where(rng.random(t.v.shape) < 0.1, 0.3, t.v)  # slow: |q| clips to 1, full lock
    T = t.tables
    s, r = T.local(t.tlane, t.x, t.y)
    v_nz = sb.not_zero(t.v)
    ref_h = T.heading_at(t.tlane, s + t.v * sb.TAU_PURSUIT) \
        + np.clip(np.arcsin(np.clip(-sb.KP_LATERAL * r / v_nz, -1, 1)), -np.pi / 4, np.pi / 4)
    q = np.clip(sb.LENGTH / 2 / v_nz * sb.KP_HEADING * sb.wrap_to_pi(ref_h - t.h), -1, 1)
    steer = np.clip(np.arctan(2 * np.tan(np.arcsin(q))), -sb.MAX_STEERING, sb.MAX_STEERING)
    assert _same(t._steering(), steer) and (np.abs(q) == 1).any() and (np.abs(steer) < sb.MAX_STEERING).sum() > 50
    t.steer[:] = steer
    beta = np.arctan(1 / 2 * np.tan(steer))
    dt, a = 1 / 15, t.alive
    want = (t.x + t.v * np.cos(t.h + beta) * dt, t.y + t.v * np.sin(t.h + beta) * dt,
            t.h + t.v * np.sin(beta) / (sb.LENGTH / 2) * dt)
    t._kinematics(dt)
    for got, ref in zip((t.x, t.y, t.h), want):
        assert _same(got[a], ref[a])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ttc_kernel_is_the_numpy_ttc(monkeypatch, seed):
    """Random traffic around the ego (slot 0): overlapping now (0 s), stationary and equal-velocity pairs (the
    axes' zero relative speed branch), axis-aligned grid boxes (exact touching), duplicates of the ego."""
    _, config = highway_config({"name": "left_turn"})
    bt = BatchedLeftTurn(8, config)
    rng = np.random.default_rng(seed)
    t = _traffic(rng, 128, 10, spread=60.0)
    t.alive[:, 0], t.ego[:, 0] = True, True
    x, y = rng.uniform(-30, 30, (2, 96, 10))  # rows 32+: no duplicates, half the others aimed at the ego
    aim = np.arctan2(y[:, :1] - y, x[:, :1] - x) + rng.normal(0, 0.1, (96, 10))
    t.x[32:], t.y[32:] = x, y
    t.h[32:] = np.where(rng.random((96, 10)) < 0.5, aim, t.h[32:])
    same = rng.random((128, 10)) < 0.15  # the ego's velocity
    t.h[same], t.v[same] = np.broadcast_to(t.h[:, :1], t.h.shape)[same], np.broadcast_to(t.v[:, :1], t.v.shape)[same]
    # exact contacts, heading 0: touching now (x, y), touching and moving together (zero relative speed, |q| =
    # half), and closing 5 m at 10 m/s: touching exactly at the grid time 0.5 s
    for row, (ox, oy, ev, ov) in enumerate([(5, 0, 0, 0), (0, 2, 0, 0), (5, 0, 3, 3), (10, 0, 10, 0), (-5, 0, 0, 0)]):
        t.alive[row, :2], t.alive[row, 2:] = True, False
        t.x[row, :2], t.y[row, :2], t.h[row, :2], t.v[row, :2] = (0, ox), (0, oy), (0, 0), (ev, ov)
    bt.traffic = t
    monkeypatch.setattr(sb, "KERNELS", set())
    every, rows = np.arange(128), rng.permutation(128)[:50]
    ref, ref_rows = bt.ttc(every), bt.ttc(rows)
    monkeypatch.setattr(sb, "KERNELS", {"ttc"})
    assert np.array_equal(bt.ttc(every), ref) and np.array_equal(bt.ttc(rows), ref_rows)
    assert (ref == 0).sum() > 3 and ((ref > 0) & np.isfinite(ref)).sum() > 10 and np.isinf(ref).sum() > 10
    assert list(ref[:5]) == [0, 0, 0, 0.5, 0]


def test_point_in_box_kernel_is_the_numpy_one_on_its_edges():
    """The regulation's point-in-box test, boxes on a 3.75 / 4 m grid heading 0 (exact arithmetic): points exactly
    on an edge count as inside, as utils.point_in_rotated_rectangle's ``<=`` (the pre-check keeps such pairs out of
    the tests above: centres within 5 m always have an interior point)."""
    L, W = 1.5 * sb.LENGTH, 0.9 * sb.WIDTH
    lx = np.array([-L / 2, -L / 2, L / 2, L / 2, 0.0, -L / 2, L / 2, 0.0, 0.0])
    ly = np.array([-W / 2, W / 2, W / 2, -W / 2, 0.0, 0.0, 0.0, -W / 2, W / 2])
    rng = np.random.default_rng(0)
    x1, y1, x2, y2 = rng.integers(-10, 11, (4, 400)) * (L / 8)
    y1[::2], y2[::2] = rng.integers(-3, 4, (2, 200)) * (W / 2)
    ref = sb._inside(sb._rect_points(x1, y1, np.zeros(400), L, W), x2, y2, np.zeros(400), L, W)
    got = np.array([kernels._any_inside(1.0, 0.0, x1[n], y1[n], 1.0, 0.0, x2[n], y2[n], lx, ly, L / 2, W / 2)
                    for n in range(400)])
    assert np.array_equal(got, ref) and 0 < ref.sum() < 400
    edge = np.abs(np.abs(x1 - x2) - L).min(), np.abs(np.abs(y1 - y2) - W).min()
    assert edge == (0.0, 0.0)  # some boxes touch exactly


PAIRWISE = {"front", "collisions", "conflicts", "closest", "ttc", "idm"}


# traffic in the fast suite (spawns, pool resets, yields, crashes); CCFtap's whole runs (~1 CPU-s) in the slow one
@pytest.mark.parametrize("env", [{}, pytest.param({"mode": "ccftap"}, marks=pytest.mark.slow)])
def test_batch_with_kernels_is_the_batch_without(monkeypatch, env):
    """Whole runs (spawns, resets through the pool, yields, crashes, TTC) with the pairwise kernels: every state
    array equal at every step. (The fused tick, which also moves the transcendental maths of steering and
    kinematics to the C library, is compared step by step below: over whole runs its last-bit differences from
    numpy's AVX-512 maths grow as any perturbation of the traffic does.)"""
    _, config = highway_config({"name": "left_turn", **env})
    runs = []
    for kset in (PAIRWISE, set()):
        monkeypatch.setattr(sb, "KERNELS", kset)
        bt = BatchedLeftTurn(16, config, pool=8)
        bt.reset(list(range(16)))
        rng, states = np.random.default_rng(0), []
        for _ in range(120):
            bt.step_autoreset(rng.integers(0, 3, 16))
            t = bt.traffic
            states.append([getattr(t, n).copy() for n in t.FIELDS if n != "vid"] + [bt.ttc()])
        runs.append(states)
    for step, (p, q) in enumerate(zip(*runs)):
        for n, u, w in zip([n for n in sb.Traffic.FIELDS if n != "vid"] + ["ttc"], p, q):
            assert _same(u, w), f"step {step}: {n}"
    assert runs[0][-1][sb.Traffic.FIELDS.index("crashed") - 1].any() or env  # the traffic run had a crash


def _lockstep(monkeypatch, config: dict, B: int, steps: int, seed: int, continuous: bool = False) -> dict:
    """Step a numpy-path engine and, from the same state each step, a fork of it on the fused tick
    (kernels.advance, ``tick``) with the same actions; every state array, clock and step result of the two must
    be the same (decisions identical, floats to _numerics' REL). Ended episodes restart from the pool (made on the
    numpy path; its warm-up is compared on its own). Returns counts of what the steps exercised."""
    monkeypatch.setattr(sb, "KERNELS", PAIRWISE)
    ref = BatchedLeftTurn(B, config, pool=8)
    ref.reset(list(range(seed, seed + B)))
    rng = np.random.default_rng(seed)
    seen = {"crashed": 0, "yielding": 0, "arrived": 0, "spawned": 0}
    for step in range(steps):
        # mostly IDLE (proceed: the CCFtap ego meets its target), else a random action
        a = rng.uniform(-1, 1, B) if continuous else np.where(rng.random(B) < 0.6, 1, rng.integers(0, 3, B))
        active = rng.random(B) < 0.9  # some envs sit a step out, as done envs waiting for their reset do
        fork = ref.fork(np.arange(B))
        monkeypatch.setattr(sb, "KERNELS", PAIRWISE | {"tick"})
        got = fork.step(a, active)
        monkeypatch.setattr(sb, "KERNELS", PAIRWISE)
        n_before = ref.traffic.alive.sum()
        want = ref.step(a, active)
        for name in sb.Traffic.FIELDS:
            if name != "vid":
                assert _same(getattr(fork.traffic, name), getattr(ref.traffic, name)), f"step {step}: {name}"
        for name in ("ticks", "time", "arrived_time", "progress_s", "cmd"):
            assert _same(getattr(fork, name), getattr(ref, name)), f"step {step}: {name}"
        assert np.array_equal(fork.traffic.road_steps, ref.traffic.road_steps)
        for u, w in zip(got, want):
            assert _same(u, w), f"step {step}: reward / terminated / truncated"
        seen["crashed"] += int(ref.traffic.crashed.sum())
        seen["yielding"] += int(ref.traffic.yielding.sum())
        seen["arrived"] += int(np.isfinite(ref.arrived_time).sum())
        seen["spawned"] += int(ref.traffic.alive.sum() > n_before)
        done = np.nonzero(want[1] | want[2])[0]
        if len(done):
            ref.start_from_pool(done)
    return seen


@pytest.mark.parametrize("env", [{}, {"mode": "ccftap"}, {"action": "continuous"}])
def test_tick_kernel_steps_as_the_numpy_path(monkeypatch, env):
    """The fused tick against the numpy path, step by step from the same state: meta-actions and continuous
    accelerations, envs left out of a step, follow_road's route changes, the regulation's yields, impacts and
    crashes, arrivals."""
    _, config = highway_config({"name": "left_turn", **env})
    seen = _lockstep(monkeypatch, config, 16, 150, seed=3, continuous="action" in env)
    assert seen["crashed"] and (seen["arrived"] or env)
    assert env or (seen["yielding"] and seen["spawned"])


def test_tick_kernel_warms_up_as_the_numpy_path(monkeypatch):
    """A reset's 3 s warm-up (60 ticks, no ego) on the fused tick gives the numpy path's initial traffic."""
    _, config = highway_config({"name": "left_turn"})
    made = []
    for kset in (PAIRWISE | {"tick"}, PAIRWISE):
        monkeypatch.setattr(sb, "KERNELS", kset)
        bt = BatchedLeftTurn(32, config)
        bt.reset(list(range(500, 532)))
        made.append(bt.traffic)
    for name in sb.Traffic.FIELDS:
        if name != "vid":
            assert _same(getattr(made[0], name), getattr(made[1], name)), name
    assert made[1].yielding.any() or made[1].crashed.any()


@pytest.mark.parametrize("seed", [0, 1])
def test_path_conflict_kernel_is_the_numpy_closest_approach(monkeypatch, seed):
    """obs["turn"]'s closest approach to the ego's path: objects anywhere around the intersection, standing
    (|v|² under 1e-6), moving along the path (exact ties in miss: the first point), on path points exactly."""
    from av_gym.estimation.turn_features import path_conflict

    _, config = highway_config({"name": "left_turn"})
    bt = BatchedLeftTurn(1, config)
    path, path_s = bt.path, bt.path_s
    rng = np.random.default_rng(seed)
    p, v = rng.uniform(-40, 40, (64, 8, 2)), rng.normal(0, 6, (64, 8, 2))
    v[:, 0] = 0.0  # standing
    p[:, 1] = path[rng.integers(0, len(path), 64)]  # on a path point
    p[:, 2], v[:, 2] = path[3], (path[4] - path[3]) * 2.0  # along a straight stretch of the path
    monkeypatch.setattr(sb, "KERNELS", set())
    ref = path_conflict(p, v, path, path_s)
    monkeypatch.setattr(sb, "KERNELS", {"path_conflict"})
    got = path_conflict(p, v, path, path_s)
    for u, w in zip(got, ref):
        assert np.array_equal(u, w)
    assert (ref[0] == 0).any() and (ref[0] == 10.0).any() and ((ref[0] > 0) & (ref[0] < 10)).any()
    assert (ref[1] == 0).any()


def _outcomes(config: dict, seeds: list, kernels: set) -> list:
    """Each seed's episode played to its end on one batch with the kernels ``kernels``: random meta-actions (a
    stream per batch, independent of the state, so both paths get the same ones); per episode its end (collision,
    arrived, time-out) and its step."""
    with sb.using_kernels(kernels):
        B = len(seeds)
        bt = BatchedLeftTurn(B, config)
        bt.reset(seeds)
        rng = np.random.default_rng(0)
        out, live, step = [None] * B, np.ones(B, bool), 0
        while live.any():
            _, terminated, truncated = bt.step(rng.integers(0, 3, B), live)
            step += 1
            for r in np.nonzero((terminated | truncated) & live)[0]:
                e = bt.ego_slot([r])
                end = "collision" if bt.traffic.crashed[r, e[0]] else "arrived" if terminated[r] else "time-out"
                out[r] = (end, step)
            live &= ~(terminated | truncated)
    return out


def _episodes_end_alike(n: int) -> None:
    _, config = highway_config({"name": "left_turn"})
    seeds = list(range(900_000, 900_000 + n))
    old = _outcomes(config, seeds, set(sb.PAIRWISE_KERNELS))
    new = _outcomes(config, seeds, set(sb.KERNELS))
    same = sum(a == b for a, b in zip(old, new))
    assert same >= 0.995 * n, [(s, a, b) for s, a, b in zip(seeds, old, new) if a != b]
    ends = {a[0] for a in old}
    assert ends == {"collision", "arrived", "time-out"}, ends


def test_compiled_step_ends_episodes_as_the_numpy_step():
    """Whole episodes (not lockstep): the compiled step's last-bit differences from numpy's maths (AVX-512 builds)
    may move a knife-edge decision late in an episode, but the episode's end and its step must be the same in
    >= 99.5 % of episodes (200 here; 1,000 with -m slow)."""
    _episodes_end_alike(200)


@pytest.mark.slow  # ~1 CPU-min: 1,000 whole episodes on both paths
def test_compiled_step_ends_1000_episodes_as_the_numpy_step():
    _episodes_end_alike(1000)


# ------------------------------------------------------------------------------------------------ generator draws
_OPS = np.array([0, 2, 1, 1, 3, 0, 4, 2, 1, 3, 5, 0, 2, 6, 1])  # the kernel's draws, in this order, per round


@numba.njit  # not cached: numba's cache would not see a change of the kernels it inlines
def _kernel_draws(fns, states, ops, out, col):
    """Round of draws ``ops`` on each generator (by state address), into ``out[:, col:]``: 0 next_double (random(),
    uniform()), 1 normal(), 2 choice(4, 2, replace=False) as 10 a + b, 3 uniform(3.5, 4.5), 4 choice(2, 2, ...),
    5 integers(0, 3) (bounded 2), 6 integers(0, 2**31 - 1) (bounded 2**31 - 2)."""
    for i in range(states.shape[0]):
        st = states[i]
        for k in range(ops.shape[0]):
            o = ops[k]
            if o == 0:
                out[i, col + k] = fns[2](st)
            elif o == 1:
                out[i, col + k] = kernels.standard_normal(fns, st)
            elif o == 2 or o == 4:
                a, b = kernels.choice2(fns, st, 4 if o == 2 else 2)
                out[i, col + k] = 10 * a + b
            elif o == 3:
                out[i, col + k] = 3.5 + (4.5 - 3.5) * fns[2](st)
            else:
                out[i, col + k] = kernels.bounded(fns, st, 2 if o == 5 else 2**31 - 2)


def _numpy_draws(g, ops) -> list:
    out = []
    for o in ops:
        if o in (2, 4):
            a, b = g.choice(range(4 if o == 2 else 2), 2, replace=False)
            out.append(10 * a + b)
        else:
            out.append({0: g.random, 1: g.normal, 3: lambda: g.uniform(low=3.5, high=4.5),
                        5: lambda: g.integers(0, 3), 6: lambda: g.integers(0, 2**31 - 1)}[o]())
    return out


def test_kernel_draws_are_the_generators_own_stream():
    """The spawn kernels' draws (kernels.standard_normal, bounded, choice2, next_double) on 1,000 seeded PCG64
    generators give numpy's values and leave numpy's states (the 32-bit buffer included), rounds of kernel draws
    interleaved with numpy calls on the same generators (a Python ``integers`` leaves half a 64-bit output in the
    buffer that the kernel's next 32-bit draw must use). The ziggurat's tail (|x| > its r) is drawn too (5 of
    these 12,000 normals). Mutation: choice2's shuffle taking ``== 1`` for the swap fails it."""
    n = 1000
    ours = [np.random.default_rng(s) for s in range(n)]
    ref = [np.random.default_rng(s) for s in range(n)]
    out, want = np.zeros((n, 4 * len(_OPS))), np.zeros((n, 4 * len(_OPS)))
    between = np.zeros((n, 3))
    for rnd in range(4):
        states = kernels.generator_states(ours)
        _kernel_draws(kernels.pcg64_functions(), states, _OPS, out, rnd * len(_OPS))
        for i in range(n):
            want[i, rnd * len(_OPS):(rnd + 1) * len(_OPS)] = _numpy_draws(ref[i], _OPS)
            if rnd < 3:  # numpy calls in between, on both
                between[i, rnd] = ours[i].integers(0, 5)
                assert ref[i].integers(0, 5) == between[i, rnd]
    assert np.array_equal(out, want)
    assert all(a.bit_generator.state == b.bit_generator.state for a, b in zip(ours, ref))
    normals = out[:, np.tile(_OPS, 4) == 1]
    assert (np.abs(normals) > kernels.ZIG_R).any()  # the tail branch ran


def test_generator_states_refuse_what_the_kernels_cannot_draw_from():
    """Only distinct PCG64 generators go to the kernels: a Philox generator or one generator on two rows (whose
    draws numpy makes in an order across rows) give None, and the batch then spawns by numpy's calls."""
    g = np.random.default_rng(1)
    assert kernels.generator_states([g, np.random.default_rng(2)]) is not None
    assert kernels.generator_states([g, g]) is None
    assert kernels.generator_states([np.random.Generator(np.random.Philox(1))]) is None


def _spawn_run(config: dict, kset: set, rngs_from: int | None = None) -> list:
    """A whole run of 16 envs (pool resets) with the kernels ``kset``: every state array and the live vehicles'
    ids (relative to the run's first) at every step. ``rngs_from``: rows from this one on get Philox generators."""
    with sb.using_kernels(kset):
        bt = BatchedLeftTurn(16, config, pool=8)
        bt.reset(list(range(40, 56)))
        if rngs_from is not None:
            for r in range(rngs_from, 16):
                bt.rngs[r] = np.random.Generator(np.random.Philox(r))
        rng, states = np.random.default_rng(0), []
        first = bt.traffic.vid[bt.traffic.alive].min()
        for _ in range(120):
            bt.step_autoreset(rng.integers(0, 3, 16))
            t = bt.traffic
            states.append([getattr(t, n).copy() for n in t.FIELDS if n != "vid"] + [t.vid[t.alive] - first,
                                                                                   np.array(t.N)])
    return states


def test_rows_sharing_a_generator_draw_by_numpy_calls():
    """A kernel draws env after env, so two rows on one generator would change the order of draws numpy's calls
    make across rows: such rows get no state addresses (the caller falls back to numpy's calls), other rows do."""
    _, config = highway_config({"name": "left_turn"})
    bt = BatchedLeftTurn(4, config)
    bt.reset([11, 12, 13, 14])
    assert bt._row_states(np.arange(4)) is not None
    bt.rngs[2] = bt.rngs[0]
    assert bt._row_states(np.arange(4)) is None and bt._row_states(np.array([0, 1, 3])) is not None
    assert bt._row_states(np.array([2, 3])) is not None


@pytest.mark.parametrize("philox", [False, True])
def test_spawn_kernels_draw_the_numpy_spawns(philox):
    """The spawn tries, a reset's initial traffic and its challenger from the kernels (``spawn``), and the clearing
    of vehicles at the exits with the compaction (``clear``), against numpy's calls (BatchedLeftTurn._spawn,
    Traffic.compact), everything else the same: every state array identical, bit for bit, at every
    step of a whole run with pool resets, the vehicle ids in the same order (``philox``: some rows' generators
    are not PCG64, so those steps spawn by numpy's calls: the same run again). Mutations: the step's spawn position
    deviation 1.0 as 1.001, choice2's swap on ``== 1``, clear_exits putting the dead slots in reverse order, or the
    speed of a spawn that found its row full (placed by Traffic.add after the kernel) + 1e-6, fail it."""
    _, config = highway_config({"name": "left_turn"})
    a = _spawn_run(config, PAIRWISE, 12 if philox else None)
    b = _spawn_run(config, PAIRWISE | {"spawn", "clear"}, 12 if philox else None)
    names = [n for n in sb.Traffic.FIELDS if n != "vid"] + ["vid", "slots"]
    for step, (p, q) in enumerate(zip(a, b)):
        for n, u, w in zip(names, p, q):
            assert u.shape == w.shape and np.array_equal(u, w), f"step {step}: {n}"
    assert a[-1][-2].max() > 16 * 12  # many vehicles were spawned
    slots = [int(s[-1]) for s in a]
    assert any(m > n for n, m in zip(slots, slots[1:]))  # a spawn found its row full: the arrays grew


# ------------------------------------------------------------------------------------------------ obs["turn"], truth
F32 = 2.0**-23  # one float32 rounding step of features in [-1, 1]: where a last-bit float64 difference crosses one


def _feature_inputs(rng, n: int, N: int) -> tuple:
    """Random egos and others around the intersection: duplicated others (exact distance ties), others exactly at
    the ego, invalid rows, NaN rows, others beyond 80 m, values beyond their scales (clipped), a NaN ego time."""
    ego = {"x": rng.uniform(-20, 20, n), "y": rng.uniform(-20, 20, n), "heading": rng.uniform(-np.pi, np.pi, n),
           "speed": rng.uniform(0, 15, n), "set_point": rng.choice([0.0, 4.5, 9.0], n),
           "stop_line_offset": rng.uniform(-40, 40, n), "distance_to_conflict": rng.uniform(-10, 50, n),
           "time": rng.uniform(0, 30, n)}
    ego["time"][0] = np.nan
    others = np.concatenate([rng.uniform(-120, 120, (n, N, 2)), rng.normal(0, 12, (n, N, 2))], axis=-1)
    dup = rng.random((n, N)) < 0.25
    others[dup] = np.broadcast_to(others[:, :1], others.shape)[dup]
    at_ego = rng.random((n, N)) < 0.05
    others[at_ego, 0], others[at_ego, 1] = np.broadcast_to(ego["x"][:, None], (n, N))[at_ego], \
        np.broadcast_to(ego["y"][:, None], (n, N))[at_ego]
    others[rng.random((n, N)) < 0.05] = np.nan
    return ego, others, rng.random((n, N)) < 0.85


@pytest.mark.parametrize("seed,N,max_objects", [(0, 12, 8), (1, 5, 8), (2, 0, 8), (3, 30, 16)])
def test_turn_features_kernel_is_the_numpy_function(monkeypatch, seed, N, max_objects):
    """obs["turn"] compiled (kernels.turn_features, both stacks) against the numpy function: the same described
    objects in the same order (ties in row order, NaN and invalid rows last) and the same features to one float32
    rounding step. Mutations that fail it: ties taken last (``_before``'s ``<`` as ``<=``); the present test's
    ``<=`` max_range as ``<``; an object's ``left`` with ``+ ry * c`` dropped."""
    from av_gym.envs.left_turn import CONFLICT_POINT
    from av_gym.estimation.turn_features import TurnFeaturesParams, turn_features

    _, config = highway_config({"name": "left_turn"})
    bt = BatchedLeftTurn(1, config)
    ego, others, valid = _feature_inputs(np.random.default_rng(seed), 96, N)
    if N:
        others[:, -1, :2] = np.stack([ego["x"] + 80.0, ego["y"]], axis=1)  # exactly at max_range: described
    params = TurnFeaturesParams(max_objects=max_objects)
    outs = []
    for kset in (sb.KERNELS - {"turn_features"}, sb.KERNELS):
        monkeypatch.setattr(sb, "KERNELS", kset)
        outs.append(turn_features(ego, others, valid, bt.path, bt.path_s, CONFLICT_POINT, params))
    (want, w_order, w_present), (got, g_order, g_present) = outs
    assert got.dtype == np.float32 and got.shape == want.shape
    assert np.array_equal(g_order, w_order) and np.array_equal(g_present, w_present)
    assert _same(got, want, rel=F32)
    if N:  # described and left-out objects, clipped values, the object exactly at max_range described
        assert w_present.any() and (~w_present).any() and (np.abs(want) == 1.0).any()
        assert (w_present & (w_order == N - 1)).any()


def _observe_lockstep(monkeypatch, config: dict, B: int, steps: int, seed: int, continuous: bool = False) -> dict:
    """Step an engine with obs["turn"], truth and rewards in numpy (sb.OBSERVE_KERNELS left out) and, from the same
    state each step, a fork with them compiled: the same rewards, terminations, progress, route hints, truth and
    features (features to one float32 rounding step). Returns counts of what the steps exercised."""
    numpy_path = sb.KERNELS - sb.OBSERVE_KERNELS
    compiled = set(sb.KERNELS)
    monkeypatch.setattr(sb, "KERNELS", numpy_path)
    ref = BatchedLeftTurn(B, config, pool=8)
    ref.reset(list(range(seed, seed + B)))
    rng = np.random.default_rng(seed)
    seen = {"crashed": 0, "arrived": 0, "described": 0}
    for step in range(steps):
        a = rng.uniform(-1, 1, B) if continuous else np.where(rng.random(B) < 0.6, 1, rng.integers(0, 3, B))
        active = rng.random(B) < 0.9
        fork = ref.fork(np.arange(B))
        monkeypatch.setattr(sb, "KERNELS", compiled)
        got = fork.step(a, active)
        got_obs, got_truth = fork.observe(), fork.last_truth
        rows = np.nonzero(active)[0][::2]
        got_rows = fork.truth(rows)
        monkeypatch.setattr(sb, "KERNELS", numpy_path)
        want = ref.step(a, active)
        want_obs, want_truth = ref.observe(), ref.last_truth
        want_rows = ref.truth(rows)
        for u, w in zip(got, want):
            assert _same(u, w), f"step {step}: reward / terminated / truncated"
        for name in ("progress_s", "_route_k"):
            assert _same(getattr(fork, name), getattr(ref, name)), f"step {step}: {name}"
        assert _same(got_obs, want_obs, rel=F32), f"step {step}: obs['turn']"
        for g, w in ((got_truth, want_truth), (got_rows, want_rows)):
            assert g.keys() == w.keys()
            for k in w:
                assert _same(g[k], w[k]), f"step {step}: truth {k}"
        for u, w in zip(fork.described, ref.described):
            assert np.array_equal(u, w), f"step {step}: described"
        seen["crashed"] += int(want_truth["collision"].sum())
        seen["arrived"] += int(want_truth["arrived"].sum())
        seen["described"] += int(ref.described[1].sum())
        done = np.nonzero(want[1] | want[2])[0]
        if len(done):
            ref.start_from_pool(done)
    return seen


@pytest.mark.parametrize("env", [{}, {"mode": "ccftap"}, {"action": "continuous"}])
def test_truth_features_and_rewards_kernels_step_as_the_numpy_code(monkeypatch, env):
    """kernels.truth, observe and rewards against BatchedLeftTurn's numpy truth, observe and _reward, step by step
    from the same state (route positions moving along the route, progress, crashes, arrivals). Mutations that
    fail it: the stop line's ``+ LENGTH / 2`` as ``-``; the comfort term's ``/ 3.0`` as ``/ 3.1``. (The route
    hint's step back never happens in these runs: an ego does not reverse.)"""
    _, config = highway_config({"name": "left_turn", **env})
    seen = _observe_lockstep(monkeypatch, config, 16, 120, seed=5, continuous="action" in env)
    assert seen["described"] and (env or (seen["crashed"] and seen["arrived"]))  # ego crashes and arrivals


def test_the_per_env_stack_computes_its_features_with_the_kernel(monkeypatch):
    """TurnFeatures (the per-env wrapper) calls the same compiled function with one row: along per-env episodes its
    feature vectors and described objects are the numpy function's (to one float32 rounding step)."""
    import gymnasium as gym

    from av_gym.estimation.turn_features import TurnFeatures

    env_id, config = highway_config({"name": "left_turn"})
    env = TurnFeatures(gym.make(env_id, config=config))
    rng = np.random.default_rng(0)
    env.reset(seed=7)
    compared = 0
    for _ in range(120):
        _, _, term, trunc, info = env.step(int(rng.integers(0, 3)))
        others = info["truth"]["others"][:, :4]
        outs = []
        for kset in (sb.KERNELS - {"turn_features"}, sb.KERNELS):
            monkeypatch.setattr(sb, "KERNELS", kset)
            outs.append((env.features(info["truth"], others), env.described.copy()))
        assert _same(outs[1][0], outs[0][0], rel=F32) and np.array_equal(outs[1][1], outs[0][1])
        compared += len(outs[0][1])
        if term or trunc:
            env.reset(seed=int(rng.integers(1000)))
    env.close()
    assert compared > 100


@pytest.mark.slow  # 200 episodes twice on the batch: ~10 s alone at load 2.3
def test_a_shipped_student_decides_as_on_the_numpy_features():
    """The committed dagger_turn (trained on the numpy features) on 200 validation episodes on the batch: every
    episode's metrics identical with obs["turn"], truth and rewards compiled and in numpy (the rest compiled both
    times): the kernels change no decision of a shipped checkpoint."""
    from av_gym.make import make_env
    from eval.agents import plan_agent, resolve_agent
    from eval.batched import run_episodes_batched

    from tests.conftest import conf

    env_cfg = conf("env", "left_turn")
    plan = plan_agent("dagger_turn", "left_turn", conf("sensors", "truth"), {"name": "none", "kind": "none"},
                      "checkpoints")
    env = make_env(env_cfg, plan.sensors, plan.shield)
    label, policy = resolve_agent(plan.spec, env, "left_turn", "checkpoints")
    env.close()
    seeds = list(range(1_000_000, 1_000_200))
    rows = []
    for kset in (sb.KERNELS - sb.OBSERVE_KERNELS, set(sb.KERNELS)):
        with sb.using_kernels(kset):
            rows.append(run_episodes_batched(env_cfg, plan, policy, seeds, 100, label, progress=False))
    assert len(rows[0]) == len(rows[1]) == 200
    for want, got in zip(*rows):  # the same episode: its outcome and length exactly, its metrics to _numerics' REL
        assert want.keys() == got.keys()
        for k in ("seed", "collision", "success", "length", "truncated", "stopped"):
            assert want[k] == got[k], (want["seed"], k)
        for k, w in want.items():
            assert k == "agent" or _same(w, got[k]), (want["seed"], k)
    assert len({r["collision"] for r in rows[0]}) == 2 and len({r["success"] for r in rows[0]}) == 2
