"""Hydra's config tree. The defaults of every component are its ``Params`` dataclass (:mod:`av_gym.params`),
stored in Hydra's ConfigStore when this package is imported (Hydra imports it to read ``pkg://conf``):
``scenario/<name>`` for each scenario, ``sensor/<key>`` for each sensor and estimator, ``command/train`` and
``command/eval`` for the commands' own settings (conf/commands.py). The yaml files here hold only what differs
from those defaults, with the reason."""

from __future__ import annotations


def register_configs() -> None:
    """Store each registered kind's defaults as a Hydra config (``sensor/gnss`` ...), from its Params."""
    from hydra.core.config_store import ConfigStore

    from av_gym.registry import SCENARIOS, SENSORS

    from conf.commands import COMMANDS

    store = ConfigStore.instance()
    for command, cls in COMMANDS.items():
        store.store(group="command", name=command, node=cls().as_dict() if command == "train" else
                    {k: v for k, v in cls().as_dict().items() if k != "agents"})  # eval.yaml sets agents
    for name, cls in SCENARIOS.items():
        store.store(group="scenario", name=name, node=cls.Params().as_dict())
    for key, cls in SENSORS.items():
        params = getattr(cls, "Params", None)
        if params is not None:
            store.store(group="sensor", name=key, node=params().as_dict())
    from agents.registry import register_configs as register_agent_kinds  # agent_kind/<kind>: each kind's Params

    register_agent_kinds(store)



def register_shield_configs() -> None:
    """``aeb/<variant>``: each AEB shield variant's defaults (av_gym/shields/aeb.py, ``config_defaults()`` of the
    classes in ``AEB_VARIANTS``), which conf/shield/aeb*.yaml start from (``defaults: [/aeb/<variant>@_here_]``)."""
    from hydra.core.config_store import ConfigStore

    from av_gym.shields.aeb import AEB_VARIANTS

    for name, cls in AEB_VARIANTS.items():
        ConfigStore.instance().store(group="aeb", name=name, node=cls.config_defaults())


register_configs()
register_shield_configs()
