"""``TurnSignals``: each nearby vehicle's direction indicator, as a camera-based indicator classifier reports it.

Why: at an unprotected left turn the other drivers' intent decides the gap. A car coming from the right that will
turn right never crosses the ego's path; one that will go straight does. Constant-velocity prediction cannot tell
the two apart until the car is already turning (docs/ppo.md: 12 % of the lookahead oracle's choices are not
predictable from the motion features, and those decide collisions). A real car reads the indicator.

The indicator a driver *intends* comes from the vehicle's route in the simulator (highway-env's intersection:
approach ``o{i}→ir{i}``, then ``ir{i}→il{j}``, then the exit ``il{j}→o{j}``): left while it approaches or crosses the
intersection towards ``o{(i+1) % 4}``, right towards ``o{(i-1) % 4}``, none when going straight or once on the exit.
What the ego's sensor reports passes through a noisy channel (defaults are suggestions; no source paper measures
this, see docs/ppo.md):

- ``no_signal_rate`` 0.25 per vehicle: the driver does not indicate at all. Chosen pessimistic on purpose:
  unsignalled turns are common in traffic, and a policy must not learn to trust the indicator blindly.
- ``wrong_rate`` 0.05 per vehicle: a turning driver's indicator shows the other direction (a mistaken one).
- ``miss_rate`` 0.1 per reading: the classifier misses an indicator that is on (occlusion, blink phase).
- ``max_range`` 60 m: beyond it no indicator is read (a few pixels per lamp for a 66-200 px wide camera).

The per-vehicle draws (does this driver indicate, and correctly?) are made once, when the vehicle is first seen,
from the sensor's seeded generator; the per-reading misses at every step, in the road's vehicle order.

``obs["signals"]``: ``Box(max_objects, 4)`` rows ``[present, x, y, signal]``, nearest first, zero rows unused;
``x, y`` (m, world) locate the vehicle the reading belongs to (so an estimator can attach it to an object or a
track), ``signal`` is +1 left, -1 right, 0 none seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.params import ROWS_MAX, Params, param
from av_gym.sensors.base import SensorWrapper, ego_pose

LEFT, NONE, RIGHT = 1.0, 0.0, -1.0
FIELDS = ("present", "x", "y", "signal")
BOUND = 1e4


def intended_signal(vehicle) -> float:
    """The indicator ``vehicle`` should show on highway-env's four-way intersection, from its route: +1 left, -1
    right, 0 straight, on the exit road, or off the intersection's roads (no route, e.g. a CCFtap target)."""
    lane = getattr(vehicle, "lane_index", None)
    route = getattr(vehicle, "route", None)
    if not lane or not route:
        return NONE
    start, end = str(lane[0]), str(lane[1])
    destination = str(route[-1][1])
    if start.startswith("o") and end.startswith("ir"):
        origin = end[2:]
    elif start.startswith("ir") and end.startswith("il"):
        origin = start[2:]
    else:  # on the exit road, or a road this rule does not know
        return NONE
    if not (origin.isdigit() and destination.startswith("o") and destination[1:].isdigit()):
        return NONE
    turn = (int(destination[1:]) - int(origin)) % 4
    return LEFT if turn == 1 else RIGHT if turn == 3 else NONE


@dataclass(frozen=True)
class TurnSignalsParams(Params):
    """The indicator channel (module docstring). No source paper measures it: the values are our suggestions."""

    max_range: float = param(60.0, "m", gt=0, doc="no indicator read farther out (a few pixels per lamp on a 66x200 "
                                                  "camera)")
    no_signal_rate: float = param(0.25, ge=0, le=1, doc="per vehicle: the driver does not indicate (pessimistic on "
                                                        "purpose: the policy must not trust it blindly)")
    wrong_rate: float = param(0.05, ge=0, le=1, doc="per vehicle: the indicator shows the other direction")
    miss_rate: float = param(0.1, ge=0, le=1, doc="per reading: an indicator that is on is not seen (occlusion, "
                                                  "blink phase)")
    max_objects: int = param(16, ge=1, le=ROWS_MAX, doc="rows in the observation")


class TurnSignals(SensorWrapper):
    """Adds ``obs["signals"]`` (see the module docstring); parameters: :class:`TurnSignalsParams`."""

    key = "signals"
    Params = TurnSignalsParams

    def __init__(self, env: gym.Env, params: TurnSignalsParams | None = None, **overrides) -> None:
        p = self.params = TurnSignalsParams.build(params, **overrides)
        self.max_range, self.max_objects = float(p.max_range), int(p.max_objects)
        self.no_signal_rate, self.wrong_rate, self.miss_rate = float(p.no_signal_rate), float(p.wrong_rate), \
            float(p.miss_rate)
        super().__init__(env)
        # Per-vehicle channel, keyed by the vehicle object (not id(): a deep copy of the stack, as the lookahead
        # oracle makes, keeps each vehicle's draw through copy's memo).
        self._channel: dict = {}
        self.last = np.zeros((self.max_objects, len(FIELDS)), dtype=np.float32)  # the latest reading

    def sensor_space(self) -> spaces.Box:
        return spaces.Box(-BOUND, BOUND, shape=(self.max_objects, len(FIELDS)), dtype=np.float32)

    def on_reset(self) -> None:
        self._channel = {}

    def measure(self) -> np.ndarray:
        unwrapped = self.env.unwrapped
        ego = unwrapped.vehicle
        x, y = ego_pose(self.env)[:2]
        rows = []
        for v in unwrapped.road.vehicles:
            if v is ego:
                continue
            d = float(np.hypot(v.position[0] - x, v.position[1] - y))
            if d > self.max_range:
                continue
            if v not in self._channel:  # first sighting: does this driver indicate, and the right way?
                self._channel[v] = (self.rng.uniform() >= self.no_signal_rate, self.rng.uniform() < self.wrong_rate)
            indicates, wrong = self._channel[v]
            seen = self.rng.uniform() >= self.miss_rate
            signal = intended_signal(v) * (-1.0 if wrong else 1.0) if indicates and seen else NONE
            rows.append((d, v.position[0], v.position[1], signal))
        out = np.zeros((self.max_objects, len(FIELDS)), dtype=np.float32)
        rows.sort(key=lambda r: r[0])
        for k, (_, px, py, signal) in enumerate(rows[: self.max_objects]):
            out[k] = (1.0, px, py, signal)
        self.last = out
        return out
