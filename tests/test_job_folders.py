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


def _composed(overrides: list[str], mode: RunMode, command: str = "train"):
    """The config Hydra hands its ``on_multirun_start`` / ``on_run_start`` hooks (Hydra.multirun / Hydra.run) of
    ``python -m <command>``, with Hydra's config loader set up as while they run."""
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
    context = initialize_config_module("conf", version_base="1.3")
    context.__enter__()
    cfg = GlobalHydra.instance().config_loader().load_configuration(command, overrides, run_mode=mode)
    return cfg, context


@pytest.fixture
def hydra_loader():
    """Compose with Hydra's loader for the test; cleared after it."""
    contexts = []

    def compose(overrides: list[str], mode: RunMode = RunMode.MULTIRUN, command: str = "train"):
        cfg, context = _composed(overrides, mode, command)
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


# ------------------------------------------------------------------------------------- python -m eval, the sweep folder
EVAL = ["agents=[always_proceed]", "episodes=1"]  # composed only: no episode runs in these tests


@pytest.mark.parametrize("flag", [[], ["overwrite=true"]])
@pytest.mark.parametrize("users", ["notes.md", ".hydra/notes.md"])
def test_an_eval_sweep_job_folder_holding_a_users_file_refuses_the_sweep_before_hydra_writes(users, flag, tmp_path,
                                                                                           capsys, hydra_loader,
                                                                                           monkeypatch):
    """python -m eval -m: job 0's folder holds the user's file; its results (its default out_dir) and Hydra's record
    would be written beside it. Refused in one line naming the job, whatever overwrite says, nothing written."""
    from eval import job_folders as eval_job_folders

    monkeypatch.chdir(tmp_path)
    (tmp_path / "sweep" / "0" / users).parent.mkdir(parents=True)
    (tmp_path / "sweep" / "0" / users).write_text("mine\n")
    before = snapshot(tmp_path)
    cfg = hydra_loader([*EVAL, "seed=1000000,1000001", "hydra.sweep.dir=sweep", *flag], command="eval")
    line = _refused(eval_job_folders.JobFolders().on_multirun_start, cfg, capsys)
    shown = f"{' '.join(EVAL)} seed=1000000{' overwrite=True' if flag else ''}"  # as the sweeper lists them
    assert line == (f"error: sweep job 0 ({shown}): hydra.sweep.dir={tmp_path}/sweep/0: holds files that are not an "
                    f"evaluation's ({users}), which an evaluation never writes among; pick another hydra.sweep.dir "
                    f"(an empty or new folder); no job of the sweep was run")
    assert snapshot(tmp_path) == before


def _earlier_evaluation(*folders: Path) -> None:
    """An earlier evaluation's job folder in each of ``folders``: Hydra's record, its log and its results."""
    for folder in folders:
        (folder / ".hydra").mkdir(parents=True)
        (folder / ".hydra" / "config.yaml").write_text("seed: 1\n")
        (folder / "__main__.log").write_text("log\n")
        (folder / "results.csv").write_text("agent,episode\n")


def test_an_eval_sweep_jobs_earlier_results_are_refused_before_hydra_writes_unless_overwrite(tmp_path, capsys,
                                                                                          hydra_loader, monkeypatch):
    """Job 1's folder holds an evaluation's results (an earlier sweep's job, its .hydra/ and log): refused before
    Hydra replaces its .hydra/ (the job's own check said so only after); overwrite=true lets the sweep replace
    them."""
    from eval import job_folders as eval_job_folders

    monkeypatch.chdir(tmp_path)
    _earlier_evaluation(tmp_path / "sweep" / "1")
    before = snapshot(tmp_path)
    cfg = hydra_loader([*EVAL, "seed=1000000,1000001", "hydra.sweep.dir=sweep"], command="eval")
    line = _refused(eval_job_folders.JobFolders().on_multirun_start, cfg, capsys)
    assert line == (f"error: sweep job 1 ({' '.join(EVAL)} seed=1000001): hydra.sweep.dir={tmp_path}/sweep/1 already "
                    f"holds results.csv of an evaluation; pick another hydra.sweep.dir, or replace it with "
                    f"overwrite=true; no job of the sweep was run")
    assert snapshot(tmp_path) == before


def test_an_eval_sweep_with_overwrite_replaces_an_earlier_evaluations_results(tmp_path, hydra_loader, monkeypatch):
    """overwrite=true: the earlier evaluation's results in job 1's folder are the sweep's to replace."""
    from eval import job_folders as eval_job_folders

    monkeypatch.chdir(tmp_path)
    _earlier_evaluation(tmp_path / "sweep" / "1")
    cfg = hydra_loader([*EVAL, "seed=1000000,1000001", "hydra.sweep.dir=sweep", "overwrite=true"], command="eval")
    eval_job_folders.JobFolders().on_multirun_start(config=cfg)


