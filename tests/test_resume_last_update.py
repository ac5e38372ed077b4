"""A run stopped by SIGTERM in its last PPO update, then resumed (train.resume=true), ends as the uninterrupted run:
the final periodic evaluation (eval.csv's last row, best.json), model.zip and the brief evaluation (results.csv,
results.md). Before: the resume found no step left, skipped PPO's learn() and crashed in the guard's check
(AttributeError), leaving no model.zip, no results and eval.csv without its row at the total."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

# agent=ppo on the per-env stack: 2 rollouts of 64 decisions, one optimizer step per update (batch 64, 1 epoch), an
# evaluation of 2 short episodes at each rollout, no checkpoint but the one a signal writes, 2 brief episodes
ARGS = ["agent=ppo", "env.duration=4", "agent.n_steps=64", "agent.batch_size=64", "agent.n_epochs=1",
        "agent.n_envs=1", "agent.total_timesteps=128", "train.eval_n=2", "train.eval_every=64",
        "train.checkpoint_every=1000000", "train.eval_episodes=2", "train.video_every=0", "train.progress_bar=false",
        "run_name=r"]

# python -m train with SIGTERM sent from inside optimizer step number argv[1] (2: the last update's)
SIGNALLING = '''
import os, runpy, signal, sys
import torch
at, calls, step = int(sys.argv.pop(1)), [0], torch.optim.Adam.step
def signalling(self, *args, **kwargs):
    out = step(self, *args, **kwargs)
    calls[0] += 1
    if calls[0] == at:
        os.kill(os.getpid(), signal.SIGTERM)
    return out
torch.optim.Adam.step = signalling
sys.argv[0] = "train"
runpy.run_module("train", run_name="__main__", alter_sys=True)
'''


def _train(folder: Path, *argv: str) -> subprocess.CompletedProcess:
    folder.mkdir(parents=True, exist_ok=True)
    return subprocess.run([sys.executable, *argv], cwd=folder, capture_output=True, text=True, timeout=600,
                          env=_env())


def _env() -> dict:
    import os

    root = str(Path(__file__).resolve().parents[1])
    return {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}


def _outcome(folder: Path) -> dict:
    """What the run leaves after learning, wall-clock times left out."""
    with open(folder / "runs" / "r" / "eval.csv") as f:
        rows = [{k: v for k, v in r.items() if k != "wall_clock_s"} for r in csv.DictReader(f)]
    best = json.loads((folder / "checkpoints" / "r" / "best.json").read_text())
    body = [ln for ln in (folder / "runs" / "r" / "results.md").read_text().splitlines() if "|" in ln]
    return {"eval": rows, "best": {k: v for k, v in best.items() if k != "wall_clock_s"},
            "results": (folder / "runs" / "r" / "results.csv").read_text(), "table": body,
            "model": (folder / "checkpoints" / "r" / "model.zip").is_file()}


@pytest.mark.slow  # three tiny training runs: ~20 s at load 1
def test_a_run_stopped_in_its_last_update_resumes_to_what_the_uninterrupted_run_leaves(tmp_path):
    whole = _train(tmp_path / "whole", "-m", "train", *ARGS)
    assert whole.returncode == 0, whole.stderr[-3000:]
    cut = tmp_path / "cut"
    stopped = _train(cut, "-c", SIGNALLING, "2", *ARGS)
    assert stopped.returncode == 130, stopped.stderr[-3000:]
    assert "holds 128 decisions" in stopped.stdout or "holds 128 env steps" in stopped.stdout, stopped.stdout[-2000:]
    assert not (cut / "runs" / "r" / "results.md").exists()
    resumed = _train(cut, "-m", "train", *ARGS, "train.resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    expected = _outcome(tmp_path / "whole")
    assert [r["steps"] for r in expected["eval"]] == ["0", "64", "128"] and expected["model"]
    assert _outcome(cut) == expected
