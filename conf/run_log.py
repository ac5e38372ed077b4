"""What a command shows while it runs (:func:`progress`), and what its run log keeps (:func:`job_log`).

The run log holds what the run printed: Hydra gives every run folder a job log (``__main__.log``, a
``logging.FileHandler`` on the root logger), but the commands report through ``print`` and progress bars, which
never reach ``logging``. :func:`job_log` copies every line written to ``sys.stdout`` and ``sys.stderr`` into that
file while a Hydra job runs; the terminal sees the same output as without it.

A progress bar redraws its line with carriage returns; the log keeps each line as it last stood when it ended
(a bar's final state, a message written beside it by ``tqdm.write``), not every redraw. Lines written by
worker processes (they write to the inherited file descriptors, not to this process's ``sys.stdout``) are not
copied."""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TextIO

from tqdm import tqdm

from av_gym.errors import ConfigError


class _Tee:
    """A text stream that writes through to ``stream`` and hands each finished line to the job log's handlers."""

    def __init__(self, stream: TextIO, name: str, handlers: list[logging.FileHandler]) -> None:
        self._stream, self._name, self._handlers, self._line = stream, name, handlers, ""

    def write(self, text: str) -> int:
        n = self._stream.write(text)
        self._collect(text)
        return n

    def _collect(self, text: str) -> None:
        *done, self._line = (self._line + text.replace("\r\n", "\n")).split("\n")
        self._line = self._line.rsplit("\r", 1)[-1]  # a bar's redraw replaces the line: only its latest state
        for line in done:
            log_line(line.rsplit("\r", 1)[-1], self._name, self._handlers)

    def flush(self) -> None:
        self._stream.flush()

    def close_line(self) -> None:
        """The unfinished last line (a bar never closed, a prompt), as it stands."""
        line, self._line = self._line, ""
        log_line(line, self._name, self._handlers)

    def __getattr__(self, name: str) -> Any:  # isatty, fileno, encoding ...: the terminal's own
        return getattr(self._stream, name)


def log_line(line: str, name: str, handlers: list[logging.FileHandler], level: int = logging.INFO) -> None:
    """``line`` into each of ``handlers`` as a record of logger ``name``, in the handler's format; blank lines and
    closed handlers (the run folder was discarded) are skipped. A log that cannot be written (a full disk, a file
    size limit) is dropped from ``handlers`` without a word: logging's own error report would go to stderr, that
    is through this copy again, and the terminal has the line anyway."""
    if not line.strip():
        return
    record = logging.LogRecord(name, level, __name__, 0, line.rstrip(), None, None)
    for handler in list(handlers):
        handler.acquire()
        try:
            if handler.stream is not None:
                handler.stream.write(handler.format(record) + handler.terminator)
                handler.stream.flush()
        except (OSError, ValueError):
            handlers.remove(handler)
        finally:
            handler.release()


def job_log_handlers() -> list[logging.FileHandler]:
    """The root logger's file handlers: Hydra's job log (none outside a Hydra job, or with ``hydra/job_logging``
    disabled). One writing to ``os.devnull`` (pytest's, when no log file is asked for) keeps nothing."""
    return [h for h in logging.getLogger().handlers
            if isinstance(h, logging.FileHandler) and h.baseFilename != os.path.abspath(os.devnull)]


@contextlib.contextmanager
def job_log() -> Iterator[None]:
    """For the block: ``sys.stdout`` and ``sys.stderr`` copied line by line into the job log (records of the
    loggers ``stdout`` / ``stderr``); a traceback that ends the run is written there too (Hydra prints it on the
    terminal only). Nothing changes where there is no job log."""
    handlers = job_log_handlers()
    if not handlers:
        yield
        return
    saved = sys.stdout, sys.stderr
    tees = _Tee(sys.stdout, "stdout", handlers), _Tee(sys.stderr, "stderr", handlers)
    sys.stdout, sys.stderr = tees
    try:
        yield
    except ConfigError as exc:  # its line goes to the terminal once the job has ended (av_gym.errors.run_cli)
        log_line("error: " + " ".join(str(exc).split()), "stderr", handlers, logging.ERROR)
        raise
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException:
        log_line(traceback.format_exc(), "stderr", handlers, logging.ERROR)
        raise
    finally:
        sys.stdout, sys.stderr = saved
        for tee in tees:
            tee.close_line()


def job_logged(fn: Callable) -> Callable:
    """``fn`` run inside :func:`job_log` (a Hydra command's job: ``run_cli(job_logged(train), cfg, ...)``)."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        with job_log():
            return fn(*args, **kwargs)

    return run


def progress(items: Iterable, total: int, desc: str, unit: str = "item", every_s: float = 5.0) -> Iterator:
    """``items``, reporting progress as it goes: a tqdm bar on a terminal; elsewhere (a pipe, a file, a test's
    capture, where a bar's redraws are noise and a line is what is read) a line ``[desc] k/total units, t s`` on
    stdout at the first item ``every_s`` seconds after the last line, and at the end. Items that arrive in bursts
    (a process pool's chunks) stretch the gaps: 5 s keeps them under ~15 s."""
    if sys.stderr.isatty():
        yield from tqdm(items, total=total, desc=desc, unit=unit)
        return
    t0 = last = time.monotonic()
    for done, item in enumerate(items, start=1):
        yield item
        now = time.monotonic()
        if now - last >= every_s or done == total:
            print(f"[{desc}] {done}/{total} {unit}s, {now - t0:.0f} s", flush=True)
            last = now
