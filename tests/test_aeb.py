"""Predictive AEB shield (av_gym/shields/aeb.py, av_gym/shields/predict.py): the paper's maths, the actuator, each
variant's typed parameters, and a few deterministic CCFtap cases (the whole grid is `python -m eval.ccftap`)."""

from __future__ import annotations

import functools
import itertools

import numpy as np
import pytest

from agents import AlwaysProceed
from av_gym.shields.aeb import AEB_VARIANTS, BrakeActuator
from av_gym.shields.predict import (aabb_limits, ca_predict, footprint_ttc, object_predict, paper_horizon,
                                    paper_limits, paper_ttc, setpoint_profile, standard_ttc)
from av_gym.envs.left_turn import CONFLICT_POINT
from av_gym.errors import ConfigError
from _numerics import assert_same
from conftest import Scripted, ccftap_cfg, conf, proceed_infos, rollout

KMH = 1 / 3.6


def shield(name: str = "aeb", **overrides) -> dict:
    cfg = conf("shield", name)
    cfg.update(overrides)
    return cfg


def run_case(make, ego_kmh, target_kmh, dt, shield_cfg=None, action="discrete", seed=0):
    env = make(ccftap_cfg(ego_kmh, target_kmh, dt, action=action), None, shield_cfg)
    return env, proceed_infos(env, seed)


# ----------------------------------------------------------------------------------------------- paper maths
def test_horizon_map_is_the_papers_linear_map_clamped():
    assert paper_horizon(10 * KMH) == pytest.approx(4.0)
    assert paper_horizon(15 * KMH) == pytest.approx(3.0)
    assert paper_horizon(20 * KMH) == pytest.approx(2.0)
    assert paper_horizon(12.5 * KMH) == pytest.approx(3.5)
    assert paper_horizon(0.0) == pytest.approx(4.0) and paper_horizon(5 * KMH) == pytest.approx(4.0)
    assert paper_horizon(40 * KMH) == pytest.approx(2.0)


def test_collision_limits_eqs_7_8_at_0_and_90_degrees():
    lt, wt, le, we = 4.8, 1.9, 4.4, 1.8
    dx, dy = paper_limits(0.0, lt, wt, le, we)
    assert (dx, dy) == pytest.approx((lt / 2 + le / 2, wt / 2))  # the ego half-width is missing at φ = 0
    dx, dy = paper_limits(np.pi / 2, lt, wt, le, we)
    assert (dx, dy) == pytest.approx((lt / 2, wt / 2 + we / 2))  # ... and Δy uses the half-width at 90°
    assert aabb_limits(0.0, lt, wt, le, we) == pytest.approx(((lt + le) / 2, (wt + we) / 2))
    assert aabb_limits(np.pi / 2, lt, wt, le, we) == pytest.approx((lt / 2 + we / 2, wt / 2 + le / 2))


def test_ca_prediction_literal_and_kinematic():
    x0, v0, a0 = np.array([1.0, 2.0]), np.array([3.0, -1.0]), np.array([0.5, 2.0])
    literal = ca_predict(x0, v0, a0, np.array([1.0, 2.0]))
    assert literal[0] == pytest.approx(x0 + v0 + a0)  # eqs. (2)-(3) substituted: X0 + (V0 + A0 t) t
    assert literal[1] == pytest.approx(x0 + 2 * v0 + 4 * a0)
    assert ca_predict(x0, v0, a0, np.array([1.0]), half_accel_term=True)[0] == pytest.approx(x0 + v0 + 0.5 * a0)
    # constant acceleration of another vehicle: braking to a stop, never reversing
    others = np.array([[0.0, 0.0, 10.0, 0.0, 0.0, 5.0, 2.0]])
    pos, _ = object_predict(others, np.array([1.0, 3.0]), accel=np.array([[-5.0, 0.0]]), accel_time=5.0)
    assert pos[0, 0] == pytest.approx([7.5, 0.0]) and pos[1, 0] == pytest.approx([10.0, 0.0])


