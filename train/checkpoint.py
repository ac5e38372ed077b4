"""Atomic checkpoint writes: write a temporary file beside the target, flush it to disk, then rename over the
target. A crash at any point leaves either the old complete file or the new complete file, never a torn one."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any


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
