"""Every folder Hydra is about to write for ``python -m train`` and ``python -m eval``, checked before it writes
(``hydra.callbacks.job_folders`` in conf/train.yaml and conf/eval.yaml; each command's own rule:
train/job_folders.py, eval/job_folders.py).

Hydra makes a job's folder, opens its job log there (``<job>.log``) and writes ``.hydra/`` *before* any hook of the
job runs (``hydra.core.utils.run_job``: ``configure_log`` and ``_save_config``, then ``on_job_start``), and the
basic sweeper writes the sweep's record ``multirun.yaml`` into ``hydra.sweep.dir`` before it launches a job
(``BasicSweeper.sweep``): a job that checked its own folder could refuse only after Hydra had written among a user's
files, and an earlier sweep's ``multirun.yaml`` was replaced by the next sweep given the same ``hydra.sweep.dir``.

The sweep-level and run-level hooks run before any of that (``Hydra.multirun``: ``on_multirun_start``, then the
sweeper; ``Hydra.run``: ``on_run_start``, then ``run_job``). Here every job's folder is resolved the way the launcher
does it (the basic sweeper's job overrides, ``ConfigLoader.load_sweep_config`` with ``hydra.job.num`` set,
``hydra.sweep.dir``/``hydra.sweep.subdir``; ``hydra.runtime.output_dir``, what ``${hydra:runtime.output_dir}``
reads, as ``run_job`` sets it), the sweep folder is checked (:func:`sweep_dir_problem`) and each job's folders as
the command's job would check them (:meth:`JobFolders.job_problem`); a refusal ends the command in one line, exit
status 2, before any job runs and with nothing written."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from av_gym.errors import ConfigError, run_cli

try:
    from hydra.experimental.callback import Callback
except ImportError:  # pragma: no cover - hydra-core < 1.1
    Callback = object

BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"
RECORD = "multirun.yaml"  # the sweep's record, written by the basic sweeper into hydra.sweep.dir
LAUNCHER_FILES = frozenset({RECORD, ".submitit"})  # a sweep's own in its folder (submitit's job logs and pickles)
_HYDRA_FILES = re.compile(r"(config|hydra|overrides)\.yaml")  # what Hydra writes in a job's .hydra/
# python -m eval.sweep's summary of the sweep, written into its folder by default (eval/sweep.py: sweep.csv, sweep.md
# and sweep_<metric>_vs_<x>.png): this project's own, of the sweep a resumed / overwrite=true sweep continues
SUMMARY_FILES = re.compile(r"sweep\.(csv|md)|sweep_.+_vs_.+\.png")


class JobFolders(Callback):
    """Checks the folders of a command's jobs before Hydra makes any; a command's subclass says what its job may
    find there (:meth:`job_problem`, :meth:`run_problem`) and whether it replaces an earlier job
    (:meth:`replaces`)."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        run_cli(self.check_run, config)  # a refusal: one line, SystemExit(2) (Hydra turns exceptions into warnings)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        run_cli(check_sweep, config, self)

    def check_run(self, config: DictConfig) -> None:
        """A plain run's ``hydra.run.dir``: :meth:`run_problem`, raised as :class:`ConfigError`."""
        with hydra_config(config):
            run_dir = Path(str(config.hydra.run.dir)).absolute()
            problem = self.run_problem(as_job(config, run_dir), run_dir)
        if problem:
            raise ConfigError(problem)

    def run_problem(self, job: DictConfig, run_dir: Path) -> str | None:
        """Why a plain run may not write ``run_dir`` (``job``: its config as the job sees it), or None."""
        return None

    def job_problem(self, num: int, job: DictConfig, run_dir: Path) -> str | None:
        """Why sweep job ``num`` may not write ``run_dir`` (its folder), or None; run with Hydra's config set to the
        job's (``${hydra:job.num}`` and ``${hydra:runtime.output_dir}`` resolve as in the job)."""
        return None

    def replaces(self, job: DictConfig) -> bool:
        """Whether the job continues or replaces an earlier job in its folder (train.resume, overwrite): then a
        sweep of such jobs alone may replace the record of the sweep it continues (:func:`sweep_dir_problem`)."""
        return False


class hydra_config:  # noqa: N801 - a context manager, named as the state it sets
    """Hydra's config (what ``${hydra:...}`` reads) set to ``config`` for the block, the previous one restored."""

    def __init__(self, config: DictConfig) -> None:
        self.config = config

    def __enter__(self) -> None:
        from hydra.core.hydra_config import HydraConfig

        self.previous = HydraConfig.instance().cfg
        HydraConfig.instance().set_config(self.config)

    def __exit__(self, *exc: Any) -> None:
        from hydra.core.hydra_config import HydraConfig

        HydraConfig.instance().cfg = self.previous


def as_job(config: DictConfig, run_dir: Path) -> DictConfig:
    """``config`` with ``hydra.runtime.output_dir`` set to ``run_dir`` as ``run_job`` sets it before the job runs
    (eval's ``out_dir: ${hydra:runtime.output_dir}`` reads it); Hydra's config set to it too."""
    from hydra.core.hydra_config import HydraConfig

    job = config.copy()
    with read_write(job.hydra.runtime):  # as run_job writes it (hydra.core.utils.run_job)
        job.hydra.runtime.output_dir = str(run_dir)
    HydraConfig.instance().set_config(job)
    return job


