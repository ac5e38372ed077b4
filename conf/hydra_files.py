"""Hydra's record of a run (``<run folder>/.hydra/config.yaml``, ``hydra.yaml``, ``overrides.yaml``), written the
house's way: each file whole or not at all (:func:`av_gym.atomic.write_text_atomic`), and a write that fails (a
file size limit, ``ulimit -f``; a full disk) ends the command in one line, exit status 2, with the run folder
Hydra had just made removed when it holds nothing but Hydra's own files. Hydra's own save writes in place and
reports a failure as a traceback, leaving a torn ``.hydra/`` behind.

Hydra writes these files itself, before the job's function runs (``hydra.core.utils.run_job``), so no check of
ours sees the failure: :func:`hydra_files_whole` puts this module's save in the place of Hydra's for the time
``python -m train`` / ``python -m eval`` run their Hydra job (hydra-core 1.3, pinned in pyproject.toml)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any


def save_config(cfg: Any, filename: str, output_dir: Path) -> None:
    """Hydra's ``_save_config``: ``cfg`` as YAML into ``output_dir/filename``, atomically; on failure one line on
    stderr, the run folder discarded if it holds only Hydra's files, and ``SystemExit(2)`` (an exception would be
    printed by Hydra as a traceback)."""
    from omegaconf import OmegaConf

    from av_gym.atomic import WriteFailed, write_text_atomic
    from av_gym.errors import discard_hydra_run_dir

    try:
        write_text_atomic(Path(output_dir) / filename, OmegaConf.to_yaml(cfg), "hydra.run.dir")
    except WriteFailed as exc:
        discard_hydra_run_dir()
        print("error: " + " ".join(f"{exc}; it is Hydra's record of the run's config, so nothing was run".split()),
              file=sys.stderr)
        raise SystemExit(2) from None


@contextlib.contextmanager
def hydra_files_whole() -> Iterator[None]:
    """While the block runs (a ``@hydra.main`` function's call), Hydra saves its config files with
    :func:`save_config`; Hydra's own save is put back after."""
    import hydra.core.utils as hydra_utils

    original = getattr(hydra_utils, "_save_config", None)
    if original is None:  # another Hydra than the pinned one: its own save
        yield
        return
    hydra_utils._save_config = save_config
    try:
        yield
    finally:
        hydra_utils._save_config = original
