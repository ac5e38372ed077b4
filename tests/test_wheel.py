"""av-gym as a package in someone else's project: a wheel built from this checkout, installed non-editable in a
fresh venv, used from a folder whose own ``conf/`` (Hydra's layout, no ``__init__.py``), ``agents/``, ``train.py``
and ``eval/`` would shadow the harness if anything imported them by those names. Four checks: the README's own-code
examples (the API with a shielded perceived stack, SB3 PPO through ``SubprocVecEnv``; a reference agent by name),
the first one again on the ``cameras`` preset, and the console script ``av-gym-eval`` with a named agent.

Why the venv shares the test environment's dependencies (a ``.pth`` line) instead of installing them: the check is
about what the wheel carries and what an install puts on ``sys.path``; downloading torch and the rest again would
test the package index, and on stock PyPI pull a CUDA torch of several GB. ``av_gym`` itself comes only from the
wheel: the checkout is on no path (no ``PYTHONPATH``; the editable install's finder is not activated by a ``.pth``
line)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.test_readme_examples import examples

ROOT = Path(__file__).resolve().parents[1]
SHADOW = "raise ImportError('the user folder\\'s {} was imported')\n"


def _run(argv: list[str], cwd: Path, timeout: int = 600) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Path:
    """A fresh venv with this checkout's wheel installed (not editable); its bin/ folder."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"  # a copy, so that the build's own build/ and egg-info stay out of the checkout
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "runs", "outputs", "multirun", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache"))
    for run in (src / "checkpoints").iterdir():  # training runs of this checkout are not the package's
        if run.name != "reference" and run.is_dir():
            shutil.rmtree(run)
    built = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                  str(tmp / "dist"), str(src)], cwd=tmp)
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = (tmp / "dist").glob("av_gym-*.whl")
    made = _run([sys.executable, "-m", "venv", str(tmp / "venv")], cwd=tmp)
    assert made.returncode == 0, made.stderr[-3000:]
    bin_dir = tmp / "venv" / "bin"
    site = Path(_run([str(bin_dir / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     cwd=tmp).stdout.strip())
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "_av_gym_test_dependencies.pth").write_text("\n".join(sorted(deps)) + "\n")
    installed = _run([str(bin_dir / "python"), "-m", "pip", "install", "-q", "--no-deps", "--no-index",
                      "--force-reinstall", str(wheel)], cwd=tmp)
    assert installed.returncode == 0, installed.stderr[-3000:]
    return bin_dir


@pytest.fixture
def user_folder(tmp_path) -> Path:
    """A project of the user's: every name the harness uses, each raising if imported."""
    (tmp_path / "conf" / "sensors").mkdir(parents=True)  # Hydra's layout: no __init__.py
    (tmp_path / "conf" / "sensors" / "turn_perceived.yaml").write_text("not: ours\n")
    (tmp_path / "conf" / "train.yaml").write_text("unrelated: 1\n")
    for package in ("agents", "eval"):
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text(SHADOW.format(package))
    (tmp_path / "train.py").write_text(SHADOW.format("train.py"))
    return tmp_path


@pytest.mark.slow  # a wheel built, a venv made, four checks in fresh interpreters: ~3 min on 2 cores
def test_the_wheel_works_from_a_project_with_shadowing_packages(venv, user_folder):
    python = str(venv / "python")
    where = _run([python, "-c", "import av_gym, av_gym_harness; print(av_gym.__file__); "
                                "print(av_gym.reference('ppo_turn')); print(av_gym_harness.harness_root())"],
                 cwd=user_folder)
    assert where.returncode == 0, where.stderr[-3000:]
    lib, ref, harness = where.stdout.split()
    assert str(venv.parent) in lib and str(ROOT) not in lib  # the wheel's, not the checkout's
    assert Path(ref).is_relative_to(Path(lib).parent) and (Path(ref) / "model.zip").is_file()
    assert Path(harness).is_relative_to(venv.parent)
    for name in ("train", "eval", "agents", "conf"):  # the install adds none of the harness's names to the path
        bare = _run([python, "-c", f"import {name}"], cwd=venv.parent)
        assert bare.returncode != 0 and "No module named" in bare.stderr, name

    training, reference = examples()
    checks = {
        "api: shielded perceived stack, PPO through SubprocVecEnv": training.replace("steps = 4_096", "steps = 64"),
        "a reference agent by name": reference,
        "PPO on the cameras preset through SubprocVecEnv": training.replace("steps = 4_096", "steps = 64").replace(
            '{"sensors": "turn_perceived", "shield": "aeb"}', '{"sensors": "cameras", "shield": "none"}'),
    }
    assert '"sensors": "cameras"' in checks["PPO on the cameras preset through SubprocVecEnv"]
    passed = []
    for what, code in checks.items():
        script = user_folder / "example.py"  # a file of the user's project, run as they would
        script.write_text(code)
        res = _run([python, str(script)], cwd=user_folder)
        assert res.returncode == 0, f"{what}: {res.stderr[-3000:]}"
        assert "'collision'" in res.stdout and "'success'" in res.stdout, what
        passed.append(what)
    res = _run([str(venv / "av-gym-eval"), "env=left_turn", "agents=[gap_acceptance,ppo_turn]", "episodes=2",
                "progress_bar=false", "plots=false"], cwd=user_folder)
    assert res.returncode == 0, res.stderr[-3000:]
    (results,) = (user_folder / "runs" / "eval").glob("*/results.csv")
    assert results.read_text().count("ppo_turn") == 2 and results.read_text().count("gap_acceptance") == 2
    assert str(Path(ref)) in res.stdout  # the wheel's shipped reference
    # the wheel carries eval/archive_commit.txt; built from a checkout, it holds the placeholder: no commit claimed
    assert (Path(harness) / "eval" / "archive_commit.txt").read_text().strip() == "$Format:%H$"
    assert json.loads((results.parent / "meta.json").read_text())["commit"] is None
    passed.append("console script with a named agent")
    assert len(passed) == 4
