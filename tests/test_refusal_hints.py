"""Refusals that name what the user gave and the form that works (prober R7, finding 5): a shield field set with
no shield named, and a train.eval_seed near the split's end counted with the episode count actually used."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import cli


def _line(res) -> str:
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    return lines[0]


def test_a_shield_field_without_a_shield_says_to_name_one(tmp_path):
    """``agents=[x+aeb] shield.mode=perceived`` sets a field on shield=none: the line says to give shield=aeb."""
    line = _line(cli("eval", "agents=[always_proceed+aeb]", "shield.mode=perceived", "episodes=1", cwd=tmp_path))
    assert "shield.mode is not a field of shield=none" in line
    assert "shield=aeb shield.mode=<value>" in line


@pytest.mark.parametrize("agent, used, other", [
    ("always_proceed", "train.eval_episodes", "train.eval_n"),  # a rule agent has no evaluation while training
    ("ppo_turn", "train.eval_n", "train.eval_episodes"),  # PPO's periodic evaluation: 30 episodes each
])
def test_an_eval_seed_near_the_split_end_names_the_count_used(tmp_path, agent, used, other):
    line = _line(cli("train", f"agent={agent}", "train.eval_seed=1999998", "train.eval_episodes=3",
                     "train.progress_bar=false", cwd=tmp_path))
    n = 3 if used == "train.eval_episodes" else 30
    assert f"with {n} episodes ({used})" in line and f"give {used} <= 2" in line and other not in line, line


def test_a_checkout_path_given_elsewhere_names_where_this_install_has_it(tmp_path, monkeypatch):
    """The docs' ``checkpoints/reference/...`` paths are a checkout's: from a wheel in another folder they were
    'no such file or folder' and nothing more."""
    from av_gym.references import checkout_path_hint, reference_root

    monkeypatch.chdir(tmp_path)
    seed = "checkpoints/reference/seeds/dagger_turn/s2"
    assert checkout_path_hint(seed).endswith(f"this install's copy is {reference_root() / 'seeds/dagger_turn/s2'}")
    assert "the shipped agent is named 'pilotnet' anywhere" in checkout_path_hint("checkpoints/reference/pilotnet")
    assert "named" not in checkout_path_hint("checkpoints/reference/pilotnet", by_name=False)
    assert checkout_path_hint("checkpoints/reference/no_such_agent") == ""  # nowhere in this install
    assert checkout_path_hint("checkpoints/my_run") == "" and checkout_path_hint(reference_root()) == ""
    (tmp_path / "checkpoints" / "reference" / "pilotnet").mkdir(parents=True)
    assert checkout_path_hint("checkpoints/reference/pilotnet") == ""  # it is here: the user's own folder


def test_eval_refusals_name_the_forms_that_work_outside_the_checkout(tmp_path):
    line = _line(cli("eval", "env=left_turn", "agents=[checkpoints/reference/seeds/dagger_turn/s2]", cwd=tmp_path))
    assert "no such file or folder; checkpoints/reference/seeds/dagger_turn/s2 is a checkout's folder" in line, line
    line = _line(cli("eval", "env=left_turn", "agents=[ppo:latest]", f"paths.checkpoints={tmp_path / 'none'}",
                     cwd=tmp_path))
    assert "train one with `av-gym-train env=left_turn agent=ppo`" in line, line  # python -m train: checkout only


def test_the_suggested_train_command_is_the_one_that_runs_here(tmp_path, monkeypatch):
    from eval.agents import train_command

    monkeypatch.chdir(tmp_path)
    assert train_command() == "av-gym-train"
    monkeypatch.chdir(Path(__file__).resolve().parents[1])  # the checkout's root: train/ is found there
    assert train_command() == "python -m train"
