"""A rule-based agent that names its own sensors preset (``gap_acceptance``, ``lookahead``: turn_truth) runs on it:
a ``sensors=<other>`` on the command line would not reach it, so eval (per env and on the batch) and train refuse
it in one line with what each accepts (eval: ``agent@preset``; train, which has no ``@`` form: ``sensors=<its
own>``), as they do for a trained agent; the command's default preset is no choice (one rule:
conf.check.own_sensors_problem). Its ``@preset`` gets the command line's ``sensors.*`` overrides as a trained
agent's sensors do, and results.md's summary says so (prober R, W1 and W2)."""

from __future__ import annotations

import pytest

from av_gym.errors import ConfigError
from av_gym.presets import compose_group
from conf.check import _own_preset_problems, default_sensors
from eval.__main__ import given_sensors_problem
from eval.agents import plan_agent, sensors_summary
from tests.test_bad_input import check_line

NONE = {"name": "none"}


def _plan(spec: str, sensors: dict):
    return plan_agent(spec, "left_turn", sensors, NONE, "checkpoints")


@pytest.mark.parametrize("argv, says", [
    (["agents=[gap_acceptance]", "sensors=turn_perceived"],
     "sensors=turn_perceived: agent 'gap_acceptance' runs on its own sensors preset (turn_truth), so "
     "sensors=turn_perceived would not reach it; drive it from turn_perceived with "
     "agents=[gap_acceptance@turn_perceived], or leave sensors= out"),
    (["agents=[always_proceed,lookahead+aeb]", "sensors=turn_perceived", "vec_env=batched"],
     "agent 'lookahead+aeb' runs on its own sensors preset (turn_truth), so sensors=turn_perceived would not reach "
     "it; drive it from turn_perceived with agents=[lookahead@turn_perceived+aeb]"),
    (["env=lane_keeping", "agents=[pid_paper]", "sensors=gnss_imu"],  # its own is the default preset, truth
     "agent 'pid_paper' runs on its own sensors preset (truth), so sensors=gnss_imu would not reach it"),
])
def test_eval_refuses_a_preset_a_rule_agent_would_not_run_on(tmp_path, monkeypatch, capsys, argv, says):
    monkeypatch.chdir(tmp_path)
    line = check_line("eval", [*argv, "episodes=1"], monkeypatch, capsys)
    assert says in line, line
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("spec, given", [("gap_acceptance", "turn_truth"), ("gap_acceptance", "truth"),
                                         ("gap_acceptance@turn_perceived", "turn_perceived"),
                                         ("gap_acceptance@turn_perceived", "cameras"), ("always_proceed", "cameras")])
def test_eval_runs_its_own_preset_the_default_and_agent_at_preset(spec, given):
    sensors = compose_group("sensors", given)
    assert given_sensors_problem(_plan(spec, sensors), sensors) is None


def test_train_refuses_it_too_and_accepts_the_default(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    line = check_line("train", ["agent=gap_acceptance", "sensors=turn_perceived"], monkeypatch, capsys)
    assert line == ("error: sensors=turn_perceived: agent 'gap_acceptance' runs on its own sensors preset "
                    "(turn_truth), so sensors=turn_perceived would not reach it; train runs it on turn_truth: leave "
                    "sensors= out, or give sensors=turn_truth (its sensors.* overrides reach it)"), line
    assert "@" not in line  # eval's agents=[x@preset]: train has no such form
    assert not any(tmp_path.iterdir())
    agent = {"name": "gap_acceptance", "kind": "gap_acceptance", "sensors": "turn_truth"}
    default = default_sensors("train")
    assert default == "truth" == default_sensors("eval")
    for name in (default, "turn_truth"):
        assert _own_preset_problems(agent, {"name": name}, default) == []
    assert _own_preset_problems({"name": "ppo_turn", "kind": "ppo", "sensors": "turn_truth"}, {"name": "cameras"},
                                default) == []  # a trained kind trains on what it is given


def test_an_agent_at_preset_gets_the_command_lines_overrides():
    sensors = compose_group("sensors", "turn_perceived")
    sensors["detector"]["miss_rate"] = 0.5
    plan = _plan("gap_acceptance@turn_perceived", sensors)
    assert plan.sensors["detector"]["miss_rate"] == 0.5
    assert sensors_summary(plan.sensors) == "turn_perceived with detector.miss_rate=0.5"
    night = compose_group("sensors", "cameras")
    night["cameras"]["night"] = True
    with pytest.raises(ConfigError, match=r"^sensors\.cameras\.night=True: agent 'gap_acceptance@turn_perceived' runs "
                                        r"on the sensors @turn_perceived gives .*which have no 'cameras'"):
        _plan("gap_acceptance@turn_perceived", night)
