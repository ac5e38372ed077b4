"""The PID gain search (train/pid_search.py) and the ``tuned`` preset it produced."""

from __future__ import annotations

import pytest

from agents.pid import PRESETS
from train import pid_search


def test_search_on_a_tiny_grid_returns_the_best_gains():
    res = pid_search.search(pid_search.GRIDS["quick"], seeds=[0], track="A", refine=0, log=lambda *_: None)
    assert res["evaluations"] == 4 and res["grid_evaluations"] == 4
    b = res["best"]
    assert b["kp"] in (0.75, 1.5) and b["ki"] == 1e-4 and b["kd"] in (1.0, 4.0)
    assert res["objective"] == min(r["objective"] for r in res["top"]) < float("inf")
    assert res["mean_abs_cte_units"] > 0


def test_search_refuses_evaluation_seeds():
    from av_gym.seeds import SPLITS

    for split in ("validation", "test"):  # a search tunes: train seeds only (av_gym/seeds.py)
        with pytest.raises(ValueError, match="train split"):
            pid_search.search(pid_search.GRIDS["quick"], seeds=[SPLITS[split].start], refine=0)


def test_tuned_preset_matches_its_yaml_and_beats_the_paper_on_a_training_seed():
    from eval.agents import load_agent_config

    cfg = load_agent_config("pid_tuned")  # composed: conf/agent/pid_tuned.yaml over the pid kind's defaults
    assert {k: cfg[k] for k in ("kp", "ki", "kd")} == PRESETS["tuned"]
    assert cfg["sensors"] == "truth" and cfg["kind"] == "pid"
    env = pid_search.lane_env("A")
    paper, tuned = (pid_search.run_laps(env, PRESETS[name], [0])[0] for name in ("paper", "tuned"))
    assert paper["lap_completed"] == tuned["lap_completed"] == 1.0
    assert tuned["cte_mean_abs_units"] < paper["cte_mean_abs_units"]
