"""Bad input found by trying to break the commands: damaged checkpoints, folders that cannot be written,
names too long, settings whose relation is wrong, a run of 10^12 episodes, a learning rate that makes training
diverge. Each gives one line naming the field and exit status 2, with nothing written and nothing measured lost.

Most cases run the command-line check in this process (what ``python -m train|eval`` runs before Hydra makes any
folder); a few run the whole command, for what only the job can find."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from av_gym.errors import run_cli

REFERENCE = resources.files("conf").parent / "checkpoints" / "reference" / "ppo_turn"


def check_line(module: str, argv: list[str], monkeypatch, capsys) -> str:
    """``python -m <module> <argv>``'s command-line check, in this process: its one line (exit status 2 asserted)."""
    import importlib

    main = importlib.import_module(f"{module}.__main__")
    monkeypatch.setattr(sys, "argv", [module, *argv])
    with pytest.raises(SystemExit) as exit_:
        run_cli(main._check_command_line)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert exit_.value.code == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def damaged(folder: Path, how: str) -> Path:
    """A copy of the reference ppo_turn checkpoint folder with its model.zip or config.yaml damaged."""
    folder.mkdir()
    shutil.copy(REFERENCE / "config.yaml", folder / "config.yaml")
    data = (REFERENCE / "model.zip").read_bytes()
    if how == "garbage":
        data = np.random.default_rng(0).bytes(3000)
    elif how == "truncated":
        data = data[: len(data) // 2]
    elif how == "empty":
        data = b""
    elif how == "flipped":  # the zip's directory intact, a member's bytes not: only its CRC tells
        data = bytearray(data)
        for i in range(len(data) // 3, len(data) // 3 + 64):
            data[i] ^= 0xFF
        data = bytes(data)
    elif how == "yaml":
        (folder / "config.yaml").write_text("agent: [unclosed\n  x: {")
    (folder / "model.zip").write_bytes(data)
    return folder


@pytest.mark.parametrize("how, needle", [
    ("garbage", "is not a readable zip (truncated or corrupt"),
    ("truncated", "is not a readable zip (truncated or corrupt"),
    ("empty", "is empty (0 bytes)"),
    ("flipped", "fails its CRC check"),
    ("yaml", "config.yaml' is not valid YAML (expected ',' or ']', but got ':' at line 2, column 4)"),
])
def test_a_damaged_checkpoint_is_one_line(tmp_path, monkeypatch, capsys, how, needle):
    folder = damaged(tmp_path / how, how)
    monkeypatch.chdir(tmp_path)
    line = check_line("eval", [f"agents=[{folder}]", "episodes=1"], monkeypatch, capsys)
    assert needle in line and str(folder) in line
    assert sorted(p.name for p in tmp_path.iterdir()) == [how], "nothing written"


def test_a_damaged_checkpoint_is_refused_by_the_loaders_too(tmp_path):
    """From Python (and at job time, should the file change after the check): the same one line, not SB3's."""
    from av_gym.errors import ConfigError
    from agents.checkpoint import load_sb3

    for how in ("truncated", "flipped"):
        with pytest.raises(ConfigError, match="truncated or corrupt|CRC"):
            load_sb3(damaged(tmp_path / how, how) / "model.zip")


def test_a_damaged_checkpoint_end_to_end(tmp_path):
    """The whole command: one line, exit 2, no run folder left (its command-line check in this process, as
    conftest.cli runs it: a refusal there is the command's; what passes runs as a process)."""
    from conftest import cli

    folder = damaged(tmp_path / "empty", "empty")
    res = cli("eval", f"agents=[{folder}]", "episodes=1", "progress_bar=false", cwd=tmp_path)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2 and len(lines) == 1 and "is empty (0 bytes)" in lines[0], res.stderr[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]


@pytest.mark.parametrize("module, argv, needle", [
    ("eval", ["out_dir=/proc/x"], "out_dir=/proc/x: nothing can be created in '/proc'"),
    ("eval", ["out_dir=a_file"], "out_dir=a_file: 'a_file' is a file, not a folder"),
    ("eval", ["out_dir=a_file/results"], "'a_file' (part of 'a_file/results') is a file, not a folder"),
    ("eval", ["out_dir=" + "x" * 300], "out_dir: the folder name 'xxxx"),
    ("train", ["run_name=" + "r" * 300], "run_name must be at most 240 characters (a folder name), got 300"),
    ("train", ["hydra.run.dir=/proc/x"], "hydra.run.dir=/proc/x: nothing can be created in '/proc'"),
    ("eval", ["hydra.run.dir=/proc/x"], "hydra.run.dir=/proc/x: nothing can be created in '/proc'"),
    ("train", ["-m", "hydra.sweep.dir=/proc/y", "seed=1,2"], "hydra.sweep.dir=/proc/y: nothing can be created"),
    ("train", ["paths.runs=a_file"], "hydra.run.dir=a_file/"),  # the run folder is paths.runs/run_name
    ("train", ["paths.checkpoints=a_file"], "paths.checkpoints=a_file/"),
    ("train", ["paths.checkpoints=/proc/z"], "paths.checkpoints=/proc/z/"),
])
def test_a_folder_that_cannot_be_written_is_refused_before_anything_runs(tmp_path, monkeypatch, capsys, module,
                                                                         argv, needle):
    if not Path("/proc").is_dir() and "/proc" in " ".join(argv):
        pytest.skip("no /proc here")
    (tmp_path / "a_file").write_text("not a folder")
    monkeypatch.chdir(tmp_path)
    line = check_line(module, [*argv, "agents=[always_proceed]"] if module == "eval" else argv, monkeypatch, capsys)
    assert needle in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"], "nothing written, not even a probe"


@pytest.mark.parametrize("argv, needle", [
    (["env.action=continuous", "env.acceleration_range=[0,0]", "agents=[always_proceed]"],
     "env.acceleration_range must be [min, max] with min < max (m/s²), got [0, 0]"),
    (["env.acceleration_range=[3,-8]", "agents=[always_proceed]"], "env.acceleration_range must be [min, max]"),
    (["env=lane_keeping", "env.lane_width=1e-9", "agents=[pid_paper]"],
     "env.lane_width must be wider than the ego vehicle's width, 2.0 m, got 1e-09"),
    (["env.simulation_frequency=15", "agents=[always_proceed]"],
     "env.simulation_frequency (15) must be a multiple of env.policy_frequency (10)"),
])
def test_settings_whose_relation_is_wrong_are_one_line(tmp_path, monkeypatch, capsys, argv, needle):
    monkeypatch.chdir(tmp_path)
    assert needle in check_line("eval", argv, monkeypatch, capsys)
    assert not any(tmp_path.iterdir())


def test_the_envs_check_the_same_relations_from_python(turn_cfg, lane_cfg):
    from av_gym.errors import ConfigError
    from av_gym.make import make_env

    with pytest.raises(ConfigError, match=r"env.acceleration_range must be \[min, max\] with min < max"):
        make_env({**turn_cfg, "action": "continuous", "acceleration_range": [0.0, 0.0]})
    with pytest.raises(ConfigError, match=r"env.lane_width must be wider than the ego vehicle.s width, 2.0 m"):
        make_env({**lane_cfg, "lane_width": 1e-9})


def test_seeds_are_drawn_lazily_and_rows_handed_back_as_episodes_end(turn_cfg):
    """episodes=10**12 must not list 10^12 seeds before the first episode; what ran is kept when it stops."""
    from agents import AlwaysProceed
    from av_gym.make import make_env
    from eval.runner import run_episodes

    def seeds():
        yield from (5, 6)
        raise KeyboardInterrupt  # the user gives up on episode 3 of 10^12

    env = make_env(turn_cfg)
    rows: list[dict] = []
    with pytest.raises(KeyboardInterrupt):
        run_episodes(env, AlwaysProceed(env.unwrapped.cruise_action()), seeds(), "ap", progress=False, out=rows)
    assert [r["seed"] for r in rows] == [5, 6] and all("collision" in r for r in rows)


@pytest.mark.slow  # 7-11 CPU-s on a clean clone: kept out of the README's 5-minute test command
def test_an_interrupted_evaluation_of_a_whole_split_keeps_what_it_measured(tmp_path):
    """No MemoryError: a million episodes (the whole validation split, the most a split holds) run; Ctrl-C after a
    few writes them (and says where) and exits 130."""
    proc = subprocess.Popen([sys.executable, "-m", "eval", "agents=[always_proceed,gap_acceptance]",
                             "episodes=1000000", "out_dir=out"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    err = bytearray()  # the progress bar (stderr) says how many episodes ended
    reader = threading.Thread(target=lambda: [err.extend(c) for c in iter(lambda: os.read(proc.stderr.fileno(),
                                                                                         4096), b"")], daemon=True)
    reader.start()
    deadline = time.time() + 240
    while not re.search(rb"\| *[2-9]/1000000", bytes(err)) and time.time() < deadline:
        assert proc.poll() is None, bytes(err)[-2000:]
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=120)
    reader.join(5)
    assert proc.returncode == 130, bytes(err)[-2000:]
    assert b"MemoryError" not in err and b"[eval] interrupted: the" in err
    rows = (tmp_path / "out" / "results.csv").read_text().splitlines()[1:]
    assert len(rows) >= 2 and all(r.startswith("always_proceed,") for r in rows)
    assert "(interrupted after" in (tmp_path / "out" / "results.md").read_text()


@pytest.mark.slow  # 15-35 CPU-s (trains or runs whole evaluations): over the README test budget
def test_a_learning_rate_that_makes_training_diverge_is_one_line_naming_it(tmp_path):
    res = subprocess.run([sys.executable, "-m", "train", "agent=ppo", "agent.learning_rate=1e308",
                          "agent.total_timesteps=256", "agent.n_steps=64", "agent.batch_size=32", "agent.n_epochs=1",
                          "agent.n_envs=1", "train.eval_episodes=0", "train.eval_n=0", "train.progress_bar=false",
                          "run_name=diverged"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-3000:]
    assert lines[0].startswith("error: training diverged at 64 steps: ") and "NaN/inf" in lines[0]
    assert "likely cause: agent.learning_rate=1e+308 is far above" in lines[0]
    assert not (tmp_path / "checkpoints" / "diverged" / "model.zip").exists(), "no model.zip from NaN parameters"


def test_a_diverged_update_never_overwrites_the_last_good_checkpoint(tmp_path):
    """The guard comes before the checkpoint callback: the latest.zip written before the divergence stays, finite."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import PPO

    from av_gym.errors import TrainingDiverged
    from train.callbacks import AtomicCheckpointCallback, FiniteGuard, nonfinite_parameter

    class Poison(AtomicCheckpointCallback.__mro__[1]):  # BaseCallback: NaN in a weight after the second update
        def _on_rollout_start(self) -> None:
            if self.num_timesteps >= 64:
                with torch.no_grad():
                    next(self.model.policy.parameters())[0] = float("nan")

        def _on_step(self) -> bool:
            return True

    model = PPO("MlpPolicy", gym.make("CartPole-v1"), n_steps=32, batch_size=32, n_epochs=1, seed=0, device="cpu")
    latest = tmp_path / "latest.zip"
    guard = FiniteGuard(3e-4, latest)
    with pytest.raises(TrainingDiverged, match=r"training diverged at 64 steps: parameter .* has NaN/inf values .* "
                                               r"steps too large .* the last good checkpoint, .*latest.zip, is kept"):
        model.learn(256, callback=[Poison(), guard, AtomicCheckpointCallback(tmp_path, 32)])
    saved = PPO.load(latest, device="cpu")
    assert saved.num_timesteps == 32 and nonfinite_parameter(saved.policy) is None
