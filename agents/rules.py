"""Rule-based baselines."""

from __future__ import annotations

from typing import Any

import numpy as np


class AlwaysProceed:
    """Left-turn baseline: keeps its speed through the intersection whatever the traffic does (the "driver who
    always proceeds" of highway-env's intersection, which collides in a large share of seeded episodes)."""

    def __init__(self, cruise_action: Any) -> None:
        self.cruise_action = cruise_action

    def reset(self) -> None:
        pass

    def act(self, obs: Any) -> Any:
        a = self.cruise_action
        return a.copy() if isinstance(a, np.ndarray) else a