def task_section(job: DictConfig) -> dict:
    """The job's own settings (every key but ``hydra``), resolved as the job resolves them."""
    return {k: OmegaConf.to_container(job[k], resolve=True) if OmegaConf.is_config(job[k]) else job[k]
            for k in job if k != "hydra"}


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


def _listed(names: list[str]) -> str:
    return f"{', '.join(names[:3])}{' ...' if len(names) > 3 else ''}"


def sweep_dir_problem(sweep_dir: Path, job_dirs: list[Path] | None, continues: bool) -> str | None:
    """Why a sweep may not write ``sweep_dir`` (``hydra.sweep.dir``), or None. Before the sweep starts nothing in it
    is this sweep's but the folders of its jobs (``job_dirs``, judged by each job's own check): an earlier sweep's
    record ``multirun.yaml`` would be replaced (Hydra writes this sweep's there), and anything else (a user's notes,
    an earlier sweep's aggregate from python -m eval.sweep) would end up among this sweep's. Only a sweep whose jobs
    all continue or replace theirs (``continues``: train.resume, overwrite) takes over the earlier sweep's record
    (and its launcher's ``.submitit``) and its summary (``python -m eval.sweep``'s sweep.csv, sweep.md, plot:
    :data:`SUMMARY_FILES`, rewritten when the sweep is summarised again); any other sweep is told what the summary
    is. ``job_dirs`` None (a sweeper that picks its jobs as it goes): nothing may be there but that record."""
    try:
        held = sorted(p.name for p in sweep_dir.iterdir())
    except (FileNotFoundError, NotADirectoryError):  # a file there is the folder check's (conf.cli.out_folder_problem)
        return None
    tops = {d.relative_to(sweep_dir).parts[0] for d in job_dirs or [] if sweep_dir in d.parents}
    odd = [name for name in held if name not in tops
           and not (continues and (name in LAUNCHER_FILES or SUMMARY_FILES.fullmatch(name)))]
    if not odd:
        return None
    summary = [name for name in odd if SUMMARY_FILES.fullmatch(name)]
    what = (f"an earlier sweep's record ({_listed(odd)}), which this sweep's would replace" if odd == [RECORD] else
            f"what is not this sweep's ({_listed(odd)}{': an earlier sweep' if RECORD in odd else ''}"
            + (f"; {_listed(summary)}: python -m eval.sweep's summary of it, which only a sweep whose every job "
               f"resumes or overwrites its own takes over" if summary else "") + ")")
    return f"hydra.sweep.dir={sweep_dir}: holds {what}; pick another hydra.sweep.dir (an empty or new folder)"


def check_sweep(config: DictConfig, folders: JobFolders) -> None:
    """A ``-m`` sweep's folder (:func:`sweep_dir_problem`), then each job's (``hydra.sweep.dir``/``subdir``) as
    ``folders`` judges it. The first refusal ends the sweep before any job ran. Raises :class:`ConfigError`."""
    with hydra_config(config):
        # resolved here first, as the sweeper does, so that a ${now:...} in it is cached in the sweep's config and
        # each job's (load_sweep_config copies the cache): the folders checked are the ones the sweep gets
        sweep_dir = Path(str(config.hydra.sweep.dir)).absolute()
        jobs = job_configs(config)
        dirs = [_job_dir(job) for _, job in jobs or []]
        continues = bool(jobs) and all(folders.replaces(job) for _, job in jobs)
        problem = sweep_dir_problem(sweep_dir, None if jobs is None else dirs, continues)
        if problem:
            raise ConfigError(f"{problem}; no job of the sweep was run")
        for num, ((overrides, job), run_dir) in enumerate(zip(jobs or [], dirs)):
            problem = folders.job_problem(num, as_job(job, run_dir), run_dir)
            if problem:
                raise ConfigError(f"sweep job {num} ({' '.join(overrides)}): {problem}; no job of the sweep was "
                                  f"run")


def _job_dir(job: DictConfig) -> Path:
    """A sweep job's folder, as the launcher makes it (``${hydra:job.num}`` and the like resolved as in the job)."""
    from hydra.core.hydra_config import HydraConfig

    HydraConfig.instance().set_config(job)
    return Path(str(job.hydra.sweep.dir)).absolute() / str(job.hydra.sweep.subdir)


def hydra_users(run_dir: Path) -> list[str]:
    """What in ``run_dir/.hydra`` Hydra does not write (its config, hydra and overrides YAML files), as
    ``.hydra/<path>``: a user's file there would be written among, or replaced, by the job's."""
    top = run_dir / ".hydra"
    if top.is_symlink() or not top.is_dir():
        return []
    return [f".hydra/{p.relative_to(top)}" for p in sorted(top.iterdir())
            if p.is_symlink() or not p.is_file() or not _HYDRA_FILES.fullmatch(p.name)]


def entries(folder: Path) -> Iterator[str]:
    """The names in ``folder``, sorted (none when it does not exist)."""
    try:
        yield from sorted(p.name for p in folder.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return
