"""eval.runner.WorkerPool: the first part to fail is raised at once, not after the parts before it finish; a pool
stopped by SIGTERM leaves nothing behind for multiprocessing's resource tracker to warn about."""
import time

import pytest

from eval.runner import WorkerPool


def _nothing() -> None:
    pass


def _part(part: tuple) -> str:
    """A part that sleeps ``part[1]`` s, then fails when ``part[0]`` is 'fail'."""
    kind, seconds = part
    time.sleep(seconds)
    if kind == "fail":
        raise ValueError("part 2 failed")
    return kind


@pytest.mark.slow  # spawns two interpreters (~2-4 s)
def test_a_later_part_that_fails_is_raised_before_an_earlier_slow_part_ends():
    start = time.monotonic()
    with pytest.raises(ValueError, match="part 2 failed"):
        with WorkerPool(2, _nothing) as pool:
            pool.parts(_part, [("slow", 60.0), ("fail", 0.0)])
    assert time.monotonic() - start < 30.0  # in order, it would wait out the 60 s part first


@pytest.mark.slow
def test_parts_come_back_in_the_order_given():
    with WorkerPool(2, _nothing) as pool:
        assert pool.parts(_part, [("a", 0.5), ("b", 0.0)]) == ["a", "b"]


STOPPED = '''
import sys
import time
from pathlib import Path

from av_gym.errors import run_cli
from eval.runner import WorkerPool


def _nothing():
    pass


def _drive(marker):
    from tqdm import tqdm

    with tqdm(total=1, disable=True):  # an eval worker's bar: play_batched(progress=False)
        Path(marker).touch()
        time.sleep(120)


def main():
    with WorkerPool(2, _nothing) as pool:
        pool.parts(_drive, [sys.argv[1] + "/running.0", sys.argv[1] + "/running.1"])


if __name__ == "__main__":
    run_cli(main)
'''


def _wait_until_both_workers_run(proc, folder, timeout_s: float) -> None:
    """Until both of ``proc``'s workers are in their task (their marker files in ``folder``); a command that exits
    first, or is still starting them after ``timeout_s`` seconds (then ended by SIGKILL to its group), fails the test
    with its exit status and the end of its stderr."""
    import os
    import signal
    import subprocess

    deadline = time.monotonic() + timeout_s
    while not all((folder / f"running.{k}").exists() for k in (0, 1)):
        if proc.poll() is not None or time.monotonic() > deadline:
            still_running = proc.poll() is None
            if still_running:
                os.killpg(proc.pid, signal.SIGKILL)
            try:
                err = proc.communicate(timeout=30)[1]
            except subprocess.TimeoutExpired:
                err = "(its stderr stayed open 30 s after it ended)"
            pytest.fail(f"the workers were not both running after {timeout_s:.0f} s "
                        f"({'still starting' if still_running else f'exit {proc.returncode}'}): {err[-2000:]}")
        time.sleep(0.1)


@pytest.mark.slow  # a command with two spawned workers, stopped by SIGTERM (~1 s each)
@pytest.mark.parametrize("sent_to", ["group", "parent"])
def test_a_pool_stopped_by_sigterm_leaves_no_leaked_semaphore(tmp_path, sent_to):
    """SIGTERM to the command's process group (``timeout``, a scheduler: the workers die of it too) or to the parent
    alone (it ends the workers, :func:`eval.runner._stop`) while both workers are in a task that made a progress bar:
    exit 130 and nothing from multiprocessing's resource tracker on stderr. Fails with tqdm's default lock in the
    workers (a named semaphore that a killed worker never releases: "There appear to be 2 leaked semaphore
    objects")."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    script = tmp_path / "stopped.py"
    script.write_text(STOPPED)
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path)], cwd=root, text=True, start_new_session=True,
                            env={**os.environ, "PYTHONPATH": str(root)}, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        _wait_until_both_workers_run(proc, tmp_path, 90.0)
        if sent_to == "group":
            os.killpg(proc.pid, signal.SIGTERM)
        else:
            proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)  # until the resource tracker, which holds stderr too, has ended
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "leaked" not in err and "resource_tracker" not in err, err
