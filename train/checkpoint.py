"""Atomic checkpoint writes (av_gym/atomic.py): a temporary file beside the target, flushed, renamed over it. A
crash or a full disk at any point leaves the old complete file or the new one, never a torn one, and no temporary
file.

``latest.zip`` carries its RNG states inside (member ``av_gym_rng.pkl``, which SB3's loader ignores): the policy
and the random streams it continues with are one file, replaced together (as two files, a full disk can replace
one and leave the other old, a pair that does not match)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from av_gym.atomic import atomic_path
from av_gym.atomic import write_text_atomic as _write_text_atomic

# Reading checkpoints (check_sb3_zip, load_sb3, read_config_yaml) is agents/checkpoint.py: the evaluation needs it
# and must not import train.

RNG_MEMBER = "av_gym_rng.pkl"
FIELD = "paths.checkpoints"


def rng_state(extra: dict | None = None) -> dict:
    """Python, NumPy and torch global RNG states, plus ``extra``."""
    import random

    import numpy as np
    import torch

    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
            **(extra or {})}


def save_model_atomic(model: Any, path: str | Path, rng_extra: dict | None = None, with_rng: bool = False,
                      members: dict[str, bytes] | None = None) -> Path:
    """``model.save`` (SB3) to ``path`` (a .zip) atomically; with ``with_rng`` (or ``rng_extra``), the RNG states
    (and ``rng_extra``) inside the same zip, and ``members`` (name → bytes, e.g. DAgger's labelled states) too, so
    that all are replaced at once. SB3's loader reads only its own members."""
    import pickle
    import zipfile

    path = Path(path)
    with atomic_path(path, FIELD) as tmp:
        model.save(str(tmp))
        if with_rng or rng_extra is not None or members:
            with zipfile.ZipFile(tmp, "a") as z:
                if with_rng or rng_extra is not None:
                    z.writestr(RNG_MEMBER, pickle.dumps(rng_state(rng_extra)))
                for name, data in (members or {}).items():
                    z.writestr(name, data)
    return path


def write_text_atomic(path: str | Path, text: str) -> Path:
    """A text file beside the checkpoints (config.yaml, best.json ...), atomically."""
    return _write_text_atomic(path, text, FIELD)


def save_rng_state(path: str | Path, extra: dict | None = None) -> Path:
    """The RNG states (plus ``extra``) as a file of their own, atomically (a pickle: our own file, loaded only on
    resume). Checkpoints keep them inside latest.zip instead (:func:`save_model_atomic`)."""
    import pickle

    path = Path(path)
    with atomic_path(path, FIELD) as tmp:
        tmp.write_bytes(pickle.dumps(rng_state(extra)))
    return path


def load_rng_state(path: str | Path) -> dict:
    """Restore the RNG states saved in checkpoint ``path`` (a .zip; else its .rng sibling, as older runs wrote) or
    in file ``path`` (:func:`save_rng_state`), and return the whole record ({} if there are none)."""
    import pickle
    import random

    import numpy as np
    import torch

    path = Path(path)
    state = None
    if path.suffix == ".zip" and path.is_file():
        import zipfile

        with zipfile.ZipFile(path) as z:
            if RNG_MEMBER in z.namelist():
                state = pickle.loads(z.read(RNG_MEMBER))
        path = path.with_suffix(".rng")  # a checkpoint written before the states moved inside the zip
    if state is None:
        if not path.is_file():
            return {}
        with open(path, "rb") as f:
            state = pickle.load(f)
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    return state
