"""Atomic checkpoint writes: write a temporary file beside the target, flush it to disk, then rename over the
target. A crash at any point leaves either the old complete file or the new complete file, never a torn one."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

# Reading checkpoints (check_sb3_zip, load_sb3, read_config_yaml) is agents/checkpoint.py: the evaluation needs it
# and must not import train.


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
