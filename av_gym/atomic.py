"""Atomic file writes: a temporary file beside the target, flushed to disk, then renamed over it (``os.replace``,
atomic on POSIX within a file system). A crash or a full disk at any point leaves the old complete file or the new
complete file, never a torn one, and no temporary file behind (a full disk left ``results.csv`` cut at
row 10 and ``.latest.<pid>.tmp`` files).

A write that fails (``OSError``: no space, quota, permissions) raises :class:`WriteFailed`, a
:class:`~av_gym.errors.ConfigError`: one line at the command line naming the file, what the system said and that
the previous version is intact."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

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
        path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        _remove(tmp)
        reason = os.strerror(exc.errno) if exc.errno else str(exc)
        kept = "the previous version is intact" if path.exists() else "nothing was written"
        raise WriteFailed(f"{field + ': ' if field else ''}cannot write {path}: {reason} ({kept})") from None
    except BaseException:
        _remove(tmp)
        raise


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
    and no empty or half-written png (a full disk left an empty ``grid.png`` and three tracebacks). The
    format comes from ``path``'s suffix, not from the temporary name's."""
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".") or "png")
    with atomic_path(path, field) as tmp:
        fig.savefig(tmp, **kwargs)
    return path


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
