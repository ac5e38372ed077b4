"""``agent.device`` (cpu | cuda | auto) for every trained kind: checked on the command line before any folder, and
resolved to a :class:`torch.device` by the trainers. CPU is the default: the results the repository reports come
from it, bit for bit."""

from __future__ import annotations

DEVICES = ("cpu", "cuda", "auto")


def device_problems(name: str, field: str = "agent.device") -> list[str]:
    """One line if ``name`` cannot be used here: not one of :data:`DEVICES`, or ``cuda`` without a GPU torch can
    use (a CPU build of torch, no driver). ``auto`` never fails: it falls back to the CPU."""
    if name not in DEVICES:
        return [f"{field} must be one of {list(DEVICES)}, got {name!r}"]
    if name == "cuda":
        import torch

        if not torch.cuda.is_available():
            return [f"{field}=cuda but torch.cuda.is_available() is False (a CPU build of torch, or no GPU/driver "
                    f"here): use {field}=cpu or {field}=auto"]
    return []


def resolve_device(name: str) -> "torch.device":  # noqa: F821 - torch is imported lazily
    """``cpu`` | ``cuda`` | ``auto`` (cuda when available, else cpu) as a :class:`torch.device`, as SB3's
    ``get_device`` resolves its own ``device=`` argument."""
    import torch

    from av_gym.errors import ConfigError

    problems = device_problems(name)
    if problems:
        raise ConfigError(problems[0])
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(name)
