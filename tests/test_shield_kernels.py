"""The AEB shield's compiled footprint test (av_gym/shields/kernels.py ``footprint_hit``, behind
:func:`av_gym.shields.predict.footprint_ttc`) against its numpy reference (``footprint_ttc_numpy``): the same first hit
(slice and other) on random scenes, on boxes exactly touching, with and without the rear rule (the same decisions over
a shielded episode: tests/test_aeb.py); the brake actuator's compiled profile (``brake_profile``)."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.shields.predict import footprint_ttc, footprint_ttc_numpy


def _times(t: np.ndarray) -> np.ndarray:
    """A time grid (s) as the shield hands it to its kernels: read-only (aeb_improved.long_times), so that a test
    calls the specialization the shield compiles (numba types read-only arrays apart), not one of its own."""
    t.flags.writeable = False
    return t


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


@pytest.mark.parametrize("speeds_kmh", [(0.0, 16.2, 32.4), (0.0, 10.0, 20.0, 30.0, 40.0)])
def test_the_setpoint_kernel_is_the_reference_with_mdpvehicles_set_points(speeds_kmh):
    """setpoint_steps (compiled: kernels.setpoint_ticks) equals setpoint_profile with highway-env's MDPVehicle.act
    for a repeated FASTER / SLOWER as ``set_at`` (speed_to_index's rounding of the nearest set-point, clipped), bit
    for bit, from speeds between and exactly on the set-points (rounding ties) and beyond them."""
    from highway_env.vehicle.controller import MDPVehicle

    from av_gym.shields.predict import setpoint_profile, setpoint_steps

    class Ego:  # MDPVehicle's set-point arithmetic on its own target speeds
        speed_to_index, index_to_speed = MDPVehicle.speed_to_index, MDPVehicle.index_to_speed

    ego = Ego()
    ego.target_speeds = np.array(speeds_kmh) / 3.6
    top, rng = len(ego.target_speeds) - 1, np.random.default_rng(11)
    halfway = 0.5 * (ego.target_speeds[:-1] + ego.target_speeds[1:])
    starts = np.concatenate([rng.uniform(0.0, 1.2 * ego.target_speeds[-1], 150), ego.target_speeds, halfway])
    t = _times(0.1 * np.arange(1, 81))
    for v0 in starts:
        for step in (1, -1):
            want = setpoint_profile(v0, lambda v: float(ego.index_to_speed(  # noqa: B023
                int(np.clip(int(ego.speed_to_index(v)) + step, 0, top)))), t, dt=0.05)  # noqa: B023
            got = setpoint_steps(v0, ego.target_speeds, step, t, dt=0.05)
            assert np.array_equal(got, want), (v0, step)


def _objects_on_lanes(rng: np.random.Generator, net, M: int):
    """M road users on the intersection's lanes: most near a lane (some beyond the on-lane distance or heading
    30° off it, some before or past its ends), some standing or at exactly 0.5 m/s, a few off the map (lane None)."""
    lanes = [(a, b, i) for a, to in net.graph.items() for b, ls in to.items() for i in range(len(ls))]
    others, lane_indices = np.zeros((M, 7)), []
    for m in range(M):
        li = lanes[rng.integers(len(lanes))]
        lane = net.get_lane(li)
        s = rng.uniform(-5.0, lane.length + 5.0)
        xy = lane.position(s, rng.normal(0.0, 1.5))
        h = lane.heading_at(s) + rng.choice([rng.normal(0.0, 0.3), np.radians(30) * rng.choice([-1, 1]), 3.0])
        speed = rng.choice([rng.uniform(0.0, 14.0), 0.5, 0.0, 0.49])
        others[m] = (*xy, speed * np.cos(h), speed * np.sin(h), h, 5.0, 2.0)
        lane_indices.append(None if rng.random() < 0.1 else li)
    return others, lane_indices


def test_the_conflict_kernel_chooses_the_references_hypotheses():
    """ConflictModel.predict in one compiled call (kernels.conflict_predict: the compiled choice of hypotheses,
    kernels.conflict_hypotheses, then the profiles, the driven-path look-ups and the constant-velocity objects) and
    with the Python reference of the choice (ConflictModel._select, then along_many and the look-ups one call
    each): the same positions, headings, owners, map flags and probabilities,
    bit for bit (the kernel takes numpy's hypot and arctan2 and computes np.dot's 2-vector sum as this machine's
    BLAS does, fused or not), on random road users on and off the intersection's lanes, some exactly at the
    thresholds (0.5 m/s, 30° off the lane), with and without indicator readings (some ruling a turn out, so
    hypotheses under min_p are dropped), braking and speeding up."""
    from av_gym.envs.left_turn import UnprotectedLeftTurnEnv
    from av_gym.shields import conflicts
    from av_gym.shields.conflicts import ConflictModel

    env = UnprotectedLeftTurnEnv()
    env.reset(seed=3)
    net = env.unwrapped.road.network
    rng = np.random.default_rng(7)
    t = _times(0.1 * np.arange(1, 81))
    seen = {"dropped": 0, "cv": 0, "map": 0}
    for trial in range(300):
        model = ConflictModel(net, min_p=(0.1, 0.3)[trial % 2], accel_time=(0.0, 1.5)[trial % 3 == 0])
        M = int(rng.integers(0, 25))
        others, lane_indices = _objects_on_lanes(rng, net, M)
        accels = rng.normal(0.0, 2.0, (M, 2))
        intent = None
        if trial % 4:
            intent = rng.dirichlet(np.ones(3), M) * rng.choice([1.0, 0.0], (M, 3), p=[0.8, 0.2])
            intent[rng.random(M) < 0.3] = np.nan
            intent[intent.sum(1) == 0] = np.nan
        outs = []
        for kernel in (True, False):
            conflicts.CONFLICT_KERNEL = kernel
            try:
                outs.append(model.predict(others, lane_indices, accels, t, intent))
            finally:
                conflicts.CONFLICT_KERNEL = True
        for got, want in zip(*outs):  # weights that rule out every continuation: uniform in both (test_conflicts)
            np.testing.assert_array_equal(got, want, err_msg=f"trial {trial}", strict=True)
        is_map, prob = outs[0][3], outs[0][4]
        seen["map"] += int(is_map.sum())
        seen["cv"] += int((~is_map).sum())
        seen["dropped"] += int(np.any(prob[is_map] < 0.5) and intent is not None)
    assert min(seen.values()) > 20, seen


def test_the_along_path_kernel_is_along_many_and_profile_speeds():
    """kernels.along_profiles equals ConflictModel.along_many (distances along a path, braking ones stopping) and
    profile_speeds of each row (the speeds the driven paths are looked up at), bit for bit: accelerating, braking
    to a stop inside and after the acceleration time, standing, and on time grids with a repeated time."""
    from av_gym.shields.conflicts import ConflictModel
    from av_gym.shields.kernels import along_profiles
    from av_gym.shields.predict import profile_speeds

    rng = np.random.default_rng(13)
    for trial in range(200):
        M = int(rng.integers(1, 30))
        v = rng.choice([0.0, 0.5, 3.0, rng.uniform(0.0, 14.0)], M) + rng.uniform(0.0, 1.0, M) * (trial % 2)
        a = rng.choice([0.0, -6.0, 2.0, rng.normal(0.0, 3.0)], M)
        t = _times(0.1 * np.arange(1, 81) if trial % 5 else np.sort(rng.choice(0.1 * np.arange(1, 30), 40)))
        model = ConflictModel.__new__(ConflictModel)
        model.accel_time = (0.0, 1.5, 3.0)[trial % 3]
        dist, speed = along_profiles(v, a, t, model.accel_time)
        want = model.along_many(v, a, t)
        np.testing.assert_array_equal(dist, want, err_msg=f"trial {trial}", strict=True)
        for m in range(M):
            np.testing.assert_array_equal(speed[m], profile_speeds(want[m], t, v[m]), err_msg=f"trial {trial}")


def test_the_driven_ttc_kernel_is_the_poses_then_the_footprint_test():
    """predict.driven_ttc (one compiled call: kernels.driven_ttc) equals what the shield computed before it, the
    ego's poses along its driven path (DrivenPath.poses at profile_speeds) then footprint_ttc, bit for bit, and the
    numpy references of both (poses_numpy, footprint_ttc_numpy): the same first hit (time and other), on the ego's
    route and on other paths, from before, inside and past the driven tables, accelerating, braking to a stop and
    standing, with margins and the rear rule, others placed so that first hits fall all over the horizon."""
    from av_gym.envs.left_turn import ROUTE, UnprotectedLeftTurnEnv
    from av_gym.shields import predict
    from av_gym.shields.aeb import _route_tables
    from av_gym.shields.conflicts import ConflictModel
    from av_gym.shields.predict import driven_ttc, profile_speeds

    env = UnprotectedLeftTurnEnv()
    env.reset(seed=3)
    net = env.unwrapped.road.network
    model = ConflictModel(net)
    paths = [_route_tables([net.get_lane(i) for i in ROUTE])[1]] * 4
    paths += [model.driven(seq) for a in net.graph for b in net.graph[a] for i in range(len(net.graph[a][b]))
              for seq, _ in model.hypotheses((a, b, i))][::7]
    rng = np.random.default_rng(19)
    hits = set()
    for trial in range(400):
        path = paths[rng.integers(len(paths))]
        K = int(rng.integers(1, 81))
        t = _times(0.1 * np.arange(1, K + 1))
        v, a = float(rng.choice([0.0, rng.uniform(0.0, 14.0)])), float(rng.choice([0.0, -4.0, 1.5]))
        ds = np.maximum.accumulate(np.maximum(v * t + 0.5 * a * t**2, 0.0))
        s0 = float(rng.uniform(-5.0, path.route.length + 10.0)) if trial % 5 else path.s_start
        M = int(rng.integers(1, 5))
        ego_xy, _ = path.poses_numpy(s0, ds, profile_speeds(ds, t, v))
        meet = rng.integers(0, K, M)  # each other near the ego's pose at a random slice, drifting there
        oxy = ego_xy[meet][None] + rng.normal(0.0, 2.0, (1, M, 2)) + rng.normal(0.0, 1.0, (1, M, 2)) * \
            (np.arange(K)[:, None, None] - meet[None, :, None])
        oh = rng.uniform(-np.pi, np.pi, (1, M)) + np.zeros((K, 1))
        size, margin = rng.uniform(2.0, 6.0, (M, 2)), (0.0, 0.3, 0.6)[trial % 3]
        rear = rng.random(M) < 0.5 if trial % 2 else False
        got = driven_ttc(path, s0, ds, t, (5.0, 2.0), oxy, oh, size, margin, rear)
        before = predict.footprint_ttc(*path.poses(s0, ds, profile_speeds(ds, t, v)), (5.0, 2.0), oxy, oh, size, t,
                                       margin, rear)
        reference = predict.footprint_ttc_numpy(*path.poses_numpy(s0, ds, profile_speeds(ds, t, v)), (5.0, 2.0),
                                                oxy, oh, size, t, margin, rear)
        assert got == before == reference, trial
        hits.add(got[0])
    assert len(hits) > 30 and np.inf in hits  # first hits all over the horizon, and misses


def _decisions(net, rng: np.random.Generator, sizes: tuple[int, ...], own: int):
    """Road users of ``len(sizes)`` decisions for ConflictModel.predict_rows, ``sizes[r]`` in decision r (0: none),
    on and off the intersection's lanes, standing and moving at most 3 m/s, some with indicator readings; decision
    ``own``'s last road user alone drives 11 m/s along an approach lane towards the box, so its driven paths read
    speed bins no other decision reads. Concatenated as predict_rows takes them: others (M, 7), lane indices,
    accelerations (M, 2) m/s², turn weights (M, 3), row offsets (len(sizes) + 1,)."""
    others, lanes = _objects_on_lanes(rng, net, sum(sizes))
    speed = np.hypot(others[:, 2], others[:, 3])
    others[:, 2:4] *= np.minimum(1.0, 3.0 / np.maximum(speed, 1e-9))[:, None]  # standing ones stay standing
    row_off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    m = row_off[own + 1] - 1
    lanes[m] = ("o1", "ir1", 0)
    lane = net.get_lane(lanes[m])
    h = lane.heading_at(lane.length - 5.0)
    others[m] = (*lane.position(lane.length - 5.0, 0.0), 11.0 * np.cos(h), 11.0 * np.sin(h), h, 5.0, 2.0)
    intent = rng.dirichlet(np.ones(3), len(others)) * rng.choice([1.0, 0.0], (len(others), 3), p=[0.8, 0.2])
    intent[(rng.random(len(others)) < 0.3) | (intent.sum(1) == 0)] = np.nan
    return others, lanes, rng.normal(0.0, 2.0, (len(others), 2)), intent, row_off


def _own_calls(model, decisions, t: np.ndarray, rows) -> list:
    """ConflictModel.predict of each decision in ``rows`` on its own slices (simulating the speed bins it reads)."""
    others, lanes, accels, intent, row_off = decisions
    return [model.predict(others[a:b], lanes[a:b], accels[a:b], t, intent[a:b])
            for a, b in (row_off[r: r + 2] for r in rows)]


def _assert_bit_equal(got: tuple, want: tuple, what: str) -> None:
    """Positions, headings, owners, map flags and probabilities: the same dtype, shape and bytes."""
    assert len(got) == len(want) == 5, what
    for a, b in zip(got, want):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), what


@pytest.fixture
def fresh_paths(monkeypatch):
    """A fresh store of driven-path tables and fresh driven paths (no speed bin simulated yet), this test's only."""
    import weakref

    from av_gym.envs.left_turn import UnprotectedLeftTurnEnv
    from av_gym.shields import conflicts, predict

    monkeypatch.setattr(predict, "_STORE", None)
    monkeypatch.setattr(conflicts, "_DRIVEN", {})
    monkeypatch.setattr(conflicts, "_BY_NETWORK", weakref.WeakKeyDictionary())
    env = UnprotectedLeftTurnEnv()
    env.reset(seed=3)
    return env.unwrapped.road.network


