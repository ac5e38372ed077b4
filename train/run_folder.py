"""A training run owns its folders.

``checkpoints/<run_name>/`` and ``runs/<run_name>/`` belong to one run:

- a ``run_name`` whose folders already hold a run is refused, unless ``train.resume=true`` (continue it) or
  ``train.overwrite=true`` (delete it and start afresh): a second ``python -m train run_name=R`` would otherwise
  replace the first run's model.zip and config.yaml and write both runs' curves into one TensorBoard folder;
- ``train.resume=true`` needs the run's ``latest.zip``, and this command's env/sensors/shield/agent sections must be
  the run's own (its ``config.yaml``): both checked before anything is written, so a refused resume leaves the run
  as it was (config.yaml included) and a resume of a run that does not exist writes nothing;
- while a process trains a run it holds an exclusive ``flock`` on ``checkpoints/<run_name>/.lock``; a second process
  on the same run is refused in one line. The kernel drops the lock when the holder exits however it exits
  (kill -9 included), so a crashed run can be resumed at once (:class:`av_gym.atomic.OwnedFolders`, which
  ``python -m eval`` takes its out_dir with too);
- a finished run (its ``model.zip``, written by every trainer only once it is done) is not resumed: resuming it
  retrained from ``latest.zip`` and replaced ``model.zip`` with another model. Every trainer is treated
  alike: ``latest.zip`` is what a resume continues (PPO: at a rollout, DAgger: at a round), ``model.zip`` what ends
  a run; a kind that writes neither (PilotNet, a rule) has nothing to resume.

- the shipped references (:func:`av_gym.references.reference_root`) are neither a run's folder nor inside one, nor
  held by one (``run_name=reference``, ``paths.checkpoints=checkpoints/reference``, ``paths.runs=.``), whatever
  ``train.resume``/``train.overwrite`` say: ``train.overwrite=true`` would clear them;
- ``train.overwrite=true`` removes only what a run writes (:data:`CKPT_NAMES`, :data:`LOG_NAMES`, and inside
  ``tb/``, ``videos/``, ``.hydra/`` only their files: :data:`_SUB_FILES`): a run's folder that also holds a user's
  files (notes, plots, a sub-folder, an export in ``tb/``) is refused with nothing deleted
  (:func:`overwrite_problem`), and a folder holding files but no run's config is never written into, whatever the
  flags (:func:`foreign_problem`); the folder Hydra makes for a ``-m`` job or a ``${hydra:...}`` run dir, which
  the command line cannot resolve, is checked before Hydra writes into it (train/job_folders.py, Hydra's sweep- and
  run-level hooks) and again in the job (:func:`job_folder_problem`);
- a refusal gives only advice that works: a finished run is not told to resume; a run of a trained kind stopped
  before its first checkpoint (its folder holds only config.yaml) is told that ``train.overwrite=true`` starts it
  again.

``.``/``..`` and path separators in ``run_name`` are refused by its Params (``name_like``).
"""

from __future__ import annotations

import errno
import os
import re
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from av_gym.atomic import LOCK, OwnedFolders, lock_holder
from av_gym.errors import ConfigError

SECTIONS = ("env", "sensors", "shield", "agent")
# What may differ on resume: how long to train (PPO's steps, DAgger's rounds) and where, not what is trained
# (DAgger's labelling processes give the aggregate of one).
RESUME_MAY_CHANGE = ("agent.total_timesteps", "agent.rounds", "agent.device", "agent.workers")
LATEST, FINAL = "latest.zip", "model.zip"  # what a resume continues; what a finished run leaves (every trainer)

_held = OwnedFolders()  # the checkpoint folders this process trains
# The log folder the command-line check of a plain run checked (ownership_problem), before Hydra wrote its .hydra/
# there (train.__main__._check_command_line): neither the run-level hook (train.job_folders) nor the job checks it
# again (job_folder_problem, for the folders only Hydra resolves, cannot tell a run's .hydra/ from the one Hydra has
# just written).
LINE_CHECKED: set[Path] = set()
# What works for a run stopped before its first checkpoint: nothing of it is worth keeping, so it is cleared.
RESTART = ("start it again with train.overwrite=true (its config.yaml and logs are removed), or pick another "
           "run_name")


