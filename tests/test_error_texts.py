"""Four one-line refusals whose text was wrong (R6 finding 3): each names the field or file and says what is
allowed, not an unrelated cause (a pickle, [Errno 22], an out-of-range seed, a vectorization mode)."""

from __future__ import annotations

import math
import shutil
import sys
from importlib import resources

import gymnasium as gym
import pytest

from agents.pilotnet import load_checkpoint
from av_gym.errors import run_cli
from av_gym.seeds import seeds

PILOTNET = resources.files("conf").parent / "checkpoints" / "reference" / "pilotnet" / "model.pt"


@pytest.mark.parametrize("damage", ["text", "truncated"])
def test_a_damaged_checkpoint_is_named_as_not_readable(tmp_path, damage):
    bad = tmp_path / "model.pt"
    if damage == "text":
        bad.write_text("garbage")
    else:
        bad.write_bytes(PILOTNET.read_bytes()[:20_000])
    with pytest.raises(ValueError) as err:
        load_checkpoint(bad)
    line = str(err.value)
    assert line.startswith(f"{bad} is not a readable checkpoint") and "\n" not in line
    assert "Python objects" not in line and "Errno" not in line
    shutil.copyfile(PILOTNET, bad)
    assert load_checkpoint(bad)["format"]  # a whole one still loads


def test_too_many_episodes_names_episodes_not_the_seed():
    with pytest.raises(ValueError) as err:
        seeds("validation", 2_000_000)
    line = str(err.value)
    assert "give episodes <= 1000000" in line and "give seed in that range" not in line
    with pytest.raises(ValueError, match=r"give episodes <= 10 \(.*\), or an earlier seed"):
        seeds("validation", 100, first=1_999_990)
    with pytest.raises(ValueError, match="give seed in that range"):  # a seed outside the split: the seed is wrong
        seeds("validation", 5, first=1000)


def test_a_bad_value_to_make_vec_has_no_vectorization_mode_hint():
    import av_gym  # noqa: F401  (registers the ids)

    with pytest.raises(ValueError) as err:
        gym.make_vec("av_gym/UnprotectedLeftTurn-v0", num_envs=2,
                     sensors={"name": "turn_perceived", "detector": {"miss_rate": math.nan}})
    line = str(err.value)
    assert line.startswith("sensors.detector.miss_rate must be a number in [0, 1), got nan")
    assert "vectorization_mode" not in line
    with pytest.raises(ValueError, match='vectorization_mode="sync"'):  # what the batch cannot run keeps it
        gym.make_vec("av_gym/UnprotectedLeftTurn-v0", num_envs=2, sensors={"name": "turn_perceived", "lidar": {}})


def test_a_camera_override_without_a_camera_preset_says_to_add_one(monkeypatch, capsys):
    import eval.__main__ as main

    monkeypatch.setattr(sys, "argv", ["eval", "env=lane_keeping", "agents=[pilotnet]",
                                      "sensors.cameras.noise.blur_sigma=-1"])
    with pytest.raises(SystemExit) as exit_:
        run_cli(main._check_command_line)
    lines = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert exit_.value.code == 2 and len(lines) == 1, lines
    assert "sensors.cameras is not a field of sensors=truth" in lines[0]
    assert "add the agent's sensors preset, e.g. sensors=cameras" in lines[0]
