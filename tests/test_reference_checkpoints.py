"""The committed reference checkpoints (checkpoints/reference/): each carries the command and config that made it,
fits the env stack its config describes, and the lane keepers drive a held-out lap as docs/agents.md reports."""

from __future__ import annotations

from importlib import resources

import pytest
import yaml

from av_gym.make import make_env
from eval.agents import check_plan, compose_group, plan_agent, resolve_agent
from eval.runner import run_episodes

REF = resources.files("conf").parent / "checkpoints" / "reference"
SB3_REFS = sorted(p.name for p in REF.iterdir() if (p / "model.zip").is_file())
# extra training seeds a multi-seed row needs: reference/seeds/<name>/s<seed>/ (the reference itself is the other seed),
# each with its kind's model file (an SB3 zip, or PilotNet's model.pt)
MODELS = ("model.zip", "model.pt")
SEED_REFS = sorted(str(p.relative_to(REF)) for p in REF.glob("seeds/*/s*") if any((p / m).is_file() for m in MODELS))
NAMED = ("dagger_turn", "dagger_turn_memory", "dagger_turn_perceived", "dagger_turn_perceived_batch",
         "dagger_turn_perceived_scale", "dagger_turn_soft", "pilotnet", "ppo_lane_camera", "ppo_lane_localized",
         "ppo_turn", "ppo_turn_perceived", "ppo_turn_shielded")


def _env_and_policy(name: str):
    saved = yaml.safe_load((REF / name / "config.yaml").read_text())
    env_name = saved["env"]["name"]
    model = next(m for m in MODELS if (REF / name / m).is_file())
    plan = plan_agent(str(REF / name / model), env_name, {}, compose_group("shield", "none"), "checkpoints")
    check_plan(plan, env_name)
    env = make_env(saved["env"], plan.sensors, plan.shield)
    return env, resolve_agent(plan.spec, env, env_name, "checkpoints")[1]


def test_every_reference_checkpoint_is_listed():
    assert {"ppo_turn", "ppo_turn_shielded", "ppo_turn_perceived", "ppo_lane_localized",
            "ppo_lane_camera"} <= set(SB3_REFS)


def test_reference_holds_the_named_agents_and_a_name_means_one_folder():
    """checkpoints/reference/ = the named agents plus seeds/, each folder the agent its config names (the name an
    eval spec says: ``pilotnet`` is ``reference/pilotnet/``)."""
    assert sorted(p.name for p in REF.iterdir() if p.is_dir()) == sorted([*NAMED, "seeds"])
    names = [yaml.safe_load((REF / n / "config.yaml").read_text())["agent"]["name"] for n in NAMED]
    assert names == list(NAMED)
    for seed in SEED_REFS:  # each extra seed belongs to a named agent and says which seed it is
        name, s = seed.split("/")[1:]
        saved = yaml.safe_load((REF / seed / "config.yaml").read_text())
        assert saved["agent"]["name"] == name and f"s{saved['seed']}" == s
    assert SEED_REFS == ["seeds/dagger_turn/s2", "seeds/dagger_turn/s3", "seeds/dagger_turn/s4", "seeds/dagger_turn/s5",
                         "seeds/dagger_turn_memory/s1", "seeds/dagger_turn_memory/s3", "seeds/dagger_turn_memory/s4",
                         "seeds/dagger_turn_memory/s5", "seeds/dagger_turn_perceived/s2",
                         "seeds/dagger_turn_perceived/s3", "seeds/dagger_turn_perceived/s4",
                         "seeds/dagger_turn_perceived/s5", "seeds/dagger_turn_perceived_batch/s2",
                         "seeds/dagger_turn_perceived_batch/s3", "seeds/dagger_turn_perceived_batch/s4",
                         "seeds/dagger_turn_perceived_batch/s5", "seeds/dagger_turn_perceived_scale/s2",
                         "seeds/dagger_turn_perceived_scale/s3", "seeds/dagger_turn_perceived_scale/s4",
                         "seeds/dagger_turn_perceived_scale/s5", "seeds/dagger_turn_soft/s1",
                         "seeds/dagger_turn_soft/s3",
                         "seeds/pilotnet/s1", "seeds/pilotnet/s2", "seeds/pilotnet/s3",
                         "seeds/pilotnet/s4", "seeds/ppo_turn/s2", "seeds/ppo_turn/s3",
                         "seeds/ppo_turn/s4", "seeds/ppo_turn/s5", "seeds/ppo_turn_perceived/s2",
                         "seeds/ppo_turn_perceived/s3", "seeds/ppo_turn_perceived/s4", "seeds/ppo_turn_perceived/s5",
                         "seeds/ppo_turn_shielded/s2", "seeds/ppo_turn_shielded/s3",
                         "seeds/ppo_turn_shielded/s4", "seeds/ppo_turn_shielded/s5"]


# the extra seeds are the named agents' kinds again (~0.15 s each to load and build an env): the named SB3 ones and
# one PilotNet seed (its model.pt: the kind SB3_REFS lacks) run in the fast suite, the other seeds in the slow one
@pytest.mark.parametrize("name", SB3_REFS + [pytest.param(s, marks=() if s == "seeds/pilotnet/s1" else pytest.mark.slow)
                                             for s in SEED_REFS])
def test_a_reference_checkpoint_has_its_command_and_fits_its_env(name):
    command = (REF / name / "COMMAND").read_text()
    assert "python -m train" in command
    env, policy = _env_and_policy(name)  # raises if the saved observation space does not match the stack
    obs, _ = env.reset(seed=1000)
    assert env.action_space.contains(policy.act(obs))


@pytest.mark.slow  # 7-11 CPU-s on a clean clone: kept out of the README's 5-minute test command
@pytest.mark.parametrize("name", ["ppo_lane_camera", "ppo_lane_localized"])
def test_a_reference_lane_keeper_drives_a_held_out_lap(name):
    env, policy = _env_and_policy(name)
    (row,) = run_episodes(env, policy, [1000], name, progress=False)
    assert row["lap_completed"] == 1.0 and row["lane_departures"] == 0
    assert row["cte_mean_abs_m"] < 0.15  # docs/agents.md, seeds 1000-1019: 0.037 m (camera), 0.087 m (localized)
