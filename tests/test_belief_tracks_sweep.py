"""benchmarks/belief_tracks_sweep.py's summary line as a user runs it (the episodes a stand-in for
eval.batched.play_batched, which the script's own runs measure): it names every seed it played, so a ``--seeds``
replay (scattered seeds) is paired by the seeds it ran, not read as ``seed`` .. ``seed + episodes``."""

from __future__ import annotations

import json
import runpy
import sys

import pytest

from tests.documented_commands import ROOT

SCRIPT = ROOT / "benchmarks" / "belief_tracks_sweep.py"


def _summary(monkeypatch, capsys, *argv: str) -> dict:
    """The script's JSON line for ``argv``; every played episode collides on its first seed only."""
    import eval.batched

    def played(*args, **kwargs):  # (env, sensors, shield, agent, seeds, n_envs, label): one row per seed
        return [{"seed": s, "collision": s == args[4][0], "success": s != args[4][0]} for s in args[4]]

    monkeypatch.setattr(eval.batched, "play_batched", played)
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *argv])
    runpy.run_path(str(SCRIPT), run_name="__main__")
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("argv, seeds", [
    (["--seeds", "1949500", "1949010", "1960000"], [1_949_500, 1_949_010, 1_960_000]),
    (["--seed", "1944000", "--episodes", "3"], [1_944_000, 1_944_001, 1_944_002]),
])
def test_the_summary_names_the_seeds_it_played(monkeypatch, capsys, argv, seeds):
    summary = _summary(monkeypatch, capsys, *argv)
    assert summary["seeds"] == seeds and summary["episodes"] == 3
    assert summary["collided"] == [seeds[0]] and summary["not_arrived"] == [seeds[0]]
