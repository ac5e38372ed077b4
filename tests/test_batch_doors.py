"""What the batch runs and refuses, tried from a user's side (every left-turn agent x sensors x shield through
``python -m eval vec_env=batched``, ``gymnasium.make_vec`` and ``python -m train agent.vec_env=batched``): each
refusal one line before anything runs or is written, and results.md says what ran."""

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


def test_a_shielded_agent_keeps_the_command_lines_fields_of_its_shield():
    """``agents=[always_proceed+aeb] shield=aeb shield.mode=perceived`` ran the shipped aeb (mode ground_truth):
    ``+aeb`` composed the preset afresh and dropped the command line's fields of that same preset. Another preset
    on the command line is still the other agents' only."""
    from conf.check import check_command_line
    from conf.commands import EvalCommand
    from eval.__main__ import _plans

    (cfg,) = check_command_line("eval", ["vec_env=batched", "agents=[always_proceed+aeb,gap_acceptance,lookahead+aeb]",
                                         "shield=aeb", "shield.mode=perceived", "shield.ttc_brake=2.0"])
    plans = _plans(cfg, EvalCommand.of(cfg))
    assert [(p.shield["name"], p.shield["mode"], p.shield["ttc_brake"]) for p in plans] == [
        ("aeb", "perceived", 2.0)] * 3
    (cfg,) = check_command_line("eval", ["agents=[always_proceed+aeb,gap_acceptance]", "shield=aeb_paper"])
    assert [p.shield["name"] for p in _plans(cfg, EvalCommand.of(cfg))] == ["aeb", "aeb_paper"]


def test_the_shield_section_names_each_shielded_agents_preset_and_changed_fields(tmp_path):
    from conf.presets import compose_group
    from eval.report import write_results

    perceived = {**compose_group("shield", "aeb"), "mode": "perceived"}
    rows = [{"agent": a, "episode": 0, "seed": 1000000, "collision": 0.0, "success": 1.0} for a in ("x", "y+aeb")]
    write_results(rows, tmp_path, "left_turn", "t", shields={"x": perceived, "y+aeb": compose_group("shield", "aeb")})
    assert (tmp_path / "results.md").read_text().endswith(
        "## Shield each agent ran behind\n\n- `x`: aeb with mode='perceived'\n- `y+aeb`: aeb (as shipped)\n")
    write_results(rows, tmp_path, "left_turn", "t")
    assert "Shield" not in (tmp_path / "results.md").read_text()


@pytest.mark.slow  # ~4 s: two evaluation episodes through python -m eval's main
def test_results_md_says_which_shield_each_agent_ran_behind(tmp_path, monkeypatch):
    """A shield from the command line (``shield=aeb shield.mode=perceived``) was in no label: the rows of
    ``always_proceed`` behind it were told from unshielded ones by nothing in results.csv or results.md (now the
    label says it too, eval/labels.py)."""
    import sys

    from eval import __main__ as eval_main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["eval", "agents=[always_proceed,gap_acceptance+aeb_paper]", "shield=aeb",
                                      "shield.mode=perceived", "episodes=1", "out_dir=out", "progress_bar=false",
                                      "hydra.run.dir=hydra"])
    eval_main.main()
    md = (tmp_path / "out" / "results.md").read_text()
    assert md.split("## Shield each agent ran behind\n\n")[1] == (
        "- `always_proceed+aeb(mode=perceived)`: aeb with mode='perceived'\n"
        "- `gap_acceptance+aeb_paper`: aeb_paper (as shipped)\n")


@pytest.mark.parametrize("fails_with", [KeyboardInterrupt, RuntimeError])
def test_an_interrupted_or_failing_evals_results_md_says_which_shield_its_rows_ran_behind(fails_with, tmp_path,
                                                                                          monkeypatch):
    """The results.md written after each agent and on Ctrl-C names the command line's shield of the agents with rows
    (and no agent that did not run): without it an interrupted evaluation of ``shield=aeb`` read as unshielded."""
    import sys

    from eval import __main__ as eval_main

    def run_agent(plan, command, env_cfg, seeds, rows) -> None:  # one row an agent, the second agent fails
        if rows:
            raise fails_with("stopped")
        rows.append({"agent": plan.label, "episode": 0, "seed": seeds.start, "collision": 0.0, "success": 1.0})

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(eval_main, "_run_agent", run_agent)
    monkeypatch.setattr(sys, "argv", ["eval", "agents=[always_proceed,gap_acceptance]", "shield=aeb",
                                      "shield.mode=perceived", "episodes=1", "out_dir=out", "progress_bar=false",
                                      "hydra.run.dir=hydra"])
    with pytest.raises((fails_with, SystemExit)):
        eval_main.main()
    md = (tmp_path / "out" / "results.md").read_text()
    assert md.split("## Shield each agent ran behind\n\n")[1] == \
        "- `always_proceed+aeb(mode=perceived)`: aeb with mode='perceived'\n"
    assert "## Sensors each agent ran with\n\n- `always_proceed+aeb(mode=perceived)`: " in md
    assert "gap_acceptance" not in md


@pytest.mark.parametrize("shield", ["aeb_paper", "aeb_belief"])
def test_dagger_on_the_batch_names_the_shield_it_was_given_and_what_it_runs(shield, tmp_path, monkeypatch, capsys):
    """``python -m train agent=dagger_turn shield=aeb_paper`` said ``shield=aeb is not available ... (python -m eval
    vec_env=batched runs shield=aeb)``: another preset than the one given, and it read as the allowed one."""
    monkeypatch.chdir(tmp_path)
    line = check_line("train", ["agent=dagger_turn", f"shield={shield}"], monkeypatch, capsys)
    assert line.startswith(f"error: shield={shield} is not available with agent.vec_env=batched here (this batch runs "
                           f"without a shield: shield=none;"), line
    assert list(tmp_path.iterdir()) == []
