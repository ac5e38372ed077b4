"""A rule-based agent with a sensors preset of its own (``gap_acceptance``, ``lookahead``: turn_truth), listed
without ``@`` while ``sensors=`` is eval's default, runs on its preset as shipped: the command line's ``sensors.*``
overrides would not reach it (results.md said ``turn_truth (as shipped)``), so eval refuses them in one line with
what does (``agent@preset``, which gets them since 83c38ce). Train's brief evaluation of its baselines plans them as
before (``plan_agent`` itself does not refuse). Train refuses the same at its command line (one rule, worded once:
conf.check.own_sensors_problem), pointing at what train accepts: ``sensors=<its own preset>`` with the overrides,
which its config.yaml records and its brief evaluation runs on."""

from __future__ import annotations

import pytest

from av_gym.presets import compose_group
from eval.__main__ import given_sensors_problem
from eval.agents import plan_agent, sensors_summary
from tests.test_bad_input import check_line

NONE = {"name": "none"}


def _truth_with_miss_rate() -> dict:
    """eval's default preset with ``+sensors.turn_signals.miss_rate=0.5`` on the command line."""
    sensors = compose_group("sensors", "truth")
    sensors["turn_signals"] = {"miss_rate": 0.5}
    return sensors


@pytest.mark.parametrize("argv, says", [
    (["agents=[gap_acceptance]"],
     "error: sensors.turn_signals.miss_rate=0.5: agent 'gap_acceptance' runs on its own sensors preset (turn_truth) "
     "as shipped, so these overrides would not reach it; give them to it with agents=[gap_acceptance@turn_truth] "
     "sensors=turn_truth sensors.turn_signals.miss_rate=0.5, or leave them out"),
    (["agents=[lookahead+aeb]", "vec_env=batched"],
     "agent 'lookahead+aeb' runs on its own sensors preset (turn_truth) as shipped, so these overrides would not "
     "reach it; give them to it with agents=[lookahead@turn_truth+aeb] sensors=turn_truth"),
])
def test_eval_refuses_overrides_its_own_preset_would_drop(tmp_path, monkeypatch, capsys, argv, says):
    monkeypatch.chdir(tmp_path)
    line = check_line("eval", [*argv, "+sensors.turn_signals.miss_rate=0.5", "episodes=1"], monkeypatch, capsys)
    assert says in line, line
    assert not any(tmp_path.iterdir())


def test_the_advised_agent_at_preset_gets_the_override():
    sensors = compose_group("sensors", "turn_truth")
    sensors["turn_signals"]["miss_rate"] = 0.5
    plan = plan_agent("gap_acceptance@turn_truth", "left_turn", sensors, NONE, "checkpoints")
    assert given_sensors_problem(plan, sensors) is None
    assert sensors_summary(plan.sensors) == "turn_truth with turn_signals.miss_rate=0.5"


def test_plan_agent_itself_still_plans_it_as_shipped():
    """What train's brief evaluation calls for its baselines: no refusal there, the agent's own preset."""
    sensors = _truth_with_miss_rate()
    plan = plan_agent("gap_acceptance", "left_turn", sensors, NONE, "checkpoints")
    assert sensors_summary(plan.sensors) == "turn_truth (as shipped)"
    assert given_sensors_problem(plan, sensors).startswith("sensors.turn_signals.miss_rate=0.5: ")
    plain = plan_agent("always_proceed", "left_turn", sensors, NONE, "checkpoints")  # no preset of its own: gets it
    assert given_sensors_problem(plain, sensors) is None


def test_train_refuses_them_too_with_what_train_accepts(tmp_path, monkeypatch, capsys):
    """``python -m train agent=gap_acceptance +sensors.turn_signals.miss_rate=0.5`` ran on turn_truth as shipped;
    now refused at the command line with eval's rule, and train's own remedy (train has no ``agent@preset``)."""
    monkeypatch.chdir(tmp_path)
    line = check_line("train", ["agent=gap_acceptance", "+sensors.turn_signals.miss_rate=0.5"], monkeypatch, capsys)
    assert line == (
        "error: sensors.turn_signals.miss_rate=0.5: agent 'gap_acceptance' runs on its own sensors preset "
        "(turn_truth) as shipped, so these overrides would not reach it; give them to it with sensors=turn_truth "
        "sensors.turn_signals.miss_rate=0.5, or leave them out"
    ), line
    assert not any(tmp_path.iterdir())


def test_the_advised_train_command_runs_the_agent_with_the_overrides(monkeypatch):
    """What the refusal advises, ``agent=gap_acceptance sensors=turn_truth sensors.turn_signals.miss_rate=0.5``:
    not refused, config.yaml records the override, and the brief evaluation builds the agent's env with it (and
    results.md's summary says so)."""
    from conf.check import check_command_line
    from conf.commands import TrainCommand
    from train import __main__ as train_main

    (cfg,) = check_command_line("train", ["agent=gap_acceptance", "sensors=turn_truth",
                                          "sensors.turn_signals.miss_rate=0.5", "train.eval_episodes=1"])
    assert train_main.config_as_ran(cfg).sensors.turn_signals.miss_rate == 0.5
    built = []

    class Built(Exception):
        pass

    def make_env(env_cfg, sensors, shield, **kwargs):
        built.append(sensors)
        raise Built

    monkeypatch.setattr("av_gym.make.make_env", make_env)
    folders = train_main.Folders(run_dir=None, ckpt_dir=None)
    ran_with: dict = {}
    with pytest.raises(Built):
        train_main._evaluate_spec(cfg, TrainCommand.of(cfg), folders, "gap_acceptance", range(1), [], ran_with, {})
    assert built[0]["turn_signals"]["miss_rate"] == 0.5 and built[0]["name"] == "turn_truth"
    assert sensors_summary(ran_with["gap_acceptance(turn_signals.miss_rate=0.5)"]) == \
        "turn_truth with turn_signals.miss_rate=0.5"


def test_train_still_takes_a_trained_agents_overrides_and_a_plain_rule_agent():
    """A trained kind trains on what it is given (overrides included); a rule-based agent on the default preset
    with no overrides, or on its own preset with them, is not refused."""
    from conf.check import _own_preset_problems, check_command_line, default_sensors

    (cfg,) = check_command_line("train", ["agent=ppo", "sensors=gnss_imu", "sensors.gnss.sigma=7.5"])
    assert cfg["sensors"]["gnss"]["sigma"] == 7.5
    default = default_sensors("train")
    gnss = compose_group("sensors", "gnss_imu")
    gnss["gnss"]["sigma"] = 7.5
    assert _own_preset_problems({"name": "ppo", "kind": "ppo", "sensors": "gnss_imu"}, gnss, default) == []
    gap = {"name": "gap_acceptance", "kind": "gap_acceptance", "sensors": "turn_truth"}
    assert _own_preset_problems(gap, compose_group("sensors", default), default) == []
    own = compose_group("sensors", "turn_truth")
    own["turn_signals"]["miss_rate"] = 0.5
    assert _own_preset_problems(gap, own, default) == []
    assert _own_preset_problems(gap, _truth_with_miss_rate(), default) != []