SIZES = (3, 0, 4, 2, 2)  # road users per decision: one decision without any


def test_the_rows_kernel_is_each_decisions_own_call_and_leaves_missing_speed_bins_to_it(fresh_paths):
    """ConflictModel.predict_rows (kernels.conflict_predict_rows: many decisions in one call) gives each decision
    exactly its own ConflictModel.predict (positions, headings, owners, map flags, probabilities, bit for bit),
    decisions of different sizes and one without road users; a decision reading a speed bin that is not simulated
    yet gets None (its shield's own call simulates it) and the decisions after it are still their own. Fails if
    a decision reads another's road users, lanes, accelerations or weights, or the flat buffers are cut wrongly."""
    from av_gym.shields.conflicts import ConflictModel

    model, t = ConflictModel(fresh_paths, min_p=0.1), _times(0.1 * np.arange(1, 81))
    decisions = _decisions(fresh_paths, np.random.default_rng(23), SIZES, own=3)
    args = (decisions[0], decisions[4], decisions[1], decisions[2], t, decisions[3])
    want = _own_calls(model, decisions, t, [0, 1, 2, 4])  # all but decision 3's speed bins simulated
    got = model.predict_rows(*args)
    assert [g is None for g in got] == [False, False, False, True, False]
    for r, w in zip([0, 1, 2, 4], want):
        _assert_bit_equal(got[r], w, f"decision {r}")
    want.insert(3, _own_calls(model, decisions, t, [3])[0])  # now simulated: the kernel serves it too
    got = model.predict_rows(*args)
    for r, (g, w) in enumerate(zip(got, want)):
        _assert_bit_equal(g, w, f"decision {r}")
    assert sum(int(w[3].sum()) for w in want) > 5 and sum(int((~w[3]).sum()) for w in want) > 2  # map and cv



