"""``python -m eval`` (and ``-m``) never writes into a folder that is not its own: a sweep job's folder holding a
user's file or an earlier evaluation's results, a sweep folder holding an earlier sweep's ``multirun.yaml``, a
``hydra.run.dir`` holding an evaluation's results are refused in one line, exit 2, before Hydra writes ``.hydra/``,
the job log or the sweep's record there (eval/job_folders.py, conf/job_folders.py, registered in conf/eval.yaml).
Before, job 0 wrote its results beside the user's notes.md, the refused job 1 left .hydra/ and __main__.log among
an earlier evaluation's results, and the earlier sweep's multirun.yaml was replaced. The fast cases:
tests/test_job_folders.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_nothing_lost import snapshot

ROOT = Path(__file__).resolve().parents[1]
EVAL = ["agents=[always_proceed]", "episodes=1", "env.duration=2.0", "progress_bar=false", "hydra/launcher=basic"]


def _eval(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.run([sys.executable, "-m", "eval", *argv, *EVAL], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def _refused(done: subprocess.CompletedProcess, needle: str) -> None:
    err = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(err) == 1 and needle in err[0], (done.returncode, done.stderr[-2000:])


@pytest.mark.slow  # three real processes of python -m eval, none running an episode: ~10 CPU-s
def test_real_eval_sweeps_and_a_run_leave_a_users_and_an_earlier_sweeps_folders_byte_for_byte(tmp_path):
    (tmp_path / "y" / "0").mkdir(parents=True)
    (tmp_path / "y" / "0" / "notes.md").write_text("mine\n")
    (tmp_path / "y" / "1").mkdir()
    (tmp_path / "y" / "1" / "results.csv").write_text("agent,episode\n")
    (tmp_path / "z").mkdir()
    (tmp_path / "z" / "multirun.yaml").write_text("an: earlier sweep\n")
    (tmp_path / "q").mkdir()
    (tmp_path / "q" / "results.csv").write_text("agent,episode\n")
    before = snapshot(tmp_path)
    _refused(_eval(["-m", "seed=1000000,1000001", "hydra.sweep.dir=y"], tmp_path),
             f"hydra.sweep.dir={tmp_path}/y/0: holds files that are not an evaluation's (notes.md)")
    _refused(_eval(["-m", "seed=1000000,1000001", "hydra.sweep.dir=z"], tmp_path),
             f"hydra.sweep.dir={tmp_path}/z: holds an earlier sweep's record (multirun.yaml)")
    _refused(_eval(["hydra.run.dir=q"], tmp_path), f"hydra.run.dir={tmp_path}/q already holds results.csv")
    assert snapshot(tmp_path) == before
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == \
        ["q", "q/results.csv", "y", "y/0", "y/0/notes.md", "y/1", "y/1/results.csv", "z", "z/multirun.yaml"]
