"""The run log (Hydra's ``__main__.log`` in every run folder) holds what the run printed (conf/run_log.py): it
stayed empty, as the commands report through ``print`` and progress bars, not ``logging``."""

from __future__ import annotations

import logging
import sys

import pytest
from tqdm import tqdm

from av_gym.errors import ConfigError
from conf.run_log import job_log
from conftest import run


@pytest.fixture
def job_log_file(tmp_path):
    """A root-logger FileHandler, as Hydra's job logging installs one."""
    path = tmp_path / "__main__.log"
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("[%(name)s][%(levelname)s] - %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield path
    finally:
        root.removeHandler(handler)
        handler.close()


def test_printed_lines_and_a_bars_last_state_reach_the_job_log(job_log_file, capsys):
    with job_log():
        print("[train] cloning 200 episodes")
        print("a warning", file=sys.stderr)
        with tqdm(total=3, desc="cloning", file=sys.stderr, mininterval=0) as bar:
            for _ in range(3):
                bar.update()
            tqdm.write("[dagger] round 1: 50 episodes")
        print("unfinished", end="")
    log = job_log_file.read_text().splitlines()
    assert log[:2] == ["[stdout][INFO] - [train] cloning 200 episodes", "[stderr][INFO] - a warning"]
    bars = [line for line in log if "cloning:" in line]
    assert len(bars) == 1 and "3/3" in bars[0]  # the bar as it ended, not each redraw
    assert "[stdout][INFO] - [dagger] round 1: 50 episodes" in log and log[-1] == "[stdout][INFO] - unfinished"
    out = capsys.readouterr()  # the terminal saw what it always saw
    assert out.out.startswith("[train] cloning 200 episodes\n") and "a warning" in out.err and "3/3" in out.err


def test_an_error_that_ends_the_run_is_in_the_log(job_log_file):
    with pytest.raises(ConfigError), job_log():
        raise ConfigError("agent.init_from: its\nobservation space differs")
    with pytest.raises(ZeroDivisionError), job_log():
        print(1 / 0)
    log = job_log_file.read_text()
    assert "[stderr][ERROR] - error: agent.init_from: its observation space differs" in log
    assert "ZeroDivisionError: division by zero" in log and "Traceback" in log


def test_no_job_log_changes_nothing(capsys):
    out = sys.stdout
    with job_log():
        assert sys.stdout is out
        print("plain")
    assert capsys.readouterr().out == "plain\n"


def test_the_eval_commands_run_log_holds_its_table(tmp_path, monkeypatch, capsys):
    """In this process (main() with its argv: the same job logging; a fresh interpreter adds ~5 CPU-s)."""
    from eval import __main__ as eval_main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["eval", "env=left_turn", "agents=[always_proceed]", "episodes=2",
                                      "progress_bar=false", "hydra.run.dir=runs/x"])
    eval_main.main()
    log = (tmp_path / "runs" / "x" / "__main__.log").read_text()
    assert "[eval] per-episode rows: " in capsys.readouterr().out and "[eval] per-episode rows: " in log
    assert "| always_proceed" in log  # the results table


@pytest.mark.slow  # ~20 s: a whole (rule-based) training command and its brief evaluation
def test_the_train_commands_run_log_holds_what_it_printed(tmp_path):
    res = run("train", "agent=gap_acceptance", "train.eval_episodes=2", "train.progress_bar=false", "run_name=r",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    log = (tmp_path / "runs" / "r" / "__main__.log").read_text()
    assert "[train] agent 'gap_acceptance' is rule-based: nothing to train" in log
    assert "[train] brief evaluation on 2 validation seeds" in log and "| gap_acceptance | 2 |" in log


def test_a_log_that_cannot_be_written_is_dropped_quietly(job_log_file, capsys):
    """A full disk under the log: logging's own error report went to stderr, that is through the copy again."""
    handler = next(h for h in logging.getLogger().handlers if getattr(h, "baseFilename", "") == str(job_log_file))

    class Full:
        def write(self, text):
            raise OSError(28, "No space left on device")

        def flush(self):
            pass

    with job_log():
        print("first")
        handler.stream = Full()
        print("second")
        print("third")
    out = capsys.readouterr()
    assert out.out == "first\nsecond\nthird\n" and out.err == ""
    assert job_log_file.read_text() == "[stdout][INFO] - first\n"
