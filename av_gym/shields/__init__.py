"""Safety shields: ``gymnasium`` wrappers that sit between any agent and the scenario and may override its action
(listed in :data:`av_gym.registry.SHIELDS`, chosen by the ``shield`` config group).

- :mod:`av_gym.shields.aeb` — the predictive AEB shield for the unprotected left turn: one wrapper class
  per decision logic (``paper``, ``improved``, ``standard``, :data:`~av_gym.shields.aeb.AEB_VARIANTS`), each with
  its own typed parameters.
- :mod:`av_gym.shields.predict` — its motion prediction and collision tests (pure numpy functions).
- :mod:`av_gym.shields.opinion` — :class:`Opinion`, what the shield asks before a brake at the stop line.

:func:`find_shield` (the AEB shield in a wrapped env) and :class:`Opinion` are importable from here::

    from av_gym.shields import find_shield
    find_shield(gym.make("av_gym/UnprotectedLeftTurn-v0", shield="aeb")).p.ttc_brake  # 1.5 (s)
"""

from __future__ import annotations

from typing import Any

from av_gym.shields.opinion import Opinion

__all__ = ["Opinion", "find_shield"]


def __getattr__(name: str) -> Any:
    # find_shield lives with the shield class (aeb_base, which loads the perception and prediction code): imported
    # when first asked for, so that importing a light submodule (predict, opinion) does not load the shield
    if name == "find_shield":
        from av_gym.shields.aeb_base import find_shield

        return find_shield
    raise AttributeError(f"module 'av_gym.shields' has no attribute {name!r}")
