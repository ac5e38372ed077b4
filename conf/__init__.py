"""Hydra's config tree. The defaults of every component are its ``Params`` dataclass (:mod:`av_gym.params`),
stored in Hydra's ConfigStore when this package is imported (Hydra imports it to read ``pkg://conf``):
``scenario/<name>`` for each scenario, ``sensor/<key>`` for each sensor and estimator, ``aeb/<variant>`` for each
AEB shield variant, ``agent_kind/<kind>`` for each agent kind, ``command/train`` and ``command/eval`` for the
commands' own settings (conf/commands.py). The yaml files here hold only what differs from those defaults, with
the reason."""

from __future__ import annotations


def register_configs() -> None:
    """Store each registered kind's defaults as a Hydra config (``sensor/gnss`` ...), from its Params."""
    from hydra.core.config_store import ConfigStore

    from agents.registry import register_configs as register_agent_kinds
    from av_gym.registry import SCENARIOS, SENSORS
    from av_gym.shields.aeb import AEB_VARIANTS
    from conf.commands import COMMANDS

    store = ConfigStore.instance()
    for command, cls in COMMANDS.items():  # eval.yaml sets `agents` (the env's compare list)
        store.store(group="command", name=command,
                    node={k: v for k, v in cls().as_dict().items() if k != "agents"})
    for name, cls in SCENARIOS.items():
        store.store(group="scenario", name=name, node=cls.Params().as_dict())
    for key, cls in SENSORS.items():
        store.store(group="sensor", name=key, node=cls.Params().as_dict())
    for name, cls in AEB_VARIANTS.items():  # conf/shield/aeb*.yaml start from /aeb/<variant>
        store.store(group="aeb", name=name, node=cls.config_defaults())
    register_agent_kinds(store)  # agent_kind/<kind>


def register_resolvers() -> None:
    """``${av_gym_groups:train}``: the groups a command lets a user choose, for --help (conf/hydra/help/av_gym.yaml).
    ``${av_gym_reference:dagger_turn}``: the shipped reference of that name (the checkout's or the wheel's copy,
    :func:`av_gym.references.reference_root`), whatever folder the command runs from: a preset that starts from a
    reference must not read a user's own ``checkpoints/reference`` (as named agents do not, eval/agents.py)."""
    from omegaconf import OmegaConf

    from av_gym.references import reference_root
    from conf.commands import help_groups

    OmegaConf.register_new_resolver("av_gym_groups", help_groups, replace=True)
    OmegaConf.register_new_resolver("av_gym_reference", lambda name: str(reference_root() / name), replace=True)


register_configs()
register_resolvers()
