"""TensorBoard event files of a resumed run: what the interrupted run wrote after its checkpoint is cut out of the
files themselves, so that every reader sees each step once.

``SummaryWriter(purge_step=s)`` only appends a ``SessionLog.START`` event at step ``s``: TensorBoard's own readers
(the Python ``EventAccumulator`` with ``purge_orphaned_data``, the Rust data server) then hide the older events at
steps >= ``s``, but a raw reader (``EventFileLoader``, ``tf.compat.v1.train.summary_iterator``, tbparse, a
pandas export) sees both the killed run's points and the resumed run's at the same steps. Measured on a kill -9 at
4096 decisions: raw readers saw steps 4608 and 5120 twice, TensorBoard once."""

from __future__ import annotations

import errno
import os
from pathlib import Path


def truncate_events(folder: str | Path, purge_step: int) -> int:
    """Remove from every ``events.out.tfevents.*`` file in ``folder`` the events at steps >= ``purge_step`` (what a
    killed or interrupted run logged after the checkpoint it is resumed from), each file rewritten atomically (temp
    file + rename: a crash leaves the old file or the new one). Events at steps below it (and the step-0 file
    header, hyperparameters and layout) are kept byte for byte; a record torn by ``kill -9`` mid-write is dropped.
    Returns the number of events removed."""
    from tensorboard.backend.event_processing.event_file_loader import RawEventFileLoader
    from tensorboard.compat.proto.event_pb2 import Event
    from tensorboard.summary.writer.record_writer import RecordWriter

    from av_gym.atomic import atomic_path

    removed = 0
    for path in sorted(Path(folder).glob("events.out.tfevents.*")):
        records = list(RawEventFileLoader(str(path)).Load())  # stops at a torn last record
        kept = [r for r in records if Event.FromString(r).step < purge_step]
        if len(kept) == len(records) and _whole(path, records):
            continue
        removed += len(records) - len(kept)
        with atomic_path(path, "paths.runs") as tmp, open(tmp, "wb") as f:
            writer = RecordWriter(f)
            for record in kept:
                writer.write(record)
    return removed


def _whole(path: Path, records: list[bytes]) -> bool:
    """Whether ``records`` (as TFRecord framing: 8-byte length, 4-byte CRC, data, 4-byte CRC) fill ``path``, i.e.
    no torn record follows them."""
    return path.stat().st_size == sum(16 + len(r) for r in records)


def resumed_writer(folder: str | Path, purge_step: int | None):
    """A ``SummaryWriter`` on ``folder`` for a run's TensorBoard log; resumed (``purge_step``: the first step the
    resumed run writes again), what the interrupted run logged at steps >= ``purge_step`` is first cut out of the
    old event files (:func:`truncate_events`: raw readers see each step once), then the writer's ``purge_step``
    marks the restart for TensorBoard's own readers. PPO's logger (train.ppo) and DAgger's round log both open it.

    A folder it cannot write (a full disk, no permission) is one line, :class:`av_gym.atomic.WriteFailed` naming
    ``paths.runs`` and the file, as a checkpoint that cannot be written is: found here (the file's first event is
    flushed at once), the event file it began is removed (no empty file left as the record of a run that never
    started); later in the run, the writer's next write or flush says it (:class:`_Refusing`)."""
    from torch.utils.tensorboard import SummaryWriter

    _quiet_writer_threads()
    if purge_step:  # before the new writer's events: only the interrupted run's are cut
        truncate_events(folder, purge_step)
    folder = Path(folder)
    existed, before = folder.is_dir(), set(folder.glob("events.out.tfevents.*"))
    writer = None
    try:
        writer = SummaryWriter(str(folder), purge_step=purge_step)
        writer.flush()  # the file's first event tried now: a disk that cannot take it is found before the run
        _started(writer)
    except OSError as exc:
        cause = _thread_error(writer, wait=True) or exc  # the writer thread's own error says why (ENOSPC, EACCES)
        made = sorted(set(folder.glob("events.out.tfevents.*")) - before)  # SummaryWriter itself may have raised
        _discard(writer, folder, existed, before)
        raise _failed(_event_file(writer) or (made[0] if made else folder), cause, "nothing was written") from None
    _refuse_in_one_line(writer)
    return writer


