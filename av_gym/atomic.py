"""Atomic file writes: a temporary file beside the target, flushed to disk, then renamed over it (``os.replace``,
atomic on POSIX within a file system). A crash or a full disk at any point leaves the old complete file or the new
complete file, never a torn one, and no temporary file behind (a full disk left ``results.csv`` cut at
row 10 and ``.latest.<pid>.tmp`` files).

A result that must be a new file (a benchmark's ``--out``) is linked into place instead (:func:`new_path`,
:func:`write_text_new`): a file that appeared at that path meanwhile is kept, and the write refused.

A write that fails (``OSError``: no space, quota, permissions) raises :class:`WriteFailed`, a
:class:`~av_gym.errors.ConfigError`: one line at the command line naming the file, what the system said and that
the previous version is intact.

Also here, the other half of "nothing written can be lost": a folder owned by one process (:class:`OwnedFolders`,
an exclusive ``flock`` on ``<folder>/.lock``) for the commands whose outputs two processes could otherwise both
write: a training run's ``checkpoints/<run>/`` (``train/run_folder.py``) and an evaluation's ``out_dir``
(``eval/__main__.py``), so that the second is refused instead of its rows replacing the first's. The kernel drops a ``flock`` when its holder exits however it exits (kill -9 included), so a crashed owner
never blocks the next; the lock file holds the holder's pid, for the message."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import NoReturn

from av_gym.errors import ConfigError


class WriteFailed(ConfigError):
    """A file could not be written; the previous version (if any) is intact and no temporary file is left."""


def temporary_name(path: Path) -> Path:
    """``.<name>.<pid>.tmp`` beside ``path``: hidden, per process (two writers never share one)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


@contextlib.contextmanager
def atomic_path(path: str | Path, field: str = "") -> Iterator[Path]:
    """Yield a temporary path to write; on leaving, flush it to disk and rename it over ``path``. On any error the
    temporary file is removed and ``path`` is untouched; an ``OSError`` becomes :class:`WriteFailed`."""
    path = Path(path)
    tmp = temporary_name(path)
    try:
        yield _beside(path, tmp)
        _flush(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        _remove(tmp)
        reason = os.strerror(exc.errno) if exc.errno else str(exc)
        kept = "the previous version is intact" if path.exists() else "nothing was written"
        raise WriteFailed(f"{field + ': ' if field else ''}cannot write {path}: {reason} ({kept})") from None
    except BaseException:
        _remove(tmp)
        raise


class FileExists(ConfigError):
    """A new file's path is taken (a result is never overwritten); the file there is intact."""


def taken(path: str | Path, field: str = "") -> FileExists:
    """The refusal of a new file whose ``path`` is taken: one line naming ``field`` (the flag that gave it)."""
    return FileExists(f"{field + ' ' if field else ''}{path} exists: choose another file (results are never "
                      "overwritten)")


def new_paths(*paths: tuple[str | Path | None, str]) -> None:
    """Raise :func:`taken` for the first of ``paths`` (``(path, field)`` pairs; a None or empty path is not asked
    for) that exists, before any is written: a caller writing several new files checks them all first, so one taken
    since its earlier check leaves none written, not half a set. Each is still written by :func:`new_path` (a file
    that appears after this check is kept)."""
    for path, field in paths:
        if path and Path(path).exists():
            raise taken(path, field)


@contextlib.contextmanager
def new_path(path: str | Path, field: str = "") -> Iterator[Path]:
    """:func:`atomic_path` for a file that must not exist: the temporary file, flushed to disk, is hard-linked to
    ``path`` (``os.link`` fails when ``path`` exists, so a file that appeared after any earlier check of the
    caller's is kept, never replaced; ``os.replace`` would replace it), then its temporary name is removed. A taken
    ``path`` raises :class:`FileExists`, one line naming ``field``; another ``OSError`` :class:`WriteFailed`; either
    way no temporary file is left."""
    path = Path(path)
    tmp = temporary_name(path)
    try:
        yield _beside(path, tmp)
        _flush(tmp)
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise taken(path, field) from None
    except OSError as exc:
        reason = os.strerror(exc.errno) if exc.errno else str(exc)
        named = f"{field}: " if field else ""
        raise WriteFailed(f"{named}cannot write {path}: {reason} (nothing was written)") from None
    finally:
        _remove(tmp)


def write_text_new(path: str | Path, text: str, field: str = "") -> Path:
    """``path``'s text as a new file, atomically, never replacing one (see :func:`new_path`)."""
    with new_path(path, field) as tmp:
        with open(tmp, "w") as f:
            f.write(text)
    return Path(path)


def write_new_or_exit(path: str | Path, text: str, field: str = "") -> Path:
    """:func:`write_text_new` as a script's last step: refused (a file there) or failed, one ``error:`` line on
    stderr and exit status 2 (the scripts' ``fail``). A script prints its result before calling it where the run
    is costly, so that a refused write loses nothing."""
    try:
        return write_text_new(path, text, field)
    except ConfigError as exc:
        exit_with(exc)


def new_paths_or_exit(*paths: tuple[str | Path | None, str]) -> None:
    """:func:`new_paths` as a script's first step, before its run: a taken path is one ``error:`` line on stderr
    and exit status 2 (the scripts' ``fail``)."""
    try:
        new_paths(*paths)
    except ConfigError as exc:
        exit_with(exc)


def exit_with(exc: ConfigError) -> NoReturn:
    """A script's refusal ``exc`` as one ``error:`` line on stderr (its whitespace folded), then exit status 2 (the
    scripts' ``fail``): what :func:`write_new_or_exit` and :func:`new_paths_or_exit` end with, and what a script
    calls on a refused write of its own (benchmarks/batched_speed.py's figure)."""
    import sys

    print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
    sys.exit(2)


def _beside(path: Path, tmp: Path) -> Path:
    """``tmp``, its folder (``path``'s) made first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    return tmp


def _flush(tmp: Path) -> None:
    """The written temporary file's bytes on disk before it takes the result's name."""
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())


def _remove(tmp: Path) -> None:
    with contextlib.suppress(OSError):
        tmp.unlink()


def write_text_atomic(path: str | Path, text: str, field: str = "") -> Path:
    """``path``'s text, atomically (see :func:`atomic_path`)."""
    with atomic_path(path, field) as tmp:
        with open(tmp, "w") as f:
            f.write(text)
    return Path(path)


def write_texts_atomic(texts: dict[str | Path, str], field: str = "") -> None:
    """Several files, all replaced or none: every temporary file is written and flushed first, then they are
    renamed in order. A failure while writing (a full disk) leaves every target as it was; the renames do not
    allocate, so once they start they finish."""
    done: list[tuple[Path, Path]] = []
    current = None
    try:
        for path, text in texts.items():
            current = Path(path)
            tmp = temporary_name(current)
            current.parent.mkdir(parents=True, exist_ok=True)
            done.append((tmp, current))
            with open(tmp, "w") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
    except OSError as exc:
        for tmp, _ in done:
            _remove(tmp)
        reason = os.strerror(exc.errno) if exc.errno else str(exc)
        kept = "the previous versions are intact" if any(p.exists() for _, p in done) else "nothing was written"
        raise WriteFailed(f"{field + ': ' if field else ''}cannot write {current}: {reason} ({kept})") from None
    except BaseException:
        for tmp, _ in done:
            _remove(tmp)
        raise
    for tmp, path in done:
        os.replace(tmp, path)


def save_figure_atomic(fig, path: str | Path, field: str = "", **kwargs) -> Path:
    """``fig.savefig(path)`` (matplotlib), atomically: a failed or interrupted save leaves the previous image whole
    and no empty or half-written png (a plain ``savefig`` on a full disk leaves an empty png and a traceback). The
    format comes from ``path``'s suffix, not from the temporary name's."""
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".") or "png")
    with atomic_path(path, field) as tmp:
        fig.savefig(tmp, **kwargs)
    return path


