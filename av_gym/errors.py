"""The one exception type for bad user input (configs, paths, checkpoints). The command-line entry points print
its message as a single line and exit with status 2."""

from __future__ import annotations

import difflib
from pathlib import Path


class ConfigError(ValueError):
    """A user-facing configuration or input error; its message names the field and the allowed values."""


def closest_hint(name: str, allowed: list[str]) -> str:
    """``"; did you mean 'mode'?"`` for a mistyped key (difflib's closest of ``allowed``), ``""`` when none is
    close: appended to a refusal that lists every allowed key, so the likely fix is named without reading the list."""
    close = difflib.get_close_matches(str(name), [str(a) for a in allowed], n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


SWEEP_FAILURES = "AV_GYM_SWEEP_FAILURES"  # env var: the file where a sweep's jobs record how they failed


def run_cli(fn, *args, hydra_run_dir: bool = False) -> None:
    """Run a command-line entry point: a :class:`ConfigError` becomes one line on stderr and exit status 2;
    Ctrl-C / SIGTERM exit with 130 (SIGTERM is raised as KeyboardInterrupt: whatever needed saving was saved by the
    code that was interrupted).

    ``hydra_run_dir``: ``fn`` runs as a Hydra job, whose folder Hydra made before ``fn`` could check anything; on a
    ConfigError it is removed again when it holds nothing but what Hydra wrote (see :func:`discard_hydra_run_dir`).
    In a sweep (``-m``, run through :func:`run_hydra`), a job that fails records one line and returns, so that
    the sweep runs its other jobs (one bad cell would otherwise end the sweep); the line is reported at the end."""
    import sys

    interrupt_on_sigterm()
    in_sweep = hydra_run_dir and _sweep_job() is not None
    try:
        fn(*args)
    except ConfigError as exc:
        if hydra_run_dir:
            discard_hydra_run_dir()
        line = " ".join(str(exc).split())  # one line, whatever the message holds
        if in_sweep:
            _record_failure(line)
            return
        print("error: " + line, file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)
    except Exception as exc:  # a sweep's job: its traceback into its folder, one line for the report
        if not in_sweep:
            raise
        _record_failure(f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]} ({_save_traceback()})")


def _sweep_job() -> tuple[int, str] | None:
    """(job number, its overrides) when this is a job of a sweep that :func:`run_hydra` started, else None."""
    import os

    if not os.environ.get(SWEEP_FAILURES):
        return None
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
        if hc.mode != RunMode.MULTIRUN:
            return None
        return int(hc.job.num), " ".join(hc.overrides.task)
    except Exception:  # not a Hydra job
        return None


def _record_failure(line: str) -> None:
    import os

    num, overrides = _sweep_job()
    text = f"sweep job {num} ({overrides}): {line}\n"
    fd = os.open(os.environ[SWEEP_FAILURES], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:  # one short write in append mode: jobs in parallel processes do not interleave
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def _save_traceback() -> str:
    """The current exception's traceback in the job's folder (``error.txt``); where it went."""
    import traceback

    try:
        from hydra.core.hydra_config import HydraConfig

        path = Path(HydraConfig.get().runtime.output_dir) / "error.txt"
        path.write_text(traceback.format_exc())
        return f"traceback in {path}"
    except Exception:
        return "no traceback saved"


def run_hydra(hydra_main) -> None:
    """Call a ``@hydra.main`` function; with ``-m``, its jobs' failures are collected (:func:`run_cli`) and
    reported once every job has run: one line each, then exit status 1 (0 when all succeeded)."""
    import os
    import sys
    import tempfile

    if not any(a in ("-m", "--multirun") for a in sys.argv[1:]):
        hydra_main()
        return
    fd, path = tempfile.mkstemp(prefix="av-gym-sweep-", suffix=".txt")
    os.close(fd)
    os.environ[SWEEP_FAILURES] = path  # inherited by the launcher's worker processes
    try:
        hydra_main()
        failures = [line for line in Path(path).read_text().splitlines() if line.strip()]
    finally:
        os.environ.pop(SWEEP_FAILURES, None)
        os.unlink(path)
    if failures:
        for line in failures:
            print(f"error: {line}", file=sys.stderr)
        print(f"error: {len(failures)} sweep job(s) failed (listed above); the other jobs finished and wrote their "
              f"results", file=sys.stderr)
        sys.exit(1)


def interrupt_on_sigterm() -> None:
    """SIGTERM (``kill PID``, ``timeout``, a scheduler's end of job) raises KeyboardInterrupt, as Ctrl-C does, so
    that what the code keeps on Ctrl-C (measured episodes, a checkpoint) is kept on SIGTERM too; its default action
    ends the process at once (rc 143, the episodes lost). Only where SIGTERM still has its default action, in the main
    thread (a handler set by the code, e.g. training's, is left alone)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread() and \
            signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, _raise_interrupt)


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def discard_hydra_run_dir() -> bool:
    """Remove the current Hydra job's output folder if it holds only Hydra's own files (``.hydra/`` and the
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
        if entry.suffix == ".log" and entry.is_file():  # the job log: what this job printed, shown on the terminal
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
