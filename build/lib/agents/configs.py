"""The agent configs shipped in ``conf/agent/``, read as files (not composed, and without importing the ``conf``
package, which imports agents): their names and their kinds, for the checks that must know which agent configs
exist (``agent.init`` names one of a teacher kind). Composing one as Hydra would is
:func:`eval.agents.load_agent_config`."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import yaml

from av_gym.errors import ConfigError

AGENT_DIR = Path(__file__).resolve().parent.parent / "conf" / "agent"
KIND_DEFAULT = "/agent_kind/"  # a conf/agent/<name>.yaml extends its kind's defaults: /agent_kind/<kind>@_here_


def available_agents() -> list[str]:
    return sorted(p.stem for p in AGENT_DIR.glob("*.yaml"))


@lru_cache(maxsize=None)
def shipped_agent(name: str) -> dict:
    """``conf/agent/<name>.yaml`` as written (a :class:`ConfigError` listing the agents if there is none)."""
    path = AGENT_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"agent {name!r} is not in conf/agent/; available: {available_agents()} or a checkpoint path")
    return yaml.safe_load(path.read_text()) or {}


def kind_default(raw: dict) -> str | None:
    """The kind whose defaults an agent config extends (``/agent_kind/<kind>@_here_`` in its defaults list)."""
    for entry in raw.get("defaults", []):
        if isinstance(entry, str) and entry.startswith(KIND_DEFAULT):
            return entry[len(KIND_DEFAULT):].split("@")[0]
    return None


def agent_kind_of(name: str) -> str | None:
    """The kind of the shipped agent config ``name`` (None for a ``_global_`` variant, which names its base agent
    config instead)."""
    raw = shipped_agent(name)
    return raw.get("kind") or kind_default(raw)
