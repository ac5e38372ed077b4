"""Atomic checkpoint writes: write a temporary file beside the target, flush it to disk, then rename over the
target. A crash at any point leaves either the old complete file or the new complete file, never a torn one."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from av_gym.errors import ConfigError

# What SB3's ``save`` always writes into its zip (``policy.optimizer.pth`` is optional: reference checkpoints drop it).
SB3_MEMBERS = ("data", "policy.pth")


def _fsync_replace(tmp: Path, path: Path) -> None:
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def save_model_atomic(model: Any, path: str | Path) -> Path:
    """``model.save`` (SB3) to ``path`` (a .zip) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp")
    model.save(str(tmp))
    _fsync_replace(tmp, path)
    return path


def write_text_atomic(path: str | Path, text: str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    _fsync_replace(tmp, path)
    return path


def save_rng_state(path: str | Path, extra: dict | None = None) -> Path:
    """Python, NumPy and torch global RNG states (plus ``extra``), written atomically (a pickle: our own file,
    loaded only on resume)."""
    import pickle
    import random

    import numpy as np
    import torch

    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
             **(extra or {})}
    with open(tmp, "wb") as f:
        pickle.dump(state, f)
    _fsync_replace(tmp, path)
    return path


def load_rng_state(path: str | Path) -> dict:
    """Restore the RNG states :func:`save_rng_state` wrote and return the whole record ({} if no file)."""
    import pickle
    import random

    import numpy as np
    import torch

    path = Path(path)
    if not path.is_file():
        return {}
    with open(path, "rb") as f:
        state = pickle.load(f)
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    return state


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
        raise ConfigError(f"checkpoint {str(path)!r} cannot be loaded: {type(exc).__name__}: {_one_line(exc)}") \
            from None


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


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."
