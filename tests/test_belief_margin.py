"""The planner's clearance margin (BeliefLookaheadParams.track_margin): in its futures the ego crashes where another
road user comes within the margin of its box (kernels._near_ego_row, on the compiled tick and on the numpy path
alike); the real engine, whose margin is 0, keeps the contact test alone, and others-vs-others pairs too."""

from __future__ import annotations

import numpy as np
import pytest

from agents.belief import BeliefLookaheadParams, BeliefPlanner
from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
from av_gym.errors import ConfigError
from av_gym.sim import batched
from av_gym.sim import kernels
from av_gym.sim.batched import LENGTH, WIDTH, Traffic
from av_gym.wrappers import GO, YIELD

SENSORS = {"name": "turn_truth", "turn_signals": {}, "turn_features": {"source": "truth"}, "turn_intent": {},
           "observe": ["turn", "intent"]}
B = 12


def _side_by_side(tables, gap: float, margin: float, ahead: bool = False, turn: float = 0.0) -> Traffic:
    """Two rows of three standing cars, no controller (plain): slot 0 the ego, slot 1 beside it with ``gap`` m
    between the boxes' long sides (``ahead``: in front of it, ``gap`` m between bumpers), slot 2 beyond slot 1 at
    the same gap (a pair of others); every car's heading the lane's plus ``turn`` rad, the row laid out along it.
    The real engine's traffic but for ``margin``."""
    t = Traffic(tables, 2, N=3, ego_margin=margin)
    x0, y0, h0 = tables.pose(0, 20.0)
    h = h0 + turn
    ux, uy = (np.cos(h), np.sin(h)) if ahead else (-np.sin(h), np.cos(h))  # along the row
    step = (LENGTH if ahead else WIDTH) + gap
    for j in range(3):
        t.alive[:, j], t.plain[:, j], t.ego[:, j] = True, True, j == 0
        t.x[:, j], t.y[:, j], t.h[:, j] = x0 + j * step * ux, y0 + j * step * uy, h
    t.lane[:] = t.tlane[:] = tables.closest(t.x.ravel(), t.y.ravel(), t.h.ravel()).reshape(2, 3)
    return t


@pytest.fixture(scope="module")
def tables():
    from av_gym.batched.left_turn import BatchedLeftTurn
    from av_gym.make import highway_config

    return BatchedLeftTurn(1, highway_config({"name": "left_turn"})[1]).T


@pytest.mark.parametrize("path", ["tick", "numpy"])
@pytest.mark.parametrize("ahead, turn", [(False, 0.0), (True, 0.0), (False, 0.6), (True, -0.9)])
def test_a_half_metre_near_miss_crashes_the_ego_at_margin_1_not_at_0(tables, path, ahead, turn):
    """Beside or ahead of the ego, the row along the lane or turned off it (the box's rotation, both ways)."""
    def run(margin: float) -> np.ndarray:
        t = _side_by_side(tables, 0.5, margin, ahead, turn)
        if path == "tick":
            t.advance(1 / 15, 3)
        else:
            with batched.using_kernels(set()):
                for _ in range(3):
                    t.act()
                    t.step(1 / 15)
        return t.crashed

    assert not run(0.0).any()  # 0.5 m apart: no contact
    near = run(1.0)
    # the ego only: its neighbour, and the pair of others 0.5 m apart, keep the contact test
    assert near[:, 0].all() and not near[:, 1:].any(), near
    assert not run(0.4).any()  # a margin short of the gap: no crash
    # a future's margin never reaches an engine of margin 0 run after it (the shared tick parameters)
    assert not run(0.0).any() and batched._TICK_PARAMS[kernels.P_EGO_MARGIN] == 0.0


@pytest.fixture(scope="module")
def scene():
    """B episodes 25 env steps at the line under YIELD, traffic crossing; planners reading every indicator: no
    margin, 1.5 m at every decision, 1.5 m for a GO to start only."""
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, SENSORS, None, B, pool=0)
    obs = venv.play(iter(range(1_200_000, 1_200_000 + B)))
    planners = [BeliefPlanner(BeliefLookaheadParams(samples=8, **kw), n_rows=B) for kw in (
        {}, {"track_margin": 1.5}, {"track_margin": 1.5, "track_margin_scope": "start"})]
    for _ in range(25):
        live = np.nonzero(~venv.idle)[0]
        for p in planners:
            p.read(venv.engine, live, obs["intent"][live])
        obs, _, _, _ = venv.step(meta_actions(np.full(B, YIELD), obs["turn"]))
    return venv.engine, planners, np.nonzero(~venv.idle)[0]


def test_the_margin_reaches_the_futures_not_the_real_engine(scene):
    engine, (plain, wide, _), rows = scene
    before = {name: getattr(engine.traffic, name).copy() for name in Traffic.FIELDS}
    p0, p1 = plain.go_collision(engine, rows), wide.go_collision(engine, rows)
    for name, value in before.items():  # the real engine: untouched, its margin 0
        np.testing.assert_array_equal(getattr(engine.traffic, name), value, err_msg=name)
    assert engine.traffic.ego_margin == 0.0
    # the same futures until the first near miss, which comes no later than a contact: never fewer collisions
    assert (p1 >= p0).all() and (p1 > p0).any(), (p0, p1)
    f = wide.futures(engine, rows[:2], 2)
    assert f.traffic.ego_margin == 1.5 and f.keep([0]).traffic.ego_margin == 1.5


def test_scope_start_keeps_a_held_go_on_contact_alone(scene):
    engine, (plain, wide, start), rows = scene
    held = np.where(np.arange(len(rows)) % 2 == 0, GO, YIELD)
    p = start._decision_collision(engine, rows, held)
    p0, p1 = plain.go_collision(engine, rows), wide.go_collision(engine, rows)
    np.testing.assert_array_equal(p, np.where(held == GO, p0, p1))
    assert (p0 != p1)[held == YIELD].any()  # the starting rows did get the margin


def test_a_bad_margin_is_one_clear_error():
    with pytest.raises((ConfigError, ValueError), match="track_margin"):
        BeliefLookaheadParams(track_margin=-1.0)

