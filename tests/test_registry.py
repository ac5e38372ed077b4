"""A new agent kind or teacher is one class (with its Params) plus one ``register`` line (agents/registry.py): the
config checker, Hydra's defaults, ``python -m eval``'s agent resolution and checkpoint loading, and the behaviour
cloning teacher lookup find it with nothing else edited. Each test registers a toy kind and unregisters it after."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import pytest
import yaml

from agents.registry import AGENT_KINDS, TEACHERS, AgentKind, AgentParams
from av_gym.errors import ConfigError
from av_gym.params import param
from conftest import conf


# ------------------------------------------------------------------------------------------------ a toy rule
@dataclass(frozen=True)
class ToyParams(AgentParams):
    """Always the same action (a toy)."""

    kind: Literal["toy"] = param("toy")
    name: str = param("toy")
    scenarios: tuple[str, ...] = param(("left_turn",))
    action: int = param(1, ge=0, le=2, doc="the meta-action it always takes")


class ToyPolicy:
    def __init__(self, action: int) -> None:
        self.action = action

    def reset(self) -> None:
        pass

    def act(self, obs):
        return self.action


class ToyAgent(AgentKind):
    Params = ToyParams

    @classmethod
    def build(cls, params: ToyParams, env, label: str) -> ToyPolicy:
        return ToyPolicy(params.action)


# ------------------------------------------------------------------------------------------------ a toy trained kind
@dataclass(frozen=True)
class ToyTrainedParams(AgentParams):
    kind: Literal["toy_trained"] = param("toy_trained")
    name: str = param("toy_trained")
    scenarios: tuple[str, ...] = param(("left_turn",))


class ToyTrainedAgent(AgentKind):
    Params = ToyTrainedParams
    checkpoint = "model.toy"

    @classmethod
    def load(cls, model_path, env) -> ToyPolicy:
        return ToyPolicy(int(model_path.read_text()))


@pytest.fixture
def toy_kinds(monkeypatch):
    """The toys registered (one line each), and ``conf/agent/toy.yaml`` as it would be shipped."""
    AGENT_KINDS.register("toy", ToyAgent)
    AGENT_KINDS.register("toy_trained", ToyTrainedAgent)
    shipped = {"toy": {"name": "toy", "kind": "toy", **ToyParams().as_dict(), "action": 2}}

    from eval import agents

    real = agents.load_agent_config
    fake = lambda name: dict(shipped[name]) if name in shipped else real(name)  # noqa: E731
    monkeypatch.setattr(agents, "load_agent_config", fake)
    try:
        yield
    finally:
        AGENT_KINDS.unregister("toy")
        AGENT_KINDS.unregister("toy_trained")


def test_the_config_check_knows_a_registered_kind(toy_kinds):
    from conf.check import problems, section_problems
    from test_validation import composed

    assert section_problems("agent", {"name": "mine", "kind": "toy", "action": 0}) == []
    assert section_problems("agent", {"name": "mine", "kind": "toy", "action": 7}) == \
        ["agent.action must be an integer in [0, 2], got 7"]
    (line,) = section_problems("agent", {"name": "mine", "kind": "toy", "speed": 1})
    assert line.startswith("agent.speed is not a field of a toy agent; allowed: ['action', 'kind', 'name',")
    cfg = composed("train", [])
    cfg["agent"] = ToyParams().as_dict()
    assert problems(cfg, "train") == []
    cfg["agent"]["kind"] = "toyy"
    assert problems(cfg, "train")[0].startswith("agent.kind must be one of ['ppo', ") and "'toy'" in \
        problems(cfg, "train")[0]


def test_hydra_gets_a_registered_kinds_defaults(toy_kinds):
    from hydra.core.config_store import ConfigStore

    from agents.registry import register_configs

    register_configs()
    node = ConfigStore.instance().load("agent_kind/toy.yaml").node
    assert dict(node) == {"name": "toy", "kind": "toy", "scenarios": ["left_turn"], "sensors": None, "action": 1}


def test_eval_resolves_a_registered_rule_and_loads_a_registered_checkpoint(toy_kinds, make, tmp_path):
    from eval.agents import check_plan, plan_agent, resolve_agent
    from eval.runner import run_episodes

    env = make(conf("env", "left_turn"))
    label, policy = resolve_agent("toy", env, "left_turn", tmp_path)
    assert label == "toy" and isinstance(policy, ToyPolicy) and policy.action == 2  # the shipped yaml's value
    (row,) = run_episodes(env, policy, [0], label, progress=False)
    assert row["agent"] == "toy"

    run = tmp_path / "checkpoints" / "toy_run"
    run.mkdir(parents=True)
    (run / "model.toy").write_text("0")
    (run / "config.yaml").write_text(yaml.safe_dump({"env": {"name": "left_turn"},
                                                     "agent": ToyTrainedParams().as_dict()}))
    plan = plan_agent(str(run), "left_turn", {"name": "truth"}, {"name": "none", "kind": "none"}, tmp_path)
    check_plan(plan, "left_turn")
    label, policy = resolve_agent(str(run), env, "left_turn", tmp_path)
    assert label == "toy_run" and isinstance(policy, ToyPolicy) and policy.action == 0
    # by kind name: the newest checkpoint of that kind for this env
    label, policy = resolve_agent("toy_trained", env, "left_turn", tmp_path / "checkpoints")
    assert policy.action == 0
    with pytest.raises(ConfigError, match="was trained on env 'left_turn', not 'lane_keeping'"):
        check_plan(plan, "lane_keeping")


def test_a_registered_teacher_labels_for_behaviour_cloning(toy_kinds):
    from train.ppo import make_teacher

    def toy_teacher(params: ToyParams, actions: str, scenario=None, action_repeat: int = 1):
        if actions != "go_yield":
            raise ConfigError(f"agent.init={params.name} teaches go/yield choices")
        return lambda env, obs, info: params.action % 2

    with pytest.raises(ConfigError, match=r"agent.init must name an agent of kind gap_acceptance or lookahead or belief_lookahead or pid"):
        make_teacher("toy", "go_yield")
    TEACHERS.register("toy", toy_teacher)
    try:
        teacher = make_teacher("toy", "go_yield")
        assert teacher(None, {"turn": np.zeros(3)}, {}) == 0
        with pytest.raises(ConfigError, match="teaches go/yield"):
            make_teacher("toy", "env")
    finally:
        TEACHERS.unregister("toy")


def test_every_shipped_kind_is_registered_and_its_defaults_are_valid():
    for kind, cls in AGENT_KINDS.items():
        params = cls.Params()
        assert params.kind == kind and params.problems() == []
        assert cls.trained() == (cls.checkpoint is not None)
        if cls.trained():
            from train.registry import TRAINERS

            assert kind in TRAINERS
    assert set(TEACHERS.names()) <= set(AGENT_KINDS.names())
