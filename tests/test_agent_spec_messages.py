"""Two refusals of an agent spec said the wrong thing (prober R4, item 10): a file that is no checkpoint listed the
model file names with model.zip twice (PPO and DAgger share it), and ``ppo_turn+aeb@turn_perceived`` (the preset
after the shield) was refused as a shield named ``aeb@turn_perceived``. Each now names what works."""

from __future__ import annotations

import pytest

from av_gym.errors import ConfigError
from eval.agents import plan_agent
from tests.test_bad_input import check_line

NONE = {"name": "none"}


def test_a_file_that_is_no_checkpoint_lists_each_model_file_once(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yaml").write_text("env: {name: left_turn}\n")
    line = check_line("eval", ["agents=[run/config.yaml]", "episodes=1"], monkeypatch, capsys)
    assert line == "error: checkpoint 'run/config.yaml': unknown file type; expected a checkpoint folder or one of " \
                   "['model.zip', 'model.pt']", line


def test_a_preset_after_the_shield_is_told_its_place(tmp_path, monkeypatch, capsys):
    with pytest.raises(ConfigError, match=r"^agent 'ppo_turn\+aeb@turn_perceived': @preset goes before \+shield: "
                                          r"ppo_turn@turn_perceived\+aeb$"):
        plan_agent("ppo_turn+aeb@turn_perceived", "left_turn", {"name": "truth"}, NONE, "checkpoints")
    monkeypatch.chdir(tmp_path)
    line = check_line("eval", ["agents=[ppo_turn+aeb@turn_perceived]", "episodes=1"], monkeypatch, capsys)
    assert line == "error: agent 'ppo_turn+aeb@turn_perceived': @preset goes before +shield: " \
                   "ppo_turn@turn_perceived+aeb", line