def test_synthetic_head_on_ttc_paper_footprint_and_standard():
    """Ego at the origin at 5 m/s along x, target 30.5 m ahead coming back at 5 m/s: the 5 m gap between centres
    (two 5 m cars) closes at 10 m/s, so contact at 2.55 s, i.e. the 26th slice of 0.1 s."""
    size = np.array([[5.0, 2.0]])
    ttc, i = paper_ttc(np.array([[30.5, 0.0]]), np.array([5.0, 0.0]), np.zeros(2), np.array([[-5.0, 0.0]]),
                       np.zeros((1, 2)), size, (5.0, 2.0), 0.0, 0.0, horizon=4.0)
    assert ttc == pytest.approx(2.6) and i == 0
    ttc, _ = paper_ttc(np.array([[30.5, 0.0]]), np.array([5.0, 0.0]), np.zeros(2), np.array([[-5.0, 0.0]]),
                       np.zeros((1, 2)), size, (5.0, 2.0), 0.0, 0.0, horizon=2.0)
    assert ttc == np.inf  # beyond the horizon
    ttc, _ = paper_ttc(np.array([[30.5, 2.5]]), np.array([5.0, 0.0]), np.zeros(2), np.array([[-5.0, 0.0]]),
                       np.zeros((1, 2)), size, (5.0, 2.0), 0.0, 0.0, horizon=4.0)
    assert ttc == np.inf  # passing 2.5 m to the side: no collision
    t = 0.1 * np.arange(1, 41)
    others = np.array([[30.5, 0.0, -5.0, 0.0, np.pi, 5.0, 2.0]])
    xy, h = object_predict(others, t)
    ego_xy = np.stack([5.0 * t, np.zeros_like(t)], -1)
    assert footprint_ttc(ego_xy, np.zeros_like(t), (5.0, 2.0), xy, h, others[:, 5:7], t)[0] == pytest.approx(2.6)
    assert footprint_ttc(ego_xy + [0, 2.5], np.zeros_like(t), (5.0, 2.0), xy, h, others[:, 5:7], t)[0] == np.inf
    assert standard_ttc(np.zeros(2), 0.0, 5.0, (5.0, 2.0), others)[0] == pytest.approx(2.55)
    beside = others.copy()
    beside[0, 1] = 4.0  # in the next lane: not "ahead" for the standard AEB
    assert standard_ttc(np.zeros(2), 0.0, 5.0, (5.0, 2.0), beside)[0] == np.inf


def test_brake_actuator_delay_jerk_and_stopping_distance():
    act = BrakeActuator(decel=8.0, delay=0.15, jerk=30.0)
    dt = 0.05
    assert act.deceleration(0.0, dt) is None and act.deceleration(0.1, dt) is None
    assert act.deceleration(0.15, dt) == pytest.approx(1.5) and act.deceleration(1.0, dt) == pytest.approx(8.0)
    xs, vs = act.profile(5.0, 0.0, 3.0, dt)
    assert vs[2] == pytest.approx(5.0)  # nothing during the delay
    assert vs.min() == 0.0 and np.all(np.diff(vs) <= 1e-12)  # stops, never reverses
    d, t_stop = act.stopping_distance(5.0, 0.0, dt)
    assert d == pytest.approx(xs[-1]) and 5.0**2 / 16 < d < 5.0**2 / 16 + 5.0 * 0.45
    step = BrakeActuator(decel=8.0, delay=0.15, jerk=0.0)  # jerk 0: full deceleration at once, a short horizon
    d0, t0 = step.stopping_distance(5.0, 0.0, dt)
    assert 5.0**2 / 16 < d0 < d and t0 < t_stop and len(step.profile(5.0, 0.0, 3.0, dt)[0]) == 60
    with pytest.raises(ValueError, match="decel must be a number > 0, got 0.0"):
        BrakeActuator(decel=0.0)


