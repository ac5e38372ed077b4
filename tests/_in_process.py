"""A checkout's script (``python <script>.py ...``) run in the test's own process, as a subprocess would run it:
its exit status, stdout and stderr in a :class:`subprocess.CompletedProcess`.

Why not a subprocess: every fresh interpreter imports the library again (``conf.cli`` alone pulls in the whole
registry: ~4 s of CPU per start at load 3), which made each tool test several seconds of start-up for a few
milliseconds of its own work. The script still runs as ``__main__`` (``runpy.run_path``) with its own
``sys.argv`` and working folder; what a process gives beyond that (a fresh interpreter's import order, the
``python`` executable found on the path) is the documented commands' check (tests/test_documented_commands.py)."""

from __future__ import annotations

import contextlib
import io
import os
import runpy
import sys
from pathlib import Path
from subprocess import CompletedProcess


def run_script(script: Path, *args: str, cwd: Path) -> CompletedProcess:
    """``python script *args`` in ``cwd``, in this process: exit status (``SystemExit``'s code, 0 when it returns),
    stdout and stderr as text. ``sys.argv``, ``sys.path``, the working folder and matplotlib's open figures are
    as they were afterwards."""
    out, err = io.StringIO(), io.StringIO()
    argv, path, here = sys.argv[:], sys.path[:], os.getcwd()
    code: int | str | None = 0
    try:
        os.chdir(cwd)
        sys.argv = [str(script), *args]
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                runpy.run_path(str(script), run_name="__main__")
            except SystemExit as exc:
                code = exc.code
    finally:
        os.chdir(here)
        sys.argv, sys.path[:] = argv, path
        if "matplotlib.pyplot" in sys.modules:
            sys.modules["matplotlib.pyplot"].close("all")
    if code is None:
        code = 0
    elif not isinstance(code, int):  # sys.exit("message"): printed to stderr, status 1
        err.write(f"{code}\n")
        code = 1
    return CompletedProcess([sys.executable, str(script), *args], code, out.getvalue(), err.getvalue())


def guarded_worker(queue) -> None:
    """A multiprocessing target that runs :func:`eval.runner.guard_worker` and says it is alive. Here, in a module
    of the standard library's imports only: a forkserver child imports the target's module, and a test module's
    imports (the registry, SB3, torch) cost its start ~4 s."""
    from eval.runner import guard_worker

    guard_worker()
    queue.put("alive")
