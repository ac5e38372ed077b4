"""``python -m train agent=gap_acceptance``: a rule-based agent with its own sensors preset (turn_truth) runs on it
when ``sensors=`` is the command's default (truth), so the run's config.yaml records turn_truth, the sensors it ran
with (as results.md's summary does), not the default it never saw."""

from __future__ import annotations

import pytest
import yaml
from conftest import run

from av_gym.presets import compose_group
from conf.check import check_command_line
from train.__main__ import config_as_ran


@pytest.mark.parametrize("argv, recorded", [(["agent=gap_acceptance"], "turn_truth"),
                                            (["agent=gap_acceptance", "sensors=turn_truth"], "turn_truth"),
                                            (["agent=always_proceed"], "truth"),  # no preset of its own
                                            (["agent=ppo", "sensors=turn_truth"], "turn_truth")])  # trains on it
def test_the_recorded_sensors_are_the_ones_the_agent_runs_with(argv, recorded):
    cfg = check_command_line("train", argv)[0]
    ran = config_as_ran(cfg)
    assert ran.sensors == compose_group("sensors", recorded)
    assert {k: ran[k] for k in ran if k != "sensors"} == {k: cfg[k] for k in cfg if k != "sensors"}


@pytest.mark.slow  # a python -m train process (~5 CPU-s: torch, highway-env)
def test_a_rule_agents_run_saves_its_own_preset_in_config_yaml(tmp_path):
    res = run("train", "agent=gap_acceptance", "train.eval_episodes=0", "run_name=gap", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    saved = yaml.safe_load((tmp_path / "checkpoints" / "gap" / "config.yaml").read_text())
    assert saved["sensors"] == compose_group("sensors", "turn_truth")
    assert saved["agent"]["name"] == "gap_acceptance"