# What a run writes, and so all that train.overwrite=true removes. In its checkpoint folder: config.yaml
# (train/__main__.py), the lock, every trainer's checkpoints (latest.zip, best.zip and best.json, model.zip or the
# kind's own file: _checkpoint_names), DAgger's rounds.csv, an older run's latest.rng. In its log folder: Hydra's
# record (.hydra, the job log *.log, a sweep's multirun.yaml), TensorBoard (tb), the periodic evaluation's eval.csv
# and videos, DAgger's rounds.csv, PilotNet's demos.npz, the brief evaluation's results, a sweep job's error.txt,
# the code's commit and versions (provenance.json, train/provenance.py).
# Anything else there is the user's (notes, plots, a sub-folder): overwrite refuses rather than delete it or leave
# it among a new run's files (overwrite_problem).
CKPT_NAMES = frozenset({"config.yaml", LATEST, FINAL, "best.zip", "best.json", "rounds.csv", "latest.rng", LOCK})
LOG_NAMES = frozenset({".hydra", "multirun.yaml", "tb", "videos", "eval.csv", "rounds.csv", "results.csv",
                       "results.md", "demos.npz", "error.txt", "provenance.json"})
_TEMPORARY = re.compile(r"\.(.+)\.\d+\.tmp")  # av_gym.atomic.temporary_name: a write cut short (kill -9) leaves it
# The files a run writes inside the sub-folders of LOG_NAMES (name: file pattern, sub-folders allowed): TensorBoard's
# event files (tb/<agent name>/ of PPO and DAgger, tb/ of PilotNet; add_gif and the custom-scalar layout go into
# them too), the periodic evaluation's GIFs (train/callbacks.py), Hydra's record of the job. A sub-folder holding
# any other file (a user's tb/my_export.csv) is not the run's alone: overwrite refuses it rather than rmtree it.
_SUB_FILES = {"tb": (re.compile(r"events\.out\.tfevents\..+"), True),
              "videos": (re.compile(r"step_\d+\.gif"), False),
              ".hydra": (re.compile(r"(config|hydra|overrides)\.yaml"), False)}


def _checkpoint_names() -> frozenset[str]:
    """:data:`CKPT_NAMES` and each trained kind's final checkpoint file (``model.pt`` of PilotNet)."""
    from agents.registry import AGENT_KINDS, trained_kinds

    return CKPT_NAMES | {AGENT_KINDS.get(kind).checkpoint for kind in trained_kinds()}


def _a_runs(name: str, names: frozenset[str], logs: bool) -> bool:
    """Whether a run writes ``name`` in a folder of ``names`` (``logs``: a log folder, where Hydra's job log
    ``<job>.log`` is too), a temporary file of one of them included."""
    temporary = _TEMPORARY.fullmatch(name)
    base = temporary.group(1) if temporary else name
    return base in names or (logs and base.endswith(".log"))


def _users_inside(folder: Path, name: str) -> list[str]:
    """The files in the log sub-folder ``folder/name`` (``tb``, ``videos``, ``.hydra``: :data:`_SUB_FILES`) that no
    run writes, as ``name/<path inside>``; an unreadable folder is listed as itself (it cannot be judged). [] when
    ``name`` is no such folder."""
    pattern, deep = _SUB_FILES.get(name, (None, False))
    top = folder / name
    if pattern is None or top.is_symlink() or not top.is_dir():
        return []
    odd: list[str] = []
    unreadable = lambda exc: odd.append(os.path.relpath(exc.filename, folder))  # noqa: E731 - os.walk's hook
    for here, dirs, files in os.walk(top, onerror=unreadable):  # symlinked folders: not followed, judged as files
        links = [d for d in dirs if os.path.islink(os.path.join(here, d))]
        entries = files + (links if deep else dirs)  # a flat folder's sub-folder is the user's
        dirs[:] = [d for d in dirs if d not in links] if deep else []
        for entry in entries:
            temporary = _TEMPORARY.fullmatch(entry)
            if not pattern.fullmatch(temporary.group(1) if temporary else entry):
                odd.append(os.path.relpath(os.path.join(here, entry), folder))
    return sorted(odd)


