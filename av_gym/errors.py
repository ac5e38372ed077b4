"""The one exception type for bad user input (configs, paths, checkpoints). The command-line entry points print
its message as a single line and exit with status 2."""

from __future__ import annotations

from pathlib import Path


class ConfigError(ValueError):
    """A user-facing configuration or input error; its message names the field and the allowed values."""


def run_cli(fn, *args, hydra_run_dir: bool = False) -> None:
    """Run a command-line entry point: a :class:`ConfigError` becomes one line on stderr and exit status 2;
    Ctrl-C / SIGTERM exit with 130 (whatever needed saving was saved by the code that was interrupted).

    ``hydra_run_dir``: ``fn`` runs as a Hydra job, whose folder Hydra made before ``fn`` could check anything; on a
    ConfigError it is removed again when it holds nothing but what Hydra wrote (see :func:`discard_hydra_run_dir`)."""
    import sys

    try:
        fn(*args)
    except ConfigError as exc:
        if hydra_run_dir:
            discard_hydra_run_dir()
        print("error: " + " ".join(str(exc).split()), file=sys.stderr)  # one line, whatever the message holds
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)


def discard_hydra_run_dir() -> bool:
    """Remove the current Hydra job's output folder if it holds only Hydra's own files (``.hydra/`` and an empty
    job log), then any parent that became empty, up to the working directory. A folder with anything of ours (a
    resumed run's TensorBoard logs, a previous run's results) is kept. Returns whether it was removed.

    The command-line check (:func:`av_gym.config_schema.check_command_line`) runs before Hydra and catches most
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
