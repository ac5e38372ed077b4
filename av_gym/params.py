"""Typed, frozen parameter dataclasses: each parameter's type, default, unit, bounds and reason in one place.

Every component (scenario, sensor, estimator, shield variant, agent kind, the commands' own settings) declares one
:class:`Params` subclass; from it come the defaults, the checks with their one-line messages, the Hydra config
checker (:mod:`av_gym.config`) and the documentation of each field. A yaml file under ``conf/`` holds only what
differs from these defaults, with its reason.

    @dataclass(frozen=True)
    class GNSSParams(Params):
        sigma: float = param(1.5, "m", ge=0, doc="white position noise per axis (digest 000 §5.1)")

A field's type is its annotation: ``float``, ``int``, ``bool``, ``str``, ``Literal[...]`` (one of), ``X | None``
(nullable), ``tuple[X, ...]`` (a list), ``tuple[X, X]`` (a list of exactly that many), another :class:`Params`
(a nested section) or ``Any``. Bounds (``ge``, ``gt``, ``le``, ``lt``) apply to numbers and to each number of a
list. Relations between fields go in :meth:`Params.relations`.

Messages name the field relative to the section (``sigma must be a number >= 0, got -1``); the config layer adds
the path (``sensors.gnss.sigma ...``), so the library does not know the config layout.

Why not Hydra's structured configs alone: their type errors are multi-line and they have no bounds; why not
pydantic: one more dependency for what a hundred lines of dataclass introspection do, with our message format.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass
from typing import Any, Literal, Union, get_args, get_origin

from av_gym.errors import ConfigError, closest_hint


class ParamError(ConfigError):
    """A bad parameter value; the message starts with the field's name relative to its section."""


def param(default: Any = MISSING, unit: str = "", *, ge: float | None = None, gt: float | None = None,
          le: float | None = None, lt: float | None = None, doc: str = "", name_like: bool = False,
          min_items: int = 0) -> Any:
    """A dataclass field with its unit, bounds and reason (``doc``: where the default comes from, why);
    ``name_like``: a string that becomes a folder name; ``min_items``: a list's least length (checked where the
    config layer checks, not on construction, so a default may be empty and be filled by a yaml)."""
    meta = {"unit": unit, "ge": ge, "gt": gt, "le": le, "lt": lt, "doc": doc, "name_like": name_like,
            "min_items": min_items}
    if isinstance(default, Params):  # a nested section: a fresh default per instance (frozen anyway)
        return dataclasses.field(default_factory=lambda: default, metadata=meta)
    if isinstance(default, (list, dict)):
        raise TypeError("param(): use a tuple for a list default (frozen)")
    return dataclasses.field(default=default, metadata=meta)


