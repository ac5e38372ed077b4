"""The tracing tools' main loops (benchmarks/belief_tracks_diagnose.py, _confirm.py, _lost.py) hand each what-if
(``_snapshot``, ``blame``, ``cause``) the choice the row held BEFORE the decision, as the decision's own p was judged
(belief_tracks_truth.decision_p: under ``track_margin_scope`` start a held GO on contact alone). The helpers are
tested in tests/test_belief_tracks_tracing.py; this runs each main loop on one validation episode.

The planner's ``decide`` is scripted here to flip every due row's choice (its own ``live`` says which rows are due),
so the choice after a decision always differs from the one held before it: a loop that handed a what-if the choice
after the decision would hand the other one. The what-ifs are recorders (their own cost is not this test's)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

from av_gym.wrappers import GO, YIELD

SEEDS = ["1000003"]  # a validation seed (a batch of one row)
# 1 future a decision (the loops' own decision_p runs for real), the margin for a GO to start only
SETS = ["samples=1", "track_margin=0.5", "track_margin_scope=start"]


def _scripted(module, monkeypatch, held_at: dict) -> None:
    """``module.traced_batch`` returning a planner whose ``decide`` flips every due row, noting in ``held_at`` the
    choice each due row held at its latest decision."""
    made = module.traced_batch

    def traced(*args, **kwargs):
        out = made(*args, **kwargs)
        planner = out[4]

        def decide(engine, rows, choice, step):
            due, final = planner.live(engine, rows, choice, step)
            held_at.update(zip(np.asarray(rows)[due].tolist(), np.asarray(choice)[due].tolist()))
            new = np.array(choice, copy=True)
            new[final] = GO
            new[due] = np.where(new[due] == GO, YIELD, GO)
            return new

        planner.decide = decide
        return out

    monkeypatch.setattr(module, "traced_batch", traced)


def _recorder(calls: list, held_at: dict, held_index: int, result):
    """A what-if that records (the held choice it was given, the one the row held at the decision) and returns
    ``result`` (a function of its arguments)."""
    def what_if(*args):
        calls.append((int(args[held_index]), held_at[int(args[2])]))
        return result(*args)
    return what_if


# each ~0.5-0.9 s once the batch is warm (the first test of a process pays ~1.5 s of imports and kernels)
@pytest.mark.parametrize("tool", ["diagnose", "confirm", "lost"])
def test_the_main_loops_hand_the_what_ifs_the_choice_held_before_the_decision(tool, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent.parent / "benchmarks"))
    module = importlib.import_module(f"belief_tracks_{tool}")
    held_at: dict[int, int] = {}
    calls: list[tuple[int, int]] = []
    _scripted(module, monkeypatch, held_at)
    sets, extra = list(SETS), []
    if tool == "diagnose":  # _snapshot(planner, engine, r, held) at each GO; the other what-ifs: nothing found
        monkeypatch.setattr(module, "_snapshot", _recorder(calls, held_at, 3, lambda *a: {}))
        monkeypatch.setattr(module, "_untracked", lambda *a: {})
        monkeypatch.setattr(module, "_blame", lambda *a: {})
    elif tool == "confirm":  # blame(planner, engine, r, p, radius, held) at each unsafe decision of a held YIELD
        monkeypatch.setattr(module, "blame", _recorder(calls, held_at, 5,
                                                       lambda *a: {"p": a[3], "p_no_unseen": a[3], "users": []}))
        sets.append("threshold=0")  # every decision with a colliding future is unsafe
    else:  # cause(planner, engine, r, p, car_of, radius, held) at each yield after the truth planner's first GO
        monkeypatch.setattr(module, "cause", _recorder(calls, held_at, 6, lambda *a: "real road users"))
        extra = ["--window", "60"]
    monkeypatch.setattr(sys, "argv", [f"belief_tracks_{tool}.py", "--seeds", *SEEDS, "--set", *sets, *extra])
    module.main()
    assert len(capsys.readouterr().out.splitlines()) == len(SEEDS) + 1  # an episode line per seed, the summary
    assert calls, "the loop asked no what-if: the test would not see the choice it hands over"
    given, held = np.array(calls).T
    np.testing.assert_array_equal(given, held)
    # which rows each loop asks about: diagnose a GO started, confirm an unsafe decision of a held YIELD (here
    # flipped to GO), lost a yield (here a GO flipped to YIELD); the choice after is always the other one
    assert set(held.tolist()) == ({YIELD} if tool in ("diagnose", "confirm") else {GO}), held
