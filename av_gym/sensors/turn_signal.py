"""``TurnSignals``: each nearby vehicle's direction indicator, as a camera-based indicator classifier reports it.

Why: at an unprotected left turn the other drivers' intent decides the gap. A car coming from the right that will
turn right never crosses the ego's path; one that will go straight does. Constant-velocity prediction cannot tell
the two apart until the car is already turning (docs/agents.md: 12 % of the lookahead oracle's choices are not
predictable from the motion features, and those decide collisions). A real car reads the indicator.

The indicator a driver *intends* comes from the vehicle's route in the simulator (highway-env's intersection:
approach ``o{i}→ir{i}``, then ``ir{i}→il{j}``, then the exit ``il{j}→o{j}``): left while it approaches or crosses the
intersection towards ``o{(i+1) % 4}``, right towards ``o{(i-1) % 4}``, none when going straight or once on the exit.
What the ego's sensor reports passes through a noisy channel (defaults are suggestions; no source paper measures
this, see docs/agents.md):

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


def node_index(node: str, prefix: str) -> int:
    """``"o3", "o"`` → 3: the index of an intersection node with that prefix, -1 for any other node."""
    node = str(node)
    return int(node[len(prefix):]) if node.startswith(prefix) and node[len(prefix):].isdigit() else -1


def route_origin(start: str, end: str) -> int:
    """The approach ``i`` of a lane ``start → end`` on the way in (``o{i}→ir{i}``) or across (``ir{i}→il{j}``);
    -1 on the exit road or a road this rule does not know."""
    start, end = str(start), str(end)
    if start.startswith("o") and end.startswith("ir"):
        return node_index(end, "ir")
    if start.startswith("ir") and end.startswith("il"):
        return node_index(start, "ir")
    return -1


def turn_signal(origin, destination) -> np.ndarray:
    """The indicator for a drive from approach ``origin`` to exit ``destination`` (ints or arrays of them, -1 =
    unknown): +1 left towards ``o{(i+1) % 4}``, -1 right towards ``o{(i-1) % 4}``, 0 straight or unknown. The one
    rule the per-env sensor, the batched stack and the shield use."""
    origin, destination = np.asarray(origin), np.asarray(destination)
    turn = (destination - origin) % 4
    known = (origin >= 0) & (destination >= 0)
    return np.where(known, np.where(turn == 1, LEFT, np.where(turn == 3, RIGHT, NONE)), NONE)


def intended_signal(vehicle) -> float:
    """The indicator ``vehicle`` should show on highway-env's four-way intersection, from its route: +1 left, -1
    right, 0 straight, on the exit road, or off the intersection's roads (no route, e.g. a CCFtap target)."""
    lane = getattr(vehicle, "lane_index", None)
    route = getattr(vehicle, "route", None)
    if not lane or not route:
        return NONE
    return float(turn_signal(route_origin(lane[0], lane[1]), node_index(route[-1][1], "o")))


# The channel (module docstring) as vectorised functions of uniform draws, one implementation for the per-env
# sensor (a batch of one), the batched stack (av_gym/batched/left_turn.py: BatchedIntent) and the shield's own
# channel (av_gym/shields/aeb_improved.py), whose Bayes filter (av_gym/estimation/driver_intent.py) reads the same
# model's likelihood below. A new rate is a TurnSignalsParams field and these functions (tests/test_one_model.py).
DRIVER_DRAWS = 2  # uniforms per driver at its first sighting: does it indicate?, the wrong side?


def first_sighting(u: np.ndarray, p: "TurnSignalsParams") -> tuple[np.ndarray, np.ndarray]:
    """Per driver, from ``u`` (..., DRIVER_DRAWS) uniforms: (indicates, indicates the wrong side)."""
    u = np.asarray(u)
    return u[..., 0] >= p.no_signal_rate, u[..., 1] < p.wrong_rate


def reported(intended, indicates, wrong, u_seen, p: "TurnSignalsParams") -> np.ndarray:
    """What one reading reports (+1 / -1 / 0) for drivers with ``intended`` signals and their per-driver draws,
    ``u_seen`` a uniform per reading (seen unless below ``miss_rate``)."""
    seen = np.asarray(u_seen) >= p.miss_rate
    return np.where(np.asarray(indicates) & seen, np.asarray(intended) * np.where(wrong, -1.0, 1.0), NONE)


