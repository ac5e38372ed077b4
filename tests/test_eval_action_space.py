"""``python -m eval`` refuses an agent whose actions the env does not take before any episode, in one line naming
the agent, the ``env.action`` given and the values it drives (R7 finding 7: always_proceed's rows were written, then
gap_acceptance's first step failed with "action 2 is not in the action space Box(...)")."""

from __future__ import annotations

import pytest

from av_gym.errors import ConfigError
from conftest import ccftap_cfg, cli, conf
from eval.agents import check_action_space, compose_group, plan_agent


def _plan(spec: str):
    return plan_agent(spec, "left_turn", compose_group("sensors", "turn_truth"), compose_group("shield", "none"),
                      "checkpoints")


def test_an_agent_of_meta_actions_is_refused_on_continuous_actions_naming_what_it_drives():
    env = ccftap_cfg(15, 45, 0.0, "continuous")
    with pytest.raises(ConfigError) as err:
        check_action_space(_plan("gap_acceptance"), env, "checkpoints")
    assert str(err.value) == ("agent 'gap_acceptance' cannot drive env.action=continuous: action 2 is not in the "
                              "action space Box(-1.0, 1.0, (1,), float32): expected shape (1,), got (); it drives "
                              "env.action=discrete")
    check_action_space(_plan("always_proceed"), env, "checkpoints")  # the env's cruise action: either
    check_action_space(_plan("gap_acceptance"), conf("env", "left_turn"), "checkpoints")  # discrete: fine


def test_eval_refuses_before_any_row(tmp_path):
    out = tmp_path / "out"
    res = cli("eval", "env=left_turn", "env.mode=ccftap", "env.action=continuous",
              "agents=[always_proceed,gap_acceptance]", "episodes=1", "progress_bar=false", f"out_dir={out}",
              cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().splitlines() == [
        "error: agent 'gap_acceptance' cannot drive env.action=continuous: action 2 is not in the action space "
        "Box(-1.0, 1.0, (1,), float32): expected shape (1,), got (); it drives env.action=discrete"]
    assert not out.exists()  # always_proceed, listed first, wrote nothing