def not_a_runs(folder: Path, logs: bool, also: frozenset[str] = frozenset()) -> list[str]:
    """The names in ``folder`` (a run's checkpoint folder, or with ``logs`` its log folder) that no run writes:
    the user's, and with ``logs`` a user's file inside a run's ``tb/``, ``videos/`` or ``.hydra/`` (as
    ``tb/<path>``: clearing the sub-folder would delete it). ``also``: more names a run writes there (the other
    folder's, when both are one folder)."""
    names = (LOG_NAMES if logs else _checkpoint_names()) | also
    odd = []
    for name in _contents(folder, ignore=()):
        if not _a_runs(name, names, logs):
            odd.append(name)
        elif logs and name not in also:
            odd += _users_inside(folder, name)
    return odd


def _listed(names: list[str]) -> str:
    return f"{', '.join(names[:3])}{' ...' if len(names) > 3 else ''}"


def _inside(outer: Path, inner: Path) -> frozenset[str]:
    """The name in ``outer`` on the way to ``inner`` when one of the run's folders holds the other
    (``hydra.run.dir=out paths.checkpoints=out/ckpt``): the run's own, neither the user's nor cleared as logs."""
    outer, inner = outer.resolve(), inner.resolve()
    return frozenset({inner.relative_to(outer).parts[0]}) if outer in inner.parents else frozenset()


def overwrite_problem(ckpt_dir: Path, runs_dir: Path | None, runs_flag: str = "paths.runs/run_name") -> str | None:
    """``train.overwrite=true`` removes only what a run writes (:data:`CKPT_NAMES`, :data:`LOG_NAMES`): a run's
    folder that holds anything else (a user's notes.md, a plot, a sub-folder) is refused with nothing deleted,
    rather than cleared or kept among the new run's files (which a later overwrite would then have to judge)."""
    same = runs_dir is not None and runs_dir.resolve() == ckpt_dir.resolve()  # paths.runs=paths.checkpoints
    found = [(ckpt_dir, "paths.checkpoints/run_name", not_a_runs(
        ckpt_dir, logs=same, also=_checkpoint_names() if same else _inside(ckpt_dir, runs_dir or ckpt_dir)))]
    if runs_dir is not None and not same:
        found.append((runs_dir, runs_flag, not_a_runs(runs_dir, logs=True, also=_inside(runs_dir, ckpt_dir))))
    for folder, flag, odd in found:
        if odd:
            return (f"train.overwrite=true: {flag}={folder} holds files a training run does not write "
                    f"({_listed(odd)}), and overwrite removes only a run's own (checkpoints, config.yaml, logs, "
                    f"TensorBoard, .hydra); nothing was deleted: move them out of it, or pick another "
                    f"{flag if flag.startswith('hydra') else 'run_name'}")
    return None


def job_folder_problem(run_dir: Path, ckpt_dir: Path, resume: bool, overwrite: bool, flag: str,
                       hydra_wrote: bool = True) -> str | None:
    """The folder Hydra makes for a job (``hydra.run.dir``, a sweep job's ``hydra.sweep.dir``/``subdir``), that the
    command line cannot resolve for a ``-m`` job or a ``${hydra:...}`` run dir: checked before Hydra writes there
    (``hydra_wrote=False``: train.job_folders, Hydra's sweep- and run-level hooks) and again in the job before
    anything of the run is written (``hydra_wrote=True``). Hydra's own files aside (``.hydra/``, the job log, a
    sweep's multirun.yaml), it may hold only a run's logs, and those only to resume or overwrite them: a user's
    files are refused whatever the flags, as the command line does. Before Hydra wrote, a user's file inside
    ``.hydra/`` is one too (after, ``.hydra/`` is the job's own)."""
    same = run_dir.resolve() == ckpt_dir.resolve()  # paths.runs=paths.checkpoints: a run's checkpoints are its too
    hydras = (".hydra", "multirun.yaml", LOCK, *_inside(run_dir, ckpt_dir))  # LOCK: paths.runs=paths.checkpoints
    held = [name for name in _contents(run_dir, ignore=hydras) if not name.endswith(".log")]
    odd = [name for name in held if not _a_runs(name, LOG_NAMES | (_checkpoint_names() if same else set()), True)]
    odd += [path for name in held if name not in odd for path in _users_inside(run_dir, name)]
    odd += [] if hydra_wrote else _users_inside(run_dir, ".hydra")
    if odd:
        return (f"{flag}={run_dir}: holds files that are not a training run's logs ({_listed(odd)}), which a run "
                f"never writes among or clears; pick another {flag} (an empty or new folder)")
    if held and not (resume or overwrite):
        return (f"{flag}={run_dir}: already holds a run's logs ({_listed(held)}); pick another {flag}, or replace "
                f"it with train.overwrite=true")
    return None


