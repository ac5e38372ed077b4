"""``train.overwrite=true`` removes only what a run writes (its checkpoints, config.yaml, logs, TensorBoard,
``.hydra``): a real run's folder that also holds a user's files (notes.md, a plot, a sub-folder) was emptied whole.
Now such a folder is refused in one line with nothing deleted, at the command line and again where the folders are
cleared (train.run_folder.clear_for_overwrite). The folder Hydra makes for a job that the command line cannot
resolve (a ``-m`` sweep's job, a ``${hydra:...}`` run dir) is checked before Hydra writes there (train/job_folders.py;
tests/test_job_folders.py) and again inside the job (train.run_folder.job_folder_problem): a user's files refuse it,
whatever the flags."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from av_gym.errors import ConfigError
from tests.test_bad_input import check_line
from tests.test_nothing_lost import ROOT, released, snapshot  # noqa: F401 - fixture

RULE = ["agent=always_proceed", "train.eval_episodes=1"]  # a rule-based agent: nothing to train
RUN_CONFIG = "env: {name: left_turn}\nagent: {name: always_proceed, kind: always_proceed}\n"


def _users(folder: Path) -> None:
    """What a user adds to a run's folder: a note and a sub-folder with a plot."""
    (folder / "plots").mkdir(parents=True, exist_ok=True)
    (folder / "notes.md").write_text("what I saw\n")
    (folder / "plots" / "curve.png").write_bytes(b"\x89PNG")


def _a_run(tmp_path: Path, name: str = "R") -> tuple[Path, Path]:
    """checkpoints/<name>/ and runs/<name>/ as a finished run leaves them (the files every run writes)."""
    ckpt, logs = tmp_path / "checkpoints" / name, tmp_path / "runs" / name
    (logs / ".hydra").mkdir(parents=True)
    (logs / "tb").mkdir()
    ckpt.mkdir(parents=True)
    (ckpt / "config.yaml").write_text(RUN_CONFIG)
    (ckpt / "model.zip").write_bytes(b"PK")
    (ckpt / ".latest.zip.4242.tmp").write_bytes(b"PK")  # a write cut short: the run's too
    (logs / ".hydra" / "config.yaml").write_text(RUN_CONFIG)
    (logs / "tb" / "events.out.tfevents.1796057912.vm.7125.0").write_bytes(b"ev")
    (logs / "results.md").write_text("# R\n")
    (logs / "__main__.log").write_text("log\n")
    return ckpt, logs


@pytest.mark.parametrize("where", ["checkpoints", "runs"])
def test_overwrite_refuses_a_runs_folder_holding_a_users_files(where, tmp_path, monkeypatch, capsys, released):
    monkeypatch.chdir(tmp_path)
    _a_run(tmp_path)
    _users(tmp_path / where / "R")
    before = snapshot(tmp_path)
    line = check_line("train", [*RULE, "run_name=R", "train.overwrite=true"], monkeypatch, capsys)
    flag = "paths.checkpoints/run_name=checkpoints/R" if where == "checkpoints" else "paths.runs/run_name=runs/R"
    assert line.startswith(f"error: train.overwrite=true: {flag} holds files a training run does not write "
                           f"(notes.md, plots), "), line
    assert "nothing was deleted" in line, line
    assert snapshot(tmp_path) == before


def test_clearing_removes_only_a_runs_files(tmp_path, released):
    """Under the lock: a user's file in either folder refuses the clearing with nothing deleted; a run's folders
    alone are cleared, but for the ``.hydra/`` and job log Hydra wrote for this job."""
    from train.run_folder import _held, clear_for_overwrite

    ckpt, logs = _a_run(tmp_path)
    _held.take(ckpt)
    (logs / "notes.md").write_text("mine\n")
    before = snapshot(tmp_path)
    with pytest.raises(ConfigError, match=r"^train.overwrite=true: hydra.run.dir=.* holds files a training run "
                                          r"does not write \(notes.md\)"):
        clear_for_overwrite(ckpt, logs)
    assert snapshot(tmp_path) == before
    (logs / "notes.md").unlink()
    removed = clear_for_overwrite(ckpt, logs)
    assert sorted(Path(p).name for p in removed) == [".latest.zip.4242.tmp", "config.yaml", "model.zip",
                                                      "results.md", "tb"]
    assert sorted(p.name for p in logs.iterdir()) == [".hydra", "__main__.log"]


@pytest.mark.parametrize("users", ["tb/my_export.csv", "tb/ppo_turn/notes.md", "videos/clip.mp4",
                                   "videos/mine/step_00000001.gif", ".hydra/my_sweep.yaml"])
