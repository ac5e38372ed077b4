"""One way in for each value: a shield reads its parameters from its Params (never a copy on
itself), takes a second opinion as an object through :class:`av_gym.shields.Opinion` (no harness name inside the
library), and :func:`find_shield` is importable where the docs name it."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import pytest

from av_gym.errors import ConfigError
from av_gym.shields.aeb import AEB_VARIANTS
from conftest import ccftap_cfg

TURN = "av_gym/UnprotectedLeftTurn-v0"


# ----------------------------------------------------------------------------------------------- shields
def test_find_shield_and_the_opinion_protocol_come_from_av_gym_shields():
    import av_gym.shields
    import av_gym.shields.aeb
    from av_gym.shields import Opinion, find_shield

    assert find_shield is av_gym.shields.aeb.find_shield
    assert sorted(av_gym.shields.__all__) == ["Opinion", "find_shield"]
    env = gym.make(TURN, shield="aeb")
    assert find_shield(env).p.ttc_brake == 1.5 and find_shield(gym.make(TURN)) is None
    assert isinstance(Opinion, type)
    with pytest.raises(AttributeError, match="has no attribute 'nothing'"):
        av_gym.shields.nothing  # noqa: B018


@pytest.mark.parametrize("variant", AEB_VARIANTS.names())
def test_a_shield_keeps_no_copy_of_its_parameters(variant):
    """Every field of a variant's Params is read from ``shield.p``: none is an attribute of the shield itself, so
    a new parameter is written once (its Params field) and cannot drift from a copy."""
    from av_gym.make import make_env

    env = make_env(ccftap_cfg(15, 45, 0.0), None, {"kind": "aeb", "variant": variant})
    shield = env.env  # EpisodeMetrics → the shield
    # (``detector``/``tracker`` name the shield's own sensor and tracker, built from those sections: not copies)
    copies = [k for k in type(shield).Params.field_names()
              if k in vars(shield) and vars(shield)[k] == getattr(shield.p, k)]
    assert type(shield).variant == variant and copies == []
    assert shield.params is shield.p and shield.ttc_brake == shield.p.ttc_brake


def test_an_object_that_is_not_an_opinion_is_refused_naming_what_it_lacks():
    from av_gym.shields import find_shield

    shield = find_shield(gym.make(TURN, shield="aeb"))

    class Half:
        def reset(self) -> None: ...

    with pytest.raises(TypeError, match=r"opinion must have reset\(\), observe\(env, obs\) and go_is_safe\(env\) "
                                        r"\(av_gym.shields.Opinion\), got Half without observe, go_is_safe"):
        shield.opinion = Half()
    shield.opinion = None  # taking it away is allowed


# a user's own opinion, from user code in a folder whose conf/agents/train/eval packages refuse to be imported: the
# library must neither need nor load the harness for a shield that asks for a second opinion
USER_CODE = """
import sys, gymnasium as gym, av_gym
from av_gym.errors import ConfigError
from av_gym.shields import find_shield

class AlwaysSafe:
    def __init__(self): self.asked = 0
    def reset(self): pass
    def observe(self, env, obs): pass
    def go_is_safe(self, env):
        self.asked += 1
        return True

env_cfg = {"mode": "ccftap", "ccftap": {"ego_speed_kmh": 15, "target_speed_kmh": 45, "dt": 0.0}}
shield = {"name": "aeb_belief", "second_opinion": "my_own"}
env = gym.make("av_gym/UnprotectedLeftTurn-v0", env=env_cfg, shield=shield)
try:
    env.reset(seed=0)
except ConfigError as exc:
    print("refused:", exc)
env = gym.make("av_gym/UnprotectedLeftTurn-v0", env=env_cfg, shield=shield)
find_shield(env).opinion = mine = AlwaysSafe()
obs, info = env.reset(seed=0)
cruise, done = env.unwrapped.cruise_action(), False
while not done:
    obs, _, terminated, truncated, info = env.step(cruise)
    done = terminated or truncated
print("asked:", mine.asked, "withheld:", info["aeb_withheld"])
print("loaded:", sorted(m for m in sys.modules if m.split(".")[0] in ("conf", "agents", "train", "eval")))
"""


def test_a_users_own_opinion_works_from_user_code_without_the_harness(tmp_path):
    for name in ("conf", "agents", "train", "eval"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(f"raise ImportError('the user folder\\'s {name} was imported')\n")
    res = subprocess.run([sys.executable, "-c", USER_CODE], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    lines = dict(line.split(": ", 1) for line in res.stdout.splitlines())
    assert lines["refused"].startswith("shield.second_opinion='my_own' is the harness's planner and none is "
                                       "installed") and "\n" not in lines["refused"]
    asked, withheld = lines["asked"].split(" withheld: ")
    assert int(asked) >= 1 and int(withheld) == int(asked)  # every stop-line brake it was asked about: withheld
    assert lines["loaded"] == "[]"


def test_the_harness_installs_the_opinion_its_shield_preset_names():
    from agents.belief import PlannerOpinion
    from agents.registry import OPINIONS, opinion_problems
    from av_gym.shields import find_shield
    from eval.agents import compose_group, make_eval_env

    env = make_eval_env(ccftap_cfg(15, 45, 0.0), compose_group("sensors", "turn_truth"),
                        compose_group("shield", "aeb_belief"))
    assert isinstance(find_shield(env).opinion, PlannerOpinion)
    assert OPINIONS.names() == ["belief_lookahead"] and opinion_problems("none") == []
    assert opinion_problems("oracle") == ["shield.second_opinion must be one of ['none', 'belief_lookahead'], got "
                                          "'oracle'"]


def test_eval_refuses_an_opinion_it_cannot_install_before_building_anything():
    from eval.agents import AgentPlan, check_plan, compose_group

    shield = {**compose_group("shield", "aeb_belief"), "second_opinion": "oracle"}
    with pytest.raises(ConfigError, match=r"agent 'always_proceed': shield.second_opinion must be one of "
                                          r"\['none', 'belief_lookahead'\], got 'oracle'"):
        check_plan(AgentPlan("always_proceed", "always_proceed", compose_group("sensors", "turn_truth"), shield),
                   "left_turn")
