"""docs/make_dagger_figure.py --curve --extend: a resumed run's later rounds join the learning curve's csv after its
own rows, every row the csv held kept byte for byte; a round it holds that comes back with other values is refused."""

from __future__ import annotations

import csv
import subprocess
from pathlib import Path

import pytest

from _in_process import run_script

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "docs" / "make_dagger_figure.py"
HEADER = "round,driver,episodes,labels,wall_s,label_s,agreement,drive_success,drive_collision,fit_accuracy," \
         "val_success,val_collision\n"
ROUNDS = ("0,teacher,10,300,1,1,0.5,0.9,0,0.9,0.5,0.2\n"
          "1,student,15,700,2,1,0.6,0.7,0.1,0.9,0.7,0.1\n")
LATER = "2,student,22,1300,3,1,0.7,0.8,0.1,0.9,0.8133,0.04\n"


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return run_script(SCRIPT, *args, cwd=cwd)  # in this process: a fresh interpreter's start-up is most of a run


@pytest.fixture
def curve(tmp_path: Path) -> Path:
    """A curve written from run s9's first two rounds and run s8's one round (300 validation episodes each) and a
    planner; then s9 resumed: its rounds.csv gains round 2."""
    for name, text in (("dagger_curve_s9", ROUNDS), ("dagger_curve_s8", ROUNDS.splitlines(True)[0])):
        ckpt = tmp_path / "checkpoints" / name
        ckpt.mkdir(parents=True)
        (ckpt / "config.yaml").write_text("train:\n  eval_n: 300\n")
        (ckpt / "rounds.csv").write_text(HEADER + text)
    rows = [{"agent": "belief_lookahead", "collision": float(i < 3), "success": float(i >= 50), "split": "validation"}
            for i in range(400)]
    with open(tmp_path / "planner.csv", "w") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    made = _run("checkpoints/dagger_curve_s9/rounds.csv", "checkpoints/dagger_curve_s8/rounds.csv", "--planner",
                "planner.csv", "--curve", "curve.csv", "--out", "a.png", cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    with open(tmp_path / "checkpoints" / "dagger_curve_s9" / "rounds.csv", "a") as f:
        f.write(LATER)
    return tmp_path


def test_a_resumed_runs_new_rounds_go_after_its_own_rows(curve: Path):
    before = (curve / "curve.csv").read_text().splitlines()
    res = _run("checkpoints/dagger_curve_s9/rounds.csv", "--curve", "curve.csv", "--extend", "--out", "b.png",
               cwd=curve)
    assert res.returncode == 0, res.stderr
    after = (curve / "curve.csv").read_text().splitlines()
    assert after[:3] + after[4:] == before  # every row it held, unchanged, in its place
    got = list(csv.DictReader(open(curve / "curve.csv")))
    assert [(r["run"], r["round"]) for r in got] == [("dagger_curve_s9", "0"), ("dagger_curve_s9", "1"),
                                                     ("dagger_curve_s9", "2"), ("dagger_curve_s8", "0"),
                                                     ("belief_lookahead", "")]
    assert (got[2]["labels"], got[2]["val_success"], got[2]["val_collision"]) == ("1300", "0.8133", "0.0400")
    assert "1 points added, 5 in all" in res.stdout


@pytest.mark.parametrize("change, needle", [
    ("other", "holds round 1 of run dagger_curve_s9 with other values"),
    ("nothing", "no validated round in checkpoints/dagger_curve_s9/rounds.csv that curve.csv does not hold"),
])
def test_extend_refuses_a_changed_round_and_nothing_new(curve: Path, change: str, needle: str):
    rounds = curve / "checkpoints" / "dagger_curve_s9" / "rounds.csv"
    if change == "other":
        rounds.write_text(rounds.read_text().replace("0.6,0.7,0.1,0.9,0.7,0.1", "0.6,0.7,0.1,0.9,0.75,0.1"))
    else:
        rounds.write_text(HEADER + ROUNDS)
    before = (curve / "curve.csv").read_text()
    res = _run(str(rounds.relative_to(curve)), "--curve", "curve.csv", "--extend", "--out", "c.png", cwd=curve)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2 and len(lines) == 1 and needle in lines[0], res.stderr
    assert (curve / "curve.csv").read_text() == before and not (curve / "c.png").exists()
