"""A training run's ``provenance.json``, in its log folder (``runs/<run_name>/``, beside results.md): which code
trained it. One entry per start of the run (a resume adds one: the code may have changed in between), each with
the command's overrides, when it started, and :func:`eval.meta.provenance`'s record, the one an evaluation's
meta.json holds: ``commit``, ``dirty`` (with the ``changed`` tracked files), ``versions`` of torch, SB3,
gymnasium, highway-env and numpy. A number is never attributed to a commit whose code did not make it.

Written atomically, listed in train/run_folder.py ``LOG_NAMES`` (``train.overwrite=true`` removes it; a user's
file of that name in a folder a run would take is not the run's to keep)."""

from __future__ import annotations

import json
from pathlib import Path

from av_gym.atomic import write_text_atomic

PROVENANCE = "provenance.json"
WRITTEN_BY = "python -m train"  # the marker of a provenance.json a run wrote (a resume appends to it)


def runs_so_far(path: Path) -> list[dict]:
    """The entries of the run's earlier starts in ``path`` ([] when there is none, or it is not one a run wrote:
    nothing of it can be trusted to describe this run)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return []
    if not isinstance(data, dict) or data.get("written_by") != WRITTEN_BY or not isinstance(data.get("runs"), list):
        return []
    return [r for r in data["runs"] if isinstance(r, dict)]


def record_start(run_dir: str | Path, overrides: list[str] | None, resume: bool) -> Path:
    """Add this start of the run (``overrides``: the command line's, None from Python; ``resume``: it continues an
    earlier start, whose entries are kept) to ``run_dir``/provenance.json, atomically; returns its path. A fresh
    start (or an overwrite) begins a new list."""
    from eval.meta import provenance, utc_now

    path = Path(run_dir) / PROVENANCE
    earlier = runs_so_far(path) if resume else []
    command = None if overrides is None else " ".join(["python -m train", *overrides])
    entry = {"command": command, "started": utc_now(), "resume": bool(resume), **provenance()}
    text = json.dumps({"runs": [*earlier, entry], "written_by": WRITTEN_BY}, indent=1) + "\n"
    return write_text_atomic(path, text, field="paths.runs")


def undo_start(run_dir: str | Path, resume: bool) -> None:
    """A start the trainer refused before it trained (an ``agent.init_from`` that does not fit): its entry goes
    again, so that a refused fresh run leaves no provenance.json to make its log folder look taken (Hydra's own
    files there are discarded with it) and a refused resume's record says only what trained."""
    path = Path(run_dir) / PROVENANCE
    earlier = runs_so_far(path)[:-1] if resume else []
    if earlier:
        write_text_atomic(path, json.dumps({"runs": earlier, "written_by": WRITTEN_BY}, indent=1) + "\n",
                          field="paths.runs")
    else:
        path.unlink(missing_ok=True)
