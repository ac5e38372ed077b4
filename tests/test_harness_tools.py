"""``python -m av_gym_harness <module> [args]``: the harness's side tools (eval.results_page, train.export ...) from
an install, where ``python -m eval.results_page`` finds no ``eval`` (prober R4, item 9: "No module named 'eval'"
from a wheel) or, run from a project with an ``eval/`` of its own, finds the user's."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from av_gym_harness.__main__ import main
from tests.test_nothing_lost import ROOT


@pytest.mark.parametrize("argv", [[], ["os"], ["-m"]])
def test_only_a_module_of_the_harness_is_run(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: python -m av_gym_harness <module> [args]: the module must be "
                                               "one of the harness's (conf, agents, train, eval"), err


@pytest.mark.parametrize("name", ["agents"])  # conf alike, but importing it (Hydra's ConfigStore) takes ~3 s
def test_a_package_without_a_main_is_one_line(name, capsys, monkeypatch):
    """``python -m av_gym_harness agents`` (or ``conf``) ended in runpy's ImportError traceback ("'agents' is a
    package and cannot be directly executed"): now one line, exit 2, nothing run. A package with a __main__ (eval)
    and a module still pass."""
    from av_gym_harness.__main__ import runnable_problem

    monkeypatch.setattr(sys, "path", list(sys.path))  # use_harness reorders it for this process
    assert main([name]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: python -m av_gym_harness <module> [args]: the harness's {name!r} is a package with "
                   f"nothing to run (no {name}.__main__); name a module of it, e.g. eval.results_page, "
                   f"train.export"], err
    assert runnable_problem("eval") is None and runnable_problem("eval.results_page") is None
    assert runnable_problem("eval.nope") == "the harness has no module 'eval.nope'"


@pytest.mark.slow  # two python processes importing the harness (~5 CPU-s)
def test_a_side_tool_runs_from_a_project_with_its_own_eval(tmp_path):
    """From a folder holding a user's ``eval/`` package: ``python -m eval.results_page`` imports the user's,
    ``python -m av_gym_harness eval.results_page --help`` runs the harness's; a module the harness lacks is one
    line, exit 2."""
    (tmp_path / "eval").mkdir()
    (tmp_path / "eval" / "__init__.py").write_text('raise SystemExit("the user\'s eval")\n')
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    plain = subprocess.run([sys.executable, "-m", "eval.results_page", "--help"], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=120)
    assert "the user's eval" in plain.stderr, plain.stderr
    tool = subprocess.run([sys.executable, "-m", "av_gym_harness", "eval.results_page", "--help"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=120)
    assert tool.returncode == 0 and tool.stdout.startswith("usage: python -m eval.results_page"), tool.stderr
    missing = subprocess.run([sys.executable, "-m", "av_gym_harness", "eval.nope"], cwd=tmp_path, env=env,
                             capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and missing.stderr == "error: python -m av_gym_harness <module> [args]: the " \
                                                         "harness has no module 'eval.nope'\n", missing.stderr
