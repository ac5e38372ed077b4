"""Every command README.md and docs/ invite a reader to run is run here, in a tiny form. The list, and
how each command's tiny form is made, is tests/documented_commands.py."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

import documented_commands as dc
from documented_commands import (KNOWN, ROOT, SCRIPT_ARGS, Chain, Command, all_blocks, documented_scripts,
                                 script_argv, tiny)


def test_every_documented_command_is_known():
    """A documented command without an entry (how it is tested) fails; so does an entry no document has any more."""
    documented = [c for block in all_blocks() for c in block]
    unknown = [f"{c.doc}:{c.line}: {c.text}" for c in documented if c.text not in KNOWN]
    assert not unknown, ("documented commands with no test; add each to tests/documented_commands.py KNOWN "
                         "(`python tests/documented_commands.py` prints them):\n" + "\n".join(unknown))
    stale = sorted(set(KNOWN) - {c.text for c in documented})
    assert not stale, f"KNOWN lists commands no document has any more: {stale}"


def test_covered_commands_name_tests_that_exist():
    for text, how in KNOWN.items():
        if how.startswith("covered:"):
            path, name = how.split(":", 1)[1].split("::")
            assert f"def {name}(" in (ROOT / path).read_text(), (text, how)
        else:
            assert how in ("run", "error", "ci"), (text, how)


def test_ci_commands_are_what_ci_runs():
    ci = (ROOT / ".ci" / "run").read_text()
    for text, how in KNOWN.items():
        if how == "ci":
            last = text.split("&&")[-1].strip()
            assert last.replace("'", '"') in ci, text


ERRORS = [c for block in all_blocks() for c in block if KNOWN.get(c.text) == "error"]


@pytest.mark.parametrize("command", ERRORS, ids=[c.text for c in ERRORS])
def test_documented_error_examples_print_what_the_document_shows(command: Command, tmp_path):
    """``$ python -m train env.mode=rush_hour`` and the line under it: the same one-line error, exit status 2
    (``...`` in the document stands for the rest of the line)."""
    from conftest import cli

    argv = command.text.split()
    assert argv[:2] == ["python", "-m"] and command.expected, command
    res = cli(argv[2], *argv[3:], cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr
    want = command.expected[0]
    if want.endswith("...]"):
        assert lines[0].startswith(want[:-len("...]")]), (lines[0], want)
    else:
        assert lines[0] == want


def _runnable_blocks() -> list:
    params = []
    for block in all_blocks():
        commands = [c for c in block if KNOWN.get(c.text) == "run"]
        if commands:
            label = f"{commands[0].doc}:{commands[0].line}"
            params.append(pytest.param(commands, id=label, marks=pytest.mark.slow))
    return params


def _user_env() -> dict[str, str]:
    """The environment a user's command has: this process's less what tests/conftest.py adds for every test's
    subprocesses, ``PYTHONPATH`` (a user has only the editable install's own paths) and its ``OMP_NUM_THREADS=1``
    (its marker ``AV_GYM_TESTS_SET_OMP`` says it chose the count; a count the user set stays, as it would for
    their own command): the thread count is what the documents' commands run with, not the test process's."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if env.get("AV_GYM_TESTS_SET_OMP") is not None and env.get("AV_GYM_TESTS_SET_OMP") == env.get("OMP_NUM_THREADS"):
        del env["OMP_NUM_THREADS"], env["AV_GYM_TESTS_SET_OMP"]
    return env


def _run(argv: list[str], tmp: Path) -> subprocess.CompletedProcess:
    """``argv`` as a user runs it: ``python ...`` from the checkout, a console script (tensorboard, av-gym-*) from a
    folder of the user's own (``tmp``), and neither in the test process's environment (:func:`_user_env`)."""
    if argv[0] == "python":
        argv, cwd = [sys.executable, *argv[1:]], ROOT
    else:
        # console scripts live beside the interpreter: found there even when the venv that runs the tests is not
        # activated
        env_bin = Path(sys.executable).parent
        if "/" not in argv[0] and (env_bin / argv[0]).exists():
            argv = [str(env_bin / argv[0]), *argv[1:]]
        cwd = tmp / "user_folder"
        cwd.mkdir(exist_ok=True)
    return subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=600, env=_user_env())