def _stopping_distance_uncapped(act: BrakeActuator, v0: float, a_before: float, dt: float) -> tuple[float, float]:
    """BrakeActuator.stopping_distance before its ramp was capped (the full ramp decel / jerk in the horizon)."""
    if v0 <= 0:
        return 0.0, 0.0
    a_before = max(a_before, 0.0)
    ramp = 1.0 / act.jerk * act.decel if act.jerk > 0 else 0.0
    xs, vs = act.profile(v0, a_before, act.delay + ramp + (v0 + a_before * act.delay) / act.decel + 1.0, dt)
    i = int(np.argmax(vs <= 0.0)) if (vs <= 0.0).any() else len(vs) - 1
    return float(xs[i]), float((i + 1) * dt)


def test_stopping_distance_with_a_capped_ramp_gives_the_uncapped_answers(monkeypatch):
    """Over a grid of speeds, accelerations before the brake, time steps and actuators (small jerks, where the cap
    is taken, included) the answers equal the uncapped horizon's to the bit; a tiny jerk (allowed: >= 0) asks for
    a horizon just past its stop, not decel / jerk (~1.2e8 ticks, ~2 GB of arrays). Fails if the cap cuts the
    horizon before the stop."""
    capped = 0
    for decel, delay, jerk in itertools.product((3.0, 8.0), (0.0, 0.15, 0.5), (0.02, 0.5, 5.0, 30.0, 0.0)):
        act = BrakeActuator(decel=decel, delay=delay, jerk=jerk)
        for v0, a0, dt in itertools.product((0.0, 0.05, 2.0, 13.9, 35.0), (-3.0, 0.0, 2.5), (0.05, 1 / 15, 0.1)):
            assert act.stopping_distance(v0, a0, dt) == _stopping_distance_uncapped(act, v0, a0, dt), \
                (decel, delay, jerk, v0, a0, dt)
            v_peak = v0 + max(a0, 0.0) * (delay + dt)
            capped += jerk > 0 and np.sqrt(2 * v_peak / jerk) + 3 * dt < decel / jerk
    assert capped > 100  # the grid exercises the cap, not only the old horizon
    tiny = BrakeActuator(decel=8.0, delay=0.15, jerk=1e-6)
    horizons, profile = [], tiny.profile

    def bounded_profile(v0: float, a_before: float, duration: float, dt: float):
        # the horizon asked for, checked before any tick is allocated (not a wall-clock limit: a regression fails
        # here at once instead of filling memory)
        horizons.append(duration)
        assert duration < np.sqrt(2 * 30.3 / 1e-6) + 10.0, f"a horizon of {duration:.3g} s for a ~7.8e3 s stop"
        return profile(v0, a_before, duration, dt)

    monkeypatch.setattr(tiny, "profile", bounded_profile)
    d, t_stop = tiny.stopping_distance(30.0, 1.0, 1 / 15)
    assert len(horizons) == 1
    # at jerk 1e-6 the speed falls as jerk t² / 2: v_peak ≈ 30.2 m/s is lost after ~7.8e3 s
    assert np.sqrt(2 * 30.0 / 1e-6) < t_stop < np.sqrt(2 * 30.3 / 1e-6) + 2.0 and d > 30.0 * t_stop / 2


# ----------------------------------------------------------------------------------------------- CCFtap cases
def test_improved_stops_behind_the_stop_line_where_no_shield_collides(make):
    _, infos = run_case(make, 15, 45, 0.0)  # the paper's case: they would meet in the middle
    assert infos[-1]["truth"]["collision"]
    env, infos = run_case(make, 15, 45, 0.0, shield())
    m = infos[-1]["episode_metrics"]
    assert not m["collision"] and m["intervention"] == 1.0 and m["success"] == 1.0
    stages = [i["aeb_stage"] for i in infos]
    assert stages.index(1) < stages.index(2)  # warned before braking
    stop = infos[-1]["aeb_stop_position"]
    assert -1.0 < stop <= 0.0  # front bumper at or behind the stop line, not a car length before it
    assert m["stop_line_offset_at_stop_m"] == pytest.approx(stop, abs=1e-6)
    assert m["oncoming_gap_at_stop_m"] > 0.5  # in its own lane
    for key in ("aeb_stage", "aeb_ttc", "aeb_horizon", "aeb_override", "shield_override", "aeb_target_id",
                "aeb_infeasible", "aeb_stop_position", "aeb_brake_time"):
        assert key in infos[-1]


