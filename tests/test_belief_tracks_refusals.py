"""The belief_tracks benchmarks refuse a taken result path with av_gym.atomic's one refusal (``taken``), before
any episode: the same line as every other tool's, whatever its wording becomes."""

from __future__ import annotations

import runpy
import sys

import pytest

import av_gym.atomic
from av_gym.errors import ConfigError
from tests.documented_commands import ROOT

BENCH = ROOT / "benchmarks"


@pytest.mark.parametrize("script, before, flag", [("belief_tracks_paired.py", ["a.csv", "b.csv"], "--out"),
                                                  ("belief_tracks_ablate.py", [], "--out"),
                                                  ("belief_tracks_sweep.py", [], "--rows")])
def test_a_taken_result_path_is_refused_with_the_shared_refusal(script, before, flag, tmp_path, monkeypatch,
                                                                 capsys):
    """A file at the result path: exit status 2, one ``error:`` line that is ``taken``'s (here replaced by a
    marker, so a script spelling the refusal out itself fails), the file intact."""
    out = tmp_path / "result"
    out.write_text("an earlier result\n")
    monkeypatch.setattr(av_gym.atomic, "taken", lambda path, field="": ConfigError(f"TAKEN {field} {path}"))
    monkeypatch.syspath_prepend(str(BENCH))  # the scripts import their neighbours, as run from their folder
    monkeypatch.setattr(sys, "argv", [str(BENCH / script), *(str(tmp_path / a) for a in before), flag, str(out)])
    with pytest.raises(SystemExit) as end:
        runpy.run_path(str(BENCH / script), run_name="__main__")
    assert end.value.code == 2
    assert capsys.readouterr().err == f"error: TAKEN {flag} {out}\n"
    assert out.read_text() == "an earlier result\n"
