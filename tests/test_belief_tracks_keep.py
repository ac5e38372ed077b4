"""``keep_recheck`` (agents/belief.py BeliefPlanner.kept): a held GO its decision's K futures find unsafe is taken
back only where the pooled share of those K and ``keep_recheck`` more futures, from their own stream, is above the
threshold too; a GO to start and a held GO the K alone cannot pass are judged as before. It reads nothing but the
planner's own futures (go_collision), so the hidden-state checks of tests/test_belief_tracks.py cover its inputs."""

from __future__ import annotations

import numpy as np
import pytest

from agents.belief import KEEP_STREAM, BeliefLookaheadParams, BeliefPlanner
from av_gym.wrappers import GO, YIELD

K = 16
# held: rows 0-3 hold GO, row 4 YIELD; the decision's K futures collide in 1, 1, 3, 0 and 1 of 16
HELD = np.array([GO, GO, GO, GO, YIELD])
P = np.array([1, 1, 3, 0, 1]) / K
P_MORE = {0: 1 / 48, 1: 2 / 48}  # the 48 more futures: pooled 2 / 64 (0.031, kept) and 3 / 64 (0.047, back)


def _planner(keep: int, monkeypatch) -> tuple[BeliefPlanner, list]:
    """A planner whose decision shares are ``P`` and whose more futures collide as ``P_MORE``, recording each
    ``go_collision`` asked (rows, K, stream, margin)."""
    params = BeliefLookaheadParams(samples=K, threshold=0.045, confirm=2, confirm_risk=0.0, keep_recheck=keep)
    planner = BeliefPlanner(params, n_rows=len(HELD))
    planner.safe_run[:] = 2  # the rows holding GO started it after two safe decisions
    asked: list = []
    shares = {"p": P}
    monkeypatch.setattr(planner, "_decision_collision", lambda engine, rows, held: shares["p"][rows])

    def more(engine, rows, K=None, stream=(), margin=None):
        asked.append((list(np.asarray(rows)), K, stream, margin))
        return np.array([P_MORE[int(r)] for r in rows])

    monkeypatch.setattr(planner, "go_collision", more)
    planner.shares = shares
    return planner, asked


@pytest.mark.parametrize("keep", [0, 48])
def test_a_held_go_is_taken_back_on_the_pooled_share(keep, monkeypatch):
    planner, asked = _planner(keep, monkeypatch)
    rows, step = np.arange(len(HELD)), np.full(len(HELD), 30)  # a regular decision (repeat 5)
    got = planner.decide(None, rows, HELD, step)
    if keep == 0:  # a held GO kept only at 0 of 16; no more futures asked
        np.testing.assert_array_equal(got, [YIELD, YIELD, YIELD, GO, YIELD])
        assert asked == []
        return
    # kept at 1 of 16 where the 48 more add at most 1; asked only of held GOs the K alone could still pass
    np.testing.assert_array_equal(got, [GO, YIELD, YIELD, GO, YIELD])
    assert asked == [([0, 1], 48, (KEEP_STREAM,), None)]
    # the kept GO is held at the next safe decision as any held GO (confirm 2 does not ask for two safe decisions
    # again), with no more futures asked
    planner.shares["p"] = np.zeros(len(HELD))
    again = planner.decide(None, rows, got, step + 5)
    np.testing.assert_array_equal(again, [GO, YIELD, YIELD, GO, YIELD])
    assert len(asked) == 1, asked