def test_large_timing_offsets_get_no_intervention(make):
    for dt in (-3.0, 3.0):
        _, infos = run_case(make, 15, 45, dt, shield())
        m = infos[-1]["episode_metrics"]
        assert not m["collision"] and m["intervention"] == 0.0 and m["success"] == 1.0


def test_continuous_actions_are_braked_too(make):
    env, infos = run_case(make, 15, 45, 0.0, shield(), action="continuous")
    m = infos[-1]["episode_metrics"]
    assert not m["collision"] and m["intervention"] == 1.0
    assert max(i["truth"]["stop_line_offset"] for i in infos if i["aeb_stage"] == 2) <= 0.0


def test_standard_aeb_does_not_prevent_the_turn_across_path_collision(make):
    _, infos = run_case(make, 10, 45, 0.0, shield("aeb_standard"))
    assert infos[-1]["truth"]["collision"]
    _, infos = run_case(make, 15, 45, 0.5, shield("aeb_standard"))
    assert infos[-1]["truth"]["collision"] and infos[-1]["episode_metrics"]["intervention"] == 0.0


def test_paper_variant_brakes_late_inside_the_intersection_and_latches(make):
    _, infos = run_case(make, 15, 45, 0.0, shield("aeb_paper", standstill_hold=0.0))
    stages = np.array([i["aeb_stage"] for i in infos])
    first = int(np.argmax(stages == 2))
    assert infos[first]["aeb_ttc"] <= 1.5
    speeds = np.array([i["truth"]["speed"] for i in infos])
    standstill = first + int(np.argmax(speeds[first:] < 0.1))
    assert np.all(stages[first:standstill + 1] == 2)  # latched until standstill, whatever the TTC did
    assert infos[first]["truth"]["stop_line_offset"] > 2.0  # only once the ego is turning: inside the box
    assert infos[-1]["aeb_stop_position"] > 4.0


def test_throttle_is_cut_while_braking(make):
    env = make(ccftap_cfg(15, 45, 0.0), None, shield())
    truths, info, *_ = rollout(env, Scripted(lambda k, o: 2), seed=0)  # the agent keeps asking for FASTER
    assert not truths[-1]["collision"] and info["episode_metrics"]["intervention"] == 1.0


def test_an_agent_that_chooses_to_stop_at_the_line_is_not_braked(make):
    """The shield checks the action it is given: an agent that asks for SLOWER (set-point 0) at the very step the
    shield would brake for the paper's case stops short of the box by itself, so the improved shield lets it;
    predicting the set-point as it was before the action (``check_action`` false), the shield brakes it anyway."""
    _, infos = run_case(make, 15, 45, 0.0, shield())
    k = [i["aeb_stage"] for i in infos].index(2)  # the step at which an always-proceeding ego is braked
    outcome = {}
    for check in (True, False):
        env = make(ccftap_cfg(15, 45, 0.0), None, shield(check_action=check))
        truths, info, *_ = rollout(env, Scripted(lambda j, o: 1 if j < k else 0), seed=0)  # IDLE, then SLOWER
        outcome[check] = info["episode_metrics"], truths
    m, truths = outcome[True]
    assert m["intervention"] == 0.0 and not truths[-1]["collision"]
    assert max(t["stop_line_offset"] for t in truths) <= 0.0  # it stopped behind the line on its own
    assert outcome[False][0]["intervention"] == 1.0 and not outcome[False][1][-1]["collision"]


