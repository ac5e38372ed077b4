"""`python -m eval.ccftap`: the shield's ``inf`` "not yet" sentinel (``av_gym.shields.aeb.NOT_YET``) reaches the
rows and the table as NaN / '–', never as ``inf``."""

from __future__ import annotations

import csv
import math

import pytest

# 20 km/h ego, 30 km/h target: at dt=-1.5 s the shield brakes but the ego never comes to a standstill (outcome
# 'b', a cell of the shipped grid); at dt=3 s it never brakes.
GRID = ["--variants", "none,improved", "--modes", "ground_truth", "--ego", "20", "--target", "30", "--dts=-1.5,3",
        "--workers", "1", "--plot-case", "20,30,-1.5"]


def test_number_maps_the_not_yet_sentinel_and_none_to_nan():
    from av_gym.shields.aeb import NOT_YET
    from eval.ccftap import _number

    assert math.isnan(_number(NOT_YET)) and math.isnan(_number(math.inf)) and math.isnan(_number(None))
    assert _number(3.8) == 3.8 and _number(-0.5) == -0.5


@pytest.mark.slow  # 2-3 CPU-s: four episodes
def test_braked_but_not_stopped_case_reads_no_stop_and_nan_times(tmp_path, capsys):
    from eval.ccftap import main

    assert main([*GRID, "--out", str(tmp_path)]) == 0
    with open(tmp_path / "results.csv") as f:
        rows = {(r["variant"], float(r["dt"])): r for r in csv.DictReader(f)}
    braked = rows[("improved", -1.5)]
    assert braked["intervention"] == "1" and braked["collision"] == "0" and braked["outcome"] == "brake_safe"
    assert braked["stop_line_offset_m"] == "nan"  # never stood still
    assert math.isfinite(float(braked["brake_time_s"]))
    for key in (("improved", 3.0), ("none", -1.5), ("none", 3.0)):  # never braked: no brake time
        assert rows[key]["brake_time_s"] == "nan", key
    table = (tmp_path / "results.md").read_text()
    assert "inf" not in table.replace("info", "")
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| always_proceed | improved"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[8] == "0" and cells[10] == "–", cells  # braking stops 0, stop offset '–' (was 1 | +inf (+inf))