def test_a_users_file_inside_a_runs_tb_videos_or_hydra_refuses_overwrite(users, tmp_path, monkeypatch, capsys,
                                                                         released):
    """``runs/R/tb/my_export.csv`` was deleted with ``tb/`` (only top-level names were judged): a sub-folder of the
    run's logs is the run's only when every file in it is one a run writes (event files, the periodic GIFs, Hydra's
    three yaml files). Refused at the command line and where the folders are cleared, nothing deleted; the run's own
    files at any depth (tb/<name>/events..., a temporary of one) still let it be cleared."""
    from train.run_folder import _held, clear_for_overwrite, job_folder_problem

    monkeypatch.chdir(tmp_path)
    ckpt, logs = _a_run(tmp_path)
    for own in ("tb/ppo_turn/events.out.tfevents.1796057912.vm.7125.0", "tb/ppo_turn/.events.out.tfevents.1.vm.2.0"
                ".4242.tmp", "videos/step_00000000.gif", ".hydra/hydra.yaml", ".hydra/overrides.yaml"):
        (logs / own).parent.mkdir(parents=True, exist_ok=True)
        (logs / own).write_bytes(b"run")
    (logs / users).parent.mkdir(parents=True, exist_ok=True)
    (logs / users).write_text("mine\n")
    before = snapshot(tmp_path)
    line = check_line("train", [*RULE, "run_name=R", "train.overwrite=true"], monkeypatch, capsys)
    assert line.startswith("error: train.overwrite=true: paths.runs/run_name=runs/R holds files a training run does "
                           f"not write ({users.replace('/step_00000001.gif', '')}), "), line
    assert snapshot(tmp_path) == before
    if not users.startswith(".hydra"):  # the job's own .hydra is Hydra's, just written: clear_for_overwrite judges it
        assert "not a training run's logs (" + users.split("/step")[0] in \
            job_folder_problem(logs, ckpt, False, True, "hydra.run.dir")
    _held.take(ckpt)
    before = snapshot(tmp_path)  # the lock file added
    with pytest.raises(ConfigError, match="holds files a training run does not write"):
        clear_for_overwrite(ckpt, logs)
    assert snapshot(tmp_path) == before
    (logs / users).unlink()
    if users.count("/") > 1 and users.startswith("videos/"):  # a flat folder's sub-folder is the user's, empty too
        (logs / users).parent.rmdir()
    removed = clear_for_overwrite(ckpt, logs)
    assert {"tb", "videos"} <= {Path(p).name for p in removed}
    assert sorted(p.name for p in logs.iterdir()) == [".hydra", "__main__.log"]


def _job(monkeypatch, run_dir: Path, sweep: bool) -> None:
    """HydraConfig as a job sees it: its folder, and for a sweep its mode and number."""
    from hydra.types import RunMode

    from train import __main__ as train_main

    hydra = SimpleNamespace(runtime=SimpleNamespace(output_dir=str(run_dir)), job=SimpleNamespace(num=0),
                            mode=RunMode.MULTIRUN if sweep else RunMode.RUN)
    monkeypatch.setattr(train_main.HydraConfig, "get", staticmethod(lambda: hydra))


@pytest.mark.parametrize("flags", [[], ["train.overwrite=true"], ["train.resume=true"]],
                         ids=["no_flag", "overwrite", "resume"])
@pytest.mark.parametrize("sweep", [True, False], ids=["sweep_job", "hydra_run_dir"])
def test_a_jobs_folder_holding_a_users_files_is_refused_in_the_job(sweep, flags, tmp_path, monkeypatch, released):
    """The job's folder as Hydra made it (its .hydra and log written, the user's files beside them): refused before
    config.yaml, a checkpoint folder or a lock is written, and nothing deleted."""
    from conf.check import check_command_line
    from conf.commands import TrainCommand
    from train import __main__ as train_main

    monkeypatch.chdir(tmp_path)
    job = tmp_path / "proj"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "config.yaml").write_text(RUN_CONFIG)  # what Hydra wrote before the job started
    (job / "__main__.log").write_text("")
    _users(job)
    before = snapshot(tmp_path)
    (cfg,) = check_command_line("train", [*RULE, "run_name=R", *flags])
    _job(monkeypatch, job, sweep)
    with pytest.raises(ConfigError) as refused:
        train_main._claim_folders(cfg, TrainCommand.of(cfg))
    flag = "hydra.sweep.dir" if sweep else "hydra.run.dir"
    assert str(refused.value) == (f"{flag}={job}: holds files that are not a training run's logs (notes.md, "
                                  f"plots), which a run never writes among or clears; pick another {flag} (an empty "
                                  f"or new folder)")
    assert snapshot(tmp_path) == before and not (tmp_path / "checkpoints").exists()


