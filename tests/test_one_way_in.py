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


@pytest.mark.slow  # a fresh interpreter (~6 s idle): an end-to-end check
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


# ----------------------------------------------------------------------------------------------- scenario configs
def _outside(meta: dict) -> float | None:
    """A number just outside a field's lower bound (None: the field has none)."""
    if meta.get("ge") is not None:
        return meta["ge"] - 1.0
    if meta.get("gt") is not None:
        return float(meta["gt"])
    return None


def _bad_configs(scenario: str):
    """``(key, config, says)`` for every key of the scenario's table with a lower bound: the key's value just
    below its field's bound, in SI, inside an otherwise default config."""
    import copy

    from av_gym.envs.base import TO_SI
    from av_gym.params import field_at
    from av_gym.registry import SCENARIOS

    cls = SCENARIOS.get(scenario)
    for key, path in cls.Params.CONFIG_KEYS.items():
        _, f = field_at(cls.Params, path)
        bad = _outside(f.metadata)
        if bad is None:
            continue
        default = cls.Params().env_config()
        *heads, last = key.split(".")
        inner = config = copy.deepcopy(default)
        for head in heads:
            inner = inner[head]
        value = TO_SI.get(f.metadata["unit"], lambda v: v)(bad)
        listed = isinstance(inner[last], list)
        inner[last] = [value] * len(inner[last]) if listed else value
        yield key, config, f"config.{key}{'[0]' if listed else ''} must be "


@pytest.mark.parametrize("scenario", ["left_turn", "lane_keeping"])
def test_every_table_key_is_checked_by_its_field_wherever_the_env_is_built(scenario):
    """One table (``Params.CONFIG_KEYS``) gives each env config key its field: ``gym.make(id, config=...)``, an env
    class built directly and the field's own check refuse the same value, the bound in SI."""
    from av_gym import ENV_IDS
    from av_gym.registry import SCENARIOS

    cls = SCENARIOS.get(scenario)
    checked = 0
    for key, config, says in _bad_configs(scenario):
        given = {key.split(".")[0]: config[key.split(".")[0]]}
        with pytest.raises(ConfigError, match="^" + says.replace("[", r"\[").replace("]", r"\]")):
            gym.make(ENV_IDS[scenario], config=given)
        with pytest.raises(ConfigError, match="^" + says.replace("[", r"\[").replace("]", r"\]")):
            cls(config=config).reset(seed=0)
        checked += 1
    assert checked >= (8 if scenario == "left_turn" else 7)


@pytest.mark.parametrize("scenario", ["left_turn", "lane_keeping"])
def test_env_config_writes_exactly_the_table(scenario):
    from av_gym.envs.base import ABSENT, config_value
    from av_gym.registry import SCENARIOS

    cls = SCENARIOS.get(scenario)
    config = cls.Params().env_config()
    flat = {f"{k}.{s}" if isinstance(v, dict) else k for k, v in config.items() for s in (v if isinstance(v, dict)
                                                                                           else [None])}
    assert flat == set(cls.Params.CONFIG_KEYS)
    assert all(config_value(config, key) is not ABSENT for key in cls.Params.CONFIG_KEYS)
    assert cls.Params.config_problems(config) == [] and cls.Params.config_problems({}) == []


def test_a_relation_names_the_config_keys_whatever_builds_the_env():
    from av_gym.envs.left_turn import UnprotectedLeftTurnEnv

    config = {"action": {"type": "continuous", "acceleration_range": [3.0, -8.0]}}
    says = r"config.action.acceleration_range must be \[min, max\] with min < max \(m/s²\), got \[3, -8\]"
    with pytest.raises(ConfigError, match=says):
        gym.make(TURN, config=config)
    full = UnprotectedLeftTurnEnv.default_config()
    full["action"] = {**full["action"], **config["action"]}
    with pytest.raises(ConfigError, match=says):
        UnprotectedLeftTurnEnv(config=full)
    with pytest.raises(ConfigError, match=r"config.simulation_frequency \(15\) must be a multiple of "
                                          r"config.policy_frequency \(10\)"):
        gym.make(TURN, config={"simulation_frequency": 15})


def test_a_config_key_unknown_to_the_scenario_is_refused_with_the_allowed_keys():
    with pytest.raises(ConfigError) as err:
        gym.make(TURN, config={"zzzz": 1})
    line = str(err.value)
    assert line.startswith("config.zzzz is not a setting of left_turn; allowed: [") and "'ccftap_dt'" in line
    with pytest.raises(ConfigError, match=r"config.action.speeds is not a setting of left_turn; allowed: "
                                          r"\['acceleration_range', 'target_speeds', 'type'\]"):
        gym.make(TURN, config={"action": {"speeds": [1.0]}})


def test_the_batched_engine_checks_the_same_table():
    from av_gym.batched.left_turn import BatchedLeftTurn
    from av_gym.envs.left_turn import LeftTurnParams

    with pytest.raises(ValueError, match=r"env.spawn_probability must be a number in \[0, 1\], got 2"):
        BatchedLeftTurn(2, {**LeftTurnParams().env_config(), "spawn_probability": 2})


# ----------------------------------------------------------------------------------------------- trainers
def test_trainers_are_registered_by_kind_on_the_training_side():
    """``train/registry.py`` maps each trained agent kind to its trainer; no agents module names a train module
    (a ``"train.x:y"`` string), so the harness's layers point one way."""
    import ast
    from pathlib import Path

    from agents.registry import trained_kinds
    from train.registry import TRAIN_CHECKS, TRAINERS, train_problems, trainer_of

    assert sorted(TRAINERS.names()) == sorted(trained_kinds())
    assert set(TRAIN_CHECKS.names()) <= set(TRAINERS.names())
    assert all(callable(trainer_of(kind)) for kind in TRAINERS.names())
    assert train_problems("pid", None) == []  # a kind without a trainer's check
    with pytest.raises(ConfigError, match=r"agent.kind 'toy' is trained but has no trainer: add it to "
                                          r"train/registry.py TRAINERS"):
        trainer_of("toy")
    root = Path(__file__).resolve().parents[1] / "agents"
    named = [f"{path.name}: {node.value}" for path in sorted(root.glob("*.py"))
             for node in ast.walk(ast.parse(path.read_text()))
             if isinstance(node, ast.Constant) and isinstance(node.value, str)
             and node.value.startswith("train.") and ":" in node.value]
    assert named == []
