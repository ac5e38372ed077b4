"""``python -m eval vec_env=batched agents=[always_proceed] sensors=turn_perceived`` ran always_proceed on the batch's
own truth features and results.md recorded turn_truth, while the same command per env ran and recorded
turn_perceived (prober R4, item 8). always_proceed reads no observation, so the batch now runs it on the sensors
chosen for it when it can (eval.batched.batch_sensors): both engines run and record the preset asked for. The
command's default preset (truth, which the batch has no form of) is no choice and still gives the batch's own
features; a preset the batch cannot run is still refused."""

from __future__ import annotations

import pytest

from conf.check import check_command_line
from conf.commands import EvalCommand
from eval.__main__ import _plans
from tests.test_bad_input import check_line


def _sensors(*argv: str) -> dict:
    (cfg,) = check_command_line("eval", ["agents=[always_proceed,always_proceed+aeb]", *argv])
    return {p.label: p.sensors for p in _plans(cfg, EvalCommand.of(cfg))}


@pytest.mark.parametrize("engine", [["vec_env=batched"], []], ids=["batched", "per_env"])
def test_a_chosen_preset_is_what_both_engines_run_and_record(engine):
    ran = _sensors("sensors=turn_perceived", "sensors.detector.miss_rate=0.2", *engine)
    assert {label: (s["name"], s["detector"]["miss_rate"]) for label, s in ran.items()} == \
        {"always_proceed@turn_perceived(detector.miss_rate=0.2)": ("turn_perceived", 0.2),
         "always_proceed@turn_perceived(detector.miss_rate=0.2)+aeb": ("turn_perceived", 0.2)}


def test_the_default_preset_gives_the_batchs_own_features_and_an_unbatchable_one_is_refused(tmp_path, monkeypatch,
                                                                                           capsys):
    from eval.batched import NO_OBS_SENSORS

    assert set(map(lambda s: s["name"], _sensors("vec_env=batched").values())) == {NO_OBS_SENSORS["name"]}
    monkeypatch.chdir(tmp_path)
    line = check_line("eval", ["vec_env=batched", "sensors=cameras", "agents=[always_proceed]"], monkeypatch, capsys)
    assert line.startswith("error: agent 'always_proceed': sensors.cameras is not available with vec_env=batched"), line


@pytest.mark.slow  # three python -m eval processes on the batch and per env (~25 CPU-s)
def test_the_chosen_preset_changes_the_record_not_the_episodes(tmp_path):
    """On the same seeds the batch's rows of always_proceed (and +aeb: the shield has its own perception) are the
    same whichever sensors it is given, and results.md records the preset it ran on; per env, the same
    outcomes."""
    import csv

    from tests.conftest import cli

    common = ["agents=[always_proceed,always_proceed+aeb]", "episodes=6", "split=validation", "progress_bar=false",
              "videos=false"]
    runs = {"default": ["vec_env=batched", "n_envs=6"], "perceived": ["vec_env=batched", "n_envs=6",
                                                                      "sensors=turn_perceived"],
            "per_env": ["sensors=turn_perceived", "n_envs=1"]}
    rows, md = {}, {}
    for name, extra in runs.items():
        res = cli("eval", *common, *extra, f"out_dir={tmp_path / name}", cwd=tmp_path)
        assert res.returncode == 0, res.stderr[-2000:]
        rows[name] = list(csv.DictReader(open(tmp_path / name / "results.csv")))
        md[name] = (tmp_path / name / "results.md").read_text()
    episodes = lambda rs: [{k: v for k, v in r.items() if k != "agent"} for r in rs]  # noqa: E731 - labels
    assert episodes(rows["perceived"]) == episodes(rows["default"])  # differ: always_proceed@turn_perceived
    outcome = ("agent", "seed", "collision", "success", "truncated", "interventions")
    assert [{k: r[k] for k in outcome} for r in rows["per_env"]] == \
        [{k: r[k] for k in outcome} for r in rows["perceived"]]
    assert "turn_perceived" in md["perceived"] and "turn_perceived" not in md["default"]
