"""av_gym.atomic.new_path / write_text_new: a result written as a new file is linked into place, so a file at its
path (one that appeared after the caller's own check included) is kept and the write refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.atomic import FileExists, WriteFailed, new_path, write_text_new


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
