"""What ``import av_gym`` gives a user's own Python: its documented submodules reachable as attributes."""

from __future__ import annotations

import subprocess
import sys

import pytest


def test_presets_are_reachable_right_after_import_av_gym(tmp_path):
    """README: ``av_gym.presets.preset_names("sensors")`` after a bare ``import av_gym``, in a fresh process (this
    one has imported ``av_gym.presets`` through other tests already), from a folder that is not the checkout."""
    code = "import av_gym; print(av_gym.presets.preset_names('sensors'))"
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "'turn_perceived'" in res.stdout and "'cameras'" in res.stdout


def test_a_name_that_is_no_submodule_is_an_attribute_error():
    import av_gym

    with pytest.raises(AttributeError, match="no attribute 'not_a_module'"):
        av_gym.not_a_module  # noqa: B018
    assert not hasattr(av_gym, "_private")


def test_a_mistyped_env_key_names_the_closest_one():
    """README: ``env=`` is checked before anything is built, an unknown key refused with the closest known one."""
    import gymnasium as gym

    import av_gym
    from av_gym.errors import ConfigError

    with pytest.raises(ConfigError) as info:
        gym.make(av_gym.ENV_IDS["left_turn"], env={"spawn_probabilty": 0.3})
    assert str(info.value).startswith("env.spawn_probabilty is not a field of env=left_turn; allowed: [")
    assert str(info.value).endswith("; did you mean 'spawn_probability'?")
    with pytest.raises(ConfigError, match=r"allowed: \['dt', 'ego_speed_kmh', 'target_speed_kmh'\]$"):
        gym.make(av_gym.ENV_IDS["left_turn"], env={"ccftap": {"zzz": 1}})  # nothing close: the list alone
