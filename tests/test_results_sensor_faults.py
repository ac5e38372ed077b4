"""The episodes' ``sensor_faults`` (non-finite sensor entries the guard replaced, av_gym/sensors/base.py) reach the
results: a results.csv column, and in results.md and the results page one note line per run naming the agents whose
episodes had any; a clean run's pages, and the shipped result folders (written before the column), are unchanged
(closing note of 2026-11-30: info["sensor_faults"] had no consumer)."""

from __future__ import annotations

import csv
import json
import shutil
import sys
from pathlib import Path

import pytest

from eval.report import faults_note, write_results
from eval.results_page import load_folder, page

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ROOT / "docs" / "results" / "left_turn_always_proceed_aeb"


def _rows(faults: dict[str, list[float]]) -> list[dict]:
    return [{"agent": agent, "episode": i, "seed": 2_000_000 + i, "collision": 0.0, "success": 1.0,
             "time_to_exit_s": 9.0 + i, "min_ttc_s": 3.0, "interventions": 0.0, "sensor_faults": f}
            for agent, values in faults.items() for i, f in enumerate(values)]


def test_results_md_names_the_agents_whose_episodes_had_sensor_faults(tmp_path):
    rows = _rows({"clean": [0.0, 0.0, 0.0], "faulty": [0.0, 4.0, 2.0]})
    write_results(rows, tmp_path, "left_turn", "t")
    md = (tmp_path / "results.md").read_text()
    assert ("Sensor faults (non-finite readings replaced and marked invalid, `sensor_faults` in results.csv): "
            "`faulty` 6 in 2 of 3 episodes.") in md
    assert "`clean`" not in md.split("Sensor faults", 1)[1]
    with open(tmp_path / "results.csv", newline="") as f:
        assert [float(r["sensor_faults"]) for r in csv.DictReader(f)] == [0, 0, 0, 0, 4, 2]


def test_a_run_without_faults_and_old_rows_without_the_column_add_no_note(tmp_path):
    assert faults_note(_rows({"a": [0.0, 0.0]})) == ""
    old = [{k: v for k, v in r.items() if k != "sensor_faults"} for r in _rows({"a": [0.0]})]
    assert faults_note(old) == ""
    write_results(_rows({"a": [0.0, 0.0]}), tmp_path, "left_turn", "t")
    assert "Sensor faults" not in (tmp_path / "results.md").read_text()


def test_the_results_page_notes_faults_in_the_folder_section_not_the_headline(tmp_path):
    folder = tmp_path / SHIPPED.name
    shutil.copytree(SHIPPED, folder)  # a shipped folder (no sensor_faults column), then the same with faults
    with open(SHIPPED / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert "sensor_faults" not in rows[0]
    clean = page([load_folder(SHIPPED)])
    rows[0]["sensor_faults"] = "3.0"
    for r in rows[1:]:
        r["sensor_faults"] = "0.0"
    with open(folder / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    faulty = page([load_folder(folder)])
    agent = rows[0]["agent"]
    assert f"`{agent}` 3 in 1 of " in faulty and "Sensor faults" not in clean
    head = lambda text: text[: text.index("<!-- results:end -->")]  # noqa: E731 - the README's block
    assert head(faulty) == head(clean)


@pytest.mark.slow  # ~2.4 s: python -m eval's Hydra composition
def test_eval_says_the_runs_sensor_faults_in_meta_json_and_on_the_terminal(tmp_path, monkeypatch, capsys):
    from eval import __main__ as eval_main

    def run_agent(plan, command, env_cfg, seeds, rows) -> None:  # stand-in episodes: the faults are the point
        rows += [{"agent": plan.label, "episode": i, "seed": s, "collision": 0.0, "success": 1.0,
                  "sensor_faults": 5.0 if (plan.label, i) == ("gap_acceptance", 1) else 0.0}
                 for i, s in enumerate(seeds)]

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(eval_main, "_run_agent", run_agent)
    monkeypatch.setattr(sys, "argv", ["eval", "agents=[always_proceed,gap_acceptance]", "split=validation",
                                      "episodes=2", "out_dir=out", "progress_bar=false", "hydra.run.dir=hydra"])
    eval_main.main()
    assert json.loads((tmp_path / "out" / "meta.json").read_text())["sensor_faults"] == 5
    note = "`gap_acceptance` 5 in 1 of 2 episodes."
    assert note in capsys.readouterr().out and note in (tmp_path / "out" / "results.md").read_text()