def test_repeated_faster_profile_follows_the_ego_setting_off(make, turn_cfg):
    """setpoint_profile (the improved shield's prediction of an agent repeating FASTER) against the simulated ego
    setting off from a standstill through the set-points 0 → 4.5 → 9 m/s: within 0.1 m over 4 s (29 m)."""
    turn_cfg.update(spawn_probability=0.0)
    env = make(turn_cfg, None, None)
    env.reset(seed=0)
    u = env.unwrapped
    for _ in range(40):  # SLOWER until standing
        env.step(0)
    assert u.vehicle.speed < 0.05
    t = 0.1 * np.arange(1, 41)
    ego = u.vehicle
    predicted = setpoint_profile(ego.speed, lambda v: ego.index_to_speed(min(int(ego.speed_to_index(v)) + 1, 2)), t,
                                 dt=1 / u.config["simulation_frequency"])
    travelled, xy = [0.0], np.array(ego.position)
    for _ in t:  # distance driven (the route's s runs faster than the car where it cuts the turn)
        env.step(2)
        travelled.append(travelled[-1] + float(np.hypot(*(ego.position - xy))))
        xy = np.array(ego.position)
    travelled = travelled[1:]
    assert u.vehicle.speed > 8.0 and not u.vehicle.crashed  # it did climb to the top set-point
    assert np.max(np.abs(np.array(travelled) - predicted)) < 0.1


def test_driven_path_predictions_start_where_the_ego_is_all_along_the_route(make, turn_cfg):
    """DrivenPath.poses from route position s0 with no distance to drive is the ego's own place, before, inside
    and after the tabulated turn (past its end the table used to clamp: every prediction started there, 6.9 m
    behind an ego 22 m down the exit road, and the forward AEB saw the car ahead 6.9 m too far away)."""
    from av_gym.shields.aeb import _route_tables
    from av_gym.envs.left_turn import ROUTE

    env = make(turn_cfg, None, None)
    env.reset(seed=0)
    net = env.unwrapped.road.network
    route, driven = _route_tables([net.get_lane(i) for i in ROUTE])
    for s0 in (50.0, 110.0, 130.0, driven.s_end + 5.0, 180.0):
        xy, _ = driven.poses(s0, np.array([0.0, 9.0]), np.array([9.0, 9.0]))
        centre, _ = route.poses(np.array([s0, s0 + 9.0]))
        # on the straight parts the driven path is the centreline; in the turn it cuts the corner by < 1 m
        tol = 1.0 if driven.s_start < s0 < driven.s_end else 0.05
        assert np.max(np.hypot(*(xy - centre).T)) < tol, s0


@pytest.mark.slow  # 7-11 CPU-s on a clean clone: kept out of the README's 5-minute test command
def test_driven_path_kernel_equals_the_numpy_reference(make, turn_cfg):
    """The compiled driven-path look-up (av_gym/shields/kernels.py: < 1 ms per decision) against
    DrivenPath.poses_numpy, the code it replaces, on random batches over every path hypothesis of the
    intersection and the ego's route: starts before, inside (exactly at the table's start too) and past the
    tables, constant and changing speeds across the speed bins and beyond them. Floats to tests/_numerics.py's
    portable 1e-12 relative (numba's cos/sin are libm's, numpy's may be its own SIMD maths)."""
    from av_gym.shields.aeb import _route_tables
    from av_gym.envs.left_turn import ROUTE
    from av_gym.shields.conflicts import ConflictModel
    from av_gym.shields.predict import driven_poses

    env = make(turn_cfg, None, None)
    env.reset(seed=0)
    net = env.unwrapped.road.network
    model = ConflictModel(net)
    paths = [model.driven(seq) for a in net.graph for b in net.graph[a] for i in range(len(net.graph[a][b]))
             for seq, _ in model.hypotheses((a, b, i))]
    paths.append(_route_tables([net.get_lane(i) for i in ROUTE])[1])
    rng = np.random.default_rng(17)
    t = 0.1 * np.arange(1, 81)
    for trial in range(40):
        H = 12
        batch = [paths[j] for j in rng.integers(0, len(paths), H)]
        s0 = np.array([rng.uniform(-5.0, p.route.length + 20.0) for p in batch])
        if trial % 4 == 0:
            s0 = np.array([p.s_start + rng.choice([0.0, -1e-9, 1e-9]) for p in batch])
        v, a = rng.uniform(0.0, 14.0, H), rng.choice([0.0, -3.0, 1.0], H)
        ds = np.maximum.accumulate(np.maximum(v[:, None] * t + 0.5 * a[:, None] * t**2, 0.0), 1)
        speeds = np.maximum(np.diff(np.concatenate([np.zeros((H, 1)), ds], 1), axis=1) / 0.1, 0.0)
        if trial % 3 == 0:
            speeds[:] = rng.choice(np.arange(0.5, 12.01, 0.5), (H, 1))  # exactly on a bin
        xy, h = driven_poses(batch, s0, ds, speeds)
        for m, p in enumerate(batch):
            ref_xy, ref_h = p.poses_numpy(s0[m], ds[m], speeds[m])
            assert_same(xy[m], ref_xy, f"trial {trial}, object {m}: positions")
            assert_same(h[m], ref_h, f"trial {trial}, object {m}: headings")


