"""Agents: anything with ``reset()`` and ``act(obs) -> action`` is a :class:`agents.base.Policy`."""

from agents.base import Policy
from agents.pid import PIDSteering
from agents.rules import AlwaysProceed

__all__ = ["AlwaysProceed", "PIDSteering", "Policy"]
