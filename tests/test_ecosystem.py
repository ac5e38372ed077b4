"""Every stack fits the ecosystem: the library's presets equal Hydra's composition, Gymnasium's ``check_env`` passes
on every sensors preset with and without every shield, and SB3's ``MultiInputPolicy`` trains on every preset (the
camera stacks through :class:`~av_gym.wrappers.FlatDictObservation`, as the README says)."""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import av_gym  # noqa: F401 - registers the ids
from av_gym.errors import ConfigError
from av_gym.presets import compose_group, preset_names
from av_gym.wrappers import FlatDictObservation

TURN, LANE = "av_gym/UnprotectedLeftTurn-v0", "av_gym/LaneKeepingLap-v0"
SHORT = {TURN: {"duration": 2.0}, LANE: {"time_limit": 2.0}}
SCENARIO_ONLY = {"turn_truth": TURN, "turn_perceived": TURN, "turn_truth_memory": TURN, "turn_perceived_memory": TURN,
                 "lane_localized": LANE}  # the rest run on both


def stacks() -> list[tuple[str, str, str]]:
    """(env id, sensors, shield) of every preset on the scenarios it is for; shields on the left turn only."""
    out = []
    for sensors in preset_names("sensors"):
        for env_id in (TURN, LANE):
            if SCENARIO_ONLY.get(sensors, env_id) == env_id:
                out += [(env_id, sensors, shield) for shield in preset_names("shield")
                        if env_id == TURN or shield == "none"]
    return out


@pytest.mark.parametrize("group", ["env", "sensors", "shield"])
def test_the_library_composes_each_preset_as_hydra_does(group):
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    with initialize_config_module("conf", version_base="1.3"):
        for name in preset_names(group):
            hydra = OmegaConf.to_container(compose(config_name="eval", overrides=[f"{group}={name}"])[group],
                                           resolve=True)
            assert compose_group(group, name) == hydra, f"{group}={name}"


def fast_or_slow(env_id: str, sensors: str, shield: str):
    """The stacks that differ in kind run in the fast suite: every sensors preset without a shield (a preset made
    for both scenarios on the lane-keeping lap, the cameras on the left turn too: another scene to render), every
    shield on the perceived left-turn stack (the shield reads its own detector and tracker there) and everything at
    once on the left turn (full + aeb); the other stacks (~28 s of check_env) are slow."""
    unshielded = shield == "none" and (env_id == LANE or sensors in SCENARIO_ONLY or sensors == "cameras")
    fast = unshielded or sensors == "turn_perceived" or (sensors, shield) == ("full", "aeb")
    return pytest.param(env_id, sensors, shield, marks=() if fast else pytest.mark.slow)


@pytest.mark.parametrize("env_id,sensors,shield", [fast_or_slow(*s) for s in stacks()],
                         ids=lambda v: v.split("/")[-1])
def test_check_env_passes(env_id, sensors, shield):
    env = gym.make(env_id, sensors=sensors, shield=shield, env=SHORT[env_id])
    if compose_group("shield", shield).get("second_opinion", "none") != "none":
        # the library has no planner: a shield asking for one says so until its owner installs one (the harness's
        # eval.agents.make_eval_env, or a user's own code as here)
        with pytest.raises(ConfigError, match="is the harness's planner and none is installed"):
            env.reset(seed=0)
        env.close()
        env = gym.make(env_id, sensors=sensors, shield=shield, env=SHORT[env_id])
        from agents.belief import PlannerOpinion
        from av_gym.shields.aeb import find_shield

        find_shield(env).opinion = PlannerOpinion()
        if "intent" not in env.observation_space.spaces:
            with pytest.raises(ConfigError, match=r"reads obs\['intent'\]"):
                env.reset(seed=0)
            return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # its advice (float32 bounds, render modes) is not a failure
        check_env(env, skip_render_check=True)
    env.close()


def test_the_shield_reports_no_nan_in_info():
    """``aeb_brake_time`` / ``aeb_stop_position`` are inf until they happen (NaN != NaN failed check_env; None beside
    a float failed Gymnasium's vector envs), and finite once the shield has braked."""
    env = gym.make(TURN, sensors="turn_truth", shield="aeb", env={"mode": "ccftap"})
    _, info = env.reset(seed=0)
    seen = []
    for _ in range(200):
        _, _, terminated, truncated, info = env.step(2)  # FASTER: drive into the oncoming car's path
        seen.append(info["aeb_brake_time"])
        assert not any(isinstance(v, float) and np.isnan(v) for v in info.values() if not isinstance(v, dict))
        if terminated or truncated:
            break
    assert seen[0] == math.inf and math.isfinite(seen[-1])  # the shield braked, and said when


def test_lane_keeping_refuses_a_shield_in_one_line():
    with pytest.raises(ConfigError, match="left_turn scenario only"):
        gym.make(LANE, sensors="truth", shield="aeb")


@pytest.mark.slow  # 20 presets x one 64-step PPO update, 1-10 s each (cameras render three images per step)
@pytest.mark.parametrize("env_id,sensors", sorted({(e, s) for e, s, _ in stacks()}), ids=lambda v: v.split("/")[-1])
def test_sb3_multi_input_policy_learns_on_every_preset(env_id, sensors):
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(env_id, n_envs=1, seed=0, wrapper_class=FlatDictObservation,
                        env_kwargs={"sensors": sensors, "env": SHORT[env_id]})
    model = PPO("MultiInputPolicy", venv, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu")
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(64)
    assert model.num_timesteps == 64
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters()))  # it took a gradient step
    venv.close()


def test_no_shipped_model_names_a_harness_module():
    """SB3 pickles the features extractor's class into model.zip and imports its module again at load; a module
    of the harness (``agents.attention``) then imported a user's own ``agents`` package in their project."""
    import base64
    import json
    import re
    import zipfile

    from av_gym.references import reference_root

    named = {}
    for path in sorted(reference_root().rglob("model.zip")):
        data = json.loads(zipfile.ZipFile(path).read("data"))
        for key, value in data.items():
            if isinstance(value, dict) and ":serialized:" in value:
                found = re.findall(rb"\b(agents|train|eval|conf)\.\w+", base64.b64decode(value[":serialized:"]))
                if found:
                    named[f"{path.relative_to(reference_root())}:{key}"] = sorted({f.decode() for f in found})
    assert named == {}