FIELD = "paths.runs"  # where a run's TensorBoard folder lives (<paths.runs>/<run>/tb/<agent>)


def _failed(path: Path, exc: OSError, kept: str):
    from av_gym.atomic import WriteFailed

    reason = os.strerror(exc.errno) if exc.errno else str(exc)
    return WriteFailed(f"{FIELD}: cannot write {path}: {reason} ({kept})")


def _event_writer(writer):
    """The writer's ``EventFileWriter`` (tensorboard's), or None (not opened)."""
    return getattr(getattr(writer, "file_writer", None), "event_writer", None)


def _event_file(writer) -> Path | None:
    name = getattr(_event_writer(writer), "_file_name", None)
    return Path(name) if name else None


def _thread_error(writer, wait: bool = False) -> BaseException | None:
    """What the event file's background writer thread failed with, if it did (tensorboard keeps it for the next
    call); ``wait``: give a thread that is failing a moment to end (it sets the error as it ends)."""
    worker = getattr(getattr(_event_writer(writer), "_async_writer", None), "_worker", None)
    if worker is None:
        return None
    if wait and worker.exception is None:
        worker.join(1.0)
    return worker.exception


def _started(writer) -> None:
    """Raise the error the writer's thread met on the file's first event. After ``flush`` its queue is drained, so
    that event was written (the file is not empty) or its write failed: decided here, not by timing."""
    error = _thread_error(writer)
    if error is not None:
        raise error
    path = _event_file(writer)
    if path is not None and (not path.is_file() or path.stat().st_size == 0):
        raise _thread_error(writer, wait=True) or OSError(errno.EIO, "its first event did not reach the file")


def _discard(writer, folder: Path, existed: bool, before: set[Path]) -> None:
    """A writer that could not start: closed (its errors ignored: the first is the one said), its new event files
    removed, and ``folder`` too when it made it and it is left empty."""
    import contextlib

    with contextlib.suppress(Exception):
        if writer is not None:
            writer.close()
    for path in set(folder.glob("events.out.tfevents.*")) - before:
        with contextlib.suppress(OSError):
            path.unlink()
    if not existed:
        with contextlib.suppress(OSError):
            folder.rmdir()


class _Refusing:
    """An event file's asynchronous writer (tensorboard's ``_AsyncWriter``) whose ``OSError`` (the disk filled up
    during the run) is one line naming the file, :class:`av_gym.atomic.WriteFailed`: the run stops as it would on a
    checkpoint it cannot write, rather than with tensorboard's traceback."""

    def __init__(self, inner, path: Path) -> None:
        self._inner, self._path = inner, path

    def _call(self, method: str, *args):
        try:
            return getattr(self._inner, method)(*args)
        except OSError as exc:
            raise _failed(self._path, exc, "the events written before are kept") from None

    def write(self, bytestring: bytes) -> None:
        self._call("write", bytestring)

    def flush(self) -> None:
        self._call("flush")

    def close(self) -> None:
        self._call("close")

    def __getattr__(self, name: str):
        return getattr(self._inner, name)


def _refuse_in_one_line(writer) -> None:
    event_writer = _event_writer(writer)
    if event_writer is not None and hasattr(event_writer, "_async_writer"):
        event_writer._async_writer = _Refusing(event_writer._async_writer, _event_file(writer))


def _quiet_writer_threads() -> None:
    """An ``OSError`` in tensorboard's writer thread is kept by the thread (``exception``) and raised by the next
    write or flush, which says it in one line (:class:`_Refusing`); the thread's own traceback on stderr
    ("Exception in thread Thread-1: ...") is not printed. Other threads' exceptions go to the previous hook."""
    import threading

    from tensorboard.summary.writer.event_file_writer import _AsyncWriterThread

    previous = threading.excepthook
    if getattr(previous, "quiet_tensorboard", False):
        return

    def hook(args) -> None:
        if isinstance(args.thread, _AsyncWriterThread) and issubclass(args.exc_type, OSError):
            return
        previous(args)

    hook.quiet_tensorboard = True  # type: ignore[attr-defined]
    threading.excepthook = hook