def read_channel(u: np.ndarray, in_range: np.ndarray, new: np.ndarray, intended: np.ndarray,
                 indicates: np.ndarray, wrong: np.ndarray, p: "TurnSignalsParams"):
    """One reading of (n envs, N vehicles in road order) with the sensor's draw order: env after env, per vehicle
    in range ``DRIVER_DRAWS`` uniforms if ``new`` (first sighting), then one for ``seen?``; ``u`` holds them all
    (:func:`draws_needed` of them). ``indicates``/``wrong`` hold the earlier drivers' draws (ignored where new).
    Returns (signal (n, N), indicates (n, N), wrong (n, N)) with the new drivers' draws filled in."""
    width = draws_needed(in_range, new)
    end = np.cumsum(width.ravel()).reshape(width.shape)  # one past each reading's last draw in u
    indicates, wrong = np.array(indicates, dtype=bool), np.array(wrong, dtype=bool)
    if new.any():
        first = end[new] - 1 - DRIVER_DRAWS
        indicates[new], wrong[new] = first_sighting(u[first[:, None] + np.arange(DRIVER_DRAWS)], p)
    u_seen = np.full(in_range.shape, -np.inf)  # out of range: never seen
    u_seen[in_range] = u[end[in_range] - 1]
    return reported(intended, indicates, wrong, u_seen, p), indicates, wrong