@pytest.mark.parametrize("switch", ["DrivenPath.kernel", "FOOTPRINT_KERNEL", "conflicts.CONFLICT_KERNEL"])
def test_shield_decisions_are_the_same_with_the_kernel_and_with_numpy(make, turn_cfg, switch):
    """A traffic episode with braking and release (seed 1001), every step's decision, with the compiled driven-path
    look-up / footprint test / conflict model's choice of hypotheses and with its numpy reference (``switch``
    False: DrivenPath.poses_numpy, predict.footprint_ttc_numpy, ConflictModel._select)."""
    from av_gym.shields import conflicts, predict

    owner = {"DrivenPath.kernel": predict.DrivenPath, "FOOTPRINT_KERNEL": predict}.get(switch, conflicts)
    name = switch.split(".")[-1]
    assert getattr(owner, name) is True  # every kernel on: the run _kernel_decisions made
    setattr(owner, name, False)
    try:
        reference = _decisions(make(turn_cfg, None, shield()))
    finally:
        setattr(owner, name, True)
    compiled = _kernel_decisions()
    assert any(s[0] == 2 for s in compiled)  # it does brake
    assert compiled == reference


def _decisions(env) -> list[tuple]:
    """Every step's shield decision of AlwaysProceed's traffic episode, seed 1001."""
    policy = AlwaysProceed(env.unwrapped.cruise_action())
    obs, _ = env.reset(seed=1001)
    steps, done = [], False
    while not done:
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        steps.append((info["aeb_stage"], info["aeb_ttc"], info["aeb_target_id"], info["aeb_horizon"]))
        done = terminated or truncated
    return steps


@functools.lru_cache(maxsize=1)
def _kernel_decisions() -> list[tuple]:
    """:func:`_decisions` with every kernel on, run once a process: the three numpy references compare with it."""
    from av_gym.make import make_env

    return _decisions(make_env(conf("env", "left_turn"), None, shield()))


def test_a_car_braking_ahead_on_the_exit_road_is_braked_for(make, turn_cfg):
    """Traffic seed 1019: down the exit road the always-proceeding ego closes on a car that then brakes at 6 m/s².
    The improved shield brakes in time; it used to hold off, its feasibility check finding a car merging into the
    exit lane predicted through the standing ego 5.9 s later (the check now looks at the object braked for).
    Without indicators (``signals: false``): reading them, the shield no
    longer stops the ego at the line for that merging car's other paths, the ego reaches the exit road earlier and
    the car ahead never brakes in front of it."""
    env = make(turn_cfg, None, shield(signals=False))
    truths, info, *_ = rollout(env, AlwaysProceed(env.unwrapped.cruise_action()), seed=1019)
    m = info["episode_metrics"]
    assert not truths[-1]["collision"] and m["success"] == 1.0 and m["intervention"] == 1.0
    assert any(t["speed"] < 0.1 and t["stop_line_offset"] > 40.0 for t in truths)  # it stopped on the exit road