@pytest.mark.parametrize("short", [1, 0])
def test_a_decision_with_more_hypotheses_than_its_block_is_left_to_its_own_call(fresh_paths, monkeypatch, short):
    """The rows kernel writes each decision into a block of the flat buffers sized in Python (kernels do not check
    bounds): a decision whose hypotheses outgrow its block (here one ``short``er than them) gets None, as a missing
    speed bin does (its shield's own call serves it), instead of spilling into the next decision's block; one that
    fills its block exactly is served. The others are their own calls bit for bit."""
    from av_gym.shields import conflicts
    from av_gym.shields.conflicts import ConflictModel

    model, t = ConflictModel(fresh_paths, min_p=0.1), _times(0.1 * np.arange(1, 81))
    decisions = _decisions(fresh_paths, np.random.default_rng(29), SIZES, own=3)
    want = _own_calls(model, decisions, t, range(len(SIZES)))
    blocks = conflicts._row_blocks

    def smaller(reg, lane_row, row_off):
        size = np.diff(blocks(reg, lane_row, row_off))
        size[2] = len(want[2][2]) - short  # decision 2's block: its hypotheses, less ``short``
        return np.concatenate([[0], np.cumsum(size)]).astype(np.int64)

    monkeypatch.setattr(conflicts, "_row_blocks", smaller)
    got = model.predict_rows(decisions[0], decisions[4], decisions[1], decisions[2], t, decisions[3])
    assert [g is None for g in got] == [False, False, bool(short), False, False]
    for r, (g, w) in enumerate(zip(got, want)):
        if g is not None:
            _assert_bit_equal(g, w, f"decision {r}")


