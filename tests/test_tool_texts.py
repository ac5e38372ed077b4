"""What the side tools say and write (prober R7, finding 5): ``python -m eval.sweep`` refusals are one line with
exit status 2 (as every command's bad input), ``best.json`` is strict JSON (``null``, not bare ``NaN``) and reads
back, and the note on a lookalike ``checkpoints/reference/<name>`` is said once."""

from __future__ import annotations

import csv
import json
import math
import runpy
import sys

import pytest
import yaml


def _sweep_refusal(argv: list[str], monkeypatch, capsys) -> str:
    """``python -m eval.sweep <argv>``: its one stderr line (exit status 2 asserted)."""
    monkeypatch.setattr(sys, "argv", ["eval.sweep", *argv])
    monkeypatch.delitem(sys.modules, "eval.sweep", raising=False)  # as under `python -m`, a fresh module
    with pytest.raises(SystemExit) as exit_:
        runpy.run_module("eval.sweep", run_name="__main__", alter_sys=False)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == 2 and len(err) == 1 and err[0].startswith("error: "), (exit_.value.code, err)
    return err[0]


def _job(root, overrides: list[str]) -> None:
    (root / ".hydra").mkdir(parents=True)
    (root / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (root / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"env": {"name": "left_turn"}}))
    with open(root / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["agent", "episode", "seed", "collision", "success"])
        writer.writeheader()
        writer.writerow({"agent": "always_proceed", "episode": 0, "seed": 1000000, "collision": 1, "success": 0})


@pytest.mark.parametrize("case, args, needle", [
    ("missing", [], "is not a folder"),
    ("empty", [], "has results.csv"),
    ("jobs", ["--metric", "colision"], "metric 'colision' is not in the jobs' results.csv"),
    ("jobs", ["--x", "seed"], "--x 'seed' was not swept"),
])
def test_sweep_refusals_exit_2_in_one_line(tmp_path, monkeypatch, capsys, case, args, needle):
    root = tmp_path / "sweep"
    if case != "missing":
        root.mkdir()
    if case == "jobs":
        for num, p in enumerate((0.1, 0.2)):
            _job(root / str(num), [f"env.spawn_probability={p}"])
    assert needle in _sweep_refusal([str(root), "--no-plot", *args], monkeypatch, capsys)


def test_best_json_is_strict_json_and_reads_back(tmp_path):
    from train.callbacks import best_json, read_best_score

    def strict(text: str):  # what jq or JavaScript accept: no NaN / Infinity tokens
        return json.loads(text, parse_constant=lambda token: pytest.fail(f"{token} in best.json"))

    text = best_json({"score": 0.25, "steps": 512, "ttc_min_s": math.nan, "time_to_exit_s": math.inf,
                      "collision": 0.5})
    assert strict(text) == {"score": 0.25, "steps": 512, "ttc_min_s": None, "time_to_exit_s": None,
                            "collision": 0.5}
    path = tmp_path / "best.json"
    path.write_text(text)
    assert read_best_score(path) == 0.25
    path.write_text(best_json({"score": math.nan, "steps": 0}))
    assert read_best_score(path) == -math.inf  # a score without a value: any evaluation beats it
    path.write_text('{"score": NaN, "steps": 0}')  # written before: Python's bare NaN
    assert read_best_score(path) == -math.inf
    assert read_best_score(tmp_path / "none.json") == -math.inf


def test_the_lookalike_note_is_said_once(tmp_path, monkeypatch, capsys):
    """The command-line check and the job both find the checkpoint; the note was printed by each."""
    from eval import agents

    monkeypatch.setattr(agents, "_NOTED", set())
    local, shipped = tmp_path / "checkpoints" / "reference" / "ppo_turn", tmp_path / "shipped" / "ppo_turn"
    local.mkdir(parents=True)
    shipped.mkdir(parents=True)
    for _ in range(2):
        agents._note_lookalike(local, shipped)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and "is not the shipped reference 'ppo_turn'" in lines[0], lines
    agents._note_lookalike(shipped, shipped)  # the checkout from its root: one folder, nothing said
    assert not capsys.readouterr().err
