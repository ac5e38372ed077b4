"""benchmarks/partition.py --chain (docs/dagger.md, "What sensing costs"): the steps between neighbours are the
differences of their rates on the same seeds, they add up to the first agent's edge over the last, and so do
their shares (to 1)."""

from __future__ import annotations

import csv
import subprocess
import sys
from collections import defaultdict

from tests.documented_commands import ROOT

ROWS = ROOT / "docs" / "results" / "left_turn_partition" / "results.csv"
CHAIN = ("lookahead", "belief_lookahead", "dagger_turn", "ppo_turn")


def test_the_chain_adds_up_to_the_first_agents_edge():
    res = subprocess.run([sys.executable, "benchmarks/partition.py", str(ROWS), "--chain", *CHAIN, "--resamples",
                          "200"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    sums: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    counts: dict[str, int] = defaultdict(int)
    for row in csv.DictReader(ROWS.open()):
        counts[row["agent"]] += 1
        for metric in ("success", "collision"):
            sums[row["agent"]][metric] += float(row[metric])
    mean = {a: {m: v / counts[a] for m, v in r.items()} for a, r in sums.items()}
    table = [line for line in res.stdout.splitlines() if line.startswith("|")]
    width = len(table[0].strip("|").split("|"))
    assert width == 3 * len(CHAIN) and len(table[1].strip("|").split("|")) == width
    n = len(CHAIN)
    for metric, sign in (("success", 1.0), ("collision", -1.0)):
        (line,) = [t for t in table if t.startswith(f"| {metric} ")]
        cells = [c.strip().split()[0] for c in line.strip("|").split("|")]
        edge = float(cells[n + 1])
        steps = [float(c) for c in cells[n + 2: 2 * n + 1]]
        shares = [float(c) for c in cells[2 * n + 1:]]
        for (a, b), step in zip(zip(CHAIN, CHAIN[1:]), steps):
            assert abs(step - sign * (mean[a][metric] - mean[b][metric])) < 1e-3
        assert abs(edge - sum(steps)) < 2e-3 and abs(sum(shares) - 1.0) < 0.02


def test_a_chain_of_one_agent_is_one_line():
    res = subprocess.run([sys.executable, "benchmarks/partition.py", str(ROWS), "--chain", "lookahead"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0 and "--chain" in res.stderr


def test_an_agent_without_rows_is_one_line_naming_what_the_files_hold():
    res = subprocess.run([sys.executable, "benchmarks/partition.py", str(ROWS), "--chain", "lookahead+aeb",
                          "belief_lookahead"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    line = res.stderr.strip()
    assert res.returncode == 2 and line.count("\n") == 0 and line.startswith("error: no rows for lookahead+aeb ")
    assert "lookahead, " in line and res.stdout == ""
