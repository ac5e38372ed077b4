"""The reference agents shipped with av_gym, by name: ``av_gym.reference("ppo_turn")`` is the folder holding its
``config.yaml``, ``model.zip`` and ``COMMAND``; ``gym.make(id, checkpoint="ppo_turn")`` takes the name too.

Where they are: in a checkout (and an editable install) ``checkpoints/reference/`` beside ``av_gym/``; in a wheel
``av_gym/_shipped/reference/`` (setup.py copies them there), so that a non-editable install carries them and no
folder of the user's can stand in for them. Only the folder is located here: loading a model needs SB3 or torch,
which this library layer does not import (the harness's ``agents.checkpoint`` does)."""

from __future__ import annotations

import os
from pathlib import Path

from av_gym.errors import ConfigError

PACKAGE = Path(__file__).resolve().parent
SHIPPED = PACKAGE / "_shipped"
"""The data a built wheel carries inside the package (``conf/`` presets, ``reference/`` agents)."""


def shipped_root() -> Path:
    """The folder holding ``conf/`` and ``reference/`` of this install: ``av_gym/_shipped`` in a wheel, the
    checkout's root (``conf/``, ``checkpoints/reference/``) otherwise."""
    return SHIPPED if SHIPPED.is_dir() else PACKAGE.parent


def reference_root() -> Path:
    """The folder of the shipped reference agents (one sub-folder per name)."""
    return SHIPPED / "reference" if SHIPPED.is_dir() else PACKAGE.parent / "checkpoints" / "reference"


def conf_root() -> Path:
    """The folder of the shipped presets (``env/``, ``sensors/``, ``shield/``, ``agent/`` yaml files)."""
    return shipped_root() / "conf"


def reference_names() -> list[str]:
    """The names of the shipped reference agents (``seeds/`` holds extra training seeds, not a name)."""
    root = reference_root()
    if not root.is_dir():
        return []
    return sorted(p.parent.name for p in root.glob("*/config.yaml"))


def reference(name: str) -> Path:
    """The folder of shipped reference agent ``name``; a :class:`ConfigError` naming the allowed names otherwise."""
    names = reference_names()
    if not isinstance(name, str) or name not in names:
        raise ConfigError(f"reference agent must be one of {names}, got {name!r}")
    return reference_root() / name


def is_shipped(path: str | os.PathLike) -> bool:
    """Whether ``path`` is inside the shipped reference folder (tools must not write there unasked)."""
    try:
        return Path(path).resolve().is_relative_to(reference_root().resolve())
    except OSError:
        return False


def holds_shipped(path: str | os.PathLike) -> bool:
    """Whether folder ``path`` holds the shipped reference folder (``checkpoints/``, or the checkout): clearing it
    would take the references along."""
    try:
        return reference_root().resolve().is_relative_to(Path(path).resolve())
    except OSError:
        return False


def shipped_problem(path: str | os.PathLike, field: str, cleared: bool = False) -> str | None:
    """Why no tool may write folder ``path`` (the value of setting ``field``), whatever its flags: it is inside the
    shipped reference agents, which are read-only to every tool, or (``cleared``: a folder the tool may empty, as
    ``train.overwrite=true`` does) it holds them; or None. The line names no flag, as none writes there (replacing
    one reference by a like checkpoint is ``python -m train.export --overwrite-reference``'s alone)."""
    root = reference_root()
    if is_shipped(path):
        where = "is" if Path(path).resolve() == root.resolve() else "is inside"
    elif cleared and holds_shipped(path):
        where = "holds"
    else:
        return None
    return (f"{field}={path}: {where} the shipped reference agents' folder ({root}), read-only to every tool; "
            f"write elsewhere (e.g. checkpoints/<name>)")


def checkout_path_hint(path: str | os.PathLike, by_name: bool = True) -> str:
    """For a ``checkpoints/reference/...`` path the docs give (relative to a checkout's root) that does not exist
    here, as from a wheel in another folder: where this install holds it, as one clause to end a refusal (a
    shipped agent's own folder, where the caller takes names (``by_name``): its name, which the harness resolves
    anywhere; else the installed copy's path); "" for any other path, or one that is nowhere in this install."""
    parts = Path(path).parts
    if Path(path).is_absolute() or parts[:2] != ("checkpoints", "reference") or len(parts) < 3 or Path(path).exists():
        return ""
    installed = reference_root().joinpath(*parts[2:])
    if not installed.exists():
        return ""
    if by_name and len(parts) == 3 and parts[2] in reference_names():
        return (f"; {path} is a checkout's folder: the shipped agent is named {parts[2]!r} anywhere (this install's "
                f"copy: {installed})")
    return f"; {path} is a checkout's folder: this install's copy is {installed}"
