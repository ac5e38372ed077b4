"""The one exception type for bad user input (configs, paths, checkpoints). The command-line entry points print
its message as a single line and exit with status 2."""


class ConfigError(ValueError):
    """A user-facing configuration or input error; its message names the field and the allowed values."""
