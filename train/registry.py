"""The trainers, by agent kind: what ``python -m train`` runs for a trained kind (one whose
:class:`agents.registry.AgentKind` names a ``checkpoint`` file). The training side names them here, so that the
agents never name a module of :mod:`train` (they sit below it).

A new trained kind is its :class:`~agents.registry.AgentKind` (Params, ``checkpoint``, ``load``) plus one line in
:data:`TRAINERS` (and one in :data:`TRAIN_CHECKS` if its trainer needs more than the Params check).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from av_gym.errors import ConfigError
from av_gym.registry import Registry

TRAINERS = Registry("agent.kind", {
    "ppo": "train.ppo:train_ppo",
    "dagger": "train.dagger:train_dagger",
    "pilotnet": "train.bc:train_pilotnet",
})
"""Trained agent kind → its trainer, ``train(cfg, ckpt_dir, run_dir, command=...) -> model path`` (the final
checkpoint, the kind's ``checkpoint`` file in ``ckpt_dir``); imported when first used."""

TRAIN_CHECKS = Registry("agent.kind", {
    "ppo": "train.ppo:validate",
    "dagger": "train.dagger:validate",
    "pilotnet": "train.bc:validate",
})
"""Trained agent kind → ``validate(cfg) -> [problems]``: what its trainer needs beyond the kind's Params (the env,
the sensors preset), each one line; checked before a run folder is claimed."""


def trainer_of(kind: str) -> Callable[..., Any]:
    """The trainer of the trained agent kind ``kind``; a :class:`ConfigError` if none is registered."""
    if kind not in TRAINERS:
        raise ConfigError(f"agent.kind {kind!r} is trained but has no trainer: add it to train/registry.py "
                          f"TRAINERS (trainers: {TRAINERS.names()})")
    return TRAINERS.get(kind)


def train_problems(kind: str, cfg: Any) -> list[str]:
    """What the trainer of ``kind`` finds missing in the composed config ``cfg`` (:data:`TRAIN_CHECKS`), one line
    each; none for a kind without a check."""
    return list(TRAIN_CHECKS.get(kind)(cfg)) if kind in TRAIN_CHECKS else []
