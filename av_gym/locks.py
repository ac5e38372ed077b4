"""A folder owned by one process: an exclusive ``flock`` on ``<folder>/.lock`` (issue 31 for training runs,
issue 39 for evaluations' out_dir: two ``python -m eval ... out_dir=X`` at once both exited 0 and X held only the
second's rows).

The kernel drops a ``flock`` when its holder exits however it exits (kill -9 included), so a crashed owner never
blocks the next; the lock file holds the holder's pid, for the message. Here, below ``eval`` and ``train``, so
that both take their folders the same way (``train/run_folder.py``: ``checkpoints/<run>/``; ``eval/__main__.py``:
``out_dir``)."""

from __future__ import annotations

import os
from pathlib import Path

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