def test_an_eval_sweep_jobs_out_dir_only_the_job_resolves_is_checked_before_hydra_writes(tmp_path, capsys,
                                                                                      hydra_loader, monkeypatch):
    """``out_dir=res/${hydra:job.num}`` (the command line cannot resolve it) holding an earlier evaluation's results:
    judged as the job would judge it, before any job's folder is made."""
    from eval import job_folders as eval_job_folders

    monkeypatch.chdir(tmp_path)
    _earlier_evaluation(tmp_path / "res" / "0")
    before = snapshot(tmp_path)
    cfg = hydra_loader([*EVAL, "seed=1000000,1000001", "hydra.sweep.dir=sweep", "out_dir=res/${hydra:job.num}"],
                       command="eval")
    line = _refused(eval_job_folders.JobFolders().on_multirun_start, cfg, capsys)
    assert line.startswith("error: sweep job 0 (") and line.endswith(
        f"): out_dir={tmp_path}/res/0 already holds results.csv of an evaluation; pick another out_dir, or replace "
        f"it with overwrite=true; no job of the sweep was run"), line
    assert snapshot(tmp_path) == before and not (tmp_path / "sweep").exists()


def test_an_eval_run_folder_holding_a_users_file_is_refused_before_hydra_writes(tmp_path, capsys, hydra_loader,
                                                                                monkeypatch):
    """python -m eval hydra.run.dir=<the user's folder>: results (the default out_dir) and Hydra's record would go
    among the user's notes; refused by the run-level hook with nothing written. A new folder passes."""
    from eval import job_folders as eval_job_folders

    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine" / "notes.md").parent.mkdir()
    (tmp_path / "mine" / "notes.md").write_text("mine\n")
    before = snapshot(tmp_path)
    cfg = hydra_loader([*EVAL, "hydra.run.dir=mine"], RunMode.RUN, command="eval")
    line = _refused(eval_job_folders.JobFolders().on_run_start, cfg, capsys)
    assert line == (f"error: hydra.run.dir={tmp_path}/mine: holds files that are not an evaluation's (notes.md), "
                    f"which an evaluation never writes among; pick another hydra.run.dir (an empty or new folder)")
    assert snapshot(tmp_path) == before
    eval_job_folders.JobFolders().on_run_start(config=hydra_loader([*EVAL, "hydra.run.dir=new"], RunMode.RUN,
                                                                   command="eval"))


@pytest.mark.parametrize("command", ["train", "eval"])
def test_a_sweep_folder_holding_an_earlier_sweeps_record_is_refused_before_hydra_replaces_it(command, tmp_path,
                                                                                          capsys, hydra_loader,
                                                                                          monkeypatch):
    """hydra.sweep.dir holds an earlier sweep's multirun.yaml (Hydra writes this sweep's over it), or a user's file
    (an earlier sweep's python -m eval.sweep table): the sweep is refused in one line naming the folder, nothing
    written (a sweep whose every job replaces its own takes the record over: the next test)."""
    from eval import job_folders as eval_job_folders

    hook = (job_folders if command == "train" else eval_job_folders).JobFolders().on_multirun_start
    args = [*(RULE if command == "train" else EVAL), "seed=0,1" if command == "train" else "seed=1000000,1000001",
            "hydra.sweep.dir=sweep"]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sweep" / "0").mkdir(parents=True)  # a job's folder (judged as the job's own: empty, fine)
    (tmp_path / "sweep" / "multirun.yaml").write_text("earlier: sweep\n")
    before = snapshot(tmp_path)
    line = _refused(hook, hydra_loader(args, command=command), capsys)
    assert line == (f"error: hydra.sweep.dir={tmp_path}/sweep: holds an earlier sweep's record (multirun.yaml), which "
                    f"this sweep's would replace; pick another hydra.sweep.dir (an empty or new folder); no job of the "
                    f"sweep was run")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("command", ["train", "eval"])
def test_a_sweep_whose_every_job_replaces_its_own_takes_an_earlier_sweeps_record_over(command, tmp_path,
                                                                                     hydra_loader, monkeypatch):
    """Every job resumes or overwrites (train.overwrite=true, overwrite=true): the sweep continues or redoes the
    earlier one in that folder, whose record (and launcher's .submitit) and python -m eval.sweep summary (sweep.csv,
    sweep.md, its plot: written there by default) it takes over."""
    from eval import job_folders as eval_job_folders

    hook = (job_folders if command == "train" else eval_job_folders).JobFolders().on_multirun_start
    args = [*(RULE if command == "train" else EVAL), "seed=0,1" if command == "train" else "seed=1000000,1000001",
            "hydra.sweep.dir=sweep", "train.overwrite=true" if command == "train" else "overwrite=true"]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sweep" / ".submitit").mkdir(parents=True)
    (tmp_path / "sweep" / "multirun.yaml").write_text("earlier: sweep\n")
    for name in ("sweep.csv", "sweep.md", "sweep_success_vs_seed.png"):
        (tmp_path / "sweep" / name).write_text("python -m eval.sweep's summary\n")
    hook(config=hydra_loader(args, command=command))


