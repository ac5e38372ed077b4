"""What a probe of the batch from a user's view found (issue 47 item 3: every left-turn agent x sensors x shield
through ``python -m eval vec_env=batched``, ``gymnasium.make_vec`` and ``python -m train agent.vec_env=batched``):
each door closed here, one line before anything runs or is written."""

from __future__ import annotations

import pytest

from tests.test_bad_input import check_line


@pytest.mark.parametrize("vec_env", ["batched", "subproc"])
def test_an_agent_at_a_preset_of_another_observation_space_is_refused_before_any_episode(vec_env, tmp_path,
                                                                                         monkeypatch, capsys):
    """``agents=[always_proceed,dagger_turn_memory@turn_perceived]`` played always_proceed's episodes and wrote its
    rows, then stopped at the checkpoint's load (its 5 intent readings against the preset's 2): exit 2 with a
    results folder that the next run refused to overwrite. Now one line at the check, naming the preset, both
    spaces and what runs, and no folder."""
    monkeypatch.chdir(tmp_path)
    line = check_line("eval", [f"vec_env={vec_env}", "agents=[always_proceed,dagger_turn_memory@turn_perceived+aeb]",
                               "episodes=2", "out_dir=out"], monkeypatch, capsys)
    assert line == ("error: agent 'dagger_turn_memory@turn_perceived+aeb': @turn_perceived gives observations "
                    "{intent: (8, 2) float32 [-1, 1], turn: (101,) float32 [-1, 1]}, but it was trained on "
                    "sensors=turn_truth_memory, {intent: (8, 5) float32 [-1, 1], turn: (101,) float32 [-1, 1]}; drive "
                    "it from a preset with that observation space (dagger_turn_memory@turn_truth_memory, or "
                    "dagger_turn_memory alone)"), line
    assert list(tmp_path.iterdir()) == []


def test_an_agent_at_a_preset_of_its_own_observation_space_still_passes_the_check():
    """``dagger_turn@turn_perceived`` (trained on turn_truth: the same spaces) and a checkpoint on its own preset."""
    from conf.check import check_command_line
    from conf.commands import EvalCommand
    from eval.__main__ import _check_plans, _plain, _plans

    (cfg,) = check_command_line("eval", ["vec_env=batched", "agents=[dagger_turn@turn_perceived+aeb,"
                                         "dagger_turn_memory@turn_truth_memory,ppo_turn_perceived]"])
    command = EvalCommand.of(cfg)
    plans = _plans(cfg, command)
    _check_plans(plans, command, _plain(cfg.env), _plain(cfg.sensors))
    assert [p.sensors["name"] for p in plans] == ["turn_perceived", "turn_truth_memory", "turn_perceived"]
