"""A TensorBoard folder that cannot be written (a full disk under paths.runs) is one line naming paths.runs and the
file, as a checkpoint that cannot be written is, with no empty event file left as the record of a run that never
started (R7 finding 2: SummaryWriter's ENOSPC was a 40-line traceback from its writer thread and Hydra, rc 1)."""

from __future__ import annotations

import errno
import io
import time

import pytest
from tensorboard.compat.tensorflow_stub.io.gfile import LocalFileSystem

from av_gym.atomic import WriteFailed
from train.ppo import _tensorboard_logger
from train.tb_events import resumed_writer

pytest.importorskip("torch.utils.tensorboard")  # imported at collection (~2 s): the cases themselves are quick
import stable_baselines3.common.logger  # noqa: E402,F401 - the same


@pytest.fixture
def thread_tracebacks(monkeypatch):
    """The exceptions of threads that reach ``threading.excepthook`` (which prints them as "Exception in thread
    ..."), after tensorboard's writer threads have ended."""
    import threading

    from tensorboard.summary.writer.event_file_writer import _AsyncWriterThread

    seen: list = []
    monkeypatch.setattr(threading, "excepthook", lambda args: seen.append(args.exc_value))

    def ended() -> list:
        for t in threading.enumerate():
            if isinstance(t, _AsyncWriterThread) and t.exception is not None:
                t.join(2.0)
        return seen

    return ended


def _full_disk(self, filename, file_content, mode) -> None:
    """What a full disk does to tensorboard's event file: opened (so created, 0 bytes), the write refused."""
    with io.open(filename, mode):
        raise OSError(errno.ENOSPC, "No space left on device")


def test_a_writer_that_cannot_start_is_one_line_and_leaves_no_event_file(tmp_path, monkeypatch, thread_tracebacks):
    monkeypatch.setattr(LocalFileSystem, "_write", _full_disk)
    folder = tmp_path / "runs" / "r" / "tb" / "ppo_turn"
    with pytest.raises(WriteFailed) as caught:
        resumed_writer(folder, None)
    line = str(caught.value)
    assert line.startswith(f"paths.runs: cannot write {folder}/events.out.tfevents.") and "\n" not in line, line
    assert line.endswith(": No space left on device (nothing was written)"), line
    assert not folder.exists() and (tmp_path / "runs" / "r" / "tb").is_dir()  # the folder it made, gone again
    assert thread_tracebacks() == []  # the writer thread's traceback is not printed


def test_the_ppo_logger_says_it_in_one_line_too(tmp_path, monkeypatch):
    monkeypatch.setattr(LocalFileSystem, "_write", _full_disk)
    (tmp_path / "tb").mkdir()
    (tmp_path / "tb" / "events.out.tfevents.1.old").write_bytes(b"x")  # a resumed run's: kept
    with pytest.raises(WriteFailed, match=r"^paths\.runs: cannot write .*: No space left on device"):
        _tensorboard_logger(tmp_path / "tb", None)
    assert [p.name for p in (tmp_path / "tb").iterdir()] == ["events.out.tfevents.1.old"]


def test_a_disk_that_fills_during_the_run_is_one_line_at_the_next_write(tmp_path, monkeypatch, thread_tracebacks):
    writer = resumed_writer(tmp_path, None)
    writer.add_scalar("a", 1.0, 1)
    writer.flush()
    monkeypatch.setattr(LocalFileSystem, "_write", _full_disk)
    deadline = time.monotonic() + 5.0
    with pytest.raises(WriteFailed) as caught:  # the thread's error is raised by a later write or flush
        for step in range(2, 10_000):
            writer.add_scalar("a", float(step), step)
            writer.flush()
            assert time.monotonic() < deadline, "the writer never said the disk was full"
    assert str(caught.value).endswith(": No space left on device (the events written before are kept)")
    assert thread_tracebacks() == []
