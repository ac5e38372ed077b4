"""The AEB shield's shortcuts that give the same decision without the full work: the stop-line trigger's bound on
the stopping distance, the kept long-prediction times and go_profile's kept decay."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from av_gym.shields.actuator import BrakeActuator
from av_gym.shields.aeb_improved import GO_TAU, ImprovedAEB, _go_rise, long_times
from av_gym.shields.aeb_params import ImprovedParams
from av_gym.shields.predict import go_profile


def test_the_stopping_bound_is_never_below_the_stopping_distance():
    """Over random speeds, accelerations before the brake, time steps and actuators (delay, jerk, a step
    included), the bound holds; and it is not vacuous (within 3x of the distance at speed). Fails with the
    delay's acceleration, the ramp or the ticks' terms left out of the bound."""
    rng = np.random.default_rng(7)
    ratios = []
    for _ in range(1500):
        act = BrakeActuator(decel=float(rng.uniform(2.0, 10.0)), delay=float(rng.choice([0.0, 0.1, 0.15, 0.3, 0.5])),
                            jerk=float(rng.choice([0.0, 5.0, 30.0, 100.0])))  # 0: a step (BrakeParams)
        v0, a0 = float(rng.choice([0.0, rng.uniform(0, 0.2), rng.uniform(0, 30)])), float(rng.uniform(-6, 6))
        dt = float(rng.choice([0.05, 0.1, 1 / 15]))
        d, _ = act.stopping_distance(v0, a0, dt)
        bound = act.stopping_bound(v0, a0, dt)
        assert d <= bound, (v0, a0, dt, act.params, d, bound)
        if v0 > 5:
            ratios.append(bound / d)
    assert max(ratios) < 3.0


def _scene(v, a, front_to_line):
    return SimpleNamespace(in_turn=True, front_to_line=front_to_line, v=v, a=a)


def test_the_trigger_point_with_the_bound_is_the_trigger_point_without_it():
    """ImprovedAEB._at_trigger_point (the bound first, the answer kept in the scene) against the rule itself
    (``front_to_line <= d_stop + v step + stop_margin``) on random scenes around the boundary and far from it."""
    p = ImprovedParams()
    shield = SimpleNamespace(actuator=BrakeActuator(p.brake), p=p, sim_dt=0.05)
    rng = np.random.default_rng(3)
    hits = skipped = 0
    for _ in range(4000):
        v, a = float(rng.uniform(0, 16)), float(rng.uniform(-4, 4))
        d_stop, _ = shield.actuator.stopping_distance(v, a, shield.sim_dt)
        edge = d_stop + v * p.step + p.stop_margin
        front = float(rng.choice([edge, np.nextafter(edge, np.inf), np.nextafter(edge, -np.inf),
                                  rng.uniform(0, 60), edge * rng.uniform(1.0, 1.05)]))
        want = front <= edge
        sc = _scene(v, a, front)
        assert ImprovedAEB._at_trigger_point(shield, sc) is want or ImprovedAEB._at_trigger_point(shield, sc) == want
        assert sc.at_trigger == want and ImprovedAEB._at_trigger_point(shield, sc) == want  # kept: asked again
        hits += want
        skipped += front > shield.actuator.stopping_bound(v, a, shield.sim_dt) + v * p.step + p.stop_margin
    assert hits > 500 and skipped > 500


def test_the_kept_long_times_and_go_decay_are_the_computed_ones():
    """long_times returns one array per parameters, equal to the expression; go_profile with the kept decay is
    go_profile without it bit for bit."""
    p = ImprovedParams()
    t = long_times(p)
    assert long_times(ImprovedParams()) is t
    ref = p.step * np.arange(1, int(round(max(p.horizon_max, 4.0 + p.horizon_min) / p.step)) + 1)
    assert t.tobytes() == ref.tobytes()
    other = ImprovedParams(horizon_max=9.0)
    assert len(long_times(other)) != len(t)
    rng = np.random.default_rng(1)
    for _ in range(200):
        v0, v_set = float(rng.uniform(0, 15)), float(rng.uniform(0, 15))
        assert go_profile(v0, v_set, t, GO_TAU, _go_rise(p)).tobytes() == go_profile(v0, v_set, t).tobytes()