@dataclass(frozen=True)
class Params:
    """Base of every parameter dataclass: checked on construction (``ParamError`` naming the first bad field)."""

    def __post_init__(self) -> None:
        found = check(type(self), self.as_dict(), construction=True)
        if found:
            raise ParamError(found[0])

    # ------------------------------------------------------------------------------------------- construction
    @classmethod
    def from_mapping(cls, values: Mapping | None = None, where: str = "", what: str | None = None,
                     **overrides: Any):
        """An instance from a (yaml) mapping: lists become tuples, nested sections their Params; the first
        problem raises :class:`ParamError` with the field's path under ``where``."""
        merged = {**(values or {}), **overrides}
        found = check(cls, merged, where, what)
        if found:
            raise ParamError(found[0])
        return _assemble(cls, merged)  # checked just now, relations included: not again by __post_init__

    @classmethod
    def build(cls, params: "Params | Mapping | None" = None, **overrides: Any):
        """``params`` (an instance or a mapping, may be None) with ``overrides`` on top: what a wrapper's
        ``__init__(env, params=None, **overrides)`` calls, so both ``GNSS(env, sigma=2)`` and
        ``GNSS(env, GNSSParams(sigma=2))`` work."""
        if isinstance(params, cls):
            return dataclasses.replace(params, **overrides) if overrides else params
        return cls.from_mapping(params, **overrides)

    def as_dict(self) -> dict:
        """Plain values (nested sections as dicts, tuples as lists): what a yaml file would hold."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    # ------------------------------------------------------------------------------------------- checks
    def problems(self, where: str = "") -> list[str]:
        return check(type(self), self.as_dict(), where)

    def relations(self) -> list[str]:
        """Problems a single field's bounds cannot say (e.g. ``min < max``), one line each, with every field
        named as ``@field`` (the checker writes its path: ``@lane_width`` → ``env.lane_width``). Called only when
        every field is valid on its own."""
        return []

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls)]


# ----------------------------------------------------------------------------------------------- the checker
def check(cls: type[Params], values: Any, where: str = "", what: str | None = None, *,
          construction: bool = False) -> list[str]:
    """Every problem of ``values`` (a mapping) against ``cls``'s fields, one line each naming the field under
    ``where``. A key ``cls`` lacks is refused, listing the allowed ones."""
    if not isinstance(values, Mapping):
        return [f"{where or cls.__name__} must be a mapping, got {_fmt(values)}"]
    what = what or f"a parameter of {cls.__name__.removesuffix('Params') or cls.__name__}"
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = _hints(cls)
    found = [f"{_join(where, k)} is not {what}; allowed: {sorted(fields)}{closest_hint(k, list(fields))}"
             for k in values if k not in fields]
    for name, f in fields.items():
        if name in values:
            meta = {**f.metadata, "min_items": 0} if construction else f.metadata
            found += _check_value(values[name], hints[name], meta, _join(where, name))
        elif f.default is MISSING and f.default_factory is MISSING:
            found.append(f"{_join(where, name)} is missing")
    if found:
        return found
    try:
        instance = _assemble(cls, values)  # without __post_init__'s own check, to ask its relations
        return [_REF.sub(lambda m: _join(where, m.group(1)), p) for p in instance.relations()]
    except (TypeError, ValueError) as exc:  # pragma: no cover - a relation that assumed more than was checked
        return [f"{where or cls.__name__}: {exc}"]


@functools.lru_cache(maxsize=None)  # asked per config key at every env reset; a class's fields never change
def field_at(cls: type[Params], path: str) -> tuple[type[Params], dataclasses.Field]:
    """The Params class holding the field ``path`` (dotted into nested sections: ``ccftap.dt``) and that field; a
    :class:`KeyError` naming ``path`` if there is none."""
    params, name = cls, path
    while "." in name:
        head, name = name.split(".", 1)
        params = _hints(params).get(head) if head in params.field_names() else None
        if not (isinstance(params, type) and issubclass(params, Params)):
            raise KeyError(f"{cls.__name__} has no section {head!r} for {path!r}")
    fields = {f.name: f for f in dataclasses.fields(params)}
    if name not in fields:
        raise KeyError(f"{cls.__name__} has no field {path!r}")
    return params, fields[name]


def field_problems(cls: type[Params], path: str, value: Any, where: str,
                   scale: Callable[[float], float] | None = None) -> list[str]:
    """The problems of ``value`` as the field ``path`` of ``cls`` (:func:`field_at`): its type and bounds, one line
    naming ``where``. ``scale`` converts the bounds first, for a value in other units than the field's (SI for a
    km/h field: the message then shows the bounds in the value's units)."""
    params, f = field_at(cls, path)
    meta = dict(f.metadata)
    if scale is not None:
        meta.update({k: scale(meta[k]) for k in ("ge", "gt", "le", "lt") if meta.get(k) is not None})
    return _check_value(value, _hints(params)[f.name], meta, where)


def relation_problems(cls: type[Params], values: Mapping, name: Callable[[str], str]) -> list[str]:
    """:meth:`Params.relations` of ``values`` (fields checked one by one already; defaults for the missing ones),
    each ``@field`` written as ``name(field)``: how a caller that holds the values under other names (an env's
    config keys) says them."""
    return [_REF.sub(lambda m: name(m.group(1)), p) for p in _assemble(cls, values).relations()]


def _assemble(cls: type[Params], values: Mapping) -> Params:
    """A frozen instance of checked ``values`` (converted to the fields' types; defaults for the missing ones),
    built without :meth:`Params.__post_init__`'s check: the caller has just made it."""
    hints = _hints(cls)
    instance = cls.__new__(cls)
    for f in dataclasses.fields(cls):
        value = _convert(hints[f.name], values[f.name]) if f.name in values else _default(f)
        object.__setattr__(instance, f.name, value)
    return instance


def _check_value(value: Any, hint: Any, meta: Mapping, where: str) -> list[str]:
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType) and type(None) in args:
        if value is None:
            return []
        rest = [a for a in args if a is not type(None)]
        inner = rest[0] if len(rest) == 1 else Union[tuple(rest)]  # type: ignore[valid-type]
        found = _check_value(value, inner, meta, where)
        return [_or_null(p) for p in found]
    if hint is Any:
        return []
    if origin is Literal:
        if any(value == a and type(value) is type(a) for a in args):
            return []
        return [f"{where} must be one of {list(args)}, got {_fmt(value)}"]
    if isinstance(hint, type) and issubclass(hint, Params):
        return check(hint, value, where) if isinstance(value, Mapping) else \
            [f"{where} must be a mapping of {hint.__name__.removesuffix('Params')} parameters, got {_fmt(value)}"]
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            return [f"{where} must be a list, got {_fmt(value)}"]
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                return [f"{where} must be a list of {len(args)} items, got {_fmt(value)}"]
            items = args
        else:
            items = (args[0] if args else Any,) * len(value)
            if len(value) < meta.get("min_items", 0):
                return [f"{where} must be a list with at least {meta['min_items']} item"
                        f"{'s' if meta['min_items'] > 1 else ''}, got {_fmt(list(value))}"]
        return [p for i, (v, h) in enumerate(zip(value, items)) for p in _check_value(v, h, meta, f"{where}[{i}]")]
    if hint is bool:
        return [] if isinstance(value, bool) else [f"{where} must be true or false, got {_fmt(value)}"]
    if hint is str:
        if not (isinstance(value, str) and value):
            return [f"{where} must be a non-empty string, got {_fmt(value)}"]
        if meta.get("name_like"):  # a folder name: no separators, short enough for the -j<n> a sweep job adds
            if not _NAME.match(value) or not value.strip("."):  # '.' and '..' name this folder or the one above
                return [f"{where} must be a folder name (letters, digits, _ . = + , : -; not '.' or '..'), got "
                        f"{_fmt(value)}"]
            if len(value) > NAME_LENGTH:
                return [f"{where} must be at most {NAME_LENGTH} characters (a folder name), got {len(value)}: "
                        f"{value[:40]!r}..."]
        return []
    if hint in (int, float):
        return _check_number(value, hint is int, meta, where)
    raise TypeError(f"{where}: unsupported parameter type {hint!r}")  # pragma: no cover - a typo in a Params


