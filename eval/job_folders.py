"""An evaluation job's folder checked before Hydra writes into it (``hydra.callbacks.job_folders`` in
conf/eval.yaml; the hooks, the sweep folder's check and how each job's folder is resolved: conf/job_folders.py,
shared with python -m train).

Hydra writes a job's ``.hydra/`` and job log (``__main__.log``) before the job can check anything, and an
evaluation's default ``out_dir`` is that folder (``${hydra:runtime.output_dir}``): a ``-m`` job whose folder held
an earlier evaluation's results was refused only after Hydra had written both there, and one whose folder held a
user's ``notes.md`` wrote its results beside it. Here each job's folder (a sweep's ``hydra.sweep.dir``/``subdir``, a
plain run's ``hydra.run.dir``) and its ``out_dir`` are judged before Hydra makes any (:func:`folder_problem`)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from av_gym.atomic import LOCK
from conf.job_folders import JobFolders as _JobFolders
from conf.job_folders import entries, hydra_users, task_section

RESULTS = ("results.csv", "results.md")  # what overwrite=true replaces (eval.__main__.results_problem)
# What an evaluation writes in its out_dir (eval/__main__.py, eval/report.py, eval/meta.py, eval/plots.py), and a
# failed sweep job's traceback (av_gym.errors._save_traceback); Hydra's .hydra/ and job log are judged apart.
EVAL_NAMES = frozenset({*RESULTS, "meta.json", LOCK, "error.txt"})
FIGURE = re.compile(r"cte_.+\.png|(lap|turn)_.+\.webm")  # eval.plots: cte_<agent>.png, cte_all.png, <kind>_<agent>.webm
_TEMPORARY = re.compile(r"\.(.+)\.\d+\.tmp(\.webm)?")  # av_gym.atomic.temporary_name (a video's ends in .webm too)


def evaluations(name: str) -> bool:
    """Whether an evaluation (or Hydra, for its job) writes ``name`` in its folder, a write cut short included."""
    temporary = _TEMPORARY.fullmatch(name)
    base = temporary.group(1) if temporary else name
    return base in EVAL_NAMES or bool(FIGURE.fullmatch(base)) or base == ".hydra" or base.endswith(".log")


def outputs_problem(folder: str | Path, overwrite: bool, flag: str, elsewhere: str = "") -> str | None:
    """Why an evaluation may not write its outputs into ``folder`` (given by ``flag``; ``elsewhere``: advice after
    "pick another <flag>"), or None: never inside the shipped references or beside a meta.json eval did not write;
    an earlier evaluation's results only with ``overwrite=true``. The job's own check too
    (eval.__main__.results_problem)."""
    from av_gym.references import shipped_problem
    from conf.cli import held_outputs_problem
    from eval.meta import hand_written_problem

    problem = shipped_problem(folder, flag) or hand_written_problem(folder)
    if problem:
        return problem.replace(f"out_dir={folder}", f"{flag}={folder}", 1)
    return held_outputs_problem(flag, folder, RESULTS, overwrite, whose=" of an evaluation", elsewhere=elsewhere,
                                replace="overwrite=true")


def folder_problem(run_dir: Path, out_dir: Path, overwrite: bool, flag: str) -> str | None:
    """Why an evaluation job may not write its folder ``run_dir`` (given by ``flag``) and ``out_dir``, before Hydra
    writes there, or None. The folder may hold only what an evaluation and Hydra write (a user's file, one inside
    ``.hydra/`` included, is refused whatever ``overwrite`` says: results and Hydra's record would be written among
    it); the results there, or in an ``out_dir`` the command line could not resolve, as the job would judge them."""
    odd = [name for name in entries(run_dir) if not evaluations(name)] + hydra_users(run_dir)
    if odd:
        shown = f"{', '.join(odd[:3])}{' ...' if len(odd) > 3 else ''}"
        return (f"{flag}={run_dir}: holds files that are not an evaluation's ({shown}), which an evaluation never "
                f"writes among; pick another {flag} (an empty or new folder)")
    return outputs_problem(run_dir, overwrite, flag) or \
        (None if out_dir == run_dir else outputs_problem(out_dir, overwrite, "out_dir"))


class JobFolders(_JobFolders):
    """Checks every job's folder and out_dir of ``python -m eval`` before Hydra makes any."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self.out_dirs: dict[Path, int] = {}  # each job's out_dir, for the next: one evaluation's folder each
        super().on_multirun_start(config, **kwargs)

    def run_problem(self, job: DictConfig, run_dir: Path) -> str | None:
        return _problem(job, run_dir, "hydra.run.dir")

    def job_problem(self, num: int, job: DictConfig, run_dir: Path) -> str | None:
        """Also two jobs given one ``out_dir`` (``-m seed=1,2 out_dir=X``): the second found the first's results
        there and was refused once the first had run."""
        from conf.commands import EvalCommand

        out_dir = Path(EvalCommand.of(task_section(job)).out_dir).absolute()
        first = self.out_dirs.setdefault(out_dir, num)
        if first != num:
            return (f"out_dir={out_dir} is job {first}'s too: each evaluation needs a folder of its own; leave "
                    f"out_dir out (each job's folder) or give one per job (e.g. out_dir=<folder>/${{hydra:job.num}})")
        return _problem(job, run_dir, "hydra.sweep.dir")

    def replaces(self, job: DictConfig) -> bool:
        """``overwrite=true``: the job replaces an earlier evaluation's results."""
        return bool(job.get("overwrite", False))


def _problem(job: DictConfig, run_dir: Path, flag: str) -> str | None:
    from conf.commands import EvalCommand

    command = EvalCommand.of(task_section(job))
    return folder_problem(run_dir, Path(command.out_dir).absolute(), command.overwrite, flag)