def test_a_crossing_car_braking_hard_in_front_is_braked_for_in_time(make, turn_cfg):
    """Traffic seed 1399: released behind the line, the always-proceeding ego enters the box
    at 7 m/s as a crossing car ahead brakes at 6 m/s². At constant speed that car's footprint only grazes the ego's
    grown one, so the emergency brake (unmargined footprints) came 0.3 s late and the ego hit it at 5 m/s; the
    emergency test now also predicts a braking road user keeping its deceleration (``emergency_accel_time``), and
    the ego stops in time and arrives. With the old rule (0) the same episode collides."""
    for accel_time, collides in ((1.5, False), (0.0, True)):
        env = make(turn_cfg, None, shield(emergency_accel_time=accel_time))
        truths, info, *_ = rollout(env, AlwaysProceed(env.unwrapped.cruise_action()), seed=1399)
        assert bool(truths[-1]["collision"]) is collides, accel_time
        assert info["episode_metrics"]["success"] == (0.0 if collides else 1.0)


def test_a_car_that_may_set_off_in_the_box_holds_the_ego_at_the_line(make, turn_cfg):
    """Traffic seed 1215: an oncoming car going straight stands in the box, creeping, as
    the unbraked always-proceeding ego comes up to the line at 9 m/s; it sets off just as the ego enters, and the
    emergency brake parks the ego in its path. Predicting a car that stands in the box after moving as possibly
    setting off (``setoff_speed``) stops the ego at the line, and it arrives; without (0) the same episode
    collides."""
    for setoff, collides in ((2.0, False), (0.0, True)):
        env = make(turn_cfg, None, shield(setoff_speed=setoff))
        truths, info, *_ = rollout(env, AlwaysProceed(env.unwrapped.cruise_action()), seed=1215)
        assert bool(truths[-1]["collision"]) is collides, setoff
        assert info["episode_metrics"]["success"] == (0.0 if collides else 1.0)


def test_the_ego_braked_in_the_box_sets_off_past_a_car_standing_there(make, turn_cfg):
    """Traffic seed 1300: braked to a standstill in the box, the ego waited for two cars
    that had collided with each other there and were sliding to a stop at ~0.5 m/s (their path hypotheses at that
    speed crossed the ego's), until the episode timed out; the release test now predicts road users slower than
    ``release_standing`` standing where they are, and the ego clears the box and arrives. With the old release (0)
    it stands there until the time-out."""
    for standing, arrives in ((1.0, True), (0.0, False)):
        env = make(turn_cfg, None, shield(release_standing=standing))
        truths, info, *_ = rollout(env, AlwaysProceed(env.unwrapped.cruise_action()), seed=1300)
        m = info["episode_metrics"]
        assert not truths[-1]["collision"]
        assert m["success"] == (1.0 if arrives else 0.0) and m["truncated"] == (0.0 if arrives else 1.0), standing


def test_feasibility_check_does_not_park_the_ego_in_the_targets_path(make):
    """The ego is 3 m before the conflict point at 15 km/h and the target 18 m away: both carrying on and braking
    end in a collision, braking with the ego standing in the oncoming lane; the improved variant does not brake
    there (the flag says why), with the check switched off it does."""
    decisions = {}
    for feasibility in (True, False):
        env = make(ccftap_cfg(15, 45, 0.0), None, shield(feasibility=feasibility))
        env.reset(seed=0)
        u, aeb = env.unwrapped, env.env
        s_conflict = aeb.route.starts[1] + u.route.lanes[1].local_coordinates(CONFLICT_POINT)[0]
        xy, h = aeb.route.poses(np.array([s_conflict - 3.0]))
        u.vehicle.position, u.vehicle.heading, u.vehicle.speed = xy[0].copy(), float(h[0]), 15 * KMH
        u.vehicle.on_state_update()
        u.ccftap_target.position = CONFLICT_POINT - np.array([0.0, 18.0])
        stage, ttc, _, _, _, infeasible = aeb._decide()
        decisions[feasibility] = (stage, infeasible)
        assert ttc <= 1.5
    assert decisions[True] == (1, True) and decisions[False] == (2, False)


def test_perceived_mode_with_its_own_detector_and_tracker(make):
    cfg = shield(mode="perceived")
    env, infos = run_case(make, 15, 45, 0.0, cfg)
    aeb = env.env
    assert aeb.detector is not None and aeb.tracker is not None and len(aeb.tracker.tracks()) >= 1
    m = infos[-1]["episode_metrics"]
    assert not m["collision"] and m["intervention"] == 1.0 and infos[-1]["aeb_stop_position"] <= 0.0
    # the agent's observation is untouched: no detector key appears for a truth-sensor agent
    assert set(env.observation_space.spaces) == {"state"}


