"""``agent=dagger_turn_perceived_scale``: the perceived student on the batch with rounds growing 1.5x (docs/dagger.md,
"The perceived student at scale"). Its shipped seeds were trained as ``agent=dagger_turn_perceived_batch
agent.round_growth=1.5 agent.rounds=7`` before the preset existed; the preset must stay that recipe."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from tests.test_dagger import _cfg

ROOT = Path(__file__).resolve().parent.parent
REF = ROOT / "checkpoints" / "reference"
FOLDERS = ["dagger_turn_perceived_scale", *(f"seeds/dagger_turn_perceived_scale/s{s}" for s in (2, 3, 4, 5))]
SWEPT = (0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95)  # the thresholds each seed's operating point was chosen from


def test_the_scale_preset_is_the_batch_preset_with_growing_rounds():
    """The preset adds exactly the two fields of the recipe (and its name) to ``dagger_turn_perceived_batch``, and
    its rounds drive 192 ... 2,187 episodes, 6,177 in all (4x the batch preset's 8 x 192)."""
    from agents.dagger import DaggerParams

    scale = _cfg("agent=dagger_turn_perceived_scale", "seed=1")
    batch = _cfg("agent=dagger_turn_perceived_batch", "seed=1", "agent.round_growth=1.5", "agent.rounds=7",
                 "agent.name=dagger_turn_perceived_scale")
    for section in ("env", "sensors", "shield", "agent"):
        assert OmegaConf.to_container(scale[section], resolve=True) == OmegaConf.to_container(batch[section],
                                                                                              resolve=True), section
    params = DaggerParams.from_mapping(OmegaConf.to_container(scale.agent, resolve=True), where="agent")
    assert params.round_sizes() == [192, 288, 432, 648, 972, 1458, 2187] and sum(params.round_sizes()) == 6177


@pytest.mark.parametrize("folder", FOLDERS)
def test_the_scale_preset_is_the_recipe_of_its_shipped_students(folder):
    """``agent=dagger_turn_perceived_scale`` composes the env, sensors and agent sections each shipped seed was
    trained with (its config.yaml), every field but the operating point, which each seed's go_threshold records
    (one of the swept thresholds; the preset keeps the training runs' 0.9)."""
    saved = yaml.safe_load((REF / folder / "config.yaml").read_text())
    cfg = _cfg("agent=dagger_turn_perceived_scale", f"seed={saved['seed']}")
    composed = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in ("env", "sensors", "agent")}
    assert saved["agent"]["go_threshold"] in SWEPT and composed["agent"]["go_threshold"] == 0.9
    saved["agent"]["go_threshold"] = composed["agent"]["go_threshold"]
    for section in composed:
        assert composed[section] == saved[section], section
    assert saved["agent"]["round_growth"] == 1.5 and saved["agent"]["rounds"] == 7
