"""``meta.json`` of an evaluation: what ran, from which code, when, how long and on how busy a machine, written by
``python -m eval`` beside its results.csv and results.md (the result folders' meta.json were written by hand).

The keys are the shipped result folders' (docs/results/*/meta.json, read by eval/results_page.py): ``command``
(``python -m eval`` and the overrides as given), ``commit`` (the git HEAD of the code that ran, or the commit a
``git archive`` snapshot of it carries; null otherwise, e.g. in an installed wheel), ``started`` / ``finished``
(UTC, ISO 8601), ``wall_s``, ``load`` (the 1-minute load average at start and end, ``"a-b"``) and ``rc`` (0; 130
on Ctrl-C; 2 on a ConfigError; 1 on any other failure; null while it runs or after a kill -9), then what a reader
needs besides: ``dirty`` (true when the checkout's tracked files differ from ``commit``, the first of them in
``changed``: its numbers are not that commit's; null where no git can tell, an archive or a wheel), ``env`` (the env
preset it ran and every field that differs from it, :func:`env_as_ran`), the settings that chose the episodes and
how they ran, the episodes written and the non-finite sensor entries their sensors replaced (``sensor_faults``, 0
when none), CPU seconds and library versions.

A meta.json this module did not write (no ``written_by``: a person's, with notes) is never replaced: ``python -m
eval`` refuses such an out_dir before any episode runs (:func:`hand_written_problem`), and :class:`EvalMeta` keeps
one that appears there all the same."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from av_gym.atomic import write_text_atomic

WRITTEN_BY = "python -m eval"  # the marker of a meta.json this module wrote (and may therefore replace)
META = "meta.json"
ARCHIVE_COMMIT = "archive_commit.txt"  # in eval/: a git archive's commit (.gitattributes export-subst)
VERSIONED = ("numpy", "torch", "gymnasium", "highway-env", "stable-baselines3")  # what changes episodes' numbers
CHANGED_LISTED = 10  # the changed tracked files a record names (then "... and N more"): enough to see what it was


def utc_now() -> str:
    """Now in UTC, ISO 8601 to the second with a ``Z`` (the shipped meta.json's form)."""
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def load_1min() -> float | None:
    """The 1-minute load average, or None where the system has none."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def code_commit(root: Path | None = None) -> str | None:
    """The git HEAD of the checkout this code runs from (``root``: the folder holding ``eval/``); outside a
    checkout's top, the commit a ``git archive`` snapshot carries (:func:`archived_commit`), else None: an
    installed wheel inside a checkout's ``.venv`` would otherwise report the checkout's HEAD for code it did not
    run."""
    root = (root or Path(__file__).resolve().parent.parent).resolve()
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--show-toplevel", "HEAD"], capture_output=True,
                             text=True, timeout=10, check=True).stdout.split()
    except (OSError, subprocess.SubprocessError):
        return archived_commit(root)
    if len(out) != 2 or Path(out[0]).resolve() != root:
        return archived_commit(root)
    return out[1]


def dirty_files(root: Path | None = None) -> list[str] | None:
    """The tracked files of the checkout at ``root`` that differ from its HEAD (staged or not), as git status
    names them; [] for a clean tree; None where git cannot tell (no git, or ``root`` is not a checkout's top: an
    archive, a wheel). Untracked files are left out: a user's notes beside the code do not change what ran."""
    root = (root or Path(__file__).resolve().parent.parent).resolve()
    try:
        top = subprocess.run(["git", "-C", str(root), "rev-parse", "--show-toplevel"], capture_output=True,
                             text=True, timeout=10, check=True).stdout.strip()
        if Path(top).resolve() != root:
            return None
        out = subprocess.run(["git", "-C", str(root), "status", "--porcelain=v1", "-z", "--untracked-files=no"],
                             capture_output=True, text=True, timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    entries = out.split("\0")
    files, skip = [], False
    for entry in entries:  # "XY path", a rename's "R  new\0old": the old name follows as its own entry
        if skip or len(entry) < 4:
            skip = False
            continue
        files.append(entry[3:])
        skip = entry[0] in "RC"
    return sorted(files)


def provenance(root: Path | None = None) -> dict:
    """Which code made a result: ``commit`` (:func:`code_commit`), ``dirty`` (true when tracked files differ from
    it, false when none do, null where no git can tell), ``changed`` (the first :data:`CHANGED_LISTED` of those
    files, then ``... and N more``; only when dirty) and ``versions`` (:func:`versions`). One record for eval's
    meta.json and a training run's provenance.json alike."""
    changed = dirty_files(root)
    record: dict = {"commit": code_commit(root), "dirty": None if changed is None else bool(changed)}
    if changed:
        record["changed"] = changed[:CHANGED_LISTED] + (
            [f"... and {len(changed) - CHANGED_LISTED} more"] if len(changed) > CHANGED_LISTED else [])
    record["versions"] = versions()
    return record


def env_as_ran(env_cfg: dict | None) -> dict | None:
    """The env an evaluation ran in, as results record it: ``preset`` (the conf/env file its ``name`` gives) and
    ``changed``, every field of ``env_cfg`` (the composed ``env`` section) that differs from that preset, dotted
    (``{"track": "B"}``; {} as shipped). The one place that says so: meta.json, results.md and the results page
    all read it. None for no env."""
    if not env_cfg:
        return None
    from conf.check import sensor_overrides

    return {"preset": env_cfg.get("name"), "changed": sensor_overrides(env_cfg, "env")}


def archived_commit(root: Path) -> str | None:
    """The commit ``git archive`` wrote into ``root``/eval/archive_commit.txt (``export-subst`` in .gitattributes
    turns its ``$Format:%H$`` into the archived commit's hash), or None where it holds anything but a 40-hex hash:
    the placeholder itself in a checkout, or in a wheel built from one, whose code may differ from any commit."""
    try:
        text = (Path(root) / "eval" / ARCHIVE_COMMIT).read_text().strip()
    except OSError:
        return None
    return text if re.fullmatch(r"[0-9a-f]{40}", text) else None


def versions() -> dict[str, str | None]:
    """Python's and each library's version that shapes the episodes (None: not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    found: dict[str, str | None] = {"python": sys.version.split()[0]}
    for name in VERSIONED:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = None
    return found


def command_line(overrides: list[str] | None) -> str | None:
    """``python -m eval`` and ``overrides`` as given (shell quoting already removed, as the shipped meta.json
    write them); None when not known (called from Python outside a Hydra job)."""
    if overrides is None:
        return None
    return " ".join(["python -m eval", *overrides])


def hydra_overrides() -> list[str] | None:
    """The command line's arguments as given: a plain run's are ``sys.argv`` (Hydra's task overrides leave out
    ``hydra.*`` ones such as ``hydra.run.dir``); a sweep's job's are its own cell's overrides. None outside a
    Hydra job (a caller from Python)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hydra_cfg = HydraConfig.get()
    except Exception:  # not a Hydra job (HydraConfig unset): a caller from Python
        return None
    if hydra_cfg.mode != RunMode.MULTIRUN:
        return sys.argv[1:]
    task = getattr(getattr(hydra_cfg, "overrides", None), "task", None)  # None: a job config without them
    return None if task is None else list(task)


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and of its finished children (the worker processes)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


class EvalMeta:
    """One evaluation's meta.json: begun when the evaluation owns its out_dir, written (atomically) each time its
    results are, and last with the exit status. ``settings``: the command's settings a reader needs (seeds,
    split, episodes, agents, vec_env, n_envs, workers); ``env_cfg``: the composed ``env`` section it ran
    (recorded as :func:`env_as_ran`)."""

    def __init__(self, out_dir: str | Path, settings: dict, overrides: list[str] | None,
                 env_cfg: dict | None = None) -> None:
        self.path = Path(out_dir) / META
        self.kept = _not_ours(self.path)  # a person's meta.json: never replaced
        self._t0, self._cpu0, self._load0 = time.monotonic(), cpu_seconds(), load_1min()
        self.episodes_written = 0  # rows in results.csv so far
        self.sensor_faults = 0  # their non-finite sensor entries replaced (results.csv's sensor_faults, summed)
        code = provenance()
        self.data = {"command": command_line(overrides), "commit": code["commit"], "started": utc_now(),
                     "finished": None, "wall_s": None, "load": None, "rc": None, "dirty": code["dirty"],
                     **({"changed": code["changed"]} if "changed" in code else {}), "cpu_s": None,
                     "episodes_written": 0, "sensor_faults": 0,
                     **({"env": env_as_ran(env_cfg)} if env_cfg else {}), **settings, "versions": code["versions"],
                     "written_by": WRITTEN_BY}
        if self.kept:
            print(f"[eval] {self.path} was not written by {WRITTEN_BY}: kept as it is (this run writes none)",
                  file=sys.stderr)

    def write(self, episodes_written: int, sensor_faults: int = 0) -> Path | None:
        """meta.json of a running evaluation (rc null) with ``episodes_written`` rows in results.csv, whose
        episodes' sensors replaced ``sensor_faults`` non-finite entries in all."""
        self.episodes_written, self.sensor_faults = episodes_written, int(sensor_faults)
        return self._write(None)

    def end(self, rc: int) -> Path | None:
        """meta.json of the ended evaluation, ``rc`` its exit status, with the rows written so far; nothing when
        it failed before writing any (nothing was measured: the folder is left as it was)."""
        if rc != 0 and self.episodes_written == 0:
            return None
        return self._write(rc)

    def _write(self, rc: int | None) -> Path | None:
        self.data.update({"finished": utc_now() if rc is not None else None,
                          "wall_s": round(time.monotonic() - self._t0, 1),
                          "load": f"{_load(self._load0)}-{_load(load_1min())}", "rc": rc,
                          "cpu_s": round(cpu_seconds() - self._cpu0, 1), "episodes_written": self.episodes_written,
                          "sensor_faults": self.sensor_faults})
        if self.kept:  # a person's meta.json is never replaced
            return None
        return write_text_atomic(self.path, json.dumps(self.data, indent=1) + "\n", field="out_dir")


def hand_written_problem(out_dir: str | Path) -> str | None:
    """One line refusing ``out_dir`` when it holds a meta.json that this module did not write (a person's, or not
    JSON): results written beside it would leave it describing a run that is not theirs, ``overwrite=true`` or
    not; None when there is none or it is eval's own (replaced by the next run's)."""
    path = Path(out_dir) / META
    if not _not_ours(path):
        return None
    return (f"out_dir={out_dir} holds {path}, which {WRITTEN_BY} did not write (no \"written_by\": "
            f"\"{WRITTEN_BY}\"); results there would not be the run it describes: move or delete it, or pick "
            f"another out_dir")


def exit_status(exc: BaseException | None) -> int:
    """The status ``python -m eval`` exits with after ``exc`` (av_gym.errors.run_cli): 0, 130 on Ctrl-C or
    SIGTERM, 2 on a ConfigError, 1 otherwise."""
    from av_gym.errors import ConfigError

    if exc is None:
        return 0
    if isinstance(exc, KeyboardInterrupt):
        return 130
    if isinstance(exc, SystemExit):
        return exc.code if isinstance(exc.code, int) else 1
    return 2 if isinstance(exc, ConfigError) else 1


def _load(value: float | None) -> str:
    return "?" if value is None else f"{value:.2f}"


def _not_ours(path: Path) -> bool:
    """True when ``path`` holds a meta.json that this module did not write (unreadable or not JSON included)."""
    if not path.exists():
        return False
    try:
        return json.loads(path.read_text()).get("written_by") != WRITTEN_BY
    except (OSError, ValueError, AttributeError):
        return True