def test_same_seed_same_decisions(make):
    cfg = shield(mode="perceived")
    runs = []
    for _ in range(2):
        _, infos = run_case(make, 20, 30, 0.5, cfg, seed=3)
        runs.append([(i["aeb_stage"], i["aeb_ttc"], i["truth"]["speed"]) for i in infos])
    assert runs[0] == runs[1]
    _, infos = run_case(make, 20, 30, 0.5, cfg, seed=4)
    assert [(i["aeb_stage"], i["aeb_ttc"], i["truth"]["speed"]) for i in infos] != runs[0]


def test_traffic_episode_runs_and_counts_interventions(make, turn_cfg):
    env = make(turn_cfg, None, shield())
    truths, info, *_ = rollout(env, AlwaysProceed(1), seed=1002)
    m = info["episode_metrics"]
    assert {"intervention", "override_fraction", "first_override_s"} <= set(m)


def test_bad_shield_config_names_the_field(make, turn_cfg, lane_cfg):
    with pytest.raises(ConfigError, match=r"shield.variant must be one of \['paper', 'improved', 'standard'\]"):
        make(turn_cfg, None, shield(variant="magic"))
    with pytest.raises(ConfigError, match="shield.horizon_max is not|shield.bogus is not a parameter"):
        make(turn_cfg, None, shield(bogus=1))
    with pytest.raises(ConfigError, match="shield.detector.miss_rate"):
        make(turn_cfg, None, shield(mode="perceived", detector={"miss_rate": 1.5}))
    with pytest.raises(ConfigError, match="left_turn scenario only"):
        make(lane_cfg, None, shield())


def test_each_variant_takes_only_the_fields_it_reads(make, turn_cfg):
    """Per-variant Params: a field another variant reads is refused, naming the variant; a partial detector
    section is completed from the shield's own defaults and the tracker's noise follows the detector's."""
    with pytest.raises(ConfigError, match=r"shield.margin is not a parameter of the AEB shield's paper variant"):
        make(turn_cfg, None, shield("aeb_paper", margin=0.5))
    with pytest.raises(ConfigError, match=r"shield.step is not a parameter of the AEB shield's standard variant"):
        make(turn_cfg, None, shield("aeb_standard", step=0.1))
    with pytest.raises(ConfigError, match=r"shield.horizon_max \(1.0\) must be >= shield.horizon_min \(2.0\)"):
        make(turn_cfg, None, shield(horizon_max=1.0))
    improved = AEB_VARIANTS.get("improved")
    p = improved.Params.from_mapping({"mode": "perceived", "detector": {"sigma_vel": 1.0}})
    assert (p.detector.miss_rate, p.detector.burst_length, p.detector.max_range) == (0.3, 5.0, 150.0)
    assert p.tracker.sigma_vel == 1.0 and p.tracker.sigma_acc == 2.0
    assert improved.Params.from_mapping({"detector": {"sigma_vel": 1.0}, "tracker": {"sigma_vel": 0.7}}) \
        .tracker.sigma_vel == 0.7
    for name in AEB_VARIANTS:  # the Hydra defaults (conf/shield/aeb*.yaml start from them) are valid as they are
        cls = AEB_VARIANTS.get(name)
        assert cls.config_problems({"variant": name, **cls.config_defaults()}) == []


def test_ccftap_cli_writes_tables_and_figures(tmp_path):
    from eval.ccftap import main

    rc = main(["--variants", "none,improved", "--modes", "ground_truth", "--ego", "15", "--target", "45",
               "--dts", "0,3", "--workers", "1", "--plot-case", "15,45,0", "--out", str(tmp_path)])
    assert rc == 0
    for name in ("results.csv", "results.md", "grid.png", "timeline.png"):
        assert (tmp_path / name).is_file()
    md = (tmp_path / "results.md").read_text()
    assert "| improved | ground_truth | 2 | 0 |" in md and "| none | - | 2 | 1 |" in md