def test_a_jobs_folder_of_a_run_is_refused_without_a_flag_and_cleared_with_overwrite(tmp_path, monkeypatch,
                                                                                    released):
    """A sweep job's folder holding a previous run's logs: refused without a flag (its logs would mix), cleared
    with train.overwrite=true (its .hydra and log kept: Hydra's of this job)."""
    from conf.check import check_command_line
    from conf.commands import TrainCommand
    from train import __main__ as train_main

    monkeypatch.chdir(tmp_path)
    _, logs = _a_run(tmp_path)
    (cfg,) = check_command_line("train", [*RULE, "run_name=S"])
    _job(monkeypatch, logs, sweep=True)
    with pytest.raises(ConfigError, match=r"hydra.sweep.dir=.*runs/R: already holds a run's logs \(results.md, "
                                          r"tb\); pick another hydra.sweep.dir, or replace it with "
                                          r"train.overwrite=true$"):
        train_main._claim_folders(cfg, TrainCommand.of(cfg))
    (cfg,) = check_command_line("train", [*RULE, "run_name=S", "train.overwrite=true"])
    folders = train_main._claim_folders(cfg, TrainCommand.of(cfg))
    assert folders.ckpt_dir == Path("checkpoints/S-j0") and (folders.ckpt_dir / "config.yaml").is_file()
    # its .hydra and log (Hydra's of this job) kept; provenance.json is this start's (train/provenance.py)
    assert sorted(p.name for p in logs.iterdir()) == [".hydra", "__main__.log", "provenance.json"]


def test_a_plain_runs_folder_the_command_line_checked_is_resumed_with_the_users_notes(tmp_path, monkeypatch,
                                                                                      released):
    """``run_name=R train.resume=true`` of a run whose runs/R/ the user added notes to: the command line saw R's
    .hydra/config.yaml and let it pass (a resume deletes nothing), so the job does not refuse it; a sweep job's
    folder like it (never checked before Hydra wrote there) is refused."""
    from conf.check import check_command_line
    from conf.commands import TrainCommand
    from tests.test_reliability import LANE, a_run
    from train import __main__ as train_main
    from train import run_folder

    monkeypatch.chdir(tmp_path)
    (a_run(tmp_path, "R", LANE) / "model.zip").unlink()  # stopped: resumable
    logs = tmp_path / "runs" / "R"
    (logs / ".hydra").mkdir(parents=True)
    (logs / ".hydra" / "config.yaml").write_text(RUN_CONFIG)
    (logs / "notes.md").write_text("mine\n")
    argv = [*LANE, "run_name=R", "train.resume=true"]
    monkeypatch.setattr(sys, "argv", ["train", *argv])
    train_main._check_command_line()
    (cfg,) = check_command_line("train", argv)
    _job(monkeypatch, logs, sweep=False)
    train_main._claim_folders(cfg, TrainCommand.of(cfg))
    assert (logs / "notes.md").read_text() == "mine\n"
    run_folder.LINE_CHECKED.clear()  # a sweep's job: its command line checked no folder
    _job(monkeypatch, logs, sweep=True)
    with pytest.raises(ConfigError, match="not a training run's logs \\(notes.md\\)"):
        train_main._claim_folders(cfg, TrainCommand.of(cfg))


def _train(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.run([sys.executable, "-m", "train", *argv, *RULE, "train.progress_bar=false"], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.slow  # two real processes of python -m train (a sweep of two jobs, one plain run): ~20 CPU-s
def test_a_real_sweep_job_and_a_hydra_interpolated_run_dir_keep_the_users_files(tmp_path):
    """``-m`` with a job's folder holding the user's files: the sweep is refused in one line naming the job, exit 2,
    before any job ran; ``hydra.run.dir=${hydra:runtime.cwd}`` in the user's folder: one line, exit 2. Both folders
    byte for byte as they were: Hydra's .hydra/ and job log were written into them before the in-job check refused
    (train/job_folders.py checks them first now); no checkpoint folder."""
    _users(tmp_path / "sweep" / "0")
    before = snapshot(tmp_path)
    done = _train(["-m", "seed=0,1", "run_name=W", "hydra.sweep.dir=sweep", "hydra/launcher=basic"], tmp_path)
    assert done.returncode == 2, done.stderr
    assert "error: sweep job 0 (seed=0 run_name=W " in done.stderr and "holds files that are not a training run's " \
        "logs (notes.md, plots)" in done.stderr and "no job of the sweep was run" in done.stderr, done.stderr
    assert snapshot(tmp_path) == before and sorted(p.name for p in (tmp_path / "sweep").iterdir()) == ["0"]
    assert not (tmp_path / "checkpoints").exists()
    project = tmp_path / "project"
    _users(project)
    before = snapshot(project)
    plain = _train(["run_name=P", "hydra.run.dir=${hydra:runtime.cwd}", "train.overwrite=true"], project)
    assert plain.returncode == 2, plain.stderr
    assert plain.stderr.strip().splitlines()[-1].startswith("error: hydra.run.dir="), plain.stderr
    assert "holds files that are not a training run's logs (notes.md, plots)" in plain.stderr, plain.stderr
    assert snapshot(project) == before and sorted(p.name for p in project.iterdir()) == ["notes.md", "plots"]
    assert not (project / "checkpoints" / "P").exists()