@pytest.mark.parametrize("user_set", [None, "3"])
def test_a_documented_command_runs_with_the_users_thread_count(user_set, monkeypatch, tmp_path):
    """The command's OMP_NUM_THREADS is the user's (none, or the one they set before running the tests), never the
    1 tests/conftest.py chose for the test processes (with its marker)."""
    if user_set is None:
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        monkeypatch.setenv("AV_GYM_TESTS_SET_OMP", "1")
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", user_set)
        monkeypatch.delenv("AV_GYM_TESTS_SET_OMP", raising=False)
    res = _run(["python", "-c", "import os; print(os.environ.get('OMP_NUM_THREADS'))"], tmp_path)
    assert res.returncode == 0 and res.stdout.strip() == str(user_set), res.stderr


@pytest.mark.parametrize("commands", _runnable_blocks())
def test_documented_commands_run(commands: list[Command], tmp_path):
    """Each block's commands in order, in their tiny forms, as a user runs them (:func:`_run`: ``python ...`` in the
    checkout, so named reference agents are found) with every output under a temporary folder; each must exit 0
    and leave nothing in the repository."""
    before = _tracked_changes()
    chain = Chain(tmp_path)
    for command in commands:
        producer = dc.PRODUCERS.get(command.text)
        if producer:
            res = _run(tiny(Command(command.doc, command.line, producer), chain), tmp_path)
            assert res.returncode == 0, f"producer of {command.text}\n{res.stderr[-3000:]}"
        argv = tiny(command, chain)
        res = _run(argv, tmp_path)
        assert res.returncode == 0, f"{command.doc}:{command.line}: {command.text}\ntiny form: {argv}\n" \
                                    f"{res.stdout[-1500:]}\n{res.stderr[-3000:]}"
    assert _tracked_changes() == before, "a documented command wrote into tracked files"


def _tracked_changes() -> str:
    """What git sees changed or new outside runs/ and checkpoints/<run>/ (where commands write by design)."""
    res = subprocess.run(["git", "status", "--porcelain", "--", "docs", "README.md", "conf", "av_gym", "agents",
                          "train", "eval", "checkpoints/reference"], cwd=ROOT, capture_output=True, text=True)
    return res.stdout if res.returncode == 0 else ""


def test_every_documented_script_exists_and_has_a_tiny_form():
    """A script a page tells a reader to run (``python benchmarks/x.py`` in a sentence too, not only in a fenced
    block) exists and has its tiny form in SCRIPT_ARGS; an entry no page names any more fails too."""
    documented = documented_scripts()
    missing = {s: where for s, where in documented.items() if not (ROOT / s).is_file()}
    assert not missing, f"documented scripts that do not exist: {missing}"
    unknown = {s: where for s, where in documented.items() if s not in SCRIPT_ARGS}
    assert not unknown, f"documented scripts without a tiny form in tests/documented_commands.py SCRIPT_ARGS: {unknown}"
    assert sorted(set(SCRIPT_ARGS) - set(documented)) == [], "SCRIPT_ARGS names scripts no page names any more"


def _scripts_outside_blocks() -> list:
    """The documented scripts no fenced block's ``run`` command runs already (those run in their block)."""
    in_blocks = {shlex.split(c.text)[1] for block in all_blocks() for c in block
                 if KNOWN.get(c.text) == "run" and c.text.startswith(("python benchmarks/", "python docs/"))}
    return [pytest.param(s, id=s, marks=pytest.mark.slow) for s in sorted(documented_scripts()) if s not in in_blocks]


@pytest.mark.parametrize("script", _scripts_outside_blocks())
def test_documented_scripts_run(script: str, tmp_path):
    """``python <script>`` in its tiny form, as a user runs it from the checkout (no ``PYTHONPATH``): a script
    that imports the harness (``conf``, ``agents``) must find it itself. Nothing tracked may change."""
    before = _tracked_changes()
    argv = ["python", script, *script_argv(script, tmp_path)]
    res = _run(argv, tmp_path)
    assert res.returncode == 0, f"{argv}\n{res.stdout[-1500:]}\n{res.stderr[-3000:]}"
    assert _tracked_changes() == before, f"{script} wrote into tracked files"