def _contents(folder: Path, ignore: tuple[str, ...] = (LOCK,)) -> list[str]:
    """Names in ``folder`` (none if it does not exist), without ``ignore``."""
    try:
        return sorted(p.name for p in folder.iterdir() if p.name not in ignore)
    except (FileNotFoundError, NotADirectoryError):
        return []


def _flat(node: Any, prefix: str) -> dict[str, Any]:
    if isinstance(node, Mapping):
        out = {}
        for key, value in node.items():
            out.update(_flat(value, f"{prefix}.{key}"))
        return out or {prefix: {}}
    return {prefix: list(node) if isinstance(node, (list, tuple)) else node}


def resume_problem(saved: Mapping, cfg: Mapping, config_path: Path) -> str | None:
    """The first setting of the sections a resumed run must keep that differs from the run's ``config.yaml``."""
    for section in SECTIONS:
        old, new = _flat(saved.get(section, {}), section), _flat(cfg.get(section, {}), section)
        first = (f"{section}.name", f"{section}.kind")  # a different scenario or kind says it all
        for key in sorted(set(old) | set(new), key=lambda k: (k not in first, k)):
            if key in RESUME_MAY_CHANGE or old.get(key, "<unset>") == new.get(key, "<unset>"):
                continue
            return (f"train.resume=true: {key} is {new.get(key, '<unset>')!r} here but {old.get(key, '<unset>')!r} "
                    f"in {config_path}; resume with the run's own settings, or train a new run_name")
    return None


def ownership_problem(ckpt_dir: Path, runs_dir: Path | None, resume: bool, overwrite: bool,
                      cfg: Mapping | None = None, runs_flag: str = "paths.runs/run_name") -> str | None:
    """Why this command may not write ``ckpt_dir`` (and ``runs_dir``, the run's log folder, given by
    ``runs_flag``), or None. The shipped references are refused first, and folders holding what is not a run's,
    whatever the flags (``train.overwrite=true`` would clear them)."""
    problem = shipped_problem_of(ckpt_dir, runs_dir) or foreign_problem(ckpt_dir, runs_dir, resume, runs_flag)
    if problem:
        return problem
    name = ckpt_dir.name
    other = "hydra.run.dir" if runs_flag == "hydra.run.dir" else "run_name"
    if resume:
        latest = ckpt_dir / LATEST
        if not latest.is_file():
            if dead_start(ckpt_dir):
                return (f"train.resume=true but run_name={name} stopped before its first checkpoint ({latest} does "
                        f"not exist, {ckpt_dir} holds only config.yaml): nothing to resume; {RESTART}")
            return (f"train.resume=true but {latest} does not exist (resume needs the run_name of a run that wrote "
                    f"a checkpoint)")
        config_path = ckpt_dir / "config.yaml"
        if cfg is not None and config_path.is_file():
            import yaml

            try:
                saved = yaml.safe_load(config_path.read_text()) or {}
            except (yaml.YAMLError, OSError) as exc:
                return f"train.resume=true: cannot read {config_path}: {' '.join(str(exc).split())[:200]}"
            if isinstance(saved, Mapping):
                problem = resume_problem(saved, cfg, config_path)
                if problem:
                    return problem
        return finished_problem(ckpt_dir)
    if overwrite:
        return overwrite_problem(ckpt_dir, runs_dir, runs_flag)
    held = _contents(ckpt_dir)
    if dead_start(ckpt_dir):
        return f"run_name={name}: {ckpt_dir} holds a run that stopped before its first checkpoint (only " \
               f"config.yaml; train.resume=true has nothing to continue); {RESTART}"
    if held:
        # only the advice that works: a finished run (or one that writes no latest.zip) has nothing to resume
        resumable = (ckpt_dir / LATEST).is_file() and not (ckpt_dir / FINAL).is_file()
        return (f"run_name={name}: {ckpt_dir} already holds a run ({', '.join(held[:3])}"
                f"{' ...' if len(held) > 3 else ''}); pick another run_name, "
                f"{'continue it with train.resume=true, ' if resumable else ''}or replace it with "
                f"train.overwrite=true")
    logs = _contents(runs_dir, ignore=()) if runs_dir is not None else []
    if logs:
        return (f"run_name={name}: {runs_dir} already holds a run's logs ({', '.join(logs[:3])}"
                f"{' ...' if len(logs) > 3 else ''}); pick another {other}, or replace it with train.overwrite=true")
    return None


