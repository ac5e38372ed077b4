"""A row's label says what ran (eval/labels.py): a shield given by the command line's ``shield=`` and sensor fields
changed by ``sensors.*`` are in it, as ``+aeb`` in the spec is, in results.csv, results.md and the results page
(R7 finding 3: ``agents=[always_proceed] shield=aeb`` wrote its shielded rows as ``always_proceed``, and the page
showed them at collision 0.000 beside the shipped unshielded 0.495). Without such a change the label is the spec."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import pytest

from eval.agents import compose_group, plan_agent
from eval.results_page import load_folder, method_of, page, trained

SHIELD_OFF, AEB = compose_group("shield", "none"), compose_group("shield", "aeb")
TRUTH, PERCEIVED = compose_group("sensors", "truth"), compose_group("sensors", "turn_perceived")
MISSING = {**PERCEIVED, "detector": {**PERCEIVED["detector"], "miss_rate": 0.5}}


def _label(spec: str, sensors: dict, shield: dict) -> str:
    return plan_agent(spec, "left_turn", sensors, shield, "checkpoints").label


def test_the_command_lines_shield_and_sensor_changes_are_in_the_label():
    assert _label("always_proceed", TRUTH, AEB) == "always_proceed+aeb"
    assert _label("always_proceed", TRUTH, {**AEB, "mode": "perceived"}) == "always_proceed+aeb(mode=perceived)"
    assert _label("always_proceed+aeb", TRUTH, {**AEB, "mode": "perceived"}) == "always_proceed+aeb(mode=perceived)"
    assert _label("gap_acceptance@turn_perceived", MISSING, SHIELD_OFF) == \
        "gap_acceptance@turn_perceived(detector.miss_rate=0.5)"
    assert _label("always_proceed", PERCEIVED, SHIELD_OFF) == "always_proceed@turn_perceived"  # not its default


def test_a_spec_run_as_it_says_keeps_its_label():
    for spec, sensors, shield in (("always_proceed", TRUTH, SHIELD_OFF), ("always_proceed+aeb", TRUTH, SHIELD_OFF),
                                  ("gap_acceptance@turn_perceived", PERCEIVED, SHIELD_OFF),
                                  ("gap_acceptance", TRUTH, SHIELD_OFF),  # its own turn_truth, sensors= left out
                                  ("always_proceed+aeb", TRUTH, AEB)):
        plan = plan_agent(spec, "left_turn", sensors, shield, "checkpoints")
        assert (plan.label, plan.given) == (spec, spec)


def test_the_results_page_reads_the_labels_parts():
    seed = "checkpoints/reference/seeds/ppo_turn/s2@turn_perceived(detector.miss_rate=0.5)+aeb"
    assert method_of(seed) == "ppo_turn@turn_perceived(detector.miss_rate=0.5)+aeb" and trained(seed)
    assert trained("ppo_turn(detector.miss_rate=0.5)") and not trained("always_proceed+aeb(mode=perceived)")


@pytest.mark.slow  # ~10 s: python -m eval's Hydra composition and 2 left-turn episodes per agent
def test_eval_writes_the_label_to_results_csv_results_md_and_the_page(tmp_path, monkeypatch):
    from eval import __main__ as eval_main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["eval", "agents=[always_proceed,gap_acceptance@turn_perceived]", "shield=aeb",
                                      "sensors=turn_perceived", "sensors.detector.miss_rate=0.5",
                                      "split=validation", "episodes=2", "out_dir=out", "progress_bar=false",
                                      "videos=false", "hydra.run.dir=hydra"])
    eval_main.main()
    out = tmp_path / "out"
    want = ["always_proceed@turn_perceived(detector.miss_rate=0.5)+aeb",
            "gap_acceptance@turn_perceived(detector.miss_rate=0.5)+aeb"]
    with open(out / "results.csv", newline="") as f:
        assert list(dict.fromkeys(r["agent"] for r in csv.DictReader(f))) == want
    md = (out / "results.md").read_text()
    meta = json.loads((out / "meta.json").read_text())
    (out / "meta.json").write_text(json.dumps({**meta, "commit": meta.get("commit") or "0" * 40}))
    text = page([load_folder(out)])
    for label in want:
        assert f"| {label} | 2 |" in md and f"| {label} |" in text


def test_a_sweep_keeps_one_line_per_agent_over_the_values_its_labels_name(tmp_path):
    """python -m eval.sweep: a label naming the swept value (``+aeb(detector.miss_rate=0.1)``) would make each value
    an agent of its own, one point per line; the swept parts are dropped (the table has their column)."""
    import yaml

    from eval.sweep import sweep_report

    for num, rate in enumerate((0.1, 0.2)):
        job = tmp_path / str(num)
        (job / ".hydra").mkdir(parents=True)
        (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(
            ["agents=[always_proceed]", "shield=aeb", "shield.mode=perceived", f"shield.detector.miss_rate={rate}"]))
        rows = [{"agent": f"always_proceed+aeb(detector.miss_rate={rate}, mode=perceived)", "episode": i,
                 "seed": 1_000_000 + i, "collision": float(i), "success": 1.0} for i in range(2)]
        with open(job / "results.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    result = sweep_report(tmp_path, metrics=["collision"], plot=False)
    assert [(line["shield.detector.miss_rate"], line["agent"]) for line in result["summary"]] == \
        [(0.1, "always_proceed+aeb(mode=perceived)"), (0.2, "always_proceed+aeb(mode=perceived)")]
