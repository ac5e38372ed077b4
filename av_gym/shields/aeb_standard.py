"""The ``standard`` AEB variant: the TTC = Δx/Δv baseline of paper 003 §2 (see :mod:`av_gym.shields.aeb`)."""

from __future__ import annotations


import gymnasium as gym
import numpy as np

from av_gym.params import Params
from av_gym.shields.predict import standard_ttc
from av_gym.shields.aeb_base import AEBShield
from av_gym.shields.aeb_params import BRAKE, MONITOR, WARN, StandardParams


class StandardAEB(AEBShield):
    """``standard``: the standard AEB of paper 003 §2 (``TTC = Δx/Δv`` on targets ahead in the ego's corridor),
    always active; parameters :class:`StandardParams`."""

    Params = StandardParams
    p: StandardParams
    variant = "standard"

    def __init__(self, env: gym.Env, params: StandardParams | None = None, **overrides) -> None:
        super().__init__(env, params, **overrides)

    def _is_active(self, ego: dict) -> bool:
        return True

    def _decide_variant(self, ego, others, a_ego, a_others, t, active):
        p = self.p
        ttc, target = standard_ttc(ego["xy"], ego["heading"], ego["speed"], ego["size"], others, p.lateral_margin)
        inhibit = p.steering_inhibit_deg
        if inhibit is not None and abs(ego["steering"]) > np.radians(inhibit):
            ttc, target = float("inf"), -1
        if self._latched and self._latched_until_standstill(ego["speed"], t):
            return BRAKE, ttc, p.warn_ttc, target, False
        if ttc <= p.ttc_brake:
            self._latch(t)
            return BRAKE, ttc, p.warn_ttc, target, False
        return (WARN if ttc <= p.warn_ttc else MONITOR), ttc, p.warn_ttc, target, False
