"""Reading checkpoints without training anything: a checkpoint folder's ``config.yaml``, and the checks an SB3 zip
must pass before it is unpickled (one-line :class:`ConfigError` instead of a traceback from SB3 or torch). Here, in
:mod:`agents`, so that the evaluation loads checkpoints without importing :mod:`train` (which writes them)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym

from av_gym.errors import ConfigError

# What SB3's ``save`` always writes into its zip (``policy.optimizer.pth`` is optional: reference checkpoints drop it).
SB3_MEMBERS = ("data", "policy.pth")
# What each tensor member holds, for the message that names a damaged one.
TENSOR_MEMBERS = {"policy.pth": "policy.pth: the weights",
                  "policy.optimizer.pth": "policy.optimizer.pth: the optimiser state"}


def check_sb3_zip(path: str | Path) -> Path:
    """Raise :class:`ConfigError` (one line) unless ``path`` is a complete SB3 checkpoint zip: not empty, a zip whose
    directory is intact (a file cut short loses it: the directory is at the end), SB3's members present and every
    member's CRC right. Checked before anything is loaded, so a damaged file gives one line instead of a traceback
    from deep inside SB3 or torch. Reads the whole file once (a few MB)."""
    import zipfile

    path = Path(path)
    where = f"checkpoint {str(path)!r}"
    if not path.is_file():
        raise ConfigError(f"{where} does not exist")
    if path.stat().st_size == 0:
        raise ConfigError(f"{where} is empty (0 bytes): a copy or download that did not finish?")
    try:
        with zipfile.ZipFile(path) as z:
            missing = [m for m in SB3_MEMBERS if m not in z.namelist()]
            bad = None if missing else z.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:  # zlib errors are zipfile's own
        raise ConfigError(f"{where} is not a readable zip (truncated or corrupt: {_one_line(exc)}); "
                          f"re-copy it or retrain") from None
    if missing:
        raise ConfigError(f"{where} is a zip but not an SB3 checkpoint: it lacks {missing}")
    if bad is not None:
        raise ConfigError(f"{where} is corrupt: member {bad!r} fails its CRC check; re-copy it or retrain")
    return path


def load_sb3(path: str | Path, **kwargs: Any):
    """``PPO.load(path, **kwargs)`` after :func:`check_sb3_zip`; what SB3 still cannot read (a zip of the right
    shape holding something else) becomes a one-line :class:`ConfigError` too. A space mismatch with ``env`` (SB3's
    ValueError) says so."""
    from stable_baselines3 import PPO

    check_sb3_zip(path)
    try:
        return PPO.load(str(path), **kwargs)
    except ConfigError:
        raise
    except Exception as exc:  # noqa: BLE001 - whatever unpickling a damaged file raises
        raise unloadable(path, exc) from None


def unloadable(path: str | Path, exc: BaseException) -> ConfigError:
    """One line for a zip of SB3's shape that SB3 or torch still cannot read. Which tensor member is damaged is
    found by reading each ``*.pth`` member alone (only here, after the load failed): garbage bytes make torch raise
    whatever its unpickler trips on (UnpicklingError, IndexError, ...), so the exception's type does not say. torch's
    own message for a tensor file it refuses (several sentences, cut mid-sentence once made one line) advises
    loading with ``weights_only=False``, which would run whatever the file holds: it is not passed on."""
    member = _unreadable_tensor_member(path)
    if member is not None or "weights_only" in str(exc):
        what = TENSOR_MEMBERS.get(member or "policy.pth", member)
        why = f"a tensor member ({what}) is not one torch reads as plain tensors: damaged, or not written by SB3"
    else:
        why = f"{type(exc).__name__}: {_one_line(exc)}"
    return ConfigError(f"checkpoint {str(path)!r} cannot be loaded ({why}); re-copy it or retrain")


def _unreadable_tensor_member(path: str | Path) -> str | None:
    """The first ``*.pth`` member of an SB3 zip that ``torch.load(weights_only=True)`` refuses, or None."""
    import io
    import zipfile

    import torch

    try:
        with zipfile.ZipFile(path) as z:
            for name in sorted(n for n in z.namelist() if n.endswith(".pth")):
                try:
                    torch.load(io.BytesIO(z.read(name)), map_location="cpu", weights_only=True)
                except Exception:  # noqa: BLE001 - any failure to read the member is the answer
                    return name
    except (zipfile.BadZipFile, OSError):
        return None
    return None


def read_config_yaml(path: str | Path) -> dict:
    """A checkpoint folder's ``config.yaml`` as a dict ({} if there is none); invalid YAML, or YAML that is not a
    mapping, is a one-line :class:`ConfigError` naming the file and where the parser stopped."""
    import yaml

    path = Path(path)
    if not path.is_file():
        return {}
    try:
        cfg = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or type(exc).__name__
        raise ConfigError(f"{str(path)!r} is not valid YAML ({problem}{at}): a checkpoint folder's config.yaml is "
                          f"the resolved config its training wrote") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{str(path)!r} is not valid YAML (not UTF-8 text)") from None
    if cfg is None:
        return {}
    if not isinstance(cfg, dict):
        raise ConfigError(f"{str(path)!r} must hold a mapping (the resolved training config), got a "
                          f"{type(cfg).__name__}")
    return cfg


def saved_config(path: str | Path) -> dict:
    """The training config saved beside a model file (or in a checkpoint folder); {} if there is none."""
    path = Path(path)
    return read_config_yaml((path if path.is_dir() else path.parent) / "config.yaml")


def describe_space(space: gym.Space) -> str:
    """A space in one line: ``{key: shape dtype [low, high]}``."""
    import numpy as np

    if isinstance(space, gym.spaces.Dict):
        return "{" + ", ".join(f"{k}: {describe_space(v)}" for k, v in space.spaces.items()) + "}"
    if isinstance(space, gym.spaces.Box):
        return f"{space.shape} {space.dtype} [{np.min(space.low):g}, {np.max(space.high):g}]"
    return str(space)


def _one_line(exc: BaseException) -> str:
    """The exception's text on one line; a long one ends at its last whole sentence within 200 characters."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if len(text) <= 200:
        return text
    cut = text[:200]
    end = cut.rfind(". ")
    return cut[: end + 1] if end > 40 else cut[: cut.rfind(" ")] + " ..."
