"""The one exception type for bad user input (configs, paths, checkpoints). The command-line entry points print
its message as a single line and exit with status 2."""

from __future__ import annotations

from pathlib import Path


class ConfigError(ValueError):
    """A user-facing configuration or input error; its message names the field and the allowed values."""


def run_cli(fn, *args, hydra_run_dir: bool = False) -> None:
    """Run a command-line entry point: a :class:`ConfigError` becomes one line on stderr and exit status 2;
    Ctrl-C / SIGTERM exit with 130 (SIGTERM is raised as KeyboardInterrupt: whatever needed saving was saved by the
    code that was interrupted).

    ``hydra_run_dir``: ``fn`` runs as a Hydra job, whose folder Hydra made before ``fn`` could check anything; on a
    ConfigError it is removed again when it holds nothing but what Hydra wrote (see :func:`discard_hydra_run_dir`)."""
    import sys

    interrupt_on_sigterm()
    try:
        fn(*args)
    except ConfigError as exc:
        if hydra_run_dir:
            discard_hydra_run_dir()
        print("error: " + " ".join(str(exc).split()), file=sys.stderr)  # one line, whatever the message holds
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)


def interrupt_on_sigterm() -> None:
    """SIGTERM (``kill PID``, ``timeout``, a scheduler's end of job) raises KeyboardInterrupt, as Ctrl-C does, so
    that what the code keeps on Ctrl-C (measured episodes, a checkpoint) is kept on SIGTERM too; it used to end the
    process at once (rc 143, the episodes lost). Only where SIGTERM still has its default action, in the main
    thread (a handler set by the code, e.g. training's, is left alone)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread() and \
            signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, _raise_interrupt)


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def discard_hydra_run_dir() -> bool:
    """Remove the current Hydra job's output folder if it holds only Hydra's own files (``.hydra/`` and an empty
    job log), then any parent that became empty, up to the working directory. A folder with anything of ours (a
    resumed run's TensorBoard logs, a previous run's results) is kept. Returns whether it was removed.

    The command-line check (:func:`conf.check.check_command_line`) runs before Hydra and catches most
    bad input with nothing written; this covers what can only be checked once the job runs (a checkpoint that
    does not fit the env, say)."""
    import shutil

    try:
        from hydra.core.hydra_config import HydraConfig

        run_dir = Path(HydraConfig.get().runtime.output_dir).resolve()
    except Exception:  # not a Hydra job (an API call): nothing of Hydra's to clean
        return False
    if not run_dir.is_dir():
        return False
    for entry in run_dir.iterdir():
        if entry.name == ".hydra" and entry.is_dir():
            continue
        if entry.suffix == ".log" and entry.is_file() and entry.stat().st_size == 0:
            continue
        return False
    import logging

    logging.shutdown()  # Hydra's job log file handler holds the .log open
    shutil.rmtree(run_dir, ignore_errors=True)
    cwd = Path.cwd().resolve()
    parent = run_dir.parent
    while parent != cwd and cwd in parent.parents:
        try:
            parent.rmdir()  # only when empty
        except OSError:
            break
        parent = parent.parent
    return True


def folder_problem(path: str | Path, field: str) -> str | None:
    """Why folder ``path`` (the value of setting ``field``) could not be made and written, in one line, or None.

    Checked before any work, so that a run does not measure for an hour and then fail to write: every name must fit
    the file system (``NAME_MAX``, ``PATH_MAX``); an existing part must be a folder; and the nearest existing folder
    must accept a new entry. The last is tried, not inferred from permissions (root passes ``os.access`` on
    ``/proc``, where nothing can be created): a temporary folder is made there and removed at once, so nothing is
    left behind."""
    import errno
    import os
    import tempfile

    path = Path(path)
    text = str(path)
    try:  # the file system of the working directory: good enough for the length limits (255 and 4096 on Linux)
        name_max, path_max = os.pathconf(".", "PC_NAME_MAX"), os.pathconf(".", "PC_PATH_MAX")
    except (OSError, ValueError):
        name_max, path_max = 255, 4096
    for part in path.parts:  # before anything is looked up: stat() itself fails on a name that is too long
        if len(os.fsencode(part)) > name_max:
            return (f"{field}: the folder name {part[:40]!r}... is {len(os.fsencode(part))} bytes long; the file "
                    f"system allows {name_max}")
    if len(os.fsencode(str(path.absolute()))) >= path_max:
        return f"{field}: the path is {len(os.fsencode(str(path.absolute())))} bytes long; the file system allows " \
               f"{path_max - 1}"
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.exists():  # a relative path: the working directory is its base
        existing = Path(".")
    if existing.exists() and not existing.is_dir():
        what = f"{text!r}" if existing == path else f"{str(existing)!r} (part of {text!r})"
        return f"{field}={text}: {what} is a file, not a folder"
    try:
        probe = tempfile.mkdtemp(prefix=".write-check-", dir=existing)
    except OSError as exc:
        reason = os.strerror(exc.errno) if exc.errno else str(exc)
        if exc.errno in (errno.ENOENT, errno.EROFS, errno.EACCES, errno.EPERM):
            reason += ": a system, read-only or someone else's folder?"
        return f"{field}={text}: nothing can be created in {str(existing)!r} ({reason})"
    os.rmdir(probe)
    return None


def check_folder(path: str | Path, field: str, create: bool = False) -> Path:
    """Raise :class:`ConfigError` with :func:`folder_problem`'s line; with ``create``, also make the folder and
    write a probe file in it (what the job itself is about to do), so that the first episode starts only once
    its results have somewhere to go."""
    import os

    problem = folder_problem(path, field)
    if problem:
        raise ConfigError(problem)
    path = Path(path)
    if create:
        try:
            path.mkdir(parents=True, exist_ok=True)
            probe = path / f".write-check-{os.getpid()}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise ConfigError(f"{field}={path}: cannot be written: {os.strerror(exc.errno) if exc.errno else exc}") \
                from None
    return path


class TrainingDiverged(ConfigError):
    """Training produced a non-finite loss or parameter. Reported like bad input (one line, exit 2): the usual cause
    is a setting (a learning rate far too large), and the message names it."""
