"""benchmarks/partition.py on the committed partition rows (docs/dagger.md, "Information vs learning"): the shares it
prints are the differences of the agents' rates on the same seeds, and the two parts add up to the edge."""

from __future__ import annotations

import csv
import subprocess
import sys
from collections import defaultdict

from tests.documented_commands import ROOT

ROWS = ROOT / "docs" / "results" / "left_turn_partition" / "results.csv"
STUDENTS = ("dagger_turn", "dagger_turn_memory", "ppo_turn")


def test_the_partition_adds_up_to_the_oracles_edge():
    res = subprocess.run([sys.executable, "benchmarks/partition.py", str(ROWS), "--students", *STUDENTS,
                          "--resamples", "200"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    rates: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    counts: dict[str, int] = defaultdict(int)
    for row in csv.DictReader(ROWS.open()):
        counts[row["agent"]] += 1
        for metric in ("success", "collision"):
            rates[row["agent"]][metric] += float(row[metric])
    mean = {a: {m: v / counts[a] for m, v in r.items()} for a, r in rates.items()}
    lines = {tuple(c.strip() for c in line.strip("|").split("|")[:2]): line
             for line in res.stdout.splitlines() if line.startswith(tuple(f"| {s} " for s in STUDENTS))}
    for student in STUDENTS:
        cells = [c.strip() for c in lines[(student, "success")].strip("|").split("|")]
        edge, info, learning = (float(cells[i].split()[0]) for i in (5, 6, 7))
        assert abs(info - (mean["lookahead"]["success"] - mean["belief_lookahead"]["success"])) < 1e-3
        assert abs(learning - (mean["belief_lookahead"]["success"] - mean[student]["success"])) < 1e-3
        assert abs(edge - (info + learning)) < 2e-3
