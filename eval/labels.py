"""The label of an evaluation row: what ran, not only the agent's name.

One rule, made once by :func:`eval.agents.plan_agent` and carried unchanged by every writer (the per-env runner,
the batch, results.csv's ``agent`` column, results.md and ``python -m eval.results_page``, which reads the column):
the agent spec as given (``always_proceed``, ``ppo_turn:latest@turn_perceived+aeb``), plus whatever the command line
changed about how it ran, in the spec's own grammar:

- the sensors: ``@<preset>`` when it ran on another preset than the bare spec runs on (its own, its ``@preset``, or
  eval's default for an agent with none), then ``(<field>=<value>, ...)`` for every field that differs from that
  preset (``gap_acceptance@turn_perceived(detector.miss_rate=0.5)``);
- the shield: ``+<shield>`` for a shield given by ``shield=`` (``always_proceed+aeb``, as the spec ``+aeb`` reads),
  then ``(<field>=<value>, ...)`` for its fields that differ from the shipped preset (``+aeb(mode=perceived)``).

Without any such change the label is the spec, so the rows of every shipped results.csv (none of whose commands
changed either) read as before."""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from typing import Any

from conf.check import _flatten, sensor_overrides

__all__ = ["label_base", "row_label", "swept_label"]

# Where an agent's name ends in a label: its `@preset`, `+shield` or `(changed fields)`
_SUFFIX = re.compile(r"[@+(]")
# A label's parts: agent, sensors preset and changed fields, shield and changed fields
_PARTS = re.compile(r"^(?P<agent>[^@+(]+)(?P<preset>@[^+(]+)?(?:\((?P<sensors>[^)]*)\))?"
                    r"(?P<shield>\+[^(]+)?(?:\((?P<shield_fields>.*)\))?$")


def label_base(label: str) -> str:
    """The agent (name, ``:latest`` form or checkpoint path) a row label starts with, without what follows it."""
    return _SUFFIX.split(label, maxsplit=1)[0]


def _value(v: Any) -> str:
    return v if isinstance(v, str) else repr(v)


def _fields(changed: Mapping[str, Any]) -> str:
    """``(a.b=1, c=x)`` for the changed fields (dotted paths, sorted), ``""`` for none."""
    return f"({', '.join(f'{k}={_value(v)}' for k, v in sorted(changed.items()))})" if changed else ""


def _sensors_part(given_preset: bool, sensors: Mapping | None, baseline: Mapping | None) -> str:
    """``@preset`` (only when the spec named none and the preset is not the one the bare spec runs on) and the
    fields of ``sensors`` that differ from the preset compared with."""
    if sensors is None or baseline is None:  # a caller that leaves the sensors to the env (ccftap): nothing chosen
        return ""
    name = sensors.get("name")
    if not given_preset and name != baseline.get("name"):
        return f"@{name}" + _fields(sensor_overrides(sensors))  # against the shipped preset it names
    flat, base = _flatten(dict(sensors)), _flatten(dict(baseline))
    return _fields({k: v for k, v in flat.items() if k != "name" and (k not in base or base[k] != v)})


def _shield_part(spec_shield: str | None, shield: Mapping | None) -> str:
    """``+shield`` as the spec gave it, or the command line's shield when it is one, with its changed fields."""
    from av_gym.batched.shield import shield_kind

    if shield_kind(shield) == "none":
        return f"+{spec_shield}" if spec_shield else ""
    return f"+{spec_shield or (shield or {}).get('name', shield_kind(shield))}" + \
        _fields(sensor_overrides(shield, "shield"))


def row_label(spec: str, sensors: Mapping | None, baseline: Mapping | None, shield: Mapping | None) -> str:
    """The row label of agent ``spec`` run on ``sensors`` behind ``shield``; ``baseline`` is the sensors config the
    bare spec runs on with no ``sensors=`` or ``sensors.*`` given (its own, its ``@preset``'s, its checkpoint's, or
    eval's default; None: do not compare). Both configs are composed dicts; the label is ``spec`` when nothing
    differs."""
    head, plus, spec_shield = str(spec).partition("+")
    return head + _sensors_part("@" in head, sensors, baseline) + _shield_part(spec_shield if plus else None, shield)


def swept_label(label: str, swept: Iterable[str]) -> str:
    """``label`` without the parts a sweep's varying overrides (``swept``: ``sensors.detector.miss_rate``,
    ``shield``, ...) put in it, so that an agent is one line over the swept values (python -m eval.sweep, whose
    table gives those values in their own columns): ``always_proceed+aeb(detector.miss_rate=0.1)`` over
    ``shield.detector.miss_rate`` is ``always_proceed+aeb``. A label that is not of this grammar is kept."""
    swept = set(swept)
    m = _PARTS.match(label)
    if m is None:
        return label

    def kept(fields: str | None, group: str) -> str:
        left = [f for f in (fields.split(", ") if fields else []) if f"{group}.{f.partition('=')[0]}" not in swept]
        return f"({', '.join(left)})" if left else ""

    preset = "" if "sensors" in swept else m["preset"] or ""
    shield = "" if "shield" in swept else m["shield"] or ""
    return m["agent"] + preset + kept(m["sensors"], "sensors") + shield + kept(m["shield_fields"], "shield")
