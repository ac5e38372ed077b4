"""The ``paper`` AEB variant: digest 003 §4.1-4.8 as written (see :mod:`av_gym.shields.aeb`)."""

from __future__ import annotations


import gymnasium as gym
import numpy as np

from av_gym.params import Params
from av_gym.shields.predict import paper_horizon, paper_ttc
from av_gym.shields.aeb_base import AEBShield, _wrap
from av_gym.shields.aeb_params import BRAKE, MONITOR, WARN, PaperParams


class PaperAEB(AEBShield):
    """``paper``: the predictive AEB of digest 003 §4.1-4.8 (module docstring); parameters :class:`PaperParams`."""

    Params = PaperParams
    p: PaperParams
    variant = "paper"

    def __init__(self, env: gym.Env, params: PaperParams | None = None, **overrides) -> None:
        super().__init__(env, params, **overrides)

    def _decide_variant(self, ego, others, a_ego, a_others, t, active):
        horizon = paper_horizon(ego["speed"])
        ttc, target = float("inf"), -1
        if len(others):
            c, s = np.cos(self.approach_heading), np.sin(self.approach_heading)
            rot = np.array([[c, s], [-s, c]])  # world → approach frame (x along the approach)
            rel = (others[:, 0:2] - ego["xy"]) @ rot.T
            phi0 = -_wrap(ego["heading"] - self.approach_heading)  # + = turning left (heading decreases here)
            ttc, target = paper_ttc(rel, rot @ ego["velocity"], rot @ a_ego, others[:, 2:4] @ rot.T,
                                    a_others @ rot.T, others[:, 5:7], ego["size"], phi0, -ego["yaw_rate"],
                                    horizon, self.p.step, self.p.half_accel_term, self.p.limits)
        if self._latched and self._latched_until_standstill(ego["speed"], t):
            return BRAKE, ttc, horizon, target, False
        if ttc <= self.p.ttc_brake:
            self._latch(t)
            return BRAKE, ttc, horizon, target, False
        return (WARN if ttc <= horizon else MONITOR), ttc, horizon, target, False
