"""The schema of every config group and field (``conf/``), checked in one function, :func:`validate_config`, before
anything runs or is written.

Why an explicit schema rather than Hydra structured configs: the groups' options have different fields (an
``env=lane_keeping`` has ``track``, ``env=left_turn`` has ``mode``; each shield variant its own parameters), the
sensor and shield sections may carry any parameter of their class, and Hydra's own type errors are multi-line. One
checker that knows the option (``env.name``, ``agent.kind``, ``shield.variant``) gives one line naming the field and
what is allowed. Values are still *read* in one place each (:mod:`av_gym.make`, the trainers, the wrappers, whose
constructors keep their own checks for use from Python); this module only says what is acceptable, and
tests/test_validation.py keeps it in step with the wrappers' signatures and with every file under ``conf/``.

Spec language (compact, so the whole schema reads as a table):

- ``"num"``, ``"int"`` with optional bounds: ``"num >=0"``, ``"num >0"``, ``"int >=1"``, ``"num [0,1]"``,
  ``"num [0,1)"``; a trailing ``"|null"`` allows null. Numbers are finite; bools are not numbers.
- ``"bool"``, ``"str"``, ``"any"``; a tuple is an enum of allowed values.
- ``["num"]`` a list of that spec; ``("list", n, "num")`` a list of exactly n.
- a dict is a nested section; a key ending in ``?`` is optional (the class has a default).
- ``Delegate(fn)``: ``fn(value, where) -> list of problems`` (a section another module defines as a dataclass).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from av_gym.errors import ConfigError


@dataclass(frozen=True)
class Delegate:
    check: Callable[[Any, str], list[str]]


def optional(spec: Mapping) -> dict:
    """Every key of a section optional (a class's keyword arguments, each with a default)."""
    return {k if k.endswith("?") else f"{k}?": v for k, v in spec.items()}


# ------------------------------------------------------------------------------------------------ sensors
DETECTOR = {"rate_hz": "num >0", "max_range": "num >0", "fov_deg": "num (0,360]", "miss_rate": "num [0,1)",
            "burst_length": "num >=1|null", "occlusion": "bool", "occlusion_fraction": "num (0,1]",
            "sigma_pos0": "num >=0", "sigma_pos_k": "num >=0", "sigma_vel": "num >=0", "sigma_size": "num >=0",
            "sigma_heading": "num >=0", "clutter_rate": "num >=0", "max_objects": "int >=1",
            "frame": ("world", "ego")}
"""The AEB shield's own detector (AEB below), until the shield checks it with DetectorParams."""
SENSORS: dict = {}  # every sensor and estimator has typed Params now (_sensor_params checks those)
"""Sensor key → its wrapper's keyword arguments (all optional: the wrappers have defaults)."""


def _sensors_section(value: Any, where: str) -> list[str]:
    # The registry in av_gym.make is the one list of sensors and estimators: one added there is checked here too.
    from av_gym.make import SENSOR_PRESETS as presets, _sensor_classes

    if not isinstance(value, Mapping):
        return [f"{where} must be a mapping, got {value!r}"]
    spec: dict = {"name": presets, "keep_state?": "bool", "observe?": ("list+", "str")}
    shipped = _shipped("sensors", value.get("name"))
    for key, cls in _sensor_classes().items():
        own = shipped.get(key) if isinstance(shipped.get(key), Mapping) else {}
        spec[f"{key}?"] = Delegate(lambda v, w, key=key, cls=cls, own=own: _sensor_params(v, w, key, cls, own))
    return _check(value, spec, where, what="a sensor preset field or a sensor", shipped=shipped)


def _sensor_params(value: Any, where: str, key: str, cls: type, shipped: Mapping) -> list[str]:
    """A sensor's keyword arguments: the table's spec where it has one, else the type of the class default (or,
    for a class taking ``**kwargs``, of the preset's shipped value)."""
    import inspect

    if not isinstance(value, Mapping):
        return [f"{where} must be a mapping of {cls.__name__} parameters, got {_fmt(value)}"]
    if getattr(cls, "Params", None) is not None:  # typed params (av_gym/params.py): the one source of truth
        from av_gym.params import check

        return check(cls.Params, value, where, what=f"a parameter of {cls.__name__}")
    params = inspect.signature(cls.__init__).parameters
    table = SENSORS.get(key, {})
    spec = {f"{p}?": table.get(p, _like(param.default)) for p, param in params.items()
            if p not in ("self", "env") and param.kind not in (param.VAR_KEYWORD, param.VAR_POSITIONAL)}
    if any(param.kind is param.VAR_KEYWORD for param in params.values()):
        spec.update({f"{k}?": _like(shipped.get(k)) for k in value if f"{k}?" not in spec})
    return _check(value, spec, where, what=f"a parameter of {cls.__name__}")


def _shipped(group: str, option: Any) -> dict:
    """The option's yaml as shipped in conf/ (empty if there is none)."""
    from importlib import resources

    import yaml

    path = resources.files("conf") / group / f"{option}.yaml" if group else resources.files("conf") / f"{option}.yaml"
    if not isinstance(option, str) or not path.is_file():
        return {}
    text = path.read_text()
    shipped = yaml.safe_load(text) or {}
    inherited: dict = {}
    for entry in shipped.get("defaults", []) if group else []:  # e.g. "/agent/ppo@agent": its fields count too
        if isinstance(entry, str) and entry.startswith(f"/{group}/"):
            inherited.update(_shipped(group, entry[len(group) + 2:].split("@")[0]))
    if text.startswith("# @package _global_") and group:  # e.g. an agent that also picks its sensors
        shipped = shipped.get(group, {}) if isinstance(shipped.get(group), dict) else {}
    return {**inherited, **shipped}


# ------------------------------------------------------------------------------------------------ shield
BRAKE = {"decel": "num >0", "delay": "num >=0", "jerk": "num >=0"}
TRACKER = {"sigma_acc": "num >0", "sigma_pos0": "num >0", "sigma_pos_k": "num >=0", "sigma_vel": "num >0",
           "use_velocity": "bool", "init_vel_sigma": "num >0", "gate": "num >0", "max_distance": "num >0",
           "min_hits": "int >=1", "max_coast": "num >=0", "size_alpha": "num [0,1]"}
AEB = {"variant": ("improved", "paper", "standard"), "mode": ("ground_truth", "perceived"), "step": "num >0",
       "ttc_brake": "num >0", "brake": optional(BRAKE), "detector": optional(DETECTOR), "tracker": optional(TRACKER),
       "activation_distance": "num >0", "half_accel_term": "bool", "limits": ("paper", "aabb"),
       "accel_alpha": "num (0,1]", "margin": "num >=0", "release_margin": "num >=0", "stop_margin": "num >=0",
       "horizon_min": "num >0", "horizon_max": "num >0", "target_model": ("cv", "ca", "map"),
       "release_hold": "num >=0", "feasibility": "bool", "go_speed": "num >0", "warn_ttc": "num >0",
       "steering_inhibit_deg": "num >0|null", "lateral_margin": "num >=0", "standstill_hold": "num >=0|null",
       "ignore_rear": "bool"}
"""AEBShield's keyword arguments (agents/aeb.py); all optional."""


def _shield_section(value: Any, where: str) -> list[str]:
    if not isinstance(value, Mapping):
        return [f"{where} must be a mapping, got {value!r}"]
    kind = value.get("kind", value.get("name", "none"))
    if kind == "none":
        return _check(value, {"name": "str", "kind?": ("none",)}, where)
    if kind != "aeb":
        return [f"{where}.kind must be one of ['none', 'aeb'], got {kind!r}"]
    return _check(value, {"name": "str", "kind": ("aeb",), **optional(AEB)}, where,
                  what="a parameter of the AEB shield", shipped=_shipped("shield", value.get("name")))


# ------------------------------------------------------------------------------------------------ agent
def _agent_section(value: Any, where: str) -> list[str]:
    """The agent section: its kind's Params (agents/registry.py AGENT_KINDS), the one source of its fields."""
    from agents.registry import agent_problems
    from av_gym.make import SENSOR_PRESETS

    found = agent_problems(value, where)
    sensors = value.get("sensors") if isinstance(value, Mapping) else None
    if not found and sensors is not None and sensors not in SENSOR_PRESETS:  # a preset of conf/sensors/
        found.append(f"{where}.sensors must be one of {[*SENSOR_PRESETS, None]}, got {sensors!r}")
    return found


# ------------------------------------------------------------------------------------------------ commands
_PATHS_TRAIN = {"runs": "str", "checkpoints": "str"}
TRAIN = {
    "env": Delegate(lambda v, w: _env_section(v, w)),
    "sensors": Delegate(_sensors_section),
    "agent": Delegate(_agent_section),
    "shield": Delegate(_shield_section),
    "seed": "int >=0",
    "run_name": "name",
    "paths": _PATHS_TRAIN,
    "train": {"checkpoint_every": "int >=1", "resume": "bool", "eval_episodes": "int >=0", "eval_seed": "int >=0",
              "baseline": "str", "progress_bar": "bool", "torch_threads": "int >=1", "eval_every": "int >=0",
              "eval_n": "int >=0", "video_every": "int >=0", "eval_n_envs": "int >=1"},
}
EVAL = {
    "env": Delegate(lambda v, w: _env_section(v, w)),
    "sensors": Delegate(_sensors_section),
    "shield": Delegate(_shield_section),
    "agents": ("list+", "str"),
    "episodes": "int >=1",
    "seed": "int >=0",
    "n_envs": "int >=1",
    "vec_env": ("subproc", "batched"),
    "paths": {"checkpoints": "str"},
    "out_dir": "str",
    "progress_bar": "bool",
    "plots": "bool",
    "videos": "bool",
}
COMMANDS = {"train": TRAIN, "eval": EVAL}


def _env_section(value: Any, where: str) -> list[str]:
    """The ``env`` section against its scenario's Params (``env.name`` picks it in av_gym.registry.SCENARIOS)."""
    from av_gym.params import check
    from av_gym.registry import SCENARIOS

    if not isinstance(value, Mapping):
        return [f"{where} must be a mapping, got {value!r}"]
    name = value.get("name")
    if name not in SCENARIOS:
        return [f"{where}.name must be one of {SCENARIOS.names()}, got {name!r}"]
    return check(SCENARIOS.get(name).Params, value, where, what=f"a field of env={name}")


# ------------------------------------------------------------------------------------------------ checker
_NUM = re.compile(r"^(num|int)(?:\s+(?:(>=|>|<=|<)(-?[\d.e]+)|([\[(])(-?[\d.e]+),(-?[\d.e]+)([\])])))?(\|null)?$")
_NAME = re.compile(r"^[A-Za-z0-9_.=+,:-]+$")
NAME_LENGTH = 240  # "name" fields (run_name): 255 bytes a folder name, less room for a sweep's -j<n>


def _fmt(v: Any) -> str:
    return repr(v) if isinstance(v, str) else str(v)


def _describe(spec: str) -> str:
    m = _NUM.match(spec)
    kind, op, bound, lo_b, lo, hi, hi_b, null = m.groups()
    text = "an integer" if kind == "int" else "a number"
    if op:
        text += f" {op} {bound}"
    elif lo_b:
        text += f" in {lo_b}{lo}, {hi}{hi_b}"
    return text + (" or null" if null else "")


def _check_num(value: Any, spec: str, where: str) -> list[str]:
    m = _NUM.match(spec)
    if m is None:  # pragma: no cover - a typo in this file
        raise AssertionError(f"bad spec {spec!r}")
    kind, op, bound, lo_b, lo, hi, hi_b, null = m.groups()
    bad = [f"{where} must be {_describe(spec)}, got {_fmt(value)}"]
    if value is None:
        return [] if null else bad
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return bad
    if kind == "int" and not isinstance(value, int):
        return bad
    if not math.isfinite(value):
        return bad
    if op:
        b = float(bound)
        ok = {">=": value >= b, ">": value > b, "<=": value <= b, "<": value < b}[op]
    elif lo_b:
        ok = (value >= float(lo) if lo_b == "[" else value > float(lo)) and \
             (value <= float(hi) if hi_b == "]" else value < float(hi))
    else:
        ok = True
    return [] if ok else bad


def _like(default: Any) -> Any:
    """The spec a field gets from its shipped default when the table above does not list it yet."""
    if isinstance(default, bool):
        return "bool"
    if isinstance(default, int):
        return "int"
    if isinstance(default, float):
        return "num"
    if isinstance(default, str):
        return "str"
    if isinstance(default, list):
        return [_like(default[0])] if default else "any"
    return "any"


def _check(value: Any, spec: Any, where: str, what: str = "a field", shipped: Mapping | None = None) -> list[str]:
    """Problems of ``value`` against ``spec`` (module docstring), each one line naming the field. A key of a
    section that the spec lacks is accepted only when the shipped yaml (``shipped``) has it, with its type: a
    field someone added to conf/ is checked at once, a key a user invents (``+agent.foo=1``) is refused."""
    if isinstance(spec, Delegate):
        return spec.check(value, where)
    if isinstance(spec, tuple) and spec and spec[0] in ("list", "list+"):
        if spec[0] == "list+":
            n, item = None, spec[1]
        else:
            n, item = spec[1], spec[2]
        if not isinstance(value, (list, tuple)) or (n is not None and len(value) != n) or (n is None and not value):
            size = f"of {n} items" if n is not None else "with at least one item"
            return [f"{where} must be a list {size}, got {_fmt(value)}"]
        return [p for i, v in enumerate(value) for p in _check(v, item, f"{where}[{i}]")]
    if isinstance(spec, tuple):
        if any(value == s and type(value) is type(s) for s in spec):
            return []
        return [f"{where} must be one of {list(spec)}, got {_fmt(value)}"]
    if isinstance(spec, list):
        if not isinstance(value, (list, tuple)):
            return [f"{where} must be a list, got {_fmt(value)}"]
        return [p for i, v in enumerate(value) for p in _check(v, spec[0], f"{where}[{i}]")]
    if isinstance(spec, dict):
        if not isinstance(value, Mapping):
            return [f"{where} must be a mapping, got {_fmt(value)}"]
        fields = {k.rstrip("?"): (s, not k.endswith("?")) for k, s in spec.items()}
        for key, default in (shipped or {}).items():
            if key not in fields and key != "defaults":
                fields[key] = (_like(default), False)
        problems = []
        for key in value:
            if key not in fields:
                problems.append(f"{_join(where, key)} is not {what}; allowed: {sorted(fields)}")
        for key, (s, required) in fields.items():
            if key in value:
                sub = (shipped or {}).get(key)
                problems += _check(value[key], s, _join(where, key),
                                   shipped=sub if isinstance(s, dict) and isinstance(sub, Mapping) else None)
            elif required:
                problems.append(f"{_join(where, key)} is missing")
        return problems
    if spec == "any":
        return []
    if spec in ("bool", "bool|null"):
        if isinstance(value, bool) or (value is None and spec.endswith("null")):
            return []
        return [f"{where} must be true or false{' or null' if spec.endswith('null') else ''}, got {_fmt(value)}"]
    if spec == "str":
        return [] if isinstance(value, str) and value else [f"{where} must be a non-empty string, got {_fmt(value)}"]
    if spec == "name":  # a folder name: no path separators, and short enough for the file system with the -j<n>
        # suffix a sweep job adds (ext4, xfs, btrfs: 255 bytes a name)
        ok = isinstance(value, str) and bool(_NAME.match(value))
        if ok and len(value) > NAME_LENGTH:
            return [f"{where} must be at most {NAME_LENGTH} characters (a folder name), got {len(value)}: "
                    f"{value[:40]!r}..."]
        return [] if ok else [f"{where} must be a folder name (letters, digits, _ . = + , : -), got {_fmt(value)}"]
    return _check_num(value, spec, where)


def _join(where: str, key: Any) -> str:
    return f"{where}.{key}" if where else str(key)


def problems(cfg: Mapping, command: str) -> list[str]:
    """Every problem of a composed, resolved ``train`` or ``eval`` config, one line each (empty if none)."""
    what = f"{'an' if command[0] in 'aeiou' else 'a'} {command} setting"
    shipped = {k: v for k, v in _shipped("", command).items() if k != "hydra"}  # Hydra's own, not ours
    return _check(cfg, COMMANDS[command], "", what=what, shipped=shipped)


def validate_config(cfg: Any, command: str) -> None:
    """Raise :class:`ConfigError` with the first problem of ``cfg`` (an OmegaConf node or a plain mapping)."""
    if hasattr(cfg, "_metadata"):
        from omegaconf import OmegaConf

        cfg = OmegaConf.to_container(cfg, resolve=True)
    found = problems(cfg, command)
    if found:
        raise ConfigError(found[0])


def section_problems(group: str, value: Any, where: str | None = None) -> list[str]:
    """Problems of one group's section (``env``, ``sensors``, ``agent``, ``shield``) on its own."""
    checks = {"env": _env_section, "sensors": _sensors_section, "agent": _agent_section, "shield": _shield_section}
    return checks[group](value, where or group)


# ------------------------------------------------------------------------------------------------ command line
_PLACEHOLDER = "hydra-runtime-value"  # a valid folder name, so run_name=${hydra:...} passes


def check_command_line(command: str, argv: list[str]) -> list:
    """Compose the config the way Hydra will for ``python -m <command> <argv>`` and check it, *before* Hydra runs:
    so a typo gives one line (not Hydra's multi-line report) and no run folder is created. Returns the composed
    configs (one per swept value with ``-m``; ``hydra:`` interpolations replaced by a placeholder) for the
    command's own checks. Hydra's own options (``--help``, ``--cfg``, ``-c`` ...) are left to Hydra.

    A sweep is checked value by value (each swept value once, the other sweeps at their first value): linear in
    the number of values, and every value a job will see has been checked."""
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
    groups = [next(iter(d)) for d in _shipped("", command).get("defaults", []) if isinstance(d, dict)]
    composed = []
    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
    with initialize_config_module("conf", version_base="1.3"):
        for combo in combos:
            try:
                composed.append(_compose_checked(command, combo, groups, compose, multirun=bool(flags)))
            except (HydraException, OmegaConfBaseException) as exc:
                raise ConfigError(_one_line(exc)) from None
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
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from av_gym.errors import folder_problem

    parsed = OverridesParser.create().parse_overrides(overrides)
    group_overrides, value_overrides = [], []
    for o, text in zip(parsed, overrides):
        key = o.key_or_group
        if key.startswith("hydra") or "/" in key or "@" in key or key in groups:
            group_overrides.append((o, text))
        else:
            value_overrides.append((o, text))
    for o, _ in group_overrides:
        if o.key_or_group in groups and not o.is_delete():
            options = _options(o.key_or_group)
            value = o.value()
            if value not in options:
                raise ConfigError(f"{o.key_or_group}={value}: {o.key_or_group} must be one of {options}")
    base = compose(config_name=command, overrides=[t for _, t in group_overrides])
    for o, _ in value_overrides:
        if o.is_add() or o.is_force_add() or o.is_delete():
            continue  # a new key: the schema below refuses it unless the section allows it
        _check_path(base, o.key_or_group, command)
    # With Hydra's own section, to check the folder Hydra will make for the job (hydra.run.dir, or hydra.sweep.dir
    # with -m) before it makes it: one line for a path it cannot create, not Hydra's traceback.
    cfg = compose(config_name=command, overrides=overrides, return_hydra_config=True)

    def hydra_values(node: Any, path: str = ""):  # ${hydra:...} values are filled by Hydra only once a job runs
        if isinstance(node, dict):
            for k, v in node.items():
                yield from hydra_values(v, f"{path}.{k}" if path else str(k))
        elif isinstance(node, str) and "${hydra:" in node:
            yield path

    for path in list(hydra_values(OmegaConf.to_container(cfg, resolve=False))):
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
    if isinstance(job_dir, str):
        problem = folder_problem(job_dir, key)
        if problem:
            given = any(o.key_or_group == key for o in parsed)
            raise ConfigError(problem if given or raw == job_dir else f"{problem} ({key} is {raw})")
    return cfg


def _options(group: str) -> list[str]:
    from importlib import resources

    return sorted(p.name[:-5] for p in (resources.files("conf") / group).iterdir() if p.name.endswith(".yaml"))


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
                raise ConfigError(f"{name} is not a field of {section}; allowed: {allowed}"
                                  if where else f"{name} is not {section}; allowed: {allowed}")
            raise ConfigError(f"{where} is a value, not a section: cannot set {key}")
        node = node._get_node(part)  # not node[part]: that would resolve an interpolation (${hydra:...})
        done.append(part)


def _option_of(cfg: Any, where: str) -> str:
    top = where.split(".")[0]
    name = cfg[top].get("name") if hasattr(cfg[top], "get") else None
    if not name or top not in ("env", "agent", "sensors", "shield"):
        return where
    return f"{top}={name}" if where == top else f"{where} (in {top}={name})"
