"""Agents: PID maths, always-proceed, and a smoke episode of every env × every agent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from stable_baselines3 import PPO

from agents import AlwaysProceed, PIDSteering, Policy
from agents.ppo import SB3Policy
from av_gym.errors import ConfigError
from conftest import conf, rollout
from eval.agents import load_agent_config, resolve_agent


def obs(cte):
    return {"state": np.array([cte], dtype=np.float32)}


def test_pid_per_step_form_matches_paper_equation():
    pid = PIDSteering(kp=0.75, ki=0.0001, kd=1.0)
    u1 = pid.act(obs(0.4))[0]  # first step: no derivative
    assert u1 == pytest.approx(-(0.75 * 0.4 + 0.0001 * 0.4), rel=1e-6)
    u2 = pid.act(obs(0.6))[0]
    assert u2 == pytest.approx(-(0.75 * 0.6 + 0.0001 * 1.0 + 1.0 * 0.2), rel=1e-6)


def test_pid_clips_and_does_not_wind_up_while_saturated():
    pid = PIDSteering(kp=0.75, ki=0.01, kd=0.0)
    for _ in range(200):
        assert pid.act(obs(5.0))[0] == -1.0
    # After long saturation the integral did not grow, so back at the centre the output is ~0, not stuck at -1.
    assert abs(pid.act(obs(0.0))[0]) < 0.1


def test_pid_rejects_nan_cte():
    with pytest.raises(ValueError, match="non-finite CTE"):
        PIDSteering().act(obs(float("nan")))


def test_pid_reset_forgets_history():
    pid = PIDSteering()
    pid.act(obs(1.0))
    pid.reset()
    assert pid.act(obs(0.5))[0] == pytest.approx(PIDSteering().act(obs(0.5))[0])


def test_always_proceed_repeats_the_cruise_action(make, turn_cfg):
    env = make(dict(turn_cfg, action="continuous"))
    a = env.unwrapped.cruise_action()
    assert env.unwrapped.action_type.get_action(a)["acceleration"] == pytest.approx(0.0, abs=1e-6)
    assert AlwaysProceed(1).act(None) == 1


def _agents_for(scenario):
    return [p for p in ("pid_paper", "always_proceed", "ppo") if scenario in load_agent_config(p)["scenarios"]]


@pytest.mark.parametrize("scenario", ["lane_keeping", "left_turn"])
def test_smoke_episode_every_env_and_agent(make, scenario, tmp_path):
    env_cfg = conf("env", scenario)
    for name in _agents_for(scenario):
        env = make(env_cfg)
        if name == "ppo":  # an untrained policy exercises the same load/predict path as a checkpoint
            model = PPO("MultiInputPolicy", env, n_steps=64, batch_size=32, seed=0, device="cpu")
            model.save(tmp_path / "model.zip")
            label, policy = resolve_agent(str(tmp_path / "model.zip"), env, scenario, tmp_path)
            assert isinstance(policy, SB3Policy)
        else:
            label, policy = resolve_agent(name, env, scenario, tmp_path)
        assert isinstance(policy, Policy)
        truths, info, terminated, truncated = rollout(env, policy, seed=0)
        assert terminated or truncated
        assert set(info["episode_metrics"]) >= {"return", "length"}
        assert all(np.isfinite(t["x"]) and np.isfinite(t["y"]) for t in truths)


def test_every_shipped_agent_config_is_its_kinds_params():
    """conf/agent/<name>.yaml composed (its kind's Params defaults + what the file changes) is a valid Params of
    its kind (agents/registry.py), and a plain file holds only what differs from those defaults."""
    import yaml

    from agents.configs import AGENT_DIR, available_agents, kind_default
    from agents.registry import AGENT_KINDS, agent_params

    for name in available_agents():
        params = agent_params(load_agent_config(name))
        assert params.name == name and type(params) is AGENT_KINDS.get(params.kind).Params
        raw = yaml.safe_load((AGENT_DIR / f"{name}.yaml").read_text())
        if kind_default(raw):  # not a _global_ variant: every value it sets differs from the kind's default
            defaults = AGENT_KINDS.get(kind_default(raw)).Params().as_dict()
            same = [k for k, v in raw.items() if k not in ("defaults", "name") and defaults.get(k) == v]
            assert same == [], (name, same)


def test_a_named_agent_resolves_to_its_own_reference_folder_whatever_the_file_times(tmp_path):
    import os

    from eval.agents import find_checkpoint

    ref = tmp_path / "reference"  # a stand-in for the shipped references

    def folder(name: str, agent_name: str, mtime: float):
        d = tmp_path / "reference" / name
        d.mkdir(parents=True)
        (d / "config.yaml").write_text(f"env: {{name: left_turn}}\nagent: {{kind: ppo, name: {agent_name}}}\n")
        (d / "model.zip").write_bytes(b"")
        os.utime(d / "model.zip", (mtime, mtime))
        return d / "model.zip"

    own = folder("ppo_turn", "ppo_turn", 1_000.0)
    folder("ppo_turn_v2_s1", "ppo_turn", 2_000.0)  # another round of the same agent, written later by git
    folder("seeds/ppo_turn/s2", "ppo_turn", 3_000.0)  # an extra training seed (the layout that says so)
    assert find_checkpoint("ppo", "left_turn", tmp_path, reference=ref, name="ppo_turn") == own
    with pytest.raises(ConfigError, match="you have no ppo_turn run"):  # :latest never falls back to the reference
        find_checkpoint("ppo", "left_turn", tmp_path, reference=ref, name="ppo_turn", latest=True)
    # a run you trained yourself does not change what the name means; ppo_turn:latest is that run (the newest)
    for i, run_name in enumerate(("old_run", "my_run")):
        run = tmp_path / run_name
        run.mkdir()
        (run / "config.yaml").write_text("env: {name: left_turn}\nagent: {kind: ppo, name: ppo_turn}\n")
        (run / "model.zip").write_bytes(b"")
        os.utime(run / "model.zip", (5_000.0 + i, 5_000.0 + i))
    assert find_checkpoint("ppo", "left_turn", tmp_path, reference=ref, name="ppo_turn") == own
    latest = find_checkpoint("ppo", "left_turn", tmp_path, reference=ref, name="ppo_turn", latest=True)
    assert latest == run / "model.zip"
    with pytest.raises(ConfigError, match="no shipped reference checkpoint for 'ppo_turn_v9'.*ppo_turn_v9:latest"):
        find_checkpoint("ppo", "left_turn", tmp_path, reference=ref, name="ppo_turn_v9")


def test_a_bare_kind_is_your_newest_run_else_an_error_naming_the_references_of_that_kind(tmp_path):
    """``pilotnet`` (a kind with a reference folder of its name) is that folder whatever you trained; ``ppo`` (a
    kind several references share) is your newest run of it on the env, never one reference picked by its name."""
    import os

    from eval.agents import find_checkpoint

    ref = tmp_path / "reference"  # a stand-in for the shipped references

    def folder(path: str, kind: str, name: str, env: str = "left_turn", mtime: float = 1_000.0):
        d = tmp_path / path
        d.mkdir(parents=True)
        (d / "config.yaml").write_text(f"env: {{name: {env}}}\nagent: {{kind: {kind}, name: {name}}}\n")
        model = d / ("model.pt" if kind == "pilotnet" else "model.zip")
        model.write_bytes(b"")
        os.utime(model, (mtime, mtime))
        return model

    pilotnet = folder("reference/pilotnet", "pilotnet", "pilotnet", env="lane_keeping")
    for name in ("ppo_turn_shielded", "ppo_turn", "ppo_turn_perceived"):
        folder(f"reference/{name}", "ppo", name)
    folder("reference/ppo_lane_camera", "ppo", "ppo_lane_camera", env="lane_keeping")
    with pytest.raises(ConfigError, match=r"no ppo checkpoint of your own for env 'left_turn'.*a kind, not a named "
                                          r"agent.*\(ppo_turn, ppo_turn_perceived, ppo_turn_shielded\)"):
        find_checkpoint("ppo", "left_turn", tmp_path, reference=ref)
    mine = folder("my_run", "ppo", "ppo", mtime=2_000.0)
    folder("older_run", "ppo", "ppo_turn", mtime=1_500.0)
    folder("my_lap", "pilotnet", "pilotnet", env="lane_keeping", mtime=3_000.0)
    assert find_checkpoint("ppo", "left_turn", tmp_path, reference=ref) == mine
    assert find_checkpoint("pilotnet", "lane_keeping", tmp_path, reference=ref) == pilotnet
    latest = find_checkpoint("pilotnet", "lane_keeping", tmp_path, reference=ref, latest=True)
    assert latest == tmp_path / "my_lap" / "model.pt"
    with pytest.raises(ConfigError, match=r"pilotnet drives \['lane_keeping'\], not env=left_turn"):
        find_checkpoint("pilotnet", "left_turn", tmp_path, reference=ref)


def test_the_shipped_pilotnet_is_the_folder_of_its_name():
    from eval.agents import REFERENCE, find_checkpoint

    assert find_checkpoint("pilotnet", "lane_keeping", "no_such_folder") == REFERENCE / "pilotnet" / "model.pt"


def test_latest_spec_plans_the_newest_run_and_labels_its_row(tmp_path):
    """`ppo_turn` and `ppo_turn:latest` are two rows with two labels: the reference and your newest run."""
    import shutil

    from eval.agents import REFERENCE, plan_agent

    root = tmp_path / "checkpoints"
    shutil.copytree(REFERENCE / "seeds" / "ppo_turn" / "s2", root / "my_run")
    ref = plan_agent("ppo_turn", "left_turn", {"name": "truth"}, {"name": "none"}, root)
    mine = plan_agent("ppo_turn:latest+aeb", "left_turn", {"name": "truth"}, {"name": "none"}, root)
    assert Path(ref.spec) == REFERENCE / "ppo_turn" / "model.zip" and ref.label == "ppo_turn"
    assert Path(mine.spec).parent.name == "my_run" and mine.label == "ppo_turn:latest+aeb"
    with pytest.raises(ConfigError, match="rule-based"):
        plan_agent("gap_acceptance:latest", "left_turn", {"name": "truth"}, {"name": "none"}, root)
