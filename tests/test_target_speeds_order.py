"""``env.target_speeds_kmh`` is the SLOWER / IDLE / FASTER ladder highway-env steps along by index: out of order,
FASTER slows the ego down. It must be strictly increasing; every way in (the command line, ``gym.make``'s SI
``config``, ``gymnasium.make_vec``) refuses it in one line naming the field. Its units are not guessed: ``[0, 4.5, 9]``
(km/h) is increasing and stays accepted."""

from __future__ import annotations

import gymnasium as gym
import pytest

import av_gym  # noqa: F401  (registers the ids)
from av_gym.envs.left_turn import LeftTurnParams
from av_gym.errors import ConfigError
from av_gym.params import check
from tests.test_bad_input import check_line

TURN = "av_gym/UnprotectedLeftTurn-v0"
RULE = "target_speeds_kmh must be strictly increasing [SLOWER, IDLE, FASTER] set-points (km/h)"


@pytest.mark.parametrize("speeds, shown", [("[9,4.5,0]", "[9, 4.5, 0]"), ("[0,9,9]", "[0, 9, 9]")])
@pytest.mark.parametrize("module", ["eval", "train"])
def test_a_ladder_out_of_order_is_one_line_at_the_command_line(tmp_path, monkeypatch, capsys, module, speeds, shown):
    monkeypatch.chdir(tmp_path)
    argv = [f"env.target_speeds_kmh={speeds}", "agents=[always_proceed]" if module == "eval" else
            "agent=always_proceed"]
    line = check_line(module, argv, monkeypatch, capsys)
    assert f"env.{RULE}, got {shown}" in line, line
    assert not any(tmp_path.iterdir())


def test_gym_make_and_make_vec_refuse_it_too():
    with pytest.raises(ConfigError, match=r"config\.action\.target_speeds must be strictly increasing"):
        gym.make(TURN, config={"action": {"type": "discrete", "target_speeds": [9.0, 4.5, 0.0]}})
    with pytest.raises(ConfigError, match=r"target_speeds_kmh must be strictly increasing"):
        gym.make_vec(TURN, num_envs=2, sensors="turn_truth", env={"target_speeds_kmh": [32.4, 16.2, 0.0]})


def test_an_increasing_ladder_is_accepted_whatever_its_numbers():
    assert check(LeftTurnParams, {"target_speeds_kmh": [0.0, 4.5, 9.0]}, "env") == []  # small, but increasing
    assert check(LeftTurnParams, {"target_speeds_kmh": [0.0, 16.2, 32.4]}, "env") == []
    assert check(LeftTurnParams, {"target_speeds_kmh": [9.0, 4.5, 0.0]}, "env") == [
        f"env.{RULE}, got [9, 4.5, 0]"]
