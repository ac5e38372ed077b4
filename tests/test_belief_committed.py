"""``committed_choice`` (agents/belief.py): past the stop line, a decision that would YIELD chooses between carrying
on and stopping, each judged on the same futures."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from agents.belief import BeliefLookaheadParams, BeliefPlanner
from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
from av_gym.presets import compose_group
from av_gym.wrappers import GO, YIELD
from tests.test_belief_tracks import _coasting_track


class _Offsets:
    """An engine whose ego is ``offset`` m past the stop line per row (all :meth:`BeliefPlanner.carry_on` reads)."""

    def __init__(self, offset) -> None:
        self.offset = np.asarray(offset, float)

    def truth(self, rows) -> dict:
        return {"stop_line_offset": self.offset[np.asarray(rows)]}


def _planner(asked: list, p_go, p_stop, **options) -> BeliefPlanner:
    """A planner whose GO / stop collision shares are given per row instead of played; ``asked`` gets the rows of
    every stop question."""
    planner = BeliefPlanner(BeliefLookaheadParams(**options), n_rows=len(p_go))
    planner.reset(np.arange(len(p_go)))
    planner.go_collision = lambda engine, rows, K=None, stream=(): np.asarray(p_go)[np.asarray(rows)]

    def stop(engine, rows, K=None, stream=(), margin=None):
        asked.append(np.asarray(rows).tolist())
        return np.asarray(p_stop)[np.asarray(rows)]

    planner.stop_collision = stop
    return planner


def test_past_the_line_a_yield_carries_on_where_stopping_collides_more():
    """Rows holding GO: past the line (3 m) with GO at 0.25 and stopping at 0.5: carries on; past it with stopping
    at 0.125: stops (YIELD); at equal shares: stops (with ``committed_margin`` 0.01 carries on); before the line
    (-5 m): YIELD whatever stopping's share (not asked); GO safe past the line: GO (not asked); a held YIELD past
    the line at 0.25 against 0.5: goes. Off: every decision as the planner without the option, no stop question
    asked."""
    p_go = [0.25, 0.25, 0.25, 0.25, 0.0, 0.25]
    p_stop = [0.5, 0.125, 0.25, 1.0, 1.0, 0.5]
    engine = _Offsets([3.0, 3.0, 3.0, -5.0, 3.0, 3.0])
    held = np.array([GO, GO, GO, GO, GO, YIELD])
    step = np.zeros(len(held), int)
    asked: list = []
    on = _planner(asked, p_go, p_stop, committed_choice=True)
    assert on.decide(engine, np.arange(6), held, step).tolist() == [GO, YIELD, YIELD, YIELD, GO, GO]
    assert asked == [[0, 1, 2, 5]]
    asked.clear()
    off = _planner(asked, p_go, p_stop)
    assert off.decide(engine, np.arange(6), held, step).tolist() == [YIELD, YIELD, YIELD, YIELD, GO, YIELD]
    assert asked == []
    # committed_margin 0.01: a tie carries on too
    assert _planner(asked, p_go, p_stop, committed_choice=True, committed_margin=0.01).decide(
        engine, np.arange(6), held, step).tolist() == [GO, YIELD, GO, YIELD, GO, GO]
    asked.clear()
    # committed_from: only a row farther past the line than this chooses
    far = _planner(asked, p_go, p_stop, committed_choice=True, committed_from=4.0)
    assert far.decide(engine, np.arange(6), held, step).tolist() == [YIELD, YIELD, YIELD, YIELD, GO, YIELD]
    assert asked == []


def test_under_margin_scope_start_stopping_is_judged_as_the_held_go_was():
    """``track_margin_scope`` start judges a held GO on contact alone; past the line, stopping must be judged so
    too (contact against contact), a YIELD held before on the margin. Row 0 holds GO: GO collides in 0.25 of the
    futures on contact, stopping in 0.125 on contact and 0.5 with the margin: it stops (carrying on against the
    margin's 0.5 would have gone). Row 1 holds YIELD: GO 0.6 with the margin against stopping's 0.5 with it: it
    stops; its GO's 0.25 on contact would have gone against 0.5."""
    p_go = {None: np.array([0.6, 0.6]), 0.0: np.array([0.25, 0.25])}
    p_stop = {None: np.array([0.5, 0.5]), 0.0: np.array([0.125, 0.125])}
    asked: list = []
    planner = BeliefPlanner(BeliefLookaheadParams(committed_choice=True, track_margin=0.5,
                                                  track_margin_scope="start"), n_rows=2)
    planner.reset(np.arange(2))
    planner.go_collision = lambda engine, rows, K=None, stream=(), margin=None: p_go[margin][np.asarray(rows)]

    def stop(engine, rows, K=None, stream=(), margin=None):
        asked.append((np.asarray(rows).tolist(), margin))
        return p_stop[margin][np.asarray(rows)]

    planner.stop_collision = stop
    held = np.array([GO, YIELD])
    assert planner.decide(_Offsets([3.0, 3.0]), np.arange(2), held, np.zeros(2, int)).tolist() == [YIELD, YIELD]
    assert sorted(asked, key=str) == sorted([([0], 0.0), ([1], None)], key=str)


@pytest.mark.slow  # ~2.5 s: the batch on tracks driven 40 steps into the junction
def test_a_go_taken_back_inside_the_junction_carries_on_on_its_futures():
    """On tracks, the ego 2-4 m past its stop line at 9 m/s under GO, one confirmed oncoming track 15 m south of the
    junction's centre at 9 m/s. In the first row GO collides in 3 of 16 futures (taken back without the option) and
    stopping in 8 of the same 16: with ``committed_choice`` it carries on; in the second GO collides in 2 and
    stopping in 1: it stops either way."""
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, compose_group("sensors", "turn_perceived"), None, 2, pool=0)
    obs = venv.play(iter([420_001, 420_002]))
    rows, e = np.arange(2), venv.engine
    planner = BeliefPlanner(BeliefLookaheadParams(samples=16, unseen=0.0), n_rows=2, perception=venv.perception)
    while (e.truth(rows)["stop_line_offset"] <= 2.0).any():
        planner.read(e, rows, obs["intent"])
        obs, _, _, _ = venv.step(meta_actions(np.full(2, GO), obs["turn"]))
    for r in rows:
        _coasting_track(venv, int(r), (-2.0, -15.0, 0.0, 9.0), 0)
    choices, shares = {}, None
    for on in (False, True):
        p = copy.deepcopy(planner, {id(venv.perception): venv.perception, id(e): e, id(planner.tracks.engine): None})
        p.params = BeliefLookaheadParams(samples=16, unseen=0.0, committed_choice=on)
        p.read(e, rows, np.zeros_like(obs["intent"]))
        if on:
            shares = (p.go_collision(e, rows), p.stop_collision(e, rows))
        choices[on] = p.decide(e, rows, np.full(2, GO), np.zeros(2, int)).tolist()
    np.testing.assert_array_equal(shares[0], [3 / 16, 2 / 16])
    np.testing.assert_array_equal(shares[1], [8 / 16, 1 / 16])
    assert choices == {False: [YIELD, YIELD], True: [GO, YIELD]}


