"""``python -m train`` never writes among, or with ``train.overwrite=true`` clears, files that are not a run's: a
checkpoint folder (``paths.checkpoints/run_name``) without a run's config.yaml, or a log folder (``hydra.run.dir``,
by default ``paths.runs/run_name``) without a run's ``.hydra/config.yaml``. What a user lost: ``run_name=proj
train.overwrite=true`` emptied a project folder, and ``hydra.run.dir=.`` replaced the user's results.md (and with the
flag deleted their scripts). Each is refused in one line by the command-line check, before Hydra writes anything; a
run's own folders are still replaced with the flag."""

from __future__ import annotations

import pytest

from tests.test_bad_input import check_line
from tests.test_nothing_lost import released, snapshot  # noqa: F401 - fixture

RULE = ["agent=always_proceed", "train.eval_episodes=1"]  # a rule-based agent: what the prober ran
FLAGS = [[], ["train.overwrite=true"]]


def _project(folder):
    """A user's folder: a file and a sub-folder of theirs, no run's config."""
    (folder / "sub").mkdir(parents=True)
    (folder / "precious.txt").write_text("the user's\n")
    (folder / "sub" / "data.csv").write_text("a,b\n1,2\n")
    return folder


@pytest.mark.parametrize("flags", FLAGS, ids=["no_flag", "overwrite"])
def test_a_checkpoint_folder_that_is_not_a_run_is_refused(flags, tmp_path, monkeypatch, capsys, released):
    """``paths.checkpoints=<dir> run_name=proj`` where proj/ is the user's: refused with or without the flag,
    the advice no flag (the flag would empty it); nothing in it changed."""
    monkeypatch.chdir(tmp_path)
    before = snapshot(_project(tmp_path / "ckpts" / "proj"))
    line = check_line("train", [*RULE, f"paths.checkpoints={tmp_path / 'ckpts'}", "run_name=proj", *flags],
                      monkeypatch, capsys)
    assert "paths.checkpoints/run_name=" in line and "not a training run's (precious.txt, sub;" in line, line
    assert "overwrite" not in line and "resume" not in line, line
    assert snapshot(tmp_path / "ckpts" / "proj") == before and not (tmp_path / "runs").exists()


@pytest.mark.parametrize("flags", FLAGS, ids=["no_flag", "overwrite"])
def test_a_hydra_run_dir_of_the_users_is_refused(flags, tmp_path, monkeypatch, capsys, released):
    """``hydra.run.dir=.`` in the user's folder (their results.md and files): refused with or without the flag,
    naming hydra.run.dir; nothing written there, no checkpoint folder made."""
    monkeypatch.chdir(_project(tmp_path / "myproj"))
    (tmp_path / "myproj" / "results.md").write_text("# my results\n")
    before = snapshot(tmp_path)
    line = check_line("train", [*RULE, f"paths.checkpoints={tmp_path / 'ckpts'}", "hydra.run.dir=.", *flags],
                      monkeypatch, capsys)
    assert line.startswith("error: hydra.run.dir=.: holds files that are not a training run's logs (precious.txt, "
                           "results.md, sub;"), line
    assert "pick another hydra.run.dir" in line and "overwrite" not in line, line
    assert snapshot(tmp_path) == before and not (tmp_path / "ckpts").exists()


def test_a_runs_own_folders_are_still_taken(tmp_path, monkeypatch, capsys, released):
    """What the refusals leave open: a new hydra.run.dir; a log folder of a run (its .hydra/config.yaml) refused
    without the flag, with the advice to pick another hydra.run.dir or overwrite, and taken with the flag."""
    from train import __main__ as train_main

    monkeypatch.chdir(tmp_path)
    ckpts = f"paths.checkpoints={tmp_path / 'ckpts'}"
    monkeypatch.setattr("sys.argv", ["train", *RULE, ckpts, "run_name=A", f"hydra.run.dir={tmp_path / 'new'}"])
    train_main._check_command_line()
    logs = tmp_path / "logs"
    (logs / ".hydra").mkdir(parents=True)
    (logs / ".hydra" / "config.yaml").write_text("env: {name: left_turn}\nagent: {name: always_proceed}\n")
    (logs / "results.md").write_text("# a run's\n")
    line = check_line("train", [*RULE, ckpts, "run_name=B", f"hydra.run.dir={logs}"], monkeypatch, capsys)
    assert "already holds a run's logs (.hydra, results.md)" in line, line
    assert "pick another hydra.run.dir, or replace it with train.overwrite=true" in line, line
    monkeypatch.setattr("sys.argv", ["train", *RULE, ckpts, "run_name=B", f"hydra.run.dir={logs}",
                                     "train.overwrite=true"])
    train_main._check_command_line()
