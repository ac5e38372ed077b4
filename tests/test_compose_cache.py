"""conf.check.composed: each command line composed once per process (the fast suite composed the same ones again
and again), handed out as a copy equal to a fresh composition, with what Hydra reads from the moment (the working
folder) as of the call: a caller's edits never reach the next caller."""

from __future__ import annotations

from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from conf.check import composed

ARGV = ["agent=gap_acceptance", "seed=3"]


def _plain(cfg) -> dict:
    out = OmegaConf.to_container(cfg, resolve=False)
    out["hydra"]["runtime"].pop("cwd")
    return out


def test_a_cached_composition_is_a_fresh_copy_of_hydras(tmp_path, monkeypatch):
    with initialize_config_module("conf", version_base="1.3"):
        fresh = compose(config_name="train", overrides=ARGV, return_hydra_config=True)
        first = composed(compose, "train", ARGV)
        first.seed = 99  # a caller's edit (check_command_line deletes hydra, fills placeholders)
        first.agent.sensors = "cameras"
        monkeypatch.chdir(tmp_path)
        again = composed(compose, "train", ARGV)
    assert _plain(again) == _plain(fresh) and again.seed == 3 and again.agent.sensors == "turn_truth"
    assert again.hydra.runtime.cwd == str(tmp_path) != fresh.hydra.runtime.cwd
