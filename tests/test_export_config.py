"""``python -m train.export`` writes a config that names no machine's folder: a run of a preset starting from a
shipped reference (``agent.init_from: ${av_gym_reference:dagger_turn}``, conf/agent/dagger_turn_perceived.yaml)
records the resolved absolute path in its config.yaml (training writes the resolved config); the export writes the
interpolation back, which every install resolves to its own references (train.export.portable_config)."""

from __future__ import annotations

import shutil
from pathlib import Path

import yaml
from omegaconf import OmegaConf

from av_gym.references import reference_root
from tests.test_nothing_lost import ROOT
from train.export import export_reference, portable_config


def _run_config(init_from: str) -> str:
    """A resolved run config.yaml as training writes it, its agent starting from ``init_from``."""
    agent = {"name": "dagger_turn_perceived", "kind": "dagger", "init_from": init_from, "rounds": 6}
    return OmegaConf.to_yaml(OmegaConf.create({"env": {"name": "left_turn"}, "agent": agent, "seed": 1}))


def test_an_export_of_a_run_from_a_shipped_reference_keeps_the_interpolation(tmp_path):
    """The composed preset's config as training writes it (the absolute path of this install's dagger_turn), then
    exported from another folder: the exported config.yaml holds ``${av_gym_reference:dagger_turn}``, no absolute
    path of this install, and resolves to this install's reference; every other line as the run wrote it."""
    from conf.check import check_command_line

    (cfg,) = check_command_line("train", ["agent=dagger_turn_perceived", "run_name=X"])
    run = tmp_path / "run"
    run.mkdir()
    text = OmegaConf.to_yaml(cfg, resolve=True)  # train/__main__.py _claim_folders
    assert f"init_from: {reference_root() / 'dagger_turn'}\n" in text
    (run / "config.yaml").write_text(text)
    shutil.copyfile(reference_root() / "dagger_turn_perceived" / "model.zip", run / "model.zip")
    export_reference(run, tmp_path / "out" / "d")
    exported = (tmp_path / "out" / "d" / "config.yaml").read_text()
    assert str(reference_root()) not in exported and "site-packages" not in exported
    assert exported.splitlines() == [line.replace(str(reference_root() / "dagger_turn"),
                                                  "${av_gym_reference:dagger_turn}") for line in text.splitlines()]
    assert OmegaConf.create(yaml.safe_load(exported)).agent.init_from == str(reference_root() / "dagger_turn")


def test_only_an_init_from_inside_the_shipped_references_is_rewritten(tmp_path, monkeypatch):
    """A model file inside a reference, and the checkout's relative form from its root, become the interpolation;
    a run of the user's and a look-alike ``checkpoints/reference/dagger_turn`` of the user's project are theirs:
    the text byte for byte, as is a config with no init_from or one already an interpolation."""
    monkeypatch.chdir(ROOT)
    model = _run_config(str(reference_root() / "dagger_turn" / "model.zip"))
    assert "init_from: ${av_gym_reference:dagger_turn/model.zip}\n" in portable_config(model)
    if reference_root().resolve() == (Path(ROOT) / "checkpoints" / "reference").resolve():  # a checkout
        relative = portable_config(_run_config("checkpoints/reference/dagger_turn"))
        assert "init_from: ${av_gym_reference:dagger_turn}\n" in relative
    monkeypatch.chdir(tmp_path)
    (tmp_path / "checkpoints" / "reference" / "dagger_turn").mkdir(parents=True)
    for init_from in ("checkpoints/reference/dagger_turn", str(tmp_path / "checkpoints" / "my_run"), "null"):
        text = _run_config(init_from).replace("'null'", "null")
        assert portable_config(text) == text
    text = _run_config("${av_gym_reference:dagger_turn}")
    assert portable_config(text) == text


def test_no_shipped_reference_config_names_a_machines_folder():
    """The shipped configs (the named agents and their extra seeds) hold no absolute path of a checkout or an
    install: dagger_turn_perceived_scale and its seeds recorded paths.runs/checkpoints=/work/main/... (provenance
    only, their text mended; their COMMAND says so)."""
    configs = sorted(reference_root().glob("**/config.yaml"))
    assert len(configs) > 40
    found = [f"{path.relative_to(reference_root())}:{n}: {line.strip()}" for path in configs
             for n, line in enumerate(path.read_text().splitlines(), 1)
             if any(s in line for s in ("/work/", "site-packages", str(ROOT)))]
    assert not found, found
