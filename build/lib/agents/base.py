"""The one shape every agent has, rule-based or learned."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable


@runtime_checkable
class Policy(Protocol):
    """Maps one (unbatched) observation to one action; ``reset()`` clears any memory between episodes."""

    def reset(self) -> None: ...

    def act(self, obs: Any) -> Any: ...
