"""A training job's folders checked before Hydra writes into them (``hydra.callbacks.job_folders`` in
conf/train.yaml; the hooks and the sweep folder's check: conf/job_folders.py, shared with python -m eval).

A folder the command line could not see (a ``-m`` sweep's ``hydra.sweep.dir``/``subdir``, a
``hydra.run.dir=${hydra:...}``) was checked only inside the job (:func:`train.run_folder.job_folder_problem`), after
Hydra had written its ``.hydra/`` and job log into it: a refused job left both among a user's files, and replaced the
``.hydra/`` of a previous run whose folder it was refused. Here each job's folders are checked as the job would check
them, in Hydra's sweep- and run-level hooks, before any job folder is made. The job keeps its own check (a sweeper
other than the basic one picks its jobs' overrides as it goes: only the job knows them)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from av_gym.errors import ConfigError
from conf.job_folders import JobFolders as _JobFolders
from conf.job_folders import hydra_config, task_section


class JobFolders(_JobFolders):
    """Checks every job's log folder (and checkpoint folder) of ``python -m train`` before Hydra makes any."""

    def check_run(self, config: DictConfig) -> None:
        check_run(config)

    def job_problem(self, num: int, job: DictConfig, run_dir: Path) -> str | None:
        """Job ``num``'s folder as :func:`job_folder_problem` judges it before Hydra writes there, and its
        checkpoint folder (``<run_name>-j<num>``) as its claim does."""
        from train.run_folder import SECTIONS, job_folder_problem, ownership_problem

        command = _command(job)
        ckpt_dir = Path(command.paths.checkpoints) / f"{command.run_name}-j{num}"  # train.__main__._claim_folders
        resume, overwrite = command.train.resume, command.train.overwrite
        sections = {k: OmegaConf.to_container(job[k], resolve=True) for k in SECTIONS}
        return job_folder_problem(run_dir, ckpt_dir, resume, overwrite, "hydra.sweep.dir", hydra_wrote=False) or \
            ownership_problem(ckpt_dir, None, resume, overwrite, sections)

    def replaces(self, job: DictConfig) -> bool:
        """A job that resumes or overwrites its run: a sweep of such jobs continues (or redoes) an earlier one."""
        command = _command(job)
        return command.train.resume or command.train.overwrite


def _command(config: DictConfig):
    """The job's TrainCommand (``run_name``, ``paths``, ``train``), its ``hydra`` section left unresolved."""
    from conf.commands import TrainCommand

    return TrainCommand.of(task_section(config))


def check_run(config: DictConfig) -> None:
    """A plain run's ``hydra.run.dir``, when the command line could not resolve it (``${hydra:...}``: see
    :func:`train.__main__.run_dir_of`): checked as the job would, before Hydra writes ``.hydra/`` and the log there.
    Raises :class:`ConfigError`."""
    from train.run_folder import LINE_CHECKED, job_folder_problem

    with hydra_config(config):  # what ${hydra:...} reads; run_job sets it again
        run_dir = Path(str(config.hydra.run.dir)).absolute()
        if run_dir.resolve() in LINE_CHECKED:  # the command line checked and claimed it before Hydra wrote there
            return
        command = _command(config)
    ckpt_dir = Path(command.paths.checkpoints) / command.run_name
    problem = job_folder_problem(run_dir, ckpt_dir, command.train.resume, command.train.overwrite,
                                 "hydra.run.dir", hydra_wrote=False)
    if problem:
        raise ConfigError(problem)
