"""The one exception type for bad user input (configs, paths, checkpoints). The command-line entry points print
its message as a single line and exit with status 2."""


class ConfigError(ValueError):
    """A user-facing configuration or input error; its message names the field and the allowed values."""


def run_cli(fn, *args) -> None:
    """Run a command-line entry point: a :class:`ConfigError` becomes one line on stderr and exit status 2;
    Ctrl-C / SIGTERM exit with 130 (whatever needed saving was saved by the code that was interrupted)."""
    import sys

    try:
        fn(*args)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)