@pytest.mark.parametrize("command", ["train", "eval"])
def test_a_sweep_folder_holding_what_is_no_sweeps_is_refused_whatever_the_flags(command, tmp_path, capsys,
                                                                                 hydra_loader, monkeypatch):
    """A file in hydra.sweep.dir that is neither a sweep's record, its python -m eval.sweep summary nor a job's
    folder (a user's notes, sweep.md.bak) would end up among this sweep's: refused even when every job replaces its
    own, nothing written."""
    from eval import job_folders as eval_job_folders

    hook = (job_folders if command == "train" else eval_job_folders).JobFolders().on_multirun_start
    args = [*(RULE if command == "train" else EVAL), "seed=0,1" if command == "train" else "seed=1000000,1000001",
            "hydra.sweep.dir=sweep", "train.overwrite=true" if command == "train" else "overwrite=true"]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sweep").mkdir()
    (tmp_path / "sweep" / "multirun.yaml").write_text("earlier: sweep\n")
    (tmp_path / "sweep" / "sweep.md").write_text("an earlier sweep's table\n")
    (tmp_path / "sweep" / "sweep.md.bak").write_text("a user's copy of it\n")
    before = snapshot(tmp_path)
    line = _refused(hook, hydra_loader(args, command=command), capsys)
    assert line == (f"error: hydra.sweep.dir={tmp_path}/sweep: holds what is not this sweep's (sweep.md.bak); pick "
                    f"another hydra.sweep.dir (an empty or new folder); no job of the sweep was run")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("command", ["train", "eval"])
def test_a_new_sweep_into_a_summarised_sweeps_folder_is_refused_naming_the_summary(command, tmp_path, capsys,
                                                                                   hydra_loader, monkeypatch):
    """A sweep whose jobs do not all continue theirs, into a folder python -m eval.sweep summarised: refused in one
    line that names the earlier sweep's record and its summary files as such, nothing written."""
    from eval import job_folders as eval_job_folders

    hook = (job_folders if command == "train" else eval_job_folders).JobFolders().on_multirun_start
    args = [*(RULE if command == "train" else EVAL), "seed=0,1" if command == "train" else "seed=1000000,1000001",
            "hydra.sweep.dir=sweep"]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sweep").mkdir()
    for name in ("multirun.yaml", "sweep.csv", "sweep.md"):
        (tmp_path / "sweep" / name).write_text("an earlier sweep's\n")
    before = snapshot(tmp_path)
    line = _refused(hook, hydra_loader(args, command=command), capsys)
    assert line == (f"error: hydra.sweep.dir={tmp_path}/sweep: holds what is not this sweep's (multirun.yaml, "
                    f"sweep.csv, sweep.md: an earlier sweep; sweep.csv, sweep.md: python -m eval.sweep's summary of "
                    f"it, which only a sweep whose every job resumes or overwrites its own takes over); pick another "
                    f"hydra.sweep.dir (an empty or new folder); no job of the sweep was run")
    assert snapshot(tmp_path) == before


def test_an_eval_sweep_giving_two_jobs_one_out_dir_is_refused_before_any_runs(tmp_path, capsys, hydra_loader,
                                                                              monkeypatch):
    """``-m seed=a,b out_dir=X``: job 1 found job 0's results in X and was refused once job 0 had run (the command
    line checks each job's X while it is still empty). Refused first now (one out_dir per job passes: the out_dir
    test above, its job 1)."""
    from eval import job_folders as eval_job_folders

    monkeypatch.chdir(tmp_path)
    cfg = hydra_loader([*EVAL, "seed=1000000,1000001", "hydra.sweep.dir=sweep", "out_dir=same"], command="eval")
    line = _refused(eval_job_folders.JobFolders().on_multirun_start, cfg, capsys)
    assert line == (f"error: sweep job 1 ({' '.join(EVAL)} seed=1000001 out_dir=same): out_dir={tmp_path}/same is job "
                    f"0's too: each evaluation needs a folder of its own; leave out_dir out (each job's folder) or "
                    f"give one per job (e.g. out_dir=<folder>/${{hydra:job.num}}); no job of the sweep was run")
    assert not list(tmp_path.iterdir())
