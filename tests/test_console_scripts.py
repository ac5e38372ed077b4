"""``av-gym-train`` / ``av-gym-eval`` (pyproject ``[project.scripts]``, av_gym_harness) from a folder of the user's
own that has ``conf/``, ``agents/``, ``train/`` and ``eval/`` folders (Hydra's usual layout), and
``--help`` listing only what a user can set.

The scripts are run as ``python -c "<the entry point pyproject names>"``: the same function the installed script
calls, with the working folder first on ``sys.path`` as ``python -m``/``-c`` put it (a worse case than the
installed script, whose ``sys.path`` starts at its bin/ folder)."""

from __future__ import annotations

import csv
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
INTERNAL = ("aeb", "agent_kind", "command", "scenario", "sensor")


def _entry(script: str) -> str:
    """``python -c`` code calling the function pyproject's ``[project.scripts]`` names for ``script``."""
    target = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"][script]
    module, function = target.split(":")
    return f"import {module}; {module}.{function}()"


@pytest.fixture
def user_folder(tmp_path) -> Path:
    """A project folder whose own packages share our top-level names: each would shadow ours if imported."""
    for name in ("conf", "agents", "train", "eval"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(f"raise ImportError('the user folder\\'s {name} was imported')\n")
    (tmp_path / "conf" / "train.yaml").write_text("unrelated: 1\n")
    return tmp_path


def _run(script: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _entry(script), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


def _groups(help_text: str) -> dict[str, str]:
    section = help_text.split("== Configuration groups ==")[1].split("== Config ==")[0]
    return dict(line.split(": ", 1) for line in section.splitlines() if ": " in line)


@pytest.mark.slow  # a fresh interpreter importing the harness, ~8 s of CPU
def test_help_from_any_folder_lists_only_the_groups_a_user_sets(user_folder):
    res = _run("av-gym-train", "--help", cwd=user_folder)
    assert res.returncode == 0, res.stderr[-3000:]
    listed = _groups(res.stdout)
    assert sorted(listed) == ["agent", "env", "sensors", "shield"], res.stdout[:2000]
    assert "ppo_turn" in listed["agent"].split(", ") and "left_turn" in listed["env"].split(", ")
    assert {p.name for p in user_folder.iterdir()} == {"conf", "agents", "train", "eval"}  # no run folder


def test_eval_help_lists_only_the_groups_eval_takes():
    """``python -m eval --help`` prints hydra.help.template (conf/hydra/help/av_gym.yaml) with $CONFIG filled in."""
    from hydra import compose, initialize_config_module

    with initialize_config_module("conf", version_base="1.3"):
        template = compose(config_name="eval", return_hydra_config=True).hydra.help.template
    listed = _groups(template)
    assert sorted(listed) == ["env", "sensors", "shield"] and not set(INTERNAL) & set(listed)
    assert "python -m eval" in template and "av-gym-eval" in template


@pytest.mark.slow  # two agents' episodes and a reference checkpoint loaded: ~15 s on 2 cores
def test_eval_from_a_folder_with_its_own_conf_and_agents_finds_the_reference_checkpoints(user_folder):
    res = _run("av-gym-eval", "env=left_turn", "agents=[always_proceed,ppo_turn]", "episodes=2",
               "progress_bar=false", cwd=user_folder)
    assert res.returncode == 0, res.stderr[-3000:]
    (results,) = (user_folder / "runs" / "eval").glob("*/results.csv")  # outputs go to the user's folder
    rows = list(csv.DictReader(results.open()))
    assert [r["agent"] for r in rows] == ["always_proceed"] * 2 + ["ppo_turn"] * 2
    assert str(ROOT / "checkpoints" / "reference" / "ppo_turn") in res.stdout  # the shipped reference, found


def test_the_entry_points_are_the_functions_pyproject_names():
    import av_gym_harness

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == {"av-gym-train": "av_gym_harness:train", "av-gym-eval": "av_gym_harness:evaluate"}
    assert callable(av_gym_harness.train) and callable(av_gym_harness.evaluate)