def test_the_driven_ttc_rows_kernel_is_each_decisions_own_driven_ttc():
    """kernels.driven_ttc_rows (the batch's first TTC of many decisions in one call, BatchedShield._screen) gives
    each decision exactly predict.driven_ttc on its own slices of flat buffers laid out as ConflictModel.predict_rows
    writes them (each decision a block, its hypotheses first, slack after): the same first hit (slice and
    hypothesis) or none, for decisions with several hypotheses, none, no slice, or not served (n_h -1: nothing
    tested), random route positions, speeds, horizons, margins, sizes and rear flags. Fails if a decision reads
    another's block, sizes, reach or flags, or its slices are cut wrongly."""
    from av_gym.envs.left_turn import ROUTE, UnprotectedLeftTurnEnv
    from av_gym.shields.aeb import _route_tables
    from av_gym.shields.kernels import driven_ttc_rows
    from av_gym.shields.predict import DRIVEN_SPEEDS, _footprint_args, _store, driven_ttc, profile_speeds

    env = UnprotectedLeftTurnEnv()
    env.reset(seed=3)
    net = env.unwrapped.road.network
    path = _route_tables([net.get_lane(i) for i in ROUTE])[1]
    path._register()
    t, K = _times(0.1 * np.arange(1, 81)), 80
    rng = np.random.default_rng(31)
    hits, misses = 0, 0
    for trial in range(30):
        R = 6
        n_h = rng.integers(0, 5, R)
        n_h[int(rng.integers(0, R))] = 0  # a decision without hypotheses
        h_off = np.concatenate([[0], np.cumsum(n_h + rng.integers(0, 3, R))]).astype(np.int64)  # slack after each
        s0 = rng.uniform(path.s_start - 20.0, path.route.length, R)
        v, a = rng.uniform(0.0, 6.0, R), rng.choice([0.0, -3.0, 1.0], R)
        ds = np.maximum.accumulate(np.maximum(v[:, None] * t + 0.5 * a[:, None] * t ** 2, 0.0), axis=1)
        n = rng.integers(1, 81, R)
        n[int(rng.integers(0, R))] = 0  # a decision with no slice
        total = int(h_off[-1])
        xy, hh = rng.normal(0.0, 50.0, 2 * K * total), rng.uniform(-np.pi, np.pi, K * total)  # slack: anything
        for r in range(R):  # each hypothesis near the decision's ego pose at a random slice, drifting there
            o, H = int(h_off[r]), int(n_h[r])
            ego_xy, _ = path.poses_numpy(s0[r], ds[r], profile_speeds(ds[r], t, v[r]))
            meet = rng.integers(0, K, H)
            block = ego_xy[meet][None] + rng.normal(0.0, 2.0, (1, H, 2)) + rng.normal(0.0, 1.0, (1, H, 2)) * \
                (np.arange(K)[:, None, None] - meet[None, :, None])
            xy[2 * K * o: 2 * K * (o + H)] = block.reshape(-1)
        osize, rear = rng.uniform(2.0, 6.0, (total, 2)), rng.random(total) < 0.4
        n_h[int(rng.integers(0, R))] = -1  # a decision not served
        margin = float(rng.choice([0.0, 0.4]))
        length, width, fxy, fhh, osize, reach, rear = _footprint_args((5.0, 2.0), xy, hh, osize, margin, rear)
        st = _store()
        need = np.zeros((R, len(DRIVEN_SPEEDS)), dtype=np.bool_)
        for _ in range(2):  # a speed bin not simulated yet: flagged, nothing tested; simulated, then called again
            missing, k, m = driven_ttc_rows(st.data, st.route, st.limits, st.bins, st.grid_table, path.store_id, s0,
                                            ds, n, t, length, width, fxy, fhh, h_off, n_h, osize, reach, rear, need)
            for i in np.flatnonzero(need.any(axis=0)).tolist():
                path._table(i)
            need[:] = False
        assert not missing.any()
        for r, (o, H) in enumerate(zip(h_off.tolist(), n_h.tolist())):
            if H < 0:
                assert (k[r], m[r]) == (-1, -1)
                continue
            obj_xy, obj_h = xy[2 * K * o: 2 * K * (o + H)].reshape(K, H, 2), hh[K * o: K * (o + H)].reshape(K, H)
            want = driven_ttc(path, float(s0[r]), ds[r, :n[r]], t[:n[r]], (5.0, 2.0), obj_xy[:n[r]], obj_h[:n[r]],
                              osize[o: o + H], margin, rear[o: o + H])
            got = (float("inf"), -1) if k[r] < 0 else (float(t[k[r]]), int(m[r]))
            assert got == want, (trial, r)
            hits, misses = hits + (k[r] >= 0), misses + (k[r] < 0)
    assert hits > 20 and misses > 20, (hits, misses)
