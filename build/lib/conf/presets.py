"""The shipped presets of conf/ (``sensors/turn_perceived``, ``shield/aeb``, ``env/left_turn`` ...) composed as the
command line composes them. Used by the evaluation, and by ``gym.make("av_gym/...", sensors=..., shield=...)``
(:mod:`av_gym.api`), which reaches this module only when a preset is asked for by name."""

from __future__ import annotations

from importlib import resources

from av_gym.errors import ConfigError


def preset_names(group: str) -> list[str]:
    """The presets shipped in conf/<group>/."""
    return sorted(p.name[:-5] for p in (resources.files("conf") / group).iterdir() if p.name.endswith(".yaml"))


def compose_group(group: str, name: str) -> dict:
    """The composed config of option ``name`` of Hydra group ``group`` (e.g. ``shield/aeb``)."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf import OmegaConf

    options = preset_names(group)
    if name not in options:
        raise ConfigError(f"{group} {name!r} is not in conf/{group}/; available: {options}")
    try:
        if GlobalHydra.instance().is_initialized():
            cfg = compose(config_name="eval", overrides=[f"{group}={name}"])
        else:
            with initialize_config_module("conf", version_base="1.3"):
                cfg = compose(config_name="eval", overrides=[f"{group}={name}"])
    except HydraException as exc:  # pragma: no cover - a broken yaml in conf/
        raise ConfigError(f"{group}={name}: {exc}") from None
    return OmegaConf.to_container(cfg[group], resolve=True)
