"""The replay tools (benchmarks/belief_tracks_*.py) drive the planner as the preset does: YIELD stops where
``wait_back`` / ``wait_gap`` ask (BeliefPlanner.meta_actions -> yield_margin), not at the line's MARGIN. Before,
they stepped ``meta_actions(choice, obs["turn"])``, so ``--set wait_back=5`` replayed the same driver as
``wait_back=0`` (conf/agent/belief_tracks.yaml sets wait_back=1.5, wait_gap=3).

Runs belief_tracks_state.py's main loop (the simplest) on one validation episode, its ``decide`` scripted to YIELD
on every row (the planner's futures are not this test's), recording the actions it steps for a few seconds."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np

from av_gym.wrappers import YIELD

SEEDS = ["1000003"]  # a validation seed (a batch of one row)
STEPS = 40  # env steps (4 s at 10 Hz): the ego approaches the line; the set-points of the two stops part


class _Enough(Exception):
    """Stops the tool's loop after STEPS steps."""


def _actions(wait_back: float, monkeypatch) -> np.ndarray:
    """The (STEPS, B) actions belief_tracks_state.main steps with ``wait_back`` (m), every choice YIELD."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent.parent / "benchmarks"))
    module = importlib.import_module("belief_tracks_state")
    made, stepped = importlib.import_module("belief_tracks_sweep").traced_batch, []  # not a patched one

    def traced(*args, **kwargs):
        out = made(*args, **kwargs)
        venv, planner = out[2], out[4]
        planner.decide = lambda engine, rows, choice, step: np.full(len(rows), YIELD)
        step = venv.step

        def recorded(actions):
            stepped.append(np.array(actions, copy=True))
            if len(stepped) >= STEPS:
                raise _Enough
            return step(actions)

        venv.step = recorded
        return out

    monkeypatch.setattr(module, "traced_batch", traced)
    monkeypatch.setattr(sys, "argv", ["belief_tracks_state.py", "--seeds", *SEEDS, "--set", "samples=1",
                                      f"wait_back={wait_back}"])
    try:
        module.main()
    except _Enough:
        pass
    assert len(stepped) == STEPS, "the episode ended before the test could compare the stops"
    return np.stack(stepped)


def test_the_replay_loop_yields_where_wait_back_asks(monkeypatch):
    near, far = _actions(0.0, monkeypatch), _actions(5.0, monkeypatch)
    # the same driver would step the same actions; wait_back=5 slows down sooner (SLOWER where 0 holds or speeds)
    assert not np.array_equal(near, far), "wait_back did not change what the replay drives"