def test_stopping_and_go_are_asked_on_the_same_split():
    """Under ``track_margin_scope`` start, rows past the line that would YIELD: the stop question is asked of the
    same rows with the same margins as the decision's GO question (held GO on contact, held YIELD with the margin),
    for any mix of held choices: the one split serves both (a stop question asked all with the margin fails)."""
    held = np.array([GO, YIELD, YIELD, GO, GO])
    asked: dict = {"go": [], "stop": []}

    def share(kind):
        def ask(engine, rows, K=None, stream=(), margin=None):
            asked[kind] += [(int(r), margin) for r in np.asarray(rows)]
            return np.full(len(rows), 0.75)
        return ask

    planner = BeliefPlanner(BeliefLookaheadParams(committed_choice=True, track_margin=0.5,
                                                  track_margin_scope="start"), n_rows=len(held))
    planner.reset(np.arange(len(held)))
    planner.go_collision, planner.stop_collision = share("go"), share("stop")
    planner.decide(_Offsets(np.full(len(held), 3.0)), np.arange(len(held)), held, np.zeros(len(held), int))
    assert sorted(asked["go"], key=str) == sorted(asked["stop"], key=str)
    assert sorted(asked["go"], key=str) == sorted([(0, 0.0), (1, None), (2, None), (3, 0.0), (4, 0.0)], key=str)
