"""TensorBoard event files of a resumed run: what the interrupted run wrote after its checkpoint is cut out of the
files themselves, so that every reader sees each step once.

``SummaryWriter(purge_step=s)`` only appends a ``SessionLog.START`` event at step ``s``: TensorBoard's own readers
(the Python ``EventAccumulator`` with ``purge_orphaned_data``, the Rust data server) then hide the older events at
steps >= ``s``, but a raw reader (``EventFileLoader``, ``tf.compat.v1.train.summary_iterator``, tbparse, a
pandas export) sees both the killed run's points and the resumed run's at the same steps. Measured on a kill -9 at
4096 decisions: raw readers saw steps 4608 and 5120 twice, TensorBoard once."""

from __future__ import annotations

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
    marks the restart for TensorBoard's own readers. PPO's logger (train.ppo) and DAgger's round log both open it."""
    from torch.utils.tensorboard import SummaryWriter

    if purge_step:  # before the new writer's events: only the interrupted run's are cut
        truncate_events(folder, purge_step)
    return SummaryWriter(str(folder), purge_step=purge_step)