def _check_number(value: Any, integer: bool, meta: Mapping, where: str) -> list[str]:
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    ok = ok and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        for key, test in (("ge", lambda b: value >= b), ("gt", lambda b: value > b), ("le", lambda b: value <= b),
                          ("lt", lambda b: value < b)):
            if meta.get(key) is not None and not test(meta[key]):
                ok = False
    return [] if ok else [f"{where} must be {_describe_number(integer, meta)}, got {_fmt(value)}"]


def _describe_number(integer: bool, meta: Mapping) -> str:
    text = "an integer" if integer else "a number"
    lo = ("[", meta["ge"]) if meta.get("ge") is not None else ("(", meta["gt"]) if meta.get("gt") is not None else None
    hi = ("]", meta["le"]) if meta.get("le") is not None else (")", meta["lt"]) if meta.get("lt") is not None else None
    if lo and hi:
        return f"{text} in {lo[0]}{_num(lo[1])}, {_num(hi[1])}{hi[0]}"
    if lo:
        return f"{text} {'>=' if lo[0] == '[' else '>'} {_num(lo[1])}"
    if hi:
        return f"{text} {'<=' if hi[0] == ']' else '<'} {_num(hi[1])}"
    return text


def _or_null(problem: str) -> str:
    head, sep, tail = problem.rpartition(", got ")
    return f"{head} or null{sep}{tail}" if sep and " must be " in head else problem


# ----------------------------------------------------------------------------------------------- helpers
_REF = re.compile(r"@(\w+)")
_NAME = re.compile(r"^[A-Za-z0-9_.=+,:-]+$")
# Seeds: numpy's legacy RandomState (SB3's set_random_seed, gymnasium's spaces) takes seeds below 2**32, and a run
# uses seed + i for its i-th env or episode: 2**31 - 1 (the largest int32) leaves room for 2**31 more.
SEED_MAX = 2**31 - 1
# Episode counts: seed + episodes must stay below 2**32 (above), and 10 million episodes is already days on a
# workstation.
EPISODES_MAX = 10_000_000
# Rates (sensor Hz, simulation and policy frequency): above the simulation's own ceiling a sensor samples at every
# observation anyway, and 1000 Hz over a 20 s episode is 20,000 ticks (~50x the default's cost); a larger value only
# makes the catch-up loops run for hours (1e9 Hz hung).
RATE_MAX_HZ = 1000
# Rows of an object list in an observation (detections, tracks, turn signals, turn features): every row is
# allocated per step, per env; 256 is 16x the defaults and more vehicles than the intersection ever holds.
ROWS_MAX = 256
NAME_LENGTH = 240  # name_like fields (run_name): 255 bytes a folder name (ext4, xfs, btrfs), less a sweep's -j<n>


def _hints(cls: type) -> dict[str, Any]:
    cached = cls.__dict__.get("_hints_cache")
    if cached is None:
        # each class's annotations in its own module (a subclass elsewhere inherits fields whose types name
        # what the base's module imports)
        cached = typing.get_type_hints(cls)
        cached = {f.name: cached[f.name] for f in dataclasses.fields(cls)}
        type.__setattr__(cls, "_hints_cache", cached)
    return cached


def _default(f: dataclasses.Field) -> Any:
    return f.default if f.default is not MISSING else f.default_factory()  # type: ignore[misc]


def _convert(hint: Any, value: Any) -> Any:
    """A checked yaml value as the field's Python type: lists → tuples, mappings → nested Params."""
    origin, args = get_origin(hint), get_args(hint)
    if value is None:
        return None
    if origin in (Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        return _convert(rest[0], value) if len(rest) == 1 else value
    if isinstance(hint, type) and issubclass(hint, Params):
        return value if isinstance(value, hint) else hint.from_mapping(value)
    if origin in (tuple, list) and isinstance(value, (list, tuple)):
        items = args if args and args[-1] is not Ellipsis else ((args[0] if args else Any),) * len(value)
        return tuple(_convert(h, v) for h, v in zip(items, value))
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def _plain(value: Any) -> Any:
    if isinstance(value, Params):
        return value.as_dict()
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


def _num(x: float) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"  # an integer bound in full (2147483647, not 2.14748e+09)


def _fmt(v: Any) -> str:
    return repr(v) if isinstance(v, str) else str(v)


def _join(where: str, key: Any) -> str:
    return f"{where}.{key}" if where else str(key)
