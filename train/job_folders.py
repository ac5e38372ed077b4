"""A training job's log folder checked before Hydra writes into it (``hydra.callbacks.job_folders`` in
conf/train.yaml).

Hydra makes a job's folder, opens its job log there (``<job>.log``) and writes ``.hydra/`` *before* any hook of the
job runs (``hydra.core.utils.run_job``: ``configure_log`` and ``_save_config``, then ``on_job_start``). A folder the
command line could not see (a ``-m`` sweep's ``hydra.sweep.dir``/``subdir``, a ``hydra.run.dir=${hydra:...}``) was
therefore checked only inside the job (:func:`train.run_folder.job_folder_problem`), after Hydra had written into it:
a refused job left its ``.hydra/`` and log among a user's files, and replaced the ``.hydra/`` of a previous run
whose folder it was refused.

The sweep-level and run-level hooks run before any job folder is made (``Hydra.multirun``: ``on_multirun_start``,
then the sweeper; ``Hydra.run``: ``on_run_start``, then ``run_job``). There every job's folder is resolved the way
the launcher does it (the basic sweeper's job overrides, ``ConfigLoader.load_sweep_config`` with ``hydra.job.num``
set, ``hydra.sweep.dir``/``hydra.sweep.subdir``) and each job's folders are checked as the job would check them; a
refusal ends the command in one line, exit status 2, before any job runs and with nothing written. The job keeps its
own check (a sweeper other than the basic one picks its jobs' overrides as it goes: only the job knows them)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from av_gym.errors import ConfigError, run_cli

try:
    from hydra.experimental.callback import Callback
except ImportError:  # pragma: no cover - hydra-core < 1.1
    Callback = object

BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


class JobFolders(Callback):
    """Checks every job's log folder (and checkpoint folder) of ``python -m train`` before Hydra makes any."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        run_cli(check_run, config)  # a refusal: one line, SystemExit(2) (Hydra turns exceptions into warnings)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        run_cli(check_sweep, config)


def _command(config: DictConfig):
    """The job's TrainCommand (``run_name``, ``paths``, ``train``), its ``hydra`` section left unresolved."""
    from conf.commands import TrainCommand

    return TrainCommand.of({k: OmegaConf.to_container(config[k], resolve=True) if OmegaConf.is_config(config[k])
                            else config[k] for k in config if k != "hydra"})


def check_run(config: DictConfig) -> None:
    """A plain run's ``hydra.run.dir``, when the command line could not resolve it (``${hydra:...}``: see
    :func:`train.__main__.run_dir_of`): checked as the job would, before Hydra writes ``.hydra/`` and the log there.
    Raises :class:`ConfigError`."""
    from hydra.core.hydra_config import HydraConfig

    from train.run_folder import LINE_CHECKED, job_folder_problem

    previous = HydraConfig.instance().cfg
    HydraConfig.instance().set_config(config)  # what ${hydra:...} reads; run_job sets it again
    try:
        run_dir = Path(str(config.hydra.run.dir)).absolute()
        if run_dir.resolve() in LINE_CHECKED:  # the command line checked and claimed it before Hydra wrote there
            return
        command = _command(config)
    finally:
        HydraConfig.instance().cfg = previous
    ckpt_dir = Path(command.paths.checkpoints) / command.run_name
    problem = job_folder_problem(run_dir, ckpt_dir, command.train.resume, command.train.overwrite,
                                 "hydra.run.dir", hydra_wrote=False)
    if problem:
        raise ConfigError(problem)


def job_configs(config: DictConfig) -> list[tuple[list[str], DictConfig]] | None:
    """Every job of the sweep ``config`` describes, in job-number order: its overrides and its config as the
    launcher composes it (``hydra.job.num``/``id`` set, so ``hydra.sweep.subdir`` resolves). None for a sweeper
    other than the basic one (it chooses its jobs as it goes)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    if config.hydra.sweeper.get("_target_") != BASIC_SWEEPER:
        return None
    loader = GlobalHydra.instance().config_loader()
    params = config.hydra.sweeper.get("params") or {}
    arguments = [f"{k}={v}" for k, v in params.items()] + list(OmegaConf.to_container(config.hydra.overrides.task))
    parsed = OverridesParser.create(config_loader=loader).parse_overrides(arguments)
    jobs = []
    for num, overrides in enumerate(o for batch in BasicSweeper.split_arguments(parsed, None) for o in batch):
        job = loader.load_sweep_config(config, list(overrides))
        with open_dict(job), read_write(job):  # as the launchers do (hydra_joblib_launcher._core.execute_job)
            job.hydra.job.id = f"{job.hydra.job.name}_{num}"
            job.hydra.job.num = num
        jobs.append((list(overrides), job))
    return jobs


def check_sweep(config: DictConfig) -> None:
    """Each job of a ``-m`` sweep: its folder (``hydra.sweep.dir``/``subdir``) as :func:`job_folder_problem` judges
    it before Hydra writes there, and its checkpoint folder (``<run_name>-j<num>``) as its claim does. The first
    refusal ends the sweep before any job ran. Raises :class:`ConfigError`."""
    from hydra.core.hydra_config import HydraConfig

    from train.run_folder import SECTIONS, job_folder_problem, ownership_problem

    previous = HydraConfig.instance().cfg
    HydraConfig.instance().set_config(config)
    try:
        # resolved here first, as the sweeper does, so that a ${now:...} in it is cached in the sweep's config and
        # each job's (load_sweep_config copies the cache): the folder checked is the one the jobs get
        str(config.hydra.sweep.dir)
        jobs = job_configs(config)
        for num, (overrides, job) in enumerate(jobs or []):
            HydraConfig.instance().set_config(job)  # ${hydra:job.num} and the like, as in the job
            run_dir = Path(str(job.hydra.sweep.dir)) / str(job.hydra.sweep.subdir)
            command = _command(job)
            ckpt_dir = Path(command.paths.checkpoints) / f"{command.run_name}-j{num}"  # train.__main__._claim_folders
            resume, overwrite = command.train.resume, command.train.overwrite
            sections = {k: OmegaConf.to_container(job[k], resolve=True) for k in SECTIONS}
            problem = job_folder_problem(run_dir.absolute(), ckpt_dir, resume, overwrite, "hydra.sweep.dir",
                                         hydra_wrote=False) or \
                ownership_problem(ckpt_dir, None, resume, overwrite, sections)
            if problem:
                raise ConfigError(f"sweep job {num} ({' '.join(overrides)}): {problem}; no job of the sweep was "
                                  f"run")
    finally:
        HydraConfig.instance().cfg = previous
