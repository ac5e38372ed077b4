"""Nothing lost, everywhere a tool writes (issue 45): the shipped references are read-only to every tool whatever
its run_name, paths or flags; every tool that writes a run or an export folder takes that folder's lock and
replaces another run's files only when asked; the side tools check what they are given in one line; and a run
stopped before its first checkpoint is told what starts it again. One test per reproduction of the issue."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from tests.test_bad_input import check_line
from tests.test_nothing_lost import REF, cli, released, shipped, snapshot  # noqa: F401 - fixtures

ROOT = Path(__file__).resolve().parents[1]
LANE = ["agent=ppo", "env=lane_keeping", "sensors=gnss_imu"]


def locked_by_another(folder: Path, pid: int = 4242) -> int:
    """An flock on ``folder/.lock`` through a separate open file description, which flock treats as another
    owner (another process); returns its descriptor, to close."""
    import fcntl

    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / ".lock", os.O_RDWR | os.O_CREAT)
    os.write(fd, f"{pid}\n".encode())
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return fd


# ------------------------------------------------------------------------------------ train and the shipped references
@pytest.mark.parametrize("where", [
    ["paths.checkpoints={root}/..", "run_name=reference"],  # run_name=reference: every shipped agent
    ["paths.checkpoints={root}", "run_name=ppo_turn"],  # one shipped agent
    ["paths.checkpoints={root}/../..", "run_name={parent}"],  # the folder that holds them
    ["run_name={parent}", "paths.runs={root}/../.."],  # a log folder (train.overwrite=true clears it) that holds them
])
@pytest.mark.parametrize("flags", [[], ["train.overwrite=true"], ["train.resume=true"]])
def test_train_never_writes_the_shipped_references(where, flags, shipped, tmp_path, monkeypatch, capsys, released):
    """``run_name=reference train.overwrite=true`` deleted every shipped reference (exit 0), and
    ``paths.checkpoints=checkpoints/reference run_name=ppo_turn`` replaced ppo_turn; the refusal without the flag
    suggested the flag. Refused whatever the flags, by a line that suggests none."""
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    argv = [a.format(root=shipped, parent=shipped.parent.name) for a in where]
    line = check_line("train", ["agent=dagger_turn", "env=left_turn", "sensors=turn_truth", *argv, *flags],
                      monkeypatch, capsys)
    assert "the shipped reference agents' folder" in line and "read-only to every tool" in line, line
    assert "overwrite" not in line and "resume" not in line, line
    assert snapshot(tmp_path) == before


def test_clearing_a_run_refuses_a_hydra_folder_that_holds_the_references(shipped, tmp_path, monkeypatch, released):
    """``hydra.run.dir`` is the user's too: clearing for ``train.overwrite=true`` refuses a log folder that holds
    the shipped references, even for a run of its own."""
    from av_gym.errors import ConfigError
    from train.run_folder import claim, clear_for_overwrite

    ckpt = claim(tmp_path / "checkpoints" / "R", None, resume=False, overwrite=True)
    before = snapshot(shipped)
    with pytest.raises(ConfigError, match="paths.runs/run_name=.*: holds the shipped reference agents' folder"):
        clear_for_overwrite(ckpt, shipped.parent)
    assert snapshot(shipped) == before


# ---------------------------------------------------------------------------- a run stopped before its first checkpoint
def dead_run(tmp_path: Path) -> Path:
    """A PPO run killed before its first checkpoint: the config.yaml train writes first, nothing else."""
    from tests.test_reliability import a_run

    ckpt = a_run(tmp_path, "R", LANE)
    for name in ("latest.zip", "model.zip"):
        (ckpt / name).unlink()
    return ckpt


def test_a_run_stopped_before_its_first_checkpoint_is_told_what_starts_it_again(tmp_path, monkeypatch, capsys,
                                                                                 released):
    """The refusal advised ``train.resume=true``, which then refused (no latest.zip). Both refusals now give the
    advice that works, and following it is accepted."""
    from train import __main__ as train_main
    import sys

    monkeypatch.chdir(tmp_path)
    dead_run(tmp_path)
    for flags in ([], ["train.resume=true"]):
        line = check_line("train", [*LANE, "run_name=R", *flags], monkeypatch, capsys)
        assert "stopped before its first checkpoint" in line, line
        assert "start it again with train.overwrite=true" in line, line
        assert "continue it with train.resume=true" not in line, line
    monkeypatch.setattr(sys, "argv", ["train", *LANE, "run_name=R", "train.overwrite=true"])
    train_main._check_command_line()  # the advice works: the run is claimed


def test_a_finished_run_is_not_told_to_resume(tmp_path, monkeypatch, capsys, released):
    """A finished run (its model.zip) refuses train.resume=true, so the refusal of a second run does not advise
    it; a rule-based run (config.yaml only) is a finished run, not a dead start."""
    from tests.test_reliability import a_run

    monkeypatch.chdir(tmp_path)
    a_run(tmp_path, "R", LANE)
    line = check_line("train", [*LANE, "run_name=R"], monkeypatch, capsys)
    assert "already holds a run" in line and "train.resume" not in line, line
    a_run(tmp_path, "rule", ["agent=always_proceed"])
    for name in ("latest.zip", "model.zip"):
        (tmp_path / "checkpoints" / "rule" / name).unlink()
    line = check_line("train", ["agent=always_proceed", "run_name=rule"], monkeypatch, capsys)
    assert "already holds a run (config.yaml)" in line and "stopped before" not in line, line
