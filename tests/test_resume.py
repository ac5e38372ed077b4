"""Crash-safe training: kill -9 mid-run, resume from the last complete checkpoint to the same total steps, and
TensorBoard curves that continue without a gap or a duplicate."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

# agent=ppo (no behaviour cloning first): what is tested is the crash-safety of PPO's loop, the same for every
# PPO agent; eval_n=2: the periodic evaluation runs, on 2 episodes
ARGS = ["agent=ppo", "train.eval_n=2", "agent.total_timesteps=3072", "agent.n_steps=128", "agent.batch_size=64",
        "agent.n_epochs=1", "agent.n_envs=1", "train.checkpoint_every=512", "train.eval_episodes=0", "train.progress_bar=false",
        "run_name=crash"]


def _raw_steps(tb: Path) -> list[int]:
    """The train/value_loss steps in the event files themselves, as raw readers (tbparse, EventFileLoader) see them."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    return [e.step for path in sorted(tb.glob("events.*")) for e in EventFileLoader(str(path)).Load()
            for v in e.summary.value if v.tag == "train/value_loss"]


def _steps(model_zip: Path) -> int:
    import json

    with zipfile.ZipFile(model_zip) as z:
        return int(json.loads(z.read("data"))["num_timesteps"])


@pytest.mark.slow  # two checkpoints, a kill, a resumed run to the total
def test_kill_9_then_resume_reaches_the_same_total_without_tensorboard_duplicates(tmp_path):
    ckpt, tb = tmp_path / "checkpoints" / "crash", tmp_path / "runs" / "crash" / "tb" / "ppo"
    proc = subprocess.Popen([sys.executable, "-m", "train", *ARGS], cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 240
    while time.time() < deadline:  # wait for the second periodic checkpoint and a point logged after it, then kill
        if ((ckpt / "latest.zip").is_file() and _steps(ckpt / "latest.zip") >= 1024
                and max(_raw_steps(tb), default=0) > _steps(ckpt / "latest.zip")):
            break
        assert proc.poll() is None, proc.stderr.read()[-2000:]
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    killed_at = _steps(ckpt / "latest.zip")
    assert max(_raw_steps(tb)) > killed_at  # what the resume must not show twice
    assert 1024 <= killed_at < 3072 and not (ckpt / "model.zip").exists()
    (ckpt / ".latest.99999.tmp").write_bytes(b"torn write")  # what a kill during a save leaves behind

    res = subprocess.run([sys.executable, "-m", "train", *ARGS, "train.resume=true"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"resuming" in res.stdout and _steps(ckpt / "model.zip") == 3072
    assert not list(ckpt.glob(".*.tmp"))

    acc = EventAccumulator(str(tb), purge_orphaned_data=True)
    acc.Reload()
    steps = [e.step for e in acc.Scalars("train/value_loss")]
    assert steps == sorted(set(steps)), "no duplicate steps"
    assert steps[-1] >= 3072 - 128 and min(b - a for a, b in zip(steps, steps[1:])) == max(
        b - a for a, b in zip(steps, steps[1:])), "one point per rollout, no gap"
    # raw readers too: the killed run's events after its checkpoint are gone from its file (not only hidden by
    # purge_step, which TensorBoard's readers honour)
    assert sorted(_raw_steps(tb)) == steps, "each step once in the event files themselves"


def test_resume_without_a_checkpoint_is_a_clear_error(tmp_path):
    from conftest import cli  # the command-line check in this process; a real process only if it passes

    res = cli("train", *ARGS, "run_name=nothing", "train.resume=true", cwd=tmp_path)
    assert res.returncode == 2 and "train.resume=true but" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.slow  # 15-35 CPU-s (trains or runs whole evaluations): over the README test budget
def test_sigterm_saves_a_checkpoint(tmp_path):
    ckpt = tmp_path / "checkpoints" / "crash"
    proc = subprocess.Popen([sys.executable, "-m", "train", *ARGS, "train.checkpoint_every=100000"], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 240
    tb = tmp_path / "runs" / "crash" / "tb" / "ppo"
    while time.time() < deadline and not (tb.is_dir() and any(tb.iterdir())):
        time.sleep(0.2)
    time.sleep(3)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert "interrupted at" in out and (ckpt / "latest.zip").is_file()
    with zipfile.ZipFile(ckpt / "latest.zip") as z:  # the RNG states travel inside the checkpoint
        assert "av_gym_rng.pkl" in z.namelist()
