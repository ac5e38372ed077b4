"""``python -m train.export`` of a PilotNet run (``model.pt``, not an SB3 zip): the extra training seeds of
``pilotnet`` (checkpoints/reference/seeds/pilotnet/s<k>) are exported this way, as ppo_turn's are."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.test_nothing_lost import REF, cli, snapshot


@pytest.fixture
def runs(tmp_path, monkeypatch):
    """A stand-in for checkpoints/reference/ (copies of pilotnet and ppo_turn), which the tools take for the
    shipped folder, and a finished PilotNet run (the reference's model.pt and config.yaml) beside it."""
    import av_gym.references
    import eval.agents  # noqa: F401 - its REFERENCE is taken at import: imported first here, it kept the stand-in

    root = tmp_path / "reference"
    for name in ("pilotnet", "ppo_turn"):
        shutil.copytree(REF / name, root / name)
    monkeypatch.setattr(av_gym.references, "reference_root", lambda: root)
    run = tmp_path / "checkpoints" / "pilotnet_s3"
    run.mkdir(parents=True)
    for name in ("model.pt", "config.yaml"):
        shutil.copy2(REF / "pilotnet" / name, run / name)
    return {"root": root, "run": run}


def test_a_pilotnet_run_is_exported_as_a_seed_of_the_reference(runs):
    """The run's model.pt was refused ("model.zip does not exist"); now it is copied byte for byte with its config
    and COMMAND, and python -m eval drives from the exported folder as from the run."""
    from train.export import main

    dest = runs["root"] / "seeds" / "pilotnet" / "s3"
    main([str(runs["run"]), str(dest), "--overwrite-reference", "--command", "python -m train agent=pilotnet seed=3"])
    assert sorted(p.name for p in dest.iterdir()) == ["COMMAND", "config.yaml", "model.pt"]
    assert (dest / "model.pt").read_bytes() == (runs["run"] / "model.pt").read_bytes()
    assert (dest / "config.yaml").read_text() == (runs["run"] / "config.yaml").read_text()
    assert (dest / "COMMAND").read_text() == "python -m train agent=pilotnet seed=3\n"
    assert _steering(dest) == _steering(runs["run"])


def _steering(folder: Path) -> float:
    """The steering the checkpoint in ``folder`` gives on the first observation of held-out lap 1000, loaded as
    ``python -m eval agents=[<folder>]`` loads it."""
    from av_gym.make import make_env
    from eval.agents import compose_group, plan_agent, resolve_agent

    plan = plan_agent(str(folder), "lane_keeping", {}, compose_group("shield", "none"), "checkpoints")
    env = make_env(compose_group("env", "lane_keeping"), plan.sensors, plan.shield)
    obs, _ = env.reset(seed=1000)
    action = resolve_agent(plan.spec, env, "lane_keeping", "checkpoints")[1].act(obs)
    env.close()
    return float(np.asarray(action).ravel()[0])


@pytest.mark.parametrize("extra, needle", [
    (["--best"], "--best: a run of agent.kind=pilotnet keeps one model.pt, already its best validation epoch"),
    ([], "is the shipped reference agent 'pilotnet'"),  # the flag is still needed
])
def test_a_pilotnet_export_refuses_what_it_cannot_do_in_one_line(extra, needle, runs, capsys):
    from train.export import main

    before = snapshot(runs["root"])
    line = cli(main, [str(runs["run"]), str(runs["root"] / "pilotnet"), "--command", "x", *extra], capsys)
    assert needle in line, line
    assert snapshot(runs["root"]) == before


def test_a_pilotnet_run_is_not_exported_over_another_kind_or_from_a_damaged_file(runs, tmp_path, capsys):
    from train.export import main

    before = snapshot(runs["root"])
    line = cli(main, [str(runs["run"]), str(runs["root"] / "ppo_turn"), "--command", "x", "--overwrite-reference"],
               capsys)
    assert "holds 'ppo_turn' with env.name=left_turn, this checkpoint has env.name=lane_keeping" in line, line
    (runs["run"] / "model.pt").write_bytes((runs["run"] / "model.pt").read_bytes()[:5000])  # a copy cut short
    line = cli(main, [str(runs["run"]), str(tmp_path / "out")], capsys)
    assert f"{runs['run'] / 'model.pt'}: " in line, line
    assert snapshot(runs["root"]) == before and not (tmp_path / "out").exists()


def test_an_export_into_a_reference_lookalike_of_yours_says_named_agents_do_not_read_it(runs, tmp_path, capsys):
    """``train.export <run> checkpoints/reference/pilotnet`` in a project of yours (not the shipped folder) writes
    the folder as any other, and says that ``agents=[pilotnet]`` still means the shipped reference (R6 finding 1:
    it was read under that name)."""
    from train.export import lookalike_note, main

    dest = tmp_path / "proj" / "checkpoints" / "reference" / "pilotnet"
    main([str(runs["run"]), str(dest)])
    out = capsys.readouterr().out
    assert (dest / "model.pt").read_bytes() == (runs["run"] / "model.pt").read_bytes()
    assert f"is not a shipped reference ({runs['root']}/...): named agents (agents=[pilotnet]) do not read it; " \
           f"evaluate it by its path, agents=[{dest}]" in out, out
    assert lookalike_note(runs["root"] / "seeds" / "pilotnet" / "s3") is None  # the shipped folder: no note
    assert lookalike_note(tmp_path / "proj" / "checkpoints" / "pilotnet_s3") is None
