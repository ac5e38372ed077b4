"""A project folder's own ``checkpoints/reference/<agent>`` (an export of yours, say) never stands in for the
shipped references (R6 finding 1): a named agent (``pilotnet``, ``ppo_turn``) is always the harness's reference,
and yours is evaluated by its path, its row labelled with that path. In the checkout, run from its root, the
working folder's ``checkpoints/reference`` is the shipped one itself."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

MARKER = b"not the shipped pilotnet: a user's 1-epoch model"


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A user's project folder (the working folder) with ``checkpoints/reference/pilotnet`` of its own: the
    shipped config beside a marker model, and no ppo_turn."""
    from eval.agents import REFERENCE

    own = tmp_path / "checkpoints" / "reference" / "pilotnet"
    own.mkdir(parents=True)
    shutil.copy2(REFERENCE / "pilotnet" / "config.yaml", own / "config.yaml")
    (own / "model.pt").write_bytes(MARKER)
    monkeypatch.chdir(tmp_path)
    return own


def test_a_named_agent_is_the_shipped_reference_not_the_working_folders(project, capsys):
    from eval.agents import REFERENCE, find_checkpoint, plan_agent

    shipped = REFERENCE / "pilotnet" / "model.pt"
    assert shipped.read_bytes() != MARKER
    assert find_checkpoint("pilotnet", "lane_keeping", "checkpoints") == shipped
    plan = plan_agent("pilotnet", "lane_keeping", {"name": "cameras"}, {"name": "none"}, "checkpoints")
    assert (Path(plan.spec), plan.label) == (shipped, "pilotnet")
    assert "checkpoints/reference/pilotnet/ is not the shipped reference 'pilotnet'" in capsys.readouterr().err
    # one local reference folder hid every other shipped one ("no shipped reference checkpoint for 'ppo_turn'")
    turn = plan_agent("ppo_turn", "left_turn", {"name": "truth"}, {"name": "none"}, "checkpoints")
    assert Path(turn.spec) == REFERENCE / "ppo_turn" / "model.zip"


def test_your_reference_folder_is_evaluated_by_its_path_and_labelled_so(project):
    from eval.agents import plan_agent

    plan = plan_agent("checkpoints/reference/pilotnet", "lane_keeping", {"name": "cameras"}, {"name": "none"},
                      "checkpoints")
    assert (plan.spec, plan.label) == ("checkpoints/reference/pilotnet", "checkpoints/reference/pilotnet")


def test_in_the_checkout_the_working_folders_reference_is_the_shipped_one(monkeypatch, capsys):
    from eval.agents import REFERENCE, find_checkpoint

    if REFERENCE.parent.name != "checkpoints":
        pytest.skip("an installed wheel: its references are inside the package, no working folder holds them")
    monkeypatch.chdir(REFERENCE.parent.parent)
    found = find_checkpoint("pilotnet", "lane_keeping", "checkpoints")
    assert found.resolve() == (REFERENCE / "pilotnet" / "model.pt").resolve()
    assert capsys.readouterr().err == ""  # the same folder (compared resolved): no note


def test_a_preset_that_starts_from_a_reference_reads_the_shipped_one_from_any_folder(project):
    """``dagger_turn_perceived`` starts from the truth student (``init_from``): from a user's project folder (with
    a ``checkpoints/reference`` of its own) it is the harness's ``dagger_turn``, not a path under the working
    folder (which was missing there, or the user's own)."""
    from agents.registry import agent_params
    from eval.agents import REFERENCE, load_agent_config

    params = agent_params(load_agent_config("dagger_turn_perceived"))
    assert Path(params.init_from) == REFERENCE / "dagger_turn" and Path(params.init_from).is_absolute()
