"""Every field of ``python -m train`` / ``python -m eval`` checked before anything runs or is written, one line
naming the field and what is allowed (exit 2 at the command line).

Nothing here describes a field: each section is checked against the typed Params of the kind it names, found in
that family's registry (``env.name`` → :data:`av_gym.registry.SCENARIOS`, each ``sensors.<key>`` →
:data:`~av_gym.registry.SENSORS`, ``shield.kind`` → :data:`~av_gym.registry.SHIELDS`, ``agent.kind`` →
:data:`agents.registry.AGENT_KINDS`), and the commands' own settings against :mod:`conf.commands`. A new kind
registered in its family is checked here with nothing else to edit. This module adds the config path to the
library's field-relative messages (``sigma ...`` → ``sensors.gnss.sigma ...``) and composes the command line the
way Hydra will, so that a typo gives one line and no run folder.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from importlib import resources
from typing import Any

from av_gym.errors import ConfigError, closest_hint
from av_gym.params import check
from av_gym.presets import preset_names


def options(group: str) -> list[str]:
    """The options of a Hydra group shipped in conf/ (``sensors`` → ``['cameras', 'detector', ...]``)."""
    return preset_names(group)


def _mapping(value: Any, where: str) -> list[str]:
    return [] if isinstance(value, Mapping) else [f"{where} must be a mapping, got {value!r}"]


# ------------------------------------------------------------------------------------------------ sections
def env_problems(value: Any, where: str = "env") -> list[str]:
    from av_gym.registry import SCENARIOS

    if _mapping(value, where):
        return _mapping(value, where)
    name = value.get("name")
    if name not in SCENARIOS:
        return [f"{where}.name must be one of {SCENARIOS.names()}, got {name!r}"]
    return check(SCENARIOS.get(name).Params, value, where, what=f"a field of env={name}")


PRESET_FIELDS = ("name", "keep_state", "observe")


def sensors_problems(value: Any, where: str = "sensors") -> list[str]:
    """A sensor preset: its name, ``keep_state``, ``observe`` and one section per sensor or estimator (each
    against its class's Params)."""
    from av_gym.registry import SENSORS

    if _mapping(value, where):
        return _mapping(value, where)
    found = []
    allowed = sorted([*PRESET_FIELDS, *SENSORS])
    for key, section in value.items():
        path = f"{where}.{key}"
        if key == "name":
            if section not in options("sensors") and section is not None:
                found.append(f"{path} must be one of {options('sensors')}, got {section!r}")
        elif key == "keep_state":
            if not isinstance(section, bool):
                found.append(f"{path} must be true or false, got {section!r}")
        elif key == "observe":
            if not (isinstance(section, (list, tuple)) and section and all(isinstance(k, str) and k for k in section)):
                found.append(f"{path} must be a list of observation keys with at least one item, got {section!r}")
        elif key in SENSORS:
            cls = SENSORS.get(key)
            if not isinstance(section, Mapping):
                found.append(f"{path} must be a mapping of {cls.__name__} parameters, got {section!r}")
            else:
                found += check(cls.Params, section, path, what=f"a parameter of {cls.__name__}")
        else:
            found.append(f"{path} is not a sensor preset field or a sensor; allowed: {allowed}")
    if "name" not in value:
        found.append(f"{where}.name is missing")
    return found


def shield_problems(value: Any, where: str = "shield") -> list[str]:
    """``kind: none`` (no shield), or a kind of :data:`av_gym.registry.SHIELDS`, whose class checks the rest
    (``config_problems(section)``: e.g. the AEB's variant picks its Params)."""
    from av_gym.registry import SHIELDS

    if _mapping(value, where):
        return _mapping(value, where)
    kind = value.get("kind", value.get("name", "none"))
    found = [] if isinstance(value.get("name", "x"), str) and value.get("name", "x") else \
        [f"{where}.name must be a non-empty string, got {value.get('name')!r}"]
    if kind == "none":
        extra = sorted(set(value) - {"name", "kind"})
        return found + ([f"{where}.{extra[0]} is not a field of shield=none; allowed: ['kind', 'name']"] if extra
                        else [])
    if kind not in SHIELDS:
        return [f"{where}.kind must be one of {['none', *SHIELDS.names()]}, got {kind!r}"]
    return found + SHIELDS.get(kind).config_problems(value, where)


def agent_problems(value: Any, where: str = "agent") -> list[str]:
    from agents.registry import agent_problems as problems_of_agent

    if _mapping(value, where):
        return _mapping(value, where)
    found = problems_of_agent(value, where)
    sensors = value.get("sensors")
    if not found and sensors is not None and sensors not in options("sensors"):
        found.append(f"{where}.sensors must be one of {[*options('sensors'), None]}, got {sensors!r}")
    return found


SECTION_CHECKS = {"env": env_problems, "sensors": sensors_problems, "shield": shield_problems,
                  "agent": agent_problems}


def section_problems(group: str, value: Any, where: str | None = None) -> list[str]:
    """Problems of one group's section (``env``, ``sensors``, ``agent``, ``shield``) on its own."""
    return SECTION_CHECKS[group](value, where or group)


# ------------------------------------------------------------------------------------------------ commands
def problems(cfg: Mapping, command: str) -> list[str]:
    """Every problem of a composed, resolved ``train`` or ``eval`` config, one line each (empty if none)."""
    from conf.commands import COMMANDS, SECTIONS

    settings_cls, sections = COMMANDS[command], SECTIONS[command]
    what = f"{'an' if command[0] in 'aeiou' else 'a'} {command} setting"
    found = []
    for group in sections:
        if group not in cfg:
            found.append(f"{group} is missing")
        else:
            found += section_problems(group, cfg[group])
    settings = {k: v for k, v in cfg.items() if k not in sections}
    allowed = sorted([*sections, *settings_cls.field_names()])
    unknown = [k for k in settings if k not in settings_cls.field_names()]
    found += [f"{k} is not {what}; allowed: {allowed}" for k in unknown]
    found += check(settings_cls, {k: v for k, v in settings.items() if k not in unknown}, "", what=what)
    if not found and command == "train":
        found += _agent_sensor_problems(cfg.get("agent"), cfg.get("sensors"))
        found += _own_preset_problems(cfg.get("agent"), cfg.get("sensors"), default_sensors(command))
    return found


def _own_preset_problems(agent: Any, sensors: Any, default: str | None) -> list[str]:
    """Train's side of :func:`own_sensors_problem`: a rule-based agent that names its own sensors preset
    (``agent.sensors``: gap_acceptance's turn_truth) runs on it, whatever ``sensors=`` says (config.yaml records it:
    train.__main__.config_as_ran). A trained kind trains on the sensors it is given."""
    from agents.registry import AGENT_KINDS

    if not isinstance(agent, Mapping) or not isinstance(sensors, Mapping) or not agent.get("sensors"):
        return []
    kind = AGENT_KINDS.get(agent.get("kind")) if agent.get("kind") in AGENT_KINDS else None
    if kind is None or kind.trained():
        return []
    line = own_sensors_problem(str(agent.get("name")), str(agent["sensors"]), dict(sensors), default, "train")
    return [line] if line else []


def own_sensors_problem(label: str, own: str | None, given: Mapping, default: str | None, command: str,
                        trained: bool = False) -> str | None:
    """The one rule, worded once, for an agent that runs on sensors of its own (``own``: a trained agent's, from
    its checkpoint or ``@preset``; a rule-based agent's own preset, gap_acceptance's turn_truth) while the command
    line gives ``sensors=`` (``given``, composed, ``default``: the command's own preset, :func:`default_sensors`):

    - its own preset: it runs on it with the command line's ``sensors.*`` overrides, so nothing to refuse;
    - the default preset: no choice of the user's; a trained agent gets the overrides on top of its own sensors,
      a rule-based agent would run on its own preset as shipped, so its overrides are refused;
    - another preset would not reach it (the table would say nothing of the preset asked for, and ``-m
      sensors=a,b`` would give the same rows twice), so it is refused.

    Each refusal ends with what ``command`` accepts instead: eval's ``agents=[agent@preset]``; train (no ``@``
    form: a rule-based agent runs on its own preset there) ``sensors=<own>``, which gets the overrides."""
    name = given.get("name")
    if own is None or name == own:
        return None
    agent, plus, shield = label.partition("+")
    if name == default:
        changed = sensor_overrides(given)
        if trained or not changed:
            return None
        given_line = " ".join(f"sensors.{k}={v!r}" for k, v in changed.items())
        where = f"agents=[{agent}@{own}{plus}{shield}] sensors={own}" if command == "eval" else f"sensors={own}"
        return (f"{given_line}: agent {label!r} runs on its own sensors preset ({own}) as shipped, so these "
                f"overrides would not reach it; give them to it with {where} {given_line}, or leave them out")
    why = "the sensors it was trained with" if trained else "its own sensors preset"
    fix = (f"drive it from {name} with agents=[{agent}@{name}{plus}{shield}]"
           f"{' (the same observation space)' if trained else ''}, or leave sensors= out" if command == "eval" else
           f"train runs it on {own}: leave sensors= out, or give sensors={own} (its sensors.* overrides reach it)")
    return f"sensors={name}: agent {label!r} runs on {why} ({own}), so sensors={name} would not reach it; {fix}"


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    """Nested mapping → ``{"a.b.c": leaf}`` (lists are leaves)."""
    if not isinstance(d, Mapping):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def sensor_overrides(sensors: Mapping | None, group: str = "sensors") -> dict[str, Any]:
    """The command line's ``sensors.*`` changes: every field of the composed ``sensors`` that differs from (or is
    not in) the shipped preset it names, as ``{"cameras.night": True}``. Works for sweeps too (each job composes
    its own ``sensors``), and needs no access to the raw command line. ``group="shield"``: a shield's. Here, below
    eval, so that train's command-line check uses it too (tests/test_imports.py)."""
    from av_gym.presets import compose_group

    if not sensors or not sensors.get("name"):
        return {}
    try:
        shipped = _flatten(compose_group(group, str(sensors["name"])))
    except ConfigError:  # a preset that is not shipped (a hand-made dict): nothing to compare with
        return {}
    return {k: v for k, v in _flatten(sensors).items() if k != "name" and (k not in shipped or shipped[k] != v)}


def _agent_sensor_problems(agent: Any, sensors: Any) -> list[str]:
    """What an agent's settings need from the sensors preset, checked before a run folder exists (the wrappers
    check it again when the env is built, too late to keep the folders clean)."""
    if not isinstance(agent, Mapping) or not isinstance(sensors, Mapping) or "turn_features" in sensors:
        return []
    wants = [f"agent.{key}={agent.get(key)}" for key, value in (("actions", "go_yield"), ("extractor", "attention"))
             if agent.get(key) == value]
    presets = [name for name in options("sensors") if name.startswith("turn_")]
    return [f"{want} needs obs['turn'] (sensors={' or '.join(presets)}), got sensors={sensors.get('name')}"
            for want in wants[:1]]


def validate_config(cfg: Any, command: str) -> None:
    """Raise :class:`ConfigError` with the first problem of ``cfg`` (an OmegaConf node or a plain mapping)."""
    if hasattr(cfg, "_metadata"):
        from omegaconf import OmegaConf

        cfg = OmegaConf.to_container(cfg, resolve=True)
    found = problems(cfg, command)
    if found:
        raise ConfigError(found[0])


# ------------------------------------------------------------------------------------------------ command line
_PLACEHOLDER = "hydra-runtime-value"  # a valid folder name, so run_name=${hydra:...} passes


def check_command_line(command: str, argv: list[str], check: Callable[[Any], Any] | None = None) -> list:
    """Compose the config the way Hydra will for ``python -m <command> <argv>`` and check it, *before* Hydra runs:
    so a typo gives one line (not Hydra's multi-line report) and no run folder is created. Returns the composed
    configs (one per swept value with ``-m``; ``hydra:`` interpolations replaced by a placeholder) for the
    command's own checks. Hydra's own options (``--help``, ``--cfg``, ``-c`` ...) are left to Hydra.

    Each composed config is checked once here: its fields (:func:`validate_config`), then ``check(cfg)``, what the
    command needs beyond them (seed ranges, a trainer's needs, the agents' checkpoints ...). Each config that
    passed is remembered (:func:`was_checked`), so that the job Hydra runs from the same command line in this
    process is not checked again.

    A sweep is checked value by value (each swept value once, the other sweeps at their first value): linear in
    the number of values, and every value a job will see has been checked."""
    _CHECKED.clear()  # only the configs of this command line: the jobs Hydra is about to run from it
    flags = [a for a in argv if a.startswith("-")]
    if any(a not in ("-m", "--multirun") for a in flags):
        return []
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    texts = [a for a in argv if not a.startswith("-")]
    try:
        parsed = OverridesParser.create().parse_overrides(texts)
    except HydraException as exc:
        raise ConfigError(f"cannot parse the command line: {_one_line(exc)}") from None
    if not flags and any(o.is_sweep_override() for o in parsed):
        sweep = next(o.input_line for o in parsed if o.is_sweep_override())
        raise ConfigError(f"{sweep!r} lists several values: add -m to sweep over them, or write key=[a,b] for a list")
    combos = _linear_combos(parsed)
    groups = _groups(command)
    composed = []
    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
    with initialize_config_module("conf", version_base="1.3"):
        for combo in combos:
            try:
                composed.append(_compose_checked(command, combo, groups, compose, multirun=bool(flags)))
            except (HydraException, OmegaConfBaseException) as exc:
                raise ConfigError(_one_line(exc)) from None
    for cfg in composed:  # every config's fields first, then what the command needs of each
        if check is not None:
            check(cfg)
        _CHECKED.add(_fingerprint(cfg))
    return composed


def _one_line(exc: BaseException) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    text = "; ".join(lines) if lines else type(exc).__name__
    return text if len(text) <= 400 else text[:397] + "..."


def _linear_combos(parsed: list) -> list[list[str]]:
    """Override lists: each swept value once, every other sweep at its first value."""
    values = []
    for o in parsed:
        if o.is_sweep_override():
            key = o.get_key_element()
            values.append([f"{key}={v}" for v in o.sweep_string_iterator()])
        else:
            values.append([o.input_line])
    first = [v[0] for v in values]
    combos = [first]
    for i, vs in enumerate(values):
        for v in vs[1:]:
            combos.append(first[:i] + [v] + first[i + 1:])
    return combos


def _compose_checked(command: str, overrides: list[str], groups: list[str], compose, multirun: bool = False) -> Any:
    """One combination of overrides composed (once, with Hydra's own section: the job's folder is checked before
    Hydra makes it) and checked; on a composition Hydra refuses, the override that caused it in one line."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from conf.cli import out_folder_problem

    parsed = OverridesParser.create().parse_overrides(overrides)
    for o in parsed:
        if o.key_or_group in groups and not o.is_delete():
            allowed = options(o.key_or_group)
            if o.value() not in allowed:
                raise ConfigError(f"{o.key_or_group}={o.value()}: {o.key_or_group} must be one of {allowed}")
    try:
        cfg = composed(compose, command, overrides)
    except (HydraException, OmegaConfBaseException):
        _explain_refused_override(command, parsed, overrides, groups, compose)
        raise
    for path in list(_hydra_values(OmegaConf.to_container(cfg, resolve=False))):
        OmegaConf.update(cfg, path, _PLACEHOLDER)
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    try:
        raw = OmegaConf.to_container(cfg.hydra, resolve=False)[key.split(".")[1]]["dir"]  # as written, to explain
        job_dir = OmegaConf.select(cfg, key)
    except OmegaConfBaseException:  # it names a value only the running job has: Hydra will report it
        job_dir = None
    OmegaConf.set_struct(cfg, False)
    del cfg["hydra"]
    OmegaConf.set_struct(cfg, True)
    validate_config(cfg, command)
    if isinstance(job_dir, str):  # never the shipped references (train.overwrite=true clears a run's folder)
        problem = out_folder_problem(job_dir, key, cleared=command == "train")
        if problem:
            given = any(o.key_or_group == key for o in parsed)
            raise ConfigError(problem if given or raw == job_dir else f"{problem} ({key} is {raw})")
    return cfg


def composed(compose: Callable, command: str, overrides: list[str]) -> Any:
    """``compose(config_name=command, overrides=overrides, return_hydra_config=True)`` (Hydra's, initialised on
    conf/), each command line composed once per process: the composition reads only the package's conf/ and the
    overrides (interpolations such as ``${now:...}`` stay unresolved), and the test suite composes the same command
    lines again and again (~0.12 CPU-s each). A deep copy each time, so a caller's edits never reach the cache, with
    what Hydra reads from the moment set as of now: ``hydra.runtime.cwd`` and ``hydra.job.env_set`` of
    ``hydra.job.env_copy``."""
    import copy
    import os

    from omegaconf import open_dict

    cfg = copy.deepcopy(_composed(compose, command, tuple(overrides)))
    with open_dict(cfg.hydra):
        cfg.hydra.runtime.cwd = os.getcwd()
        for key in cfg.hydra.job.env_copy:
            cfg.hydra.job.env_set[key] = os.environ[key]
    return cfg


@functools.lru_cache(maxsize=512)
def _composed(compose: Callable, command: str, overrides: tuple[str, ...]) -> Any:
    return compose(config_name=command, overrides=list(overrides), return_hydra_config=True)


def _explain_refused_override(command: str, parsed: list, overrides: list[str], groups: list[str], compose) -> None:
    """A value override Hydra refused to compose names a field that does not exist: one line naming the nearest
    section's fields, from the config composed with the group choices alone."""
    group_overrides = [text for o, text in zip(parsed, overrides)
                       if o.key_or_group.startswith("hydra") or "/" in o.key_or_group or "@" in o.key_or_group
                       or o.key_or_group in groups]
    base = compose(config_name=command, overrides=group_overrides)
    for o in parsed:
        key = o.key_or_group
        if key.startswith("hydra") or "/" in key or "@" in key or key in groups:
            continue
        if o.is_add() or o.is_force_add() or o.is_delete():
            continue  # a new key: the section's Params refuse it unless it is one of their fields
        _check_path(base, key, command)


def _hydra_values(node: Any, path: str = ""):
    """Paths of the values only a running job has (``${hydra:...}``, filled by Hydra once the job runs)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _hydra_values(v, f"{path}.{k}" if path else str(k))
    elif isinstance(node, str) and "${hydra:" in node:
        yield path


# The configs of the last command line this process checked, unresolved: the job Hydra composes from it is the
# same config, checked already (a sweep's jobs in other processes, and callers from Python, check their own).
_CHECKED: set[str] = set()


def _fingerprint(cfg: Any) -> str:
    import json

    from omegaconf import OmegaConf

    plain = OmegaConf.to_container(cfg, resolve=False)
    for path in list(_hydra_values(plain)):
        node = plain
        *parents, last = path.split(".")
        for part in parents:
            node = node[part]
        node[last] = _PLACEHOLDER
    return json.dumps(plain, sort_keys=True, default=str)


def was_checked(cfg: Any) -> bool:
    """Whether :func:`check_command_line` checked this very config in this process (the job of a plain run)."""
    return _fingerprint(cfg) in _CHECKED


def _groups(command: str) -> list[str]:
    """The config groups the command's defaults list picks (``env``, ``sensors`` ...)."""
    import yaml

    shipped = yaml.safe_load((resources.files("conf") / f"{command}.yaml").read_text())
    return [next(iter(d)) for d in shipped.get("defaults", []) if isinstance(d, dict) and
            not next(iter(d)).startswith(("override", "/"))]


def default_sensors(command: str) -> str | None:
    """The sensors preset ``python -m <command>`` gives when ``sensors=`` is left out (its defaults list in
    conf/<command>.yaml: ``truth``): what an agent without sensors of its own runs on, and no choice of the user's
    (:func:`own_sensors_problem`). Read here alone, for train and eval."""
    return _default_option(command, "sensors")


def _default_option(command: str, group: str) -> str | None:
    """The option of ``group`` the command's defaults list picks (``train``, ``sensors`` → ``truth``)."""
    import yaml

    shipped = yaml.safe_load((resources.files("conf") / f"{command}.yaml").read_text())
    return next((d[group] for d in shipped.get("defaults", []) if isinstance(d, dict) and group in d), None)


def _no_shield_hint(key: str, section: str) -> str:
    """A shield's fields come with its name: ``agents=[x+aeb] shield.mode=perceived`` names no shield to set them on
    (``x+aeb`` runs the command line's ``shield=aeb`` with its fields when one is given)."""
    if section != "shield=none":
        return ""
    return f" (no shield is named: give one with its fields, e.g. shield=aeb {key}=<value>; agent+aeb runs with them)"


def _check_path(cfg: Any, key: str, command: str) -> None:
    """``key`` (dotted) must name an existing field; else one line naming the nearest section's fields."""
    from omegaconf import DictConfig

    node, done = cfg, []
    for part in key.split("."):
        if not isinstance(node, DictConfig) or part not in node:
            where = ".".join(done)
            section = _option_of(cfg, where) if where else f"{'an' if command[0] in 'aeiou' else 'a'} {command} setting"
            allowed = sorted(node.keys()) if isinstance(node, DictConfig) else []
            name = ".".join([*done, part])
            if isinstance(node, DictConfig) and not allowed:  # an empty section, e.g. localizer.noise: {}
                raise ConfigError(f"{name} is not set in {section}; add a key with +{key}=<value>")
            if isinstance(node, DictConfig):
                hint = closest_hint(part, allowed) or (_preset_hint(part) if where == "sensors" else "") or \
                    _no_shield_hint(key, section)
                raise ConfigError(f"{name} is not a field of {section}; allowed: {allowed}{hint}"
                                  if where else f"{name} is not {section}; allowed: {allowed}{hint}")
            raise ConfigError(f"{where} is a value, not a section: cannot set {key}")
        node = node._get_node(part)  # not node[part]: that would resolve an interpolation (${hydra:...})
        done.append(part)


def _preset_hint(sensor: str) -> str:
    """``sensors.cameras.*`` on a preset without cameras (the default, truth, when ``sensors=`` is left out, though
    the agent runs on cameras): name the shipped presets that have that sensor, to add as ``sensors=``."""
    import yaml

    have = sorted(p.name[:-5] for p in (resources.files("conf") / "sensors").iterdir() if p.name.endswith(".yaml")
                  and any(isinstance(d, str) and d.startswith(f"/sensor/{sensor}@")
                          for d in (yaml.safe_load(p.read_text()) or {}).get("defaults", [])))
    pick = sensor if sensor in have else (have[0] if have else "")
    return (f"; add the agent's sensors preset, e.g. sensors={pick} (presets with {sensor}: {have})" if have else "")


def _option_of(cfg: Any, where: str) -> str:
    top = where.split(".")[0]
    name = cfg[top].get("name") if hasattr(cfg[top], "get") else None
    if not name or top not in ("env", "agent", "sensors", "shield"):
        return where
    return f"{top}={name}" if where == top else f"{where} (in {top}={name})"
