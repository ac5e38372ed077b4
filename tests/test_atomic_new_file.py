"""av_gym.atomic.new_path / write_text_new: a result written as a new file is linked into place, so a file at its
path (one that appeared after the caller's own check included) is kept and the write refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.atomic import FileExists, WriteFailed, new_path, new_paths, write_text_new


def test_a_new_file_is_written_whole_and_no_temporary_file_is_left(tmp_path):
    out = tmp_path / "sub" / "result.json"
    assert write_text_new(out, '{"a": 1}\n', "--out") == out
    assert out.read_text() == '{"a": 1}\n'
    assert [p.name for p in out.parent.iterdir()] == ["result.json"]


def test_a_file_that_appears_while_writing_is_kept(tmp_path):
    out = tmp_path / "result.json"
    with pytest.raises(FileExists, match=r"^--out .*result\.json exists: choose another file") as refused:
        with new_path(out, "--out") as tmp:
            tmp.write_text("ours\n")
            out.write_text("theirs\n")  # another process, between any check and the write
    assert "\n" not in str(refused.value)
    assert out.read_text() == "theirs\n"
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]


def test_a_failed_write_leaves_nothing(tmp_path):
    out = tmp_path / "result.json"
    with pytest.raises(RuntimeError):
        with new_path(out) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []
    blocked = tmp_path / "a file"
    blocked.write_text("")
    with pytest.raises(WriteFailed, match="--out: cannot write"):
        write_text_new(blocked / "result.json", "x", "--out")  # a folder that is a file
    assert [p.name for p in tmp_path.iterdir()] == ["a file"]


def test_label_noise_keeps_an_out_or_states_file_that_appeared_after_its_check(tmp_path):
    """benchmarks/label_noise.py checks --out and --states when parsing, writes them after the episodes: a file
    there by then (another run's) is kept and the write refused (a ConfigError: one line through run_cli)."""
    import argparse

    from tests.test_label_noise import ln

    for name in ("out", "states"):
        taken = tmp_path / f"{name}.file"
        taken.write_text("another run's result\n")
        args = argparse.Namespace(**{"out": None, "states": None, name: str(taken)})
        states = {"student": np.zeros(1), "unseen": np.zeros(1), "labels": {}, "collided": {}}
        with pytest.raises(FileExists, match=f"--{name} "):
            ln._write(args, [{"K": 1, "agreement": 1.0}], states)
        assert taken.read_text() == "another run's result\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.file", "states.file"]


def test_label_noise_writes_neither_file_when_one_is_taken(tmp_path):
    """--out free, --states taken since _args' check: neither is written (not the table without its states)."""
    import argparse

    from tests.test_label_noise import ln

    taken = tmp_path / "states.npz"
    taken.write_text("another run's states\n")
    args = argparse.Namespace(out=str(tmp_path / "table.csv"), states=str(taken))
    states = {"student": np.zeros(1), "unseen": np.zeros(1), "labels": {}, "collided": {}}
    with pytest.raises(FileExists, match="--states "):
        ln._write(args, [{"K": 1, "agreement": 1.0}], states)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["states.npz"]


def _new_path_refusal(path, field: str) -> str:
    """What :func:`new_path` says when ``path`` (taken) is linked into place for ``field``."""
    with pytest.raises(FileExists) as refused:
        with new_path(path, field) as tmp:
            tmp.write_text("ours\n")
    return str(refused.value)


def test_new_paths_refuses_before_writing_any_in_new_paths_words(tmp_path):
    """new_paths: every (path, field) checked before any write (a None path not asked for); a taken one refused
    in the one line new_path gives that file, the file kept."""
    free, taken = tmp_path / "table.csv", tmp_path / "states.npz"
    taken.write_text("another run's states\n")
    assert new_paths((free, "--out"), (None, "--rows"), ("", "--plot")) is None
    with pytest.raises(FileExists) as refused:
        new_paths((free, "--out"), (taken, "--states"))
    assert str(refused.value) == _new_path_refusal(taken, "--states")
    assert taken.read_text() == "another run's states\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["states.npz"]


def test_label_noise_refuses_a_taken_file_in_new_paths_words(tmp_path, capsys):
    """benchmarks/label_noise.py's two refusals of a taken --states (at parsing, and _write's check before
    writing either file) say what av_gym.atomic.new_path says of it: one text, not copies that drift ('nothing was
    written' in one of them only)."""
    import argparse

    from tests.test_label_noise import ln

    taken = tmp_path / "states.npz"
    taken.write_text("another run's states\n")
    said = _new_path_refusal(taken, "--states")
    with pytest.raises(FileExists) as refused:
        ln._write(argparse.Namespace(out=str(tmp_path / "table.csv"), states=str(taken)), [], {})
    assert str(refused.value) == said
    with pytest.raises(SystemExit) as stop:
        ln.main(["--states", str(taken)])
    assert stop.value.code == 2 and capsys.readouterr().err.strip().splitlines()[-1].endswith(said)


def test_the_sweep_prints_its_summary_before_a_refused_rows(tmp_path, monkeypatch, capsys):
    """benchmarks/belief_tracks_sweep.py: a --rows file that appeared while the episodes ran is kept and the write
    refused in one line, after the run's summary was printed (the run is not lost)."""
    import json
    import runpy
    import sys

    import eval.batched
    from tests.documented_commands import ROOT

    rows = tmp_path / "rows.csv"
    seeds = [1_949_010, 1_949_500]

    def played(*args, **kwargs):  # the episodes (stand-in); another run writes --rows meanwhile
        rows.write_text("another run's rows\n")
        return [{"seed": s, "collision": s == seeds[0], "success": s != seeds[0]} for s in args[4]]

    monkeypatch.setattr(eval.batched, "play_batched", played)
    script = ROOT / "benchmarks" / "belief_tracks_sweep.py"
    monkeypatch.setattr(sys, "argv", [str(script), "--seeds", *map(str, seeds), "--rows", str(rows)])
    with pytest.raises(SystemExit) as end:
        runpy.run_path(str(script), run_name="__main__")
    out = capsys.readouterr()
    assert end.value.code == 2 and len(out.err.strip().splitlines()) == 1 and "--rows" in out.err
    summary = json.loads(out.out)
    assert summary["collided"] == [seeds[0]] and summary["episodes"] == 2
    assert rows.read_text() == "another run's rows\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rows.csv"]
