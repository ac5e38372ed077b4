"""A resumed PPO run's ``videos/``: the GIFs of the interrupted run's evaluations after its checkpoint (a model that
is gone, at steps the resumed run evaluates again) are removed when it resumes, as its eval.csv rows and TensorBoard
events are (train.callbacks.remove_videos_after); a user's file there, and the GIFs up to the checkpoint, stay."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from tests.test_nothing_lost import snapshot
from train.callbacks import PeriodicEval

HEADER = "steps,wall_clock_s,collision,success,score\n"


def _interrupted_run(run_dir):
    """The log folder of a run killed after evaluating at 0, 512, ..., 2048 decisions, one GIF each (and one GIF
    write cut short at 2560), with a user's files in videos/."""
    videos = run_dir / "videos"
    (videos / "mine").mkdir(parents=True)
    for step in range(0, 2049, 512):
        (videos / f"step_{step:08d}.gif").write_bytes(b"GIF89a" + str(step).encode())
    (videos / ".step_00002560.gif.4242.tmp").write_bytes(b"GIF8")
    (videos / "notes.txt").write_text("the turn at 1536 looks odd\n")
    (videos / "step_00001536.gif.bak").write_bytes(b"GIF89a mine")
    (videos / "mine" / "step_00002048.gif").write_bytes(b"GIF89a mine too")
    (run_dir / "eval.csv").write_text(HEADER + "".join(f"{s},{s / 100},0.1,0.8,0.7\n" for s in range(0, 2049, 512)))


def _start(run_dir, ckpt_dir, decisions: int, video_every: int = 512) -> PeriodicEval:
    """PeriodicEval as SB3 starts it (``on_training_start``) for a model at ``decisions`` (a resume when > 0)."""
    callback = PeriodicEval(lambda mode: None, "left_turn", [1_000_000], 512, ckpt_dir, run_dir, video_every)
    callback.model = SimpleNamespace(num_timesteps=decisions)
    callback.on_training_start({}, {})
    return callback


@pytest.mark.parametrize("video_every", [512, 0], ids=["videos_on", "videos_off_now"])
def test_a_resume_removes_exactly_the_videos_after_its_checkpoint(video_every, tmp_path, capsys):
    run_dir, ckpt_dir = tmp_path / "runs" / "R", tmp_path / "checkpoints" / "R"
    ckpt_dir.mkdir(parents=True)
    _interrupted_run(run_dir)
    before = snapshot(run_dir)
    _start(run_dir, ckpt_dir, 1024, video_every)  # resumed from latest.zip at 1024 decisions
    gone = {"videos/step_00001536.gif", "videos/step_00002048.gif", "videos/.step_00002560.gif.4242.tmp"}
    after = snapshot(run_dir)
    assert set(before) - set(after) == gone and set(after) <= set(before)
    assert {k: v for k, v in after.items() if k != "eval.csv"} == {k: v for k, v in before.items()
                                                                    if k not in gone | {"eval.csv"}}
    assert after["eval.csv"].decode() == HEADER + "0,0.0,0.1,0.8,0.7\n512,5.12,0.1,0.8,0.7\n1024,10.24,0.1,0.8,0.7\n"
    assert "removed 3 videos of the interrupted run's evaluations after it" in capsys.readouterr().out


def test_a_fresh_run_and_a_resume_without_videos_touch_nothing(tmp_path):
    run_dir, ckpt_dir = tmp_path / "runs" / "R", tmp_path / "checkpoints" / "R"
    ckpt_dir.mkdir(parents=True)
    _interrupted_run(run_dir)
    before = snapshot(run_dir)
    _start(run_dir, ckpt_dir, 2560)  # resumed at the last video's step: nothing after it
    assert snapshot(run_dir) == before
    _start(tmp_path / "runs" / "new", ckpt_dir, 4096)  # no videos/ folder at all
    assert not (tmp_path / "runs" / "new").exists()


def _gif_steps(videos) -> list[int]:
    return sorted(int(p.name[5:13]) for p in videos.glob("step_*.gif"))


@pytest.mark.slow  # a PPO run killed (kill -9) after a video past its checkpoint, then resumed: ~30 CPU-s
def test_a_killed_run_resumed_keeps_no_video_of_a_model_that_is_gone(tmp_path):
    """Videos at every evaluation (512 decisions, checkpoints every 1024), a kill -9 once one is written after the
    last checkpoint; resumed with ``train.video_every=0`` (no GIF of the resumed run replaces them): the killed
    run's GIFs after its checkpoint are gone, those up to it stay byte for byte, and a user's file in videos/
    stays."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from tests.test_nothing_lost import ROOT
    from tests.test_resume import ARGS, _steps

    args = [*ARGS, "train.checkpoint_every=1024", "train.eval_every=512", "train.video_every=512"]
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    ckpt, videos = tmp_path / "checkpoints" / "crash", tmp_path / "runs" / "crash" / "videos"
    proc = subprocess.Popen([sys.executable, "-m", "train", *args], cwd=tmp_path, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 240
    while time.time() < deadline:  # a checkpoint, then a GIF of a later evaluation: kill
        if (ckpt / "latest.zip").is_file() and max(_gif_steps(videos), default=-1) > _steps(ckpt / "latest.zip"):
            break
        assert proc.poll() is None, proc.stderr.read()[-2000:]
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    killed_at = _steps(ckpt / "latest.zip")
    assert max(_gif_steps(videos)) > killed_at and not (ckpt / "model.zip").exists()
    (videos / "notes.txt").write_text("mine\n")
    kept = {p.name: p.read_bytes() for p in videos.iterdir() if p.name == "notes.txt" or
            p.name.startswith("step_") and int(p.name[5:13]) <= killed_at}
    res = subprocess.run([sys.executable, "-m", "train", *args[:-1], "train.video_every=0", "train.resume=true"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert {p.name: p.read_bytes() for p in videos.iterdir()} == kept
    assert _steps(ckpt / "model.zip") == 3072 and "videos of the interrupted run's evaluations after it" in res.stdout