def is_run_config(path: Path) -> bool:
    """Whether ``path`` is a training run's config (a YAML mapping with env and agent sections): what every run
    writes first, beside its checkpoints (config.yaml) and, through Hydra, in its log folder (.hydra/config.yaml)."""
    import yaml

    try:
        saved = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, OSError, UnicodeDecodeError):
        return False
    return isinstance(saved, Mapping) and all(isinstance(saved.get(k), Mapping) for k in ("env", "agent"))


def foreign_problem(ckpt_dir: Path, runs_dir: Path | None, resume: bool, runs_flag: str) -> str | None:
    """A folder of the run that holds files but no run's config (a user's project, ``hydra.run.dir=.``): a run
    would write its files among them and ``train.overwrite=true`` delete them all, so it is refused whatever the
    flags (a resume's checkpoint folder is checked by its own ``latest.zip`` and config.yaml instead)."""
    held = [] if resume else _contents(ckpt_dir)
    if held and not is_run_config(ckpt_dir / "config.yaml"):
        return (f"paths.checkpoints/run_name={ckpt_dir}: holds files that are not a training run's "
                f"({', '.join(held[:3])}{' ...' if len(held) > 3 else ''}; no run's config.yaml), which a run "
                f"never writes among or clears; pick another run_name")
    logs = _contents(runs_dir, ignore=()) if runs_dir is not None else []
    if logs and not is_run_config(runs_dir / ".hydra" / "config.yaml"):
        other = "hydra.run.dir (an empty or new folder)" if runs_flag == "hydra.run.dir" else "run_name"
        return (f"{runs_flag}={runs_dir}: holds files that are not a training run's logs ({', '.join(logs[:3])}"
                f"{' ...' if len(logs) > 3 else ''}; no run's .hydra/config.yaml), which a run never writes among "
                f"or clears; pick another {other}")
    return None


def shipped_problem_of(ckpt_dir: Path, runs_dir: Path | None) -> str | None:
    """The run's folders may neither be nor hold the shipped references (:func:`av_gym.references.shipped_problem`):
    ``run_name=reference`` or ``paths.checkpoints=checkpoints/reference`` would write, and with
    ``train.overwrite=true`` clear, the shipped agents."""
    from av_gym.references import shipped_problem

    return shipped_problem(ckpt_dir, "paths.checkpoints/run_name", cleared=True) or \
        (shipped_problem(runs_dir, "paths.runs/run_name", cleared=True) if runs_dir is not None else None)


def dead_start(ckpt_dir: Path) -> bool:
    """A run of a trained kind stopped before its first checkpoint: its folder holds the ``config.yaml`` the command
    wrote and nothing else (no ``latest.zip`` to resume, no model to keep). A rule-based agent's finished run holds
    only its config.yaml too, and is not one."""
    if _contents(ckpt_dir) != ["config.yaml"]:
        return False
    import yaml

    from agents.registry import trained_kinds

    try:
        saved = yaml.safe_load((ckpt_dir / "config.yaml").read_text())
    except (yaml.YAMLError, OSError):
        return False
    agent = saved.get("agent") if isinstance(saved, Mapping) else None
    return isinstance(agent, Mapping) and agent.get("kind") in trained_kinds()


def finished_problem(ckpt_dir: Path) -> str | None:
    """``train.resume=true`` of a run that finished (its ``model.zip`` exists): refused, so that its model and
    results are never replaced by a second training from ``latest.zip``."""
    final = ckpt_dir / FINAL
    if final.is_file():
        return (f"train.resume=true: run_name={ckpt_dir.name} finished ({final} is its final model), nothing to "
                f"resume; to train on from it, start a new run_name with agent.init_from={ckpt_dir}")
    return None


