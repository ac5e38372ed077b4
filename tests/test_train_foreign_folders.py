"""``python -m train`` never writes among, or with ``train.overwrite=true`` clears, files that are not a run's: a
checkpoint folder (``paths.checkpoints/run_name``) without a run's config.yaml. The prober's reproduction (issue 47,
R's D1): ``run_name=proj train.overwrite=true`` emptied a project folder. Refused in one line by the command-line
check, before Hydra writes anything; a run's own folder is still replaced with the flag
(tests/test_reliability.py: test_resume_and_overwrite_are_allowed_and_hold_the_lock)."""

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
    """D1: ``paths.checkpoints=<dir> run_name=proj`` where proj/ is the user's: refused with or without the flag,
    the advice no flag (the flag would empty it); nothing in it changed."""
    monkeypatch.chdir(tmp_path)
    before = snapshot(_project(tmp_path / "ckpts" / "proj"))
    line = check_line("train", [*RULE, f"paths.checkpoints={tmp_path / 'ckpts'}", "run_name=proj", *flags],
                      monkeypatch, capsys)
    assert "paths.checkpoints/run_name=" in line and "not a training run's (precious.txt, sub;" in line, line
    assert "overwrite" not in line and "resume" not in line, line
    assert snapshot(tmp_path / "ckpts" / "proj") == before and not (tmp_path / "runs").exists()
