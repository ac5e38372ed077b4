"""A job folder the command line cannot resolve (a ``-m`` sweep's ``hydra.sweep.dir``/``subdir``, a
``hydra.run.dir=${hydra:...}``) is checked in Hydra's sweep- and run-level hooks (train/job_folders.py), before
Hydra opens the job log and writes ``.hydra/`` there: a refused job used to leave both among the user's files (the
in-job check, train.run_folder.job_folder_problem, runs after Hydra's writes). The real commands:
tests/test_train_overwrite_keeps_users.py's slow case."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra.types import RunMode

import train.run_folder as run_folder
from tests.test_nothing_lost import snapshot
from train import job_folders

RULE = ["agent=always_proceed", "train.eval_episodes=1"]  # a rule-based agent: nothing to train


def _composed(overrides: list[str], mode: RunMode):
    """The config Hydra hands its ``on_multirun_start`` / ``on_run_start`` hooks (Hydra.multirun / Hydra.run), with
    Hydra's config loader set up as while they run."""
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
    context = initialize_config_module("conf", version_base="1.3")
    context.__enter__()
    cfg = GlobalHydra.instance().config_loader().load_configuration("train", overrides, run_mode=mode)
    return cfg, context


@pytest.fixture
def hydra_loader():
    """Compose with Hydra's loader for the test; cleared after it."""
    contexts = []

    def compose(overrides: list[str], mode: RunMode = RunMode.MULTIRUN):
        cfg, context = _composed(overrides, mode)
        contexts.append(context)
        return cfg

    yield compose
    for context in contexts:
        context.__exit__(None, None, None)


def _refused(hook, cfg, capsys) -> str:
    with pytest.raises(SystemExit) as stop:  # SystemExit: Hydra turns a hook's exception into a warning
        hook(config=cfg)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert stop.value.code == 2 and len(err) == 1, (stop.value.code, err)
    return err[0]


@pytest.mark.parametrize("users", ["notes.md", ".hydra/notes.md"])
def test_a_sweep_job_folder_holding_a_users_file_refuses_the_sweep_before_hydra_writes(users, tmp_path, capsys,
                                                                                      hydra_loader, monkeypatch):
    """Job 1's folder holds the user's file (beside, or inside a .hydra/ Hydra would write into): the sweep is
    refused in one line naming the job, before any job's folder is written; job 0's new folder passes."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sweep" / "1" / users).parent.mkdir(parents=True)
    (tmp_path / "sweep" / "1" / users).write_text("mine\n")
    before = snapshot(tmp_path)
    cfg = hydra_loader([*RULE, "seed=0,1", "run_name=W", "hydra.sweep.dir=sweep"])
    line = _refused(job_folders.JobFolders().on_multirun_start, cfg, capsys)
    assert line == (f"error: sweep job 1 (agent=always_proceed train.eval_episodes=1 seed=1 run_name=W): "
                    f"hydra.sweep.dir={tmp_path}/sweep/1: holds files that are not a training run's logs ({users}), "
                    f"which a run never writes among or clears; pick another hydra.sweep.dir (an empty or new "
                    f"folder); no job of the sweep was run")
    assert snapshot(tmp_path) == before and sorted(p.name for p in tmp_path.iterdir()) == ["sweep"]
    (tmp_path / "sweep" / "1" / users).unlink()
    job_folders.JobFolders().on_multirun_start(config=hydra_loader([*RULE, "seed=0,1", "hydra.sweep.dir=sweep"]))


def test_a_sweep_jobs_checkpoint_folder_is_checked_before_hydra_writes(tmp_path, capsys, hydra_loader,
                                                                        monkeypatch):
    """A job whose checkpoint folder (``<run_name>-j<num>``) holds a run is refused as its claim would refuse it,
    before Hydra writes into the job's folder (a previous run's logs there, its .hydra/ replaced)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "checkpoints" / "W-j0").mkdir(parents=True)
    (tmp_path / "checkpoints" / "W-j0" / "config.yaml").write_text("env: {name: left_turn}\nagent: {name: x}\n")
    before = snapshot(tmp_path)
    cfg = hydra_loader([*RULE, "seed=0,1", "run_name=W", "hydra.sweep.dir=sweep"])
    line = _refused(job_folders.JobFolders().on_multirun_start, cfg, capsys)
    assert line.startswith("error: sweep job 0 (agent=always_proceed train.eval_episodes=1 seed=0 run_name=W): "
                           "run_name=W-j0: ") and line.endswith("; no job of the sweep was run"), line
    assert snapshot(tmp_path) == before and not (tmp_path / "sweep").exists()


def test_the_folder_checked_is_the_one_the_sweep_writes(tmp_path, hydra_loader, monkeypatch):
    """A ``${now:...}`` in hydra.sweep.dir resolves once for the sweep: the hook checks the folders the jobs will
    get (hydra.job.num in hydra.sweep.subdir), not ones of a later microsecond."""
    from hydra.core.global_hydra import GlobalHydra

    monkeypatch.chdir(tmp_path)
    checked, original = [], run_folder.job_folder_problem
    monkeypatch.setattr(run_folder, "job_folder_problem", lambda run_dir, *a, **k: checked.append(run_dir) or
                        original(run_dir, *a, **k))
    cfg = hydra_loader([*RULE, "seed=0,1", "hydra.sweep.dir=s/${now:%H%M%S%f}",
                        "hydra.sweep.subdir=j${hydra.job.num}"])
    job_folders.JobFolders().on_multirun_start(config=cfg)
    sweep_dir = Path(str(cfg.hydra.sweep.dir)).absolute()  # what the sweeper then makes (BasicSweeper.sweep)
    assert checked == [sweep_dir / "j0", sweep_dir / "j1"]
    job = GlobalHydra.instance().config_loader().load_sweep_config(cfg, ["seed=1"])  # as the launcher composes
    assert Path(str(job.hydra.sweep.dir)).absolute() == sweep_dir


def test_a_hydra_interpolated_run_dir_holding_a_users_file_is_refused_before_hydra_writes(tmp_path, capsys,
                                                                                         hydra_loader, monkeypatch):
    """``hydra.run.dir=${hydra:runtime.cwd}`` (the command line cannot resolve it) in the user's project: refused
    by the run-level hook, nothing written; a folder the command line checked is left to it."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.md").write_text("mine\n")
    before = snapshot(tmp_path)
    cfg = hydra_loader([*RULE, "run_name=P", "hydra.run.dir=${hydra:runtime.cwd}"], RunMode.RUN)
    line = _refused(job_folders.JobFolders().on_run_start, cfg, capsys)
    assert line == (f"error: hydra.run.dir={tmp_path}: holds files that are not a training run's logs (notes.md), "
                    f"which a run never writes among or clears; pick another hydra.run.dir (an empty or new "
                    f"folder)")
    assert snapshot(tmp_path) == before
    monkeypatch.setattr(run_folder, "LINE_CHECKED", run_folder.LINE_CHECKED | {tmp_path.resolve()})
    job_folders.JobFolders().on_run_start(config=cfg)
