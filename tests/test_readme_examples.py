"""README "Use it from your own code": its Python examples run as printed (from the checkout here; from a user's
folder against a wheel in tests/test_wheel.py)."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.documented_commands import ROOT


def examples() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Use it from your own code", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"^```python\n(.*?)^```", section, re.S | re.M)


def test_the_section_has_both_examples() -> None:
    found = examples()
    assert len(found) == 2
    assert "SubprocVecEnv" in found[0] and "FlatDictObservation" in found[0]
    assert 'checkpoint="ppo_turn"' in found[1] and 'av_gym.reference("ppo_turn")' in found[1]


def test_reference_checkpoint_example(monkeypatch, capsys, tmp_path) -> None:
    monkeypatch.chdir(tmp_path)  # by name: from any folder
    exec(compile(examples()[1], "README.md", "exec"), {"__name__": "readme_example"})
    out = capsys.readouterr().out
    assert "'success'" in out and "'collision'" in out  # the episode's metrics were printed


@pytest.mark.slow  # ~40 s: two fresh worker processes, one PPO rollout, one episode
def test_training_example_runs() -> None:
    code = examples()[0]
    assert "steps = 4_096" in code
    code = code.replace("steps = 4_096", "steps = 64")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "'success'" in done.stdout