def draws_needed(in_range: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Uniforms each reading takes (:func:`read_channel`)."""
    return np.where(in_range, 1 + DRIVER_DRAWS * new, 0)


def fit_ids(array: np.ndarray, ids: np.ndarray, fill) -> np.ndarray:
    """``array`` (indexed by driver row or vehicle id along its first axis) long enough to index ``ids``: itself,
    or a copy grown with ``fill`` to at least twice its length (a growing id costs amortised O(1))."""
    top = int(np.max(ids, initial=-1))
    if top < len(array):
        return array
    grown = np.full((max(top + 1, 2 * len(array), 64), *array.shape[1:]), fill, dtype=array.dtype)
    grown[: len(array)] = array
    return grown


class DriverDraws:
    """The channel's per-driver draws (does the driver indicate? the wrong side?), made at a driver's first reading
    and kept for the episode: arrays by driver row, one representation for the per-env sensor, the batched stack
    and the shield's own channel. A driver is an integer row (the batch's vehicle ids, unique in the process) or,
    through :meth:`rows`, any hashable key (a vehicle object: a deep copy of the stack keeps each vehicle's draws
    through copy's memo)."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        """Forget every driver (a new episode)."""
        self.known, self.indicates, self.wrong = (np.zeros(0, bool) for _ in range(3))
        self._row: dict = {}

    def rows(self, keys) -> np.ndarray:
        """The rows of hashable ``keys`` (new keys get the next free rows)."""
        row = self._row
        return np.array([row.setdefault(k, len(row)) for k in keys], dtype=int)

    def get(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(drawn already, indicates, indicates the wrong side) of the drivers ``rows`` (any shape)."""
        rows = np.asarray(rows, dtype=int)
        self.known, self.indicates, self.wrong = (fit_ids(a, rows, False)
                                                  for a in (self.known, self.indicates, self.wrong))
        return self.known[rows], self.indicates[rows], self.wrong[rows]

    def keep(self, rows: np.ndarray, indicates: np.ndarray, wrong: np.ndarray) -> None:
        """The first-sighting draws of the drivers ``rows`` (after :meth:`get` on them)."""
        self.known[rows], self.indicates[rows], self.wrong[rows] = True, indicates, wrong


def read_signals(x: np.ndarray, y: np.ndarray, d: np.ndarray, candidates: np.ndarray, intended: np.ndarray,
                 drivers: np.ndarray, draws: DriverDraws, rngs, p: "TurnSignalsParams") -> np.ndarray:
    """``obs["signals"]`` for n egos at once: (n, max_objects, 4) float32 rows ``[present, x, y, signal]``, nearest
    first (ties in road order), of the vehicles ``candidates`` (n, N) within ``max_range`` (``d`` (n, N) m from the
    ego; positions ``x``, ``y``; ``intended`` signals; ``drivers`` their rows in ``draws``). Each env draws its
    step's uniforms from its generator of ``rngs`` at once (one ``uniform(size=k)`` gives the numbers of k scalar
    calls), in the sensor's order (:func:`read_channel`)."""
    in_range = candidates & (d <= p.max_range)
    known, indicates, wrong = draws.get(drivers)
    new = in_range & ~known
    counts = draws_needed(in_range, new).sum(axis=1)
    parts = [rng.uniform(size=int(c)) for rng, c in zip(rngs, counts) if c]
    u = np.concatenate(parts) if parts else np.zeros(0)
    signal, indicates, wrong = read_channel(u, in_range, new, intended, indicates, wrong, p)
    draws.keep(drivers[new], indicates[new], wrong[new])
    M, n = int(p.max_objects), len(d)
    order = np.argsort(np.where(in_range, d, np.inf), axis=1, kind="stable")[:, :M]
    env = np.arange(n)[:, None]
    seen = in_range[env, order]
    out = np.zeros((n, M, len(FIELDS)), dtype=np.float32)
    rows = out[:, : order.shape[1]]
    rows[..., 0], rows[..., 1], rows[..., 2], rows[..., 3] = 1.0, x[env, order], y[env, order], signal[env, order]
    rows[~seen] = 0.0
    return out


def channel_likelihood(reading: float, miss_rate: float) -> np.ndarray:
    """``P(reading | turn, driver kind)`` (3 turns right/straight/left × 3 kinds right side/wrong side/never) of
    this channel: the inverse view of :func:`first_sighting` and :func:`reported`, what a Bayes filter over a
    driver's readings uses (av_gym/estimation/driver_intent.py)."""
    lik = np.zeros((3, 3))
    for i, turn in enumerate((RIGHT, NONE, LEFT)):
        for j, shows in enumerate((turn, -turn, NONE)):  # indicates the right side, the wrong side, never
            if shows == NONE:  # going straight shows nothing, whatever the driver
                lik[i, j] = 1.0 if reading == NONE else 0.0
            else:
                lik[i, j] = (1.0 - miss_rate) if reading == shows else miss_rate if reading == NONE else 0.0
    return lik


def driver_kinds(p: "TurnSignalsParams") -> np.ndarray:
    """Prior of the driver kinds (right side, wrong side, never), from the per-driver rates."""
    return np.array([(1.0 - p.no_signal_rate) * (1.0 - p.wrong_rate), (1.0 - p.no_signal_rate) * p.wrong_rate,
                     p.no_signal_rate])


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
    """Adds ``obs["signals"]`` (see the module docstring); parameters: :class:`TurnSignalsParams`.

    Example: rows ``[present, x, y, signal]`` nearest first (signal +1 left, -1 right, 0 none seen):

        >>> import gymnasium as gym
        >>> import av_gym
        >>> from av_gym.sensors.turn_signal import TurnSignals
        >>> env = TurnSignals(gym.make("av_gym/UnprotectedLeftTurn-v0"), no_signal_rate=0.0)
        >>> obs, info = env.reset(seed=0)
        >>> obs["signals"].shape[1]
        4
        >>> set(obs["signals"][:, 3].tolist()) <= {-1.0, 0.0, 1.0}
        True
    """

    key = "signals"
    Params = TurnSignalsParams

    def __init__(self, env: gym.Env, params: TurnSignalsParams | None = None, **overrides) -> None:
        p = self.params = TurnSignalsParams.build(params, **overrides)
        self.max_range, self.max_objects = float(p.max_range), int(p.max_objects)
        self.no_signal_rate, self.wrong_rate, self.miss_rate = float(p.no_signal_rate), float(p.wrong_rate), \
            float(p.miss_rate)
        super().__init__(env)
        self.draws = DriverDraws()  # the per-driver channel, keyed by the vehicle object
        self.last = np.zeros((self.max_objects, len(FIELDS)), dtype=np.float32)  # the latest reading

    def sensor_space(self) -> spaces.Box:
        return spaces.Box(-BOUND, BOUND, shape=(self.max_objects, len(FIELDS)), dtype=np.float32)

    def on_reset(self) -> None:
        self.draws.clear()

    def measure(self) -> np.ndarray:
        unwrapped = self.env.unwrapped
        ego = unwrapped.vehicle
        x, y = ego_pose(self.env)[:2]
        out = np.zeros((self.max_objects, len(FIELDS)), dtype=np.float32)
        vehicles = [v for v in unwrapped.road.vehicles if v is not ego]
        if vehicles:  # read_signals on a batch of one
            pos = np.array([v.position for v in vehicles], dtype=float)
            d = np.hypot(pos[:, 0] - x, pos[:, 1] - y)
            intended = np.array([intended_signal(v) if r else NONE for v, r in zip(vehicles, d <= self.max_range)])
            out = read_signals(pos[None, :, 0], pos[None, :, 1], d[None], np.ones((1, len(vehicles)), bool),
                               intended[None], self.draws.rows(vehicles)[None], self.draws, [self.rng],
                               self.params)[0]
        self.last = out
        return out
