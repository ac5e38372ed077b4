"""Command-line ``sensors.*`` overrides reach trained agents: the checkpoint's sensors are the base, the
overrides go on top, those that would change the observation space are refused, and results.md says what each
agent ran with."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from av_gym.errors import ConfigError
from av_gym.make import make_env
from av_gym.sensors.camera import Cameras
from eval.agents import check_sensor_overrides, compose_group, plan_agent

ROOT = Path(__file__).resolve().parents[1]
PILOTNET = ROOT / "checkpoints" / "reference" / "pilotnet"
NO_SHIELD = {"name": "none", "kind": "none"}


def cameras_with(**fields) -> dict:
    sensors = compose_group("sensors", "cameras")
    sensors["cameras"].update(fields)
    return sensors


def camera_wrapper(env) -> Cameras:
    while not isinstance(env, Cameras):
        env = env.env
    return env


def test_night_on_the_command_line_reaches_a_trained_agents_env():
    saved = yaml.safe_load((PILOTNET / "config.yaml").read_text())
    assert saved["sensors"]["cameras"]["night"] is False  # trained by day
    for spec in (str(PILOTNET), "pilotnet"):  # a path, and the named agent (its reference folder)
        plan = plan_agent(spec, "lane_keeping", cameras_with(night=True, fog_visibility=80.0), NO_SHIELD,
                          ROOT / "checkpoints")
        assert plan.sensor_overrides == {"cameras.night": True, "cameras.fog_visibility": 80.0}
        assert plan.trained_sensors["cameras"]["night"] is False
        check_sensor_overrides(plan, saved["env"])  # same observation space: accepted
        env = make_env(saved["env"], plan.sensors, None)
        weather = camera_wrapper(env).weather
        assert weather.night and weather.fog_visibility == 80.0
        # the rest is the checkpoint's own settings, not the shipped preset's
        assert plan.sensors["cameras"]["noise"] == saved["sensors"]["cameras"]["noise"]
        env.close()


def test_no_override_runs_the_checkpoints_own_sensors():
    plan = plan_agent(str(PILOTNET), "lane_keeping", compose_group("sensors", "truth"), NO_SHIELD, "checkpoints")
    assert plan.sensor_overrides == {}
    assert plan.sensors == yaml.safe_load((PILOTNET / "config.yaml").read_text())["sensors"]


def test_overrides_that_change_the_observation_space_are_refused():
    env_cfg = yaml.safe_load((PILOTNET / "config.yaml").read_text())["env"]
    plan = plan_agent(str(PILOTNET), "lane_keeping", cameras_with(width=100, night=True), NO_SHIELD, "checkpoints")
    with pytest.raises(ConfigError, match=r"^sensors\.cameras\.width=100 changes the observation space"):
        check_sensor_overrides(plan, env_cfg)
    sensors = compose_group("sensors", "full")
    sensors["gnss"]["sigma"] = 3.0  # PilotNet's stack has no GNSS: adding one would add an observation key
    with pytest.raises(ConfigError, match=r"sensors\.gnss\.sigma=3\.0: .* no 'gnss'"):
        plan_agent(str(PILOTNET), "lane_keeping", sensors, NO_SHIELD, "checkpoints")


def run_eval(*overrides: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "eval", "env=lane_keeping", f"agents=[{PILOTNET}]",
                           "sensors=cameras", "progress_bar=false", "plots=false", *overrides], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def test_cli_refuses_a_space_changing_override_in_one_line(tmp_path):
    from conftest import cli  # the command-line check in this process; a real process only if it passes

    res = cli("eval", "env=lane_keeping", f"agents=[{PILOTNET}]", "sensors=cameras", "progress_bar=false",
              "plots=false", "sensors.cameras.height=80", cwd=tmp_path)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    assert lines[0].startswith("error: sensors.cameras.height=80 changes the observation space"), lines[0]
    assert not any(tmp_path.iterdir())


@pytest.mark.slow  # 7-15 CPU-s: keeps the README's fast command under 5 min on 2 cores
def test_results_md_states_the_sensors_each_agent_ran_with(tmp_path):
    res = run_eval("sensors.cameras.night=true", "episodes=1", "env.time_limit=5", f"out_dir={tmp_path}/out",
                   cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    text = (tmp_path / "out" / "results.md").read_text()
    assert "## Sensors each agent ran with" in text
    assert f"- `{PILOTNET}(cameras.night=True)`: cameras with cameras.night=True" in text  # label: eval/labels.py
    full = yaml.safe_load(text.split("```yaml\n")[1].split("```")[0])
    assert full["cameras"]["night"] is True
    # which policy the row measured: the checkpoint is named beside the sensors
    assert "## Checkpoint each trained agent ran" in text
    assert str(PILOTNET) in text.split("## Checkpoint each trained agent ran")[1].split("##")[0]
