"""The shipped presets (``sensors: turn_perceived``, ``shield: aeb``, ``env: left_turn``) composed by the library
itself, from the yaml files read by path (:func:`av_gym.references.conf_root`) and the ``Params`` defaults of the
kinds they name.

Why not Hydra's ``compose`` here: it finds the configs through an importable module called ``conf``, and a user's
project that holds its own ``conf/`` (Hydra's usual layout) shadows it, or is shadowed by it; inside a user's own
Hydra app the global Hydra instance is theirs. The presets use one small part of Hydra's defaults list, written out
below; ``tests/test_ecosystem.py`` checks that this composition equals Hydra's for every shipped preset.

A preset file holds a ``defaults`` list of

- ``/sensor/<key>@<key>``: that sensor's (or estimator's) ``Params`` defaults under ``<key>``;
- ``/scenario/<name>@_here_``: the scenario's ``Params`` defaults at the top;
- ``/aeb/<variant>@_here_``: the AEB variant's config defaults at the top;
- ``<preset>``: another preset of the same group;
- ``_self_``: the file's own values, merged over what came before (last when the list does not name it).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from av_gym.errors import ConfigError
from av_gym.references import conf_root

def preset_names(group: str) -> list[str]:
    """The presets shipped for ``group`` (``sensors`` → ``['camera_centre', 'cameras', ...]``)."""
    folder = conf_root() / group
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def compose_group(group: str, name: str) -> dict:
    """Preset ``name`` of ``group`` composed as ``python -m train <group>=<name>`` composes it."""
    options = preset_names(group)
    if name not in options:
        raise ConfigError(f"{group} {name!r} is not in conf/{group}/; available: {options}")
    return _compose(conf_root() / group / f"{name}.yaml", group)


def _compose(path: Path, group: str) -> dict:
    raw = yaml.safe_load(path.read_text()) or {}
    defaults = [str(e) for e in raw.pop("defaults", None) or []]
    if "_self_" not in defaults:  # Hydra (version_base 1.1+) puts a config's own values last unless told
        defaults.append("_self_")
    out: dict = {}
    for entry in defaults:
        if entry == "_self_":
            out = deep_merge(out, raw)
            continue
        target, _, package = str(entry).partition("@")
        if not target.startswith("/"):  # another preset of the same group
            out = deep_merge(out, compose_group(group, target))
            continue
        node = _params_node(*target.strip("/").split("/", 1))
        out = deep_merge(out, node if package == "_here_" else {package: node})
    return out


def _params_node(kind: str, name: str) -> dict:
    """The defaults that Hydra's ConfigStore holds as ``<kind>/<name>`` (stored from these same Params by the
    harness's ``conf`` package)."""
    from av_gym.registry import SCENARIOS, SENSORS

    if kind == "sensor":
        return SENSORS.get(name, where="sensors key").Params().as_dict()
    if kind == "scenario":
        return SCENARIOS.get(name, where="env.name").Params().as_dict()
    if kind == "aeb":
        from av_gym.shields.aeb import AEB_VARIANTS

        return copy.deepcopy(AEB_VARIANTS.get(name, where="shield.variant").config_defaults())
    raise ConfigError(f"a preset's defaults entry must start /sensor/, /scenario/ or /aeb/, got /{kind}/{name}")


def deep_merge(base: Mapping, over: Mapping) -> dict:
    """``over`` merged into a copy of ``base``, nested mappings key by key (as OmegaConf merges)."""
    out = copy.deepcopy(dict(base))
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def plain(value: Any) -> Any:
    """``value`` with an OmegaConf node turned into plain dicts and lists (callers may hold either)."""
    if hasattr(value, "_metadata"):
        from omegaconf import OmegaConf

        return OmegaConf.to_container(value, resolve=True)
    return value


def as_section(group: str, value: Any, default: str) -> dict:
    """What a ``sensors=`` / ``shield=`` / ``env=`` keyword means: a preset name, a mapping naming a preset with
    fields to change (deep-merged over it), or a hand-made mapping; ``None`` is ``default``."""
    if value is None:
        value = default
    if isinstance(value, str):
        return compose_group(group, value)
    value = plain(value)
    if not isinstance(value, Mapping):
        raise ConfigError(f"{group} must be a mapping or one of {preset_names(group)}, got {value!r}")
    name = value.get("name")
    return deep_merge(compose_group(group, name), value) if name in preset_names(group) else dict(value)