def claim(ckpt_dir: str | Path, runs_dir: str | Path | None, resume: bool, overwrite: bool,
          cfg: Mapping | None = None, runs_flag: str = "paths.runs/run_name") -> Path:
    """Check that this command may write the run (:func:`ownership_problem`; ``runs_flag``: what gave
    ``runs_dir``), then take its lock for the life of this process (or until :func:`release`). Raises
    :class:`ConfigError` with one line; a refused claim leaves nothing behind. Claiming a folder this process
    already holds returns at once."""
    ckpt_dir = Path(ckpt_dir)
    if ckpt_dir in _held:
        return ckpt_dir
    runs_dir = Path(runs_dir) if runs_dir is not None else None
    problem = ownership_problem(ckpt_dir, runs_dir, resume, overwrite, cfg, runs_flag)
    if problem:
        raise ConfigError(problem)
    try:
        _held.take(ckpt_dir)
    except BlockingIOError:
        pid = lock_holder(ckpt_dir / LOCK)
        raise ConfigError(f"run_name={ckpt_dir.name}: another process{f' (pid {pid})' if pid else ''} is training "
                          f"this run ({ckpt_dir / LOCK} is locked); wait for it, or pick another run_name") from None
    except OSError as exc:
        raise ConfigError(f"paths.checkpoints: cannot write {ckpt_dir}: {os.strerror(exc.errno or errno.EIO)}") \
            from None
    # Checked again under the lock: two commands started together both passed the check above.
    problem = ownership_problem(ckpt_dir, runs_dir, resume, overwrite, cfg, runs_flag)
    if problem:
        release(ckpt_dir)
        raise ConfigError(problem)
    return ckpt_dir


def release(ckpt_dir: str | Path) -> None:
    """Drop the lock on ``ckpt_dir`` (the lock file is removed, and the folder if nothing else is in it)."""
    _held.release(ckpt_dir)


def release_all(keep: str | Path | None = None) -> None:
    """Release every run this process holds but ``keep`` (the command-line check claims ``run_name`` as it
    composes it; a ``${now:...}`` in it may resolve a second later in the job)."""
    _held.release_all(keep)


def discard_if_unstarted(ckpt_dir: Path) -> bool:
    """A fresh run refused once its job had started (an ``agent.init_from`` that does not fit, found by the
    trainer): remove the ``config.yaml`` this command wrote when it is all the folder holds, so that the refused
    run leaves nothing behind and its run_name stays free. Returns whether it was removed."""
    if _contents(ckpt_dir) != ["config.yaml"]:
        return False
    (ckpt_dir / "config.yaml").unlink()
    return True


def clear_for_overwrite(ckpt_dir: Path, run_dir: Path | None, runs_flag: str = "hydra.run.dir") -> list[str]:
    """``train.overwrite=true``: delete the previous run's files (checkpoints; logs and TensorBoard except the
    ``.hydra/`` and log Hydra just wrote for this job), and only those (:func:`overwrite_problem`, checked again
    here: nothing is deleted when either folder holds what a run does not write). Only under the run's lock.
    Returns what was removed."""
    if ckpt_dir not in _held:
        raise RuntimeError(f"clear_for_overwrite({ckpt_dir}) without holding its lock")
    problem = shipped_problem_of(ckpt_dir, run_dir) or overwrite_problem(ckpt_dir, run_dir, runs_flag)
    if problem:  # Hydra's run folder too (hydra.run.dir is the user's)
        raise ConfigError(problem)
    removed = []
    for folder, keep, logs in ((ckpt_dir, (LOCK,), False), (run_dir, (".hydra",), True)):
        if folder is None:
            continue
        names = LOG_NAMES if logs else _checkpoint_names()
        keep = (*keep, *_inside(folder, run_dir if folder == ckpt_dir else ckpt_dir)) if run_dir else keep
        for name in _contents(folder, ignore=keep):
            path = folder / name
            if (folder == run_dir and path.suffix == ".log") or not _a_runs(name, names, logs):
                continue
            shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
            removed.append(str(path))
    return removed
