"""PID lane keeping on cross-track error, in paper 001's per-step form (digest 001 §4, §8.4).

    u_k = -(Kp·e_k + Ki·Σ_{j≤k} e_j + Kd·(e_k − e_{k−1}))          (eq. (1) discretised per step, no dt)

e is the CTE in metres (+ = right of centre), u the normalised steering in [-1, 1] (+ = right), so a car right of
centre steers left. The gains of paper 001 (Kp 0.75, Ki 0.0001, Kd 1) only make sense in this per-step form: the
sum stays tiny and Kd multiplies a per-step difference. Anti-windup: the integral is frozen while the output
saturates (conditional integration) and clamped to ``i_max``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PRESETS: dict[str, dict[str, float]] = {
    "paper": {"kp": 0.75, "ki": 0.0001, "kd": 1.0},  # digest 001 Table 2, set by hand by the authors
    # `python -m train.pid_search` (grid 120 + Nelder-Mead 60, layout A, training seeds 0-4, gain margin 2):
    # mean |CTE| 0.713 units on those laps vs 4.88 for "paper". The search drops I and D: see train/pid_search.py.
    "tuned": {"kp": 4.88591, "ki": 0.0, "kd": 0.0},
}


@dataclass
class PIDSteering:
    """Per-step PID on CTE → normalised steering. ``cte_index`` picks the CTE from ``obs[obs_key]``."""

    kp: float = 0.75
    ki: float = 0.0001
    kd: float = 1.0
    i_max: float = 1000.0  # m·steps, integral clamp
    obs_key: str = "state"
    cte_index: int = 0

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._integral = 0.0
        self._prev: float | None = None

    def act(self, obs: dict) -> np.ndarray:
        e = float(np.asarray(obs[self.obs_key]).reshape(-1)[self.cte_index])
        if not np.isfinite(e):
            raise ValueError(f"PID got a non-finite CTE ({e}) from obs[{self.obs_key!r}][{self.cte_index}]")
        d = 0.0 if self._prev is None else e - self._prev
        self._prev = e
        integral = float(np.clip(self._integral + e, -self.i_max, self.i_max))
        u = -(self.kp * e + self.ki * integral + self.kd * d)
        if abs(u) < 1.0:  # conditional integration: no wind-up while saturated
            self._integral = integral
        return np.array([np.clip(u, -1.0, 1.0)], dtype=np.float32)