def save_figure_new(fig, path: str | Path, field: str = "", **kwargs) -> Path:
    """:func:`save_figure_atomic` for a figure that must be a new file (:func:`new_path`): a file at ``path``, there
    before or appeared meanwhile, is kept and the save refused (:class:`FileExists`, one line naming ``field``)."""
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".") or "png")
    with new_path(path, field) as tmp:
        fig.savefig(tmp, **kwargs)
    return path


def save_figure(fig, path: str | Path, field: str = "", overwrite: bool = False, **kwargs) -> Path:
    """:func:`save_figure_atomic` where the user asked to replace (``overwrite``), else :func:`save_figure_new`."""
    return (save_figure_atomic if overwrite else save_figure_new)(fig, path, field, **kwargs)


def _exchange(a: Path, b: Path) -> bool:
    """Swap the folders ``a`` and ``b`` in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the system
    or the file system cannot (the caller falls back to two renames)."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):  # glibc < 2.28, musl
        return False
    at_fdcwd, rename_exchange = -100, 2
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(at_fdcwd, os.fsencode(str(a)), at_fdcwd, os.fsencode(str(b)), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    import errno

    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def replace_folder_atomic(folder: str | Path, fill, field: str = "") -> Path:
    """Replace every file of ``folder`` at once: ``fill(tmp)`` writes the new contents into a hidden sibling folder,
    which is then swapped with ``folder`` in one rename (``renameat2`` exchange on Linux), so a reader finds the
    old folder whole or the new one whole, never a model of one and a config or COMMAND of the other (a
    reference's model and config were replaced one file at a time and its COMMAND left stale). A failure while
    writing (a full disk) leaves ``folder`` as it was and no temporary folder; an ``OSError`` becomes
    :class:`WriteFailed`. Without the exchange (another system) the old folder is renamed aside first, so for an
    instant ``folder`` is missing, never mixed."""
    import shutil

    folder = Path(folder)
    tmp = folder.with_name(f".{folder.name}.{os.getpid()}.tmp")
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        fill(tmp)
        for p in tmp.iterdir():
            if p.is_file():
                with open(p, "rb") as f:
                    os.fsync(f.fileno())
        if not folder.exists():
            os.rename(tmp, folder)
        elif _exchange(tmp, folder):
            shutil.rmtree(tmp, ignore_errors=True)  # now the old contents
        else:
            old = folder.with_name(f".{folder.name}.{os.getpid()}.old")
            os.rename(folder, old)
            os.rename(tmp, folder)
            shutil.rmtree(old, ignore_errors=True)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        reason = os.strerror(exc.errno) if exc.errno else str(exc)
        kept = "the previous version is intact" if folder.exists() else "nothing was written"
        raise WriteFailed(f"{field + ': ' if field else ''}cannot write {folder}: {reason} ({kept})") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


def csv_text(rows: list[dict], columns: list[str] | None = None) -> str:
    """``rows`` as CSV text (header: ``columns``, default every key in order of appearance), for
    :func:`write_text_atomic`: a table is formatted in memory, then written whole."""
    import csv
    import io

    columns = columns or list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns)
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


# ------------------------------------------------------------------------ folders owned by one process
LOCK = ".lock"


def lock_file(path: Path) -> int:
    """An exclusive, non-blocking ``flock`` on ``path`` (created), with this process's id written in it; raises
    :class:`BlockingIOError` while another process holds it. Retried when the file was unlinked by a releasing
    holder between our open and our lock (the lock would then be on a file no one else can see)."""
    import fcntl

    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)


def lock_holder(path: Path) -> int | None:
    """The pid written in lock file ``path`` (None if unreadable)."""
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


class OwnedFolders:
    """The folders this process holds (``<folder>/.lock``), released at exit or by :meth:`release`: the lock file
    is removed, and the folder too when nothing else is in it (a refused or empty command leaves nothing)."""

    def __init__(self) -> None:
        self._held: dict[Path, int] = {}  # folder (resolved) → the lock file's descriptor
        self._made: dict[Path, Path] = {}  # folder (resolved) → the outermost folder that taking it made

    def __contains__(self, folder: str | Path) -> bool:
        return Path(folder).resolve() in self._held

    def take(self, folder: str | Path) -> bool:
        """Lock ``folder`` (made if missing) for this process; False if this process already holds it. Raises
        :class:`BlockingIOError` when another process holds it (the folder is then left as it was), and
        ``OSError`` when it cannot be made or written."""
        folder = Path(folder)
        key = folder.resolve()
        if key in self._held:
            return False
        top = None  # the outermost folder made here (checkpoints/ of checkpoints/<run>/, say)
        for parent in (key, *key.parents):
            if parent.exists():
                break
            top = parent
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd = lock_file(folder / LOCK)
        except OSError:
            if top is not None:
                _remove_empty(key, top)
            raise
        if top is not None:
            self._made[key] = top
        if not self._held:
            import atexit

            atexit.register(self.release_all)  # however the command ends: no .lock (and no empty folder) left
        self._held[key] = fd
        return True

    def claim(self, folder: str | Path, field: str, holder: str = "another process") -> bool:
        """:meth:`take` for a command: one line naming ``field`` (the setting or flag that gave ``folder``) when
        another process holds it (``holder``, with its pid) or it cannot be made, as a :class:`ConfigError`."""
        try:
            return self.take(folder)
        except BlockingIOError:
            pid = lock_holder(Path(folder) / LOCK)
            raise ConfigError(f"{field}={folder}: {holder}{f' (pid {pid})' if pid else ''} is writing it "
                              f"({Path(folder) / LOCK} is locked); wait for it, or pick another {field}") from None
        except OSError as exc:
            raise ConfigError(f"{field}={folder}: cannot be written: "
                              f"{os.strerror(exc.errno) if exc.errno else exc}") from None

    def release(self, folder: str | Path) -> None:
        folder = Path(folder)
        key = folder.resolve()
        fd = self._held.pop(key, None)
        if fd is None:
            return
        try:
            (folder / LOCK).unlink()
        except FileNotFoundError:
            pass
        os.close(fd)
        _remove_empty(key, self._made.pop(key, key))

    def release_all(self, keep: str | Path | None = None) -> None:
        keep_key = Path(keep).resolve() if keep is not None else None
        for key in [k for k in self._held if k != keep_key]:
            self.release(key)


def _remove_empty(folder: Path, top: Path) -> None:
    """Remove ``folder`` and its parents up to ``top`` while they are empty (what nothing else has written to)."""
    for path in (folder, *folder.parents):
        try:
            path.rmdir()  # only when empty
        except OSError:
            return
        if path == top:
            return
