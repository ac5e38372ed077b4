"""What the AEB shield asks before a brake at the stop line: a second opinion (:class:`Opinion`).

The shield holds one in :attr:`~av_gym.shields.aeb.AEBShield.opinion` (or takes it as ``opinion=`` when built);
whoever builds the shield installs it. The library has no opinion of its own: the harness installs its belief
planner for ``shield.second_opinion`` (conf/shield/aeb_belief.yaml), and your own code passes any object with
these three methods::

    class NeverSafe:
        def reset(self) -> None: ...
        def observe(self, env, obs) -> None: ...
        def go_is_safe(self, env) -> bool:
            return False

    find_shield(env).opinion = NeverSafe()
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import gymnasium as gym


@runtime_checkable
class Opinion(Protocol):
    """A second opinion on a brake at the stop line (never asked about an emergency brake)."""

    def reset(self) -> None:
        """A new episode starts (before the first :meth:`observe`)."""

    def observe(self, env: gym.Env, obs: Any) -> None:
        """Every observation of the sensed env the shield wraps: the reset's, then each step's."""

    def go_is_safe(self, env: gym.Env) -> bool:
        """Whether going on is safe now; True withholds the stop-line brake the shield was about to command."""


def check_opinion(opinion: Any, where: str = "opinion") -> None:
    """A :class:`TypeError` naming what ``opinion`` lacks, unless it is None or an :class:`Opinion`."""
    if opinion is not None and not isinstance(opinion, Opinion):
        missing = [m for m in ("reset", "observe", "go_is_safe") if not callable(getattr(opinion, m, None))]
        raise TypeError(f"{where} must have reset(), observe(env, obs) and go_is_safe(env) (av_gym.shields."
                        f"Opinion), got {type(opinion).__name__} without {', '.join(missing)}")
