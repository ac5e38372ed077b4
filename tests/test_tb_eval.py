"""TensorBoard's eval/* scalars equal eval.csv, row for row: every evaluation (the first, the last) and after a
resume (they appeared one rollout late, the final one never, and a resumed run lost one)."""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

# agent=ppo on the per-env stack, an evaluation of 2 short episodes at every 64-step rollout, a checkpoint every 128
ARGS = ["agent=ppo", "env.duration=4", "agent.n_steps=64", "agent.batch_size=64", "agent.n_epochs=1",
        "agent.n_envs=1", "train.eval_n=2", "train.eval_every=64", "train.checkpoint_every=128",
        "train.eval_episodes=0", "train.video_every=0", "train.progress_bar=false", "run_name=tb"]


def _tensorboard(run) -> dict[str, dict[int, float]]:
    acc = EventAccumulator(str(run / "tb" / "ppo"), purge_orphaned_data=True, size_guidance={"scalars": 0})
    acc.Reload()
    return {tag[len("eval/"):]: {e.step: e.value for e in acc.Scalars(tag)}
            for tag in acc.Tags()["scalars"] if tag.startswith("eval/")}


def _csv(run) -> list[dict]:
    with open(run / "eval.csv") as f:
        return list(csv.DictReader(f))


def _assert_same(run) -> list[int]:
    tb, rows = _tensorboard(run), _csv(run)
    steps = [int(r["steps"]) for r in rows]
    assert steps == sorted(set(steps))
    for metric in rows[0]:
        if metric == "steps":
            continue
        tag = metric
        defined = [r for r in rows if float(r[metric]) == float(r[metric])]  # NaN (no arrival: no time) is no point
        assert sorted(tb.get(tag, {})) == [int(r["steps"]) for r in defined], metric  # same evaluations, same steps
        for r in defined:
            tol = 0.051 if metric == "wall_clock_s" else 1e-6 * max(1.0, abs(float(r[metric])))  # csv rounds time
            assert tb[tag][int(r["steps"])] == pytest.approx(float(r[metric]), abs=tol), (metric, r["steps"])
    return steps


@pytest.mark.slow  # two tiny training runs (~20 s each)
def test_tensorboard_eval_scalars_equal_eval_csv_also_after_a_resume(tmp_path):
    def train(*extra):
        res = subprocess.run([sys.executable, "-m", "train", *ARGS, *extra], cwd=tmp_path, capture_output=True,
                             text=True, timeout=600)
        assert res.returncode == 0, res.stderr[-3000:]

    run = tmp_path / "runs" / "tb"
    train("agent.total_timesteps=256")
    assert _assert_same(run) == [0, 64, 128, 192, 256]  # the start, each rollout, and the final model
    # a finished run is not resumed; without its final model.zip the folder is what a kill after the last
    # checkpoint leaves. latest.zip is at 128: the resumed run drops the evaluations after it (TensorBoard purges
    # them too) and goes on
    (tmp_path / "checkpoints" / "tb" / "model.zip").unlink()
    train("agent.total_timesteps=384", "train.resume=true")
    assert _assert_same(run) == [0, 64, 128, 192, 256, 320, 384]
