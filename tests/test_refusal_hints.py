"""Refusals that name what the user gave and the form that works (prober R7, finding 5): a shield field set with
no shield named, and a train.eval_seed near the split's end counted with the episode count actually used."""

from __future__ import annotations

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
