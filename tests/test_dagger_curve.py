"""docs/make_dagger_figure.py --curve: the learning curve's csv (every validated round of the chosen runs and the
planner's line, each with its validation episodes and Wilson intervals) and its figure; the csv is the record of
runs whose rounds.csv is not tracked, so it is never written over."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from _in_process import run_script
from av_gym.metrics.stats import wilson_ci

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "docs" / "make_dagger_figure.py"
HEADER = "round,driver,episodes,labels,wall_s,label_s,agreement,drive_success,drive_collision,fit_accuracy," \
         "val_success,val_collision\n"


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], cwd=cwd, capture_output=True, text=True, timeout=120)


def _run_here(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return run_script(SCRIPT, *args, cwd=cwd)  # in this process: a fresh interpreter's start-up is most of a run


@pytest.fixture
def runs(tmp_path: Path) -> Path:
    """A one-run rounds.csv in its checkpoint folder (300 validation episodes per round, one round unvalidated),
    a several-run rounds.csv (run column, no config: --val-n) and the planner's validation results.csv."""
    ckpt = tmp_path / "checkpoints" / "dagger_curve_s9"
    ckpt.mkdir(parents=True)
    (ckpt / "config.yaml").write_text("train:\n  eval_n: 300\n")
    (ckpt / "rounds.csv").write_text(HEADER + "0,teacher,10,300,1,1,0.5,0.9,0,0.9,0.5,0.2\n"
                                              "1,student,15,700,2,1,0.6,0.7,0.1,0.9,nan,nan\n"
                                              "2,student,22,1300,3,1,0.7,0.8,0.1,0.9,0.8,0.03\n")
    (tmp_path / "several.csv").write_text("run," + HEADER + "memory_s1,0,teacher,5,100,1,1,.5,.9,0,.9,0.4,0.1\n"
                                                            "other_s1,0,teacher,5,100,1,1,.5,.9,0,.9,0.1,0.5\n")
    rows = [{"agent": "belief_lookahead", "episode": i, "collision": float(i < 3), "success": float(i >= 50),
             "split": "validation"} for i in range(400)]
    with open(tmp_path / "planner.csv", "w") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return tmp_path


@pytest.mark.slow  # the figure script as a process, writing the curve and its figure: ~10 s alone at load 2.3
def test_the_curve_keeps_every_validated_round_with_its_episodes_and_intervals(runs: Path):
    res = _run("several.csv", "checkpoints/dagger_curve_s9/rounds.csv", "--runs", "memory_s*", "dagger_curve_*",
               "--val-n", "200", "--planner", "planner.csv", "--curve", "curve.csv", "--out", "curve.png", cwd=runs)
    assert res.returncode == 0, res.stderr
    got = list(csv.DictReader(open(runs / "curve.csv")))
    assert [(r["series"], r["run"], r["round"], r["labels"], r["val_episodes"]) for r in got] == [
        ("student", "memory_s1", "0", "100", "200"), ("student", "dagger_curve_s9", "0", "300", "300"),
        ("student", "dagger_curve_s9", "2", "1300", "300"), ("planner", "belief_lookahead", "", "", "400")]
    planner = got[-1]
    assert float(planner["val_success"]) == 350 / 400 and float(planner["val_collision"]) == 3 / 400
    _, lo, hi = wilson_ci(9, 300)
    assert (float(got[2]["collision_lo"]), float(got[2]["collision_hi"])) == (round(lo, 4), round(hi, 4))
    assert (runs / "curve.png").stat().st_size > 10_000
    again = _run("--curve", "curve.csv", "--out", "again.png", cwd=runs)  # the figure from the csv alone
    assert again.returncode == 0 and (runs / "again.png").stat().st_size > 10_000, again.stderr


@pytest.mark.parametrize("planner, needle", [
    ("test", "--planner: planner.csv must hold one agent on the validation split"),
    ("exists", "--curve: curve.csv exists; it is not written over"),
])
def test_the_curve_refuses_a_test_split_planner_and_an_existing_csv(runs: Path, planner: str, needle: str):
    if planner == "test":
        text = (runs / "planner.csv").read_text()
        (runs / "planner.csv").write_text(text.replace(",validation\n", ",test\n"))
    else:
        (runs / "curve.csv").write_text("the record\n")
    res = _run_here("several.csv", "--planner", "planner.csv", "--curve", "curve.csv", "--out", "c.png", cwd=runs)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2 and len(lines) == 1 and needle in lines[0], res.stderr
    assert not (runs / "c.png").exists()
    assert planner == "test" or (runs / "curve.csv").read_text() == "the record\n"
    assert planner == "exists" or not (runs / "curve.csv").exists()
