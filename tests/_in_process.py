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


def _call(main, argv: list[str], cwd: Path, args: list[str]) -> CompletedProcess:
    """``main()`` with ``sys.argv`` = ``argv`` in ``cwd``, in this process: exit status (``SystemExit``'s code, 0
    when it returns; ``sys.exit("message")`` printed to stderr, status 1), stdout and stderr as text, reported as the
    process ``args``. ``sys.argv`` and the working folder are as they were afterwards."""
    out, err = io.StringIO(), io.StringIO()
    saved_argv, here = sys.argv[:], os.getcwd()
    code: int | str | None = 0
    try:
        os.chdir(cwd)
        sys.argv = argv
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main()
            except SystemExit as exc:
                code = exc.code
    finally:
        os.chdir(here)
        sys.argv = saved_argv
    if code is None:
        code = 0
    elif not isinstance(code, int):
        err.write(f"{code}\n")
        code = 1
    return CompletedProcess(args, code, out.getvalue(), err.getvalue())


def run_script(script: Path, *args: str, cwd: Path) -> CompletedProcess:
    """``python script *args`` in ``cwd``, in this process (:func:`_call`). ``sys.argv``, ``sys.path``, the working
    folder and matplotlib's open figures are as they were afterwards."""
    path = sys.path[:]
    try:
        return _call(lambda: runpy.run_path(str(script), run_name="__main__"), [str(script), *args], cwd,
                     [sys.executable, str(script), *args])
    finally:
        sys.path[:] = path
        if "matplotlib.pyplot" in sys.modules:
            sys.modules["matplotlib.pyplot"].close("all")


def guarded_worker(queue) -> None:
    """A multiprocessing target that runs :func:`eval.runner.guard_worker` and says it is alive. Here, in a module
    of the standard library's imports only: a forkserver child imports the target's module, and a test module's
    imports (the registry, SB3, torch) cost its start ~4 s."""
    from eval.runner import guard_worker

    guard_worker()
    queue.put("alive")


def run_command(module: str, *overrides: str, cwd: Path) -> CompletedProcess:
    """``python -m <module> <overrides>`` (``train`` or ``eval``) in ``cwd``, in this process: ``<module>/__main__.py:
    main()`` with its own ``sys.argv``; exit status, stdout and stderr as :func:`run_script` gives them. Afterwards
    the working folder, ``sys.argv``, torch's thread count (train sets its own), the root logger (Hydra's job log)
    and the run folders and out_dirs the command locked for its process are as they were.

    Why: a fresh interpreter imports torch, SB3, highway-env and the registry again (~9 CPU-s, and ~3.5 more for
    ``torch._dynamo``, which the first optimizer imports), work that a test worker has already done."""
    import importlib
    import logging

    import torch

    entry = importlib.import_module(f"{module}.__main__")
    threads = torch.get_num_threads()
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        return _call(entry.main, [f"{module}/__main__.py", *overrides], cwd, [sys.executable, "-m", module, *overrides])
    finally:
        from eval.__main__ import OUT_DIRS
        from train.run_folder import release_all

        release_all()
        OUT_DIRS.release_all()
        torch.set_num_threads(threads)
        for handler in [h for h in root.handlers if h not in handlers]:
            root.removeHandler(handler)
            handler.close()
        root.setLevel(level)
