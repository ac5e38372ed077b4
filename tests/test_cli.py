"""``python -m train`` and ``python -m eval`` end to end, as a user runs them (small budgets)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import yaml
from conftest import FAST_PPO, cli, run  # `trained` (one tiny PPO run per session) is a conftest fixture too


def test_train_writes_checkpoint_config_tensorboard_and_prints_where(trained):
    cwd, res = trained
    ckpt = cwd / "checkpoints" / "tiny"
    assert (ckpt / "model.zip").is_file() and (ckpt / "config.yaml").is_file()
    assert "name: left_turn" in (ckpt / "config.yaml").read_text()
    assert list((cwd / "runs" / "tiny" / "tb").rglob("events.out.tfevents.*"))
    assert (cwd / "runs" / "tiny" / "results.md").is_file()
    for word in ("tensorboard --logdir", "checkpoint:", "logs:"):
        assert word in res.stdout
    assert not list(ckpt.glob("*.tmp")), "no temporary files left behind"


@pytest.mark.slow  # 15-35 CPU-s (trains or runs whole evaluations): over the README test budget
def test_eval_compares_checkpoint_with_baseline_on_the_same_seeds(trained):
    cwd, _ = trained
    res = run("eval", "agents=[always_proceed,ppo]", "episodes=3", "split=train", "seed=7", "out_dir=out", "progress_bar=false",
              cwd=cwd)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = list(csv.DictReader(open(cwd / "out" / "results.csv")))
    assert [r["agent"] for r in rows] == ["always_proceed"] * 3 + ["ppo"] * 3
    assert [r["seed"] for r in rows] == ["7", "8", "9"] * 2
    assert {"collision", "success", "min_ttc_s", "time_to_exit_s"} <= set(rows[0])
    md = (cwd / "out" / "results.md").read_text()
    assert "| always_proceed | 3 |" in md and "| ppo | 3 |" in md


@pytest.mark.slow  # python -m eval as a process, a lap with its figures: ~7.5 s alone at load 2.4
def test_eval_lane_keeping_pid(tmp_path):
    """pid_paper declares sensors=truth (the paper's simulator CTE) and laps on it; another sensors= is refused,
    as it would not reach it (tests/test_rule_agent_sensors.py)."""
    res = run("eval", "env=lane_keeping", "agents=[pid_paper]", "episodes=2", "out_dir=out",
              "progress_bar=false", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = list(csv.DictReader(open(tmp_path / "out" / "results.csv")))
    assert [float(r["lap_completed"]) for r in rows] == [1.0, 1.0]
    assert all(0 < float(r["cte_mean_abs_m"]) < 1.0 for r in rows)


@pytest.mark.slow  # 15-35 CPU-s (trains or runs whole evaluations): over the README test budget
def test_train_ppo_on_lane_keeping_override(tmp_path):
    res = run("train", "env=lane_keeping", "agent=ppo", *FAST_PPO, "seed=4", "run_name=lk", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert (tmp_path / "checkpoints" / "lk" / "model.zip").is_file()
    assert "pid_paper" in res.stdout  # compared with the lane-keeping baseline


@pytest.mark.slow  # every sensor, cameras and LiDAR included, renders at every step
def test_train_ppo_on_the_full_sensor_preset(tmp_path):
    """Nested camera observations are flattened for SB3; the checkpoint then evaluates on the same preset."""
    # every sensor renders at every step: one rollout (64 steps) and one evaluation episode say what is tested
    res = run("train", "agent=ppo", "sensors=full", *FAST_PPO, "agent.total_timesteps=64", "train.eval_n=0",
              "train.eval_episodes=1", "run_name=full", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "| ppo | 1 |" in res.stdout and "[train] 64 env steps" in res.stdout


@pytest.mark.slow  # a CNN on camera images, cloned then trained, exported, reloaded twice
def test_train_the_camera_lane_keeper_with_a_narrow_cnn(tmp_path):
    """agent=ppo_lane_camera composes (centre camera only, cloned PID start) and agent.cnn_output_dim reaches SB3."""
    from stable_baselines3 import PPO

    res = run("train", "env=lane_keeping", "agent=ppo_lane_camera", *FAST_PPO, "agent.init_episodes=1",
              "agent.init_epochs=1", "agent.cnn_output_dim=16", "run_name=cam", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "cloned pid_tuned from 1 episodes" in res.stdout
    model = PPO.load(tmp_path / "checkpoints" / "cam" / "model.zip", device="cpu")
    assert list(model.observation_space.spaces) == ["cameras_centre"]
    assert model.policy.features_extractor.features_dim == 16

    # exported as a reference checkpoint: smaller (no optimizer state), the same actions
    res = run("train.export", "checkpoints/cam", "ref", "--command", "python -m train run_name=cam", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert (tmp_path / "ref" / "COMMAND").read_text() == "python -m train run_name=cam\n"
    run_dir, ref_dir = tmp_path / "checkpoints" / "cam", tmp_path / "ref"
    ref = PPO.load(ref_dir / "model.zip", device="cpu")
    assert (ref_dir / "model.zip").stat().st_size < 0.6 * (run_dir / "model.zip").stat().st_size
    obs = {k: s.sample() for k, s in model.observation_space.spaces.items()}
    np.testing.assert_array_equal(ref.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    assert (ref_dir / "config.yaml").read_text() == (run_dir / "config.yaml").read_text()
    res = run("train.export", "checkpoints/nothing_here", "ref", cwd=tmp_path)
    assert res.returncode == 2 and "checkpoints/nothing_here/model.zip does not exist" in res.stderr


@pytest.mark.parametrize("module, overrides, needle", [
    ("train", ["env.mode=rush_hour"], "env.mode must be one of ['traffic', 'ccftap']"),
    ("train", ["env=lane_keeping", "agent=always_proceed"], "drives scenarios ['left_turn']"),
    ("train", ["agent.n_envs=0"], "agent.n_envs must be an integer in [1, 4096], got 0"),
    # Hydra's own errors (unknown key, unknown option), caught before Hydra reports them over several lines
    ("train", ["agent.epoch=3"], "agent.epoch is not a field of agent=ppo_turn; allowed: ['action_repeat', 'actions',"),
    ("train", ["env.mod=ccftap"], "env.mod is not a field of env=left_turn; allowed: ['acceleration_range', "),
    ("train", ["env.mod=ccftap"], "'target_speeds_kmh']; did you mean 'mode'?"),  # the closest key, last
    ("eval", ["sensors=turn_perceived", "sensors.detector.mis_rate=0.2"], "; did you mean 'miss_rate'?"),
    ("train", ["env=foo"], "env=foo: env must be one of ['lane_keeping', 'left_turn']"),
    ("train", ["+foo=1"], "foo is not a train setting; allowed: ['agent', 'env',"),
    ("train", ["seed=0,1"], "add -m to sweep over them"),
    ("train", ["env.duration=abc"], "env.duration must be a number in (0, 600], got 'abc'"),
    ("train", ["env.spawn_probability=1.5"], "env.spawn_probability must be a number in [0, 1], got 1.5"),
    ("train", ["-m", "agent=always_proceed", "sensors=gnss_imu", "sensors.gnss.sigma=0.5,-1"],
     "sensors.gnss.sigma must be a number >= 0"),
    ("eval", ["agents=[no_such_agent]"], "agent 'no_such_agent' is not in conf/agent/"),
    ("eval", ["agents=[always_proceed+no_such_shield]"], "shield 'no_such_shield' is not in conf/shield/"),
    ("eval", ["sensors=gnss_imu", "env.name=left_turn", "agents=[always_proceed]", "sensors.gnss.sigma=-2"],
     "sensors.gnss.sigma must be a number >= 0, got -2"),
    ("eval", ["agents=[missing/model.zip]"], "'missing/model.zip': no such file or folder"),
    ("eval", ["env=lane_keeping", "agents=[ppo]", "paths.checkpoints=nowhere"], "no ppo checkpoint"),
    ("eval", ["n_envs=0"], "n_envs must be an integer in [1, 1024], got 0"),
    ("eval", ["shield=aeb", "+shield.detector.sigma_vel=-1"], "shield.detector.sigma_vel must be a number >= 0"),
])
def test_bad_input_gives_one_line_and_exit_code_2(tmp_path, module, overrides, needle):
    # the command-line check in this process (conftest.cli); test_bad_input_in_a_new_process runs two as a user does
    quiet = "progress_bar=false" if module == "eval" else "train.progress_bar=false"
    refused_in_one_line(cli(module, *overrides, quiet, cwd=tmp_path), needle, tmp_path)


@pytest.mark.parametrize("module, overrides, needle", [
    ("eval", ["n_envs=0"], "n_envs must be an integer in [1, 1024], got 0"),
    # a second interpreter (~5 s) says nothing the eval case does not: slow
    pytest.param("train", ["env.mode=rush_hour"], "env.mode must be one of ['traffic', 'ccftap']",
                 marks=pytest.mark.slow),
])
def test_bad_input_in_a_new_process(tmp_path, module, overrides, needle):
    quiet = "progress_bar=false" if module == "eval" else "train.progress_bar=false"
    refused_in_one_line(run(module, *overrides, quiet, cwd=tmp_path), needle, tmp_path)


def refused_in_one_line(res, needle: str, tmp_path) -> None:
    """Exit status 2, one line on stderr holding ``needle``, no traceback, nothing written in ``tmp_path``."""
    assert res.returncode == 2, res.stderr[-2000:]
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert not any(tmp_path.iterdir()), f"nothing written, found {sorted(tmp_path.rglob('*'))}"


@pytest.mark.slow  # 15-35 CPU-s (trains or runs whole evaluations): over the README test budget
def test_checkpoint_that_does_not_fit_the_env_is_refused_and_its_run_folder_removed(trained, tmp_path):
    """Found only once the job runs (the model must be loaded): Hydra's run folder is removed again."""
    cwd, _ = trained
    other = tmp_path / "other"
    other.mkdir()
    (other / "model.zip").write_bytes((cwd / "checkpoints" / "tiny" / "model.zip").read_bytes())
    config = yaml.safe_load((cwd / "checkpoints" / "tiny" / "config.yaml").read_text())
    config["sensors"] = {"name": "gnss_imu", "gnss": {}, "imu": {}}  # another preset than it was trained on
    (other / "config.yaml").write_text(yaml.safe_dump(config))
    res = run("eval", f"agents=[{other}]", "episodes=1", "progress_bar=false", cwd=tmp_path)
    assert res.returncode == 2, res.stderr[-2000:]
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "expects observations {intent:" in lines[0], res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other"]

    res = run("eval", f"agents=[{cwd / 'checkpoints' / 'tiny'}]", "env.action=continuous", "episodes=1",
              "progress_bar=false", cwd=tmp_path)
    assert res.returncode == 2 and "acts in Discrete(3)" in res.stderr, res.stderr[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other"]
