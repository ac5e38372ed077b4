"""CI runs what the README tells a newcomer to run: the test commands in README.md and in .ci/run are the same."""

from __future__ import annotations

import re
from importlib import resources

ROOT = resources.files("conf").parent


def pytest_commands(text: str) -> list[str]:
    """Each ``python -m pytest ...`` command, in order (the part after the last ``&&`` of its line)."""
    return [line.split("&&")[-1].strip() for line in text.splitlines()
            if re.search(r"python -m pytest", line) and not line.lstrip().startswith("#")]


def test_ci_runs_exactly_the_readme_test_commands():
    readme = pytest_commands((ROOT / "README.md").read_text())
    ci = pytest_commands((ROOT / ".ci" / "run").read_text())
    assert readme == ci == ['python -m pytest -q -n auto -m "not slow"', "python -m pytest -q -n auto -m slow"]


def test_the_slow_marker_is_declared():
    """An undeclared marker would only warn; `-m slow` would then select nothing without a word."""
    assert "slow:" in (ROOT / "pyproject.toml").read_text()
