"""`python -m eval.ccftap --agents ...`: the CCFtap grid for any agent, on a two-case grid."""

from __future__ import annotations

import csv

import gymnasium as gym
import pytest
import yaml

GRID = ["--variants", "none,improved", "--modes", "ground_truth", "--ego", "15", "--target", "45", "--dts", "0,3",
        "--workers", "1", "--plot-case", "15,45,0"]
SAME = ("variant", "mode", "ego_kmh", "target_kmh", "dt", "collision", "intervention", "stop_line_offset_m",
        "min_oncoming_gap_m", "time_to_exit_s", "unnecessary", "outcome")


def _rows(path) -> list[dict]:
    with open(path / "results.csv") as f:
        return list(csv.DictReader(f))


@pytest.fixture
def tiny_ppo(tmp_path):
    """An untrained go/yield PPO checkpoint on the turn_truth features, saved the way train/ saves one."""
    from stable_baselines3 import PPO

    from agents.ppo import sb3_space
    from av_gym.make import make_env
    from eval.agents import compose_group
    from eval.ccftap import env_config

    sensors = compose_group("sensors", "turn_truth")
    env = make_env(env_config(15, 45, 0.0), sensors, None)

    class Spaces(gym.Env):
        observation_space = sb3_space(env.observation_space)
        action_space = gym.spaces.Discrete(2)

    env.close()
    model = PPO("MultiInputPolicy", Spaces(), n_steps=8, batch_size=8, policy_kwargs={"net_arch": [8]}, device="cpu")
    folder = tmp_path / "ckpt" / "tiny_turn"
    folder.mkdir(parents=True)
    model.save(folder / "model.zip")
    cfg = {"env": {"name": "left_turn"}, "sensors": sensors,
           "agent": {"name": "tiny_turn", "kind": "ppo", "actions": "go_yield", "action_repeat": 5}}
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    return folder


@pytest.mark.slow  # 7-15 CPU-s: keeps the README's fast command under 5 min on 2 cores
def test_agents_column_and_always_proceed_rows_unchanged(tmp_path, tiny_ppo):
    import eval.ccftap as ccftap

    assert ccftap.main([*GRID, "--out", str(tmp_path / "default")]) == 0
    default = _rows(tmp_path / "default")
    assert {r["agent"] for r in default} == {"always_proceed"} and len(default) == 4

    ccftap._POLICIES.clear()
    agents = f"always_proceed,always_proceed@turn_truth,{tiny_ppo}"
    assert ccftap.main([*GRID, "--agents", agents, "--checkpoints", str(tmp_path / "ckpt"),
                        "--out", str(tmp_path / "multi")]) == 0
    rows = _rows(tmp_path / "multi")
    labels = ["always_proceed", "always_proceed@turn_truth", str(tiny_ppo)]
    assert [r["agent"] for r in rows] == [x for x in labels for _ in range(4)]  # agent-major, 2 configs × 2 cases
    by_agent = {a: [{k: r[k] for k in SAME} for r in rows if r["agent"] == a] for a in labels}
    old = [{k: r[k] for k in SAME} for r in default]
    assert by_agent["always_proceed"] == old
    assert by_agent["always_proceed@turn_truth"] == old  # other sensors, same driver: same outcomes
    assert len(by_agent[str(tiny_ppo)]) == 4
    # the checkpoint was loaded once for its 4 runs (sensors turn_truth, from its config.yaml)
    loaded = [k for k in ccftap._POLICIES if k[0] == str(tiny_ppo)]
    assert len(loaded) == 1 and '"name": "turn_truth"' in loaded[0][1]

    md = (tmp_path / "multi" / "results.md").read_text()
    assert "| always_proceed | improved | ground_truth | 2 | 0 |" in md
    assert "## always_proceed@turn_truth: improved / ground_truth" in md
    for name in ("grid.png", "timeline.png"):
        assert (tmp_path / "multi" / name).is_file()


@pytest.mark.parametrize("agents, message", [
    ("no_such_agent", "agent 'no_such_agent' is not in conf/agent/"),
    ("ppo_turn:latest", "you have no ppo_turn run for env 'left_turn'"),  # plain ppo_turn: the shipped reference
    ("always_proceed+aeb", "the shield comes from --variants"),
    ("always_proceed,always_proceed", "is given twice"),
])
def test_bad_agent_fails_fast_with_one_line(tmp_path, capsys, agents, message):
    from eval.ccftap import main

    out = tmp_path / "out"
    assert main([*GRID, "--agents", agents, "--checkpoints", str(tmp_path / "empty"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and err.startswith("error: ") and "\n" not in err
    assert not out.exists()  # nothing run, nothing written
