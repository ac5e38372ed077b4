"""Batched left-turn traffic: B intersections stepped together, vehicle state as (B, N) arrays.

The same models as highway-env's ``IntersectionEnv`` as ``av_gym.envs.left_turn`` uses it, as array maths over
every vehicle of every environment at once instead of one Python object per vehicle:

- lanes (``StraightLane`` / ``CircularLane``): ``local_coordinates``, ``position``, ``heading_at`` on lane-id
  arrays (:class:`LaneTable`); ``RoadNetwork.get_closest_lane_index`` as an argmin over all lanes;
- ``Vehicle.step``: the kinematic bicycle; ``ControlledVehicle.steering_control`` / ``speed_control`` /
  ``follow_road``; ``IDMVehicle.act`` (IDM with ``Road.neighbour_vehicles`` on the current and the target lane);
  ``MDPVehicle.act`` for the ego's meta-actions;
- ``RegulatedRoad.enforce_road_rules`` (every 0.5 s): constant-speed predictions along each route, the stock
  pre-check and ``rotated_rectangles_intersect`` for every pair, ``respect_priorities``;
- ``Road.step``'s collisions: the stock spherical pre-check on all pairs at once; the few pairs it lets through go
  to highway-env's own ``utils.are_polygons_intersecting`` in the stock pair order (impacts overwrite as there);
- ``IntersectionEnv._spawn_vehicle`` / ``_make_vehicles`` / ``_clear_vehicles``: per environment, the same calls on
  that environment's own ``np.random.Generator`` in the same order, so env i reset with seed s draws the traffic
  that ``reset(seed=s)`` of the per-env stack draws.

The pairwise parts (leader search and IDM, regulation conflicts, collisions, closest lane) run as numba kernels
(:mod:`av_gym.sim.kernels`, the numpy code's formulas in its order, which stays as their reference: ``KERNELS``),
and a policy step's ticks run as one compiled call (:meth:`Traffic.advance`, ``KERNELS``'s "tick"); the
engine's state is these arrays, which its own methods fork and view (BatchedLeftTurn.fork / keep / observed).

Slot order in the arrays is ``road.vehicles`` order (the regulation, collisions and neighbour ties depend on it):
new vehicles go after the last live one, cleared vehicles are removed with a stable compaction.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
from highway_env.road.lane import CircularLane

from av_gym.geometry import wrap_angle
from av_gym.sim import kernels

# The pairwise parts run as numba kernels (av_gym/sim/kernels.py: the same formulas, bit-identical results) when
# named here (``ttc``: BatchedLeftTurn.ttc); ``tick``: a policy step's ticks (act + step, every part) as one
# compiled call per batch step (Traffic.advance); ``path_conflict``: obs["turn"]'s closest approach to the ego's
# path (av_gym.estimation.turn_features.path_conflict, both stacks). The numpy code stays as their reference
# (tests/test_kernels.py runs the batch both ways; benchmarks/batched_speed.py times both). ``spawn``: the spawn
# tries and a reset's initial traffic and challenger drawn in kernels from each env's own generator
# (BatchedLeftTurn._spawn's draws, the same stream: kernels.spawn_tries and the generator draws above them);
# ``clear``: the step's removal of vehicles at the end of a leaving lane and the compaction (kernels.clear_exits).
# ``turn_features``: obs["turn"] (av_gym.estimation.turn_features.turn_features, both stacks: kernels.turn_features);
# ``truth``: BatchedLeftTurn.truth, and observe's truth and features in one call (kernels.truth, kernels.observe);
# ``reward``: the step's rewards, crashes and arrivals (kernels.rewards).
KERNELS = {"front", "collisions", "conflicts", "closest", "ttc", "idm", "tick", "path_conflict", "spawn", "clear",
           "turn_features", "truth", "reward"}
# the pairwise kernels alone, the numpy step around them: the engine before the compiled tick, which the
# benchmarks time beside the compiled one (benchmarks/batched_speed.py, oracle_labels.py, belief_planner.py)
PAIRWISE_KERNELS = frozenset({"front", "collisions", "conflicts", "closest", "ttc", "idm"})
# obs["turn"], truth and rewards compiled: without them, the compiled step before they were (the benchmarks' "before")
OBSERVE_KERNELS = frozenset({"turn_features", "truth", "reward"})

# highway-env constants (IntersectionEnv._make_vehicles sets the IDM class attributes to these)
LENGTH, WIDTH = 5.0, 2.0
DIAGONAL = float(np.sqrt(LENGTH**2 + WIDTH**2))
VEHICLE_LENGTH = 5.0  # AbstractLane.VEHICLE_LENGTH
COMFORT_ACC_MAX, COMFORT_ACC_MIN, ACC_MAX = 6.0, -3.0, 6.0
DISTANCE_WANTED, TIME_WANTED = 7.0, 1.5
TAU_PURSUIT, KP_LATERAL, KP_HEADING, KP_A = 0.1, 1 / 0.6, 1 / 0.2, 1 / 0.6
MAX_STEERING = np.pi / 3
REG_TIMES = np.arange(0.25, 3, 0.25)  # RegulatedRoad.is_conflict_possible(horizon=3, step=0.25)
EGO_TARGET_SPEEDS = np.array([0.0, 4.5, 9.0])
EXIT_DISTANCE = 25.0  # m along the leaving lane: IntersectionEnv.has_arrived
SLOWER, IDLE, FASTER = 0, 1, 2
_VEHICLE_IDS = itertools.count(1)  # unique over all batches of the process (episodes move between them)


def numbered(kernel_call: Callable[[int], int]) -> int:
    """Run ``kernel_call(first_id)``, a kernel that numbers the vehicles it adds from ``first_id`` on and returns how
    many ids it used; the process's vehicle ids go on after them. Returns that count."""
    global _VEHICLE_IDS
    first = next(_VEHICLE_IDS)
    n = int(kernel_call(first))
    _VEHICLE_IDS = itertools.count(first + n)
    return n


@dataclass(frozen=True)
class SpawnPrior:
    """The traffic's draws per spawned driver (IntersectionEnv._spawn_vehicle, IDMVehicle.randomize_behavior):
    its speed, which is also its cruise set-point, ``speed`` + N(0, 1)·deviation (m/s), and its IDM exponent
    ~ U(``delta``). One instance (:data:`SPAWN_PRIOR`) is read by the engine that draws spawns and by the belief
    planner that redraws what the car cannot observe, so the two cannot drift apart."""

    speed: float = 8.0
    """m/s, the mean spawn speed"""
    speed_sd: float = 1.0
    """m/s, the spawn speed's standard deviation (the spawn's ``speed_deviation`` scales it)"""
    delta: tuple[float, float] = (3.5, 4.5)
    """the IDM exponent's uniform range"""

    def draw_speed(self, rng: np.random.Generator, deviation: float = 1.0) -> float:
        """One spawn speed (m/s), one ``normal()`` draw as highway-env makes it: speed + normal · sd · deviation
        (``deviation`` 0: the challenger's exact speed)."""
        return self.speed + rng.normal() * (self.speed_sd * deviation)

    def draw_delta(self, rng: np.random.Generator) -> float:
        """One IDM exponent, one ``uniform`` draw as IDMVehicle.randomize_behavior makes it."""
        return rng.uniform(low=self.delta[0], high=self.delta[1])

    def speeds(self, rng: np.random.Generator, shape: tuple) -> np.ndarray:
        """Spawn speeds (m/s) of the given shape from standard normals: speed + speed_sd · N(0, 1)."""
        return self.speed + self.speed_sd * rng.standard_normal(shape)

    def deltas(self, rng: np.random.Generator, shape: tuple) -> np.ndarray:
        """IDM exponents of the given shape, U(delta)."""
        return rng.uniform(*self.delta, size=shape)


SPAWN_PRIOR = SpawnPrior()


@contextmanager
def using_kernels(names) -> Iterator[None]:
    """Run the batch with the kernels ``names`` only (the rest on the numpy path) inside the block."""
    global KERNELS
    before, KERNELS = KERNELS, set(names)
    try:
        yield
    finally:
        KERNELS = before


def not_zero(x: np.ndarray, eps: float = 1e-2) -> np.ndarray:
    """utils.not_zero, elementwise."""
    return np.where(np.abs(x) > eps, x, np.where(x >= 0, eps, -eps))


wrap_to_pi = wrap_angle  # highway_env.utils.wrap_to_pi on arrays (av_gym.geometry, the one angle wrap)


class LaneTable:
    """Every lane of the intersection as arrays, in ``RoadNetwork.graph`` order (the argmin tie order of
    ``get_closest_lane_index``)."""

    def __init__(self, network) -> None:
        self.index = []  # (from, to, id) per lane id
        lanes = []
        for _from, to_dict in network.graph.items():
            for _to, ls in to_dict.items():
                for _id, lane in enumerate(ls):
                    self.index.append((_from, _to, _id))
                    lanes.append(lane)
        self.id = {idx: k for k, idx in enumerate(self.index)}
        n = len(lanes)
        self.circular = np.array([isinstance(lane, CircularLane) for lane in lanes])
        self.length = np.array([float(lane.length) for lane in lanes])
        self.width = np.array([float(lane.width) for lane in lanes])
        self.priority = np.array([lane.priority for lane in lanes])
        self.speed_limit = np.array([float(lane.speed_limit) for lane in lanes])
        # straight: start, direction, heading; circular: centre, radius, start phase, direction (+1 clockwise)
        self.ox, self.oy, self.dx, self.dy, self.h = (np.zeros(n) for _ in range(5))
        self.radius, self.phase0, self.cdir = np.ones(n), np.zeros(n), np.ones(n)
        for k, lane in enumerate(lanes):
            if self.circular[k]:
                self.ox[k], self.oy[k] = lane.center
                self.radius[k], self.phase0[k], self.cdir[k] = lane.radius, lane.start_phase, lane.direction
            else:
                self.ox[k], self.oy[k] = lane.start
                self.dx[k], self.dy[k] = lane.direction
                self.h[k] = lane.heading
        # leaving lanes: "il" → "o" (IntersectionEnv.has_arrived / _clear_vehicles)
        self.box = np.array([_centreline_box(lane) for lane in lanes])  # (L, 4) xmin, ymin, xmax, ymax
        self.exit = np.array(["il" in f and "o" in t for f, t, _ in self.index])
        self.to_node = [t for _, t, _ in self.index]
        self.from_node = [f for f, _, _ in self.index]
        self.arr = kernels.lane_array(self)  # the same table for the kernels
        self._lines = [tuple(float(a[k]) for a in (self.ox, self.oy, self.dx, self.dy, self.h)) for k in range(n)]
        node = {n: k for k, n in enumerate(sorted(set(self.from_node) | set(self.to_node)))}
        # the rules' per-lane columns for kernels.advance: speed limit, priority, leaving lane, from / to node ids
        self.rules = np.ascontiguousarray(np.column_stack([
            self.speed_limit, self.priority, self.exit, [node[f] for f in self.from_node],
            [node[t] for t in self.to_node]]).astype(float))

    def local(self, k, x, y):
        """(StraightLane|CircularLane).local_coordinates for lane ids ``k`` (broadcast with x, y); the arc formula
        only where the lane is circular."""
        k, x, y = np.broadcast_arrays(k, x, y)
        ex, ey = x - self.ox[k], y - self.oy[k]
        dx, dy = self.dx[k], self.dy[k]
        s, r = ex * dx + ey * dy, ex * -dy + ey * dx
        circ = self.circular[k]
        if circ.any():
            kc, exc, eyc = k[circ], ex[circ], ey[circ]
            p0, R, cd = self.phase0[kc], self.radius[kc], self.cdir[kc]
            phi = p0 + wrap_to_pi(np.arctan2(eyc, exc) - p0)
            s[circ] = cd * (phi - p0) * R
            r[circ] = cd * (R - np.hypot(exc, eyc))
        return s, r

    def position(self, k, s, r):
        circ = self.circular[k]
        phi = self.cdir[k] * s / self.radius[k] + self.phase0[k]
        rad = self.radius[k] - r * self.cdir[k]
        x_c, y_c = self.ox[k] + rad * np.cos(phi), self.oy[k] + rad * np.sin(phi)
        dx, dy = self.dx[k], self.dy[k]
        x_s, y_s = self.ox[k] + s * dx + r * -dy, self.oy[k] + s * dy + r * dx
        return np.where(circ, x_c, x_s), np.where(circ, y_c, y_s)

    def pose(self, k: int, s: float) -> tuple[float, float, float]:
        """:meth:`position` (k, s, 0) and :meth:`heading_at` (k, s) for one lane id and one s (m), as floats: on a
        straight lane the same arithmetic in plain floats (the same results, without the array calls' overhead:
        spawns and resets place vehicles one at a time), on an arc the array code."""
        if self.circular[k]:
            x, y = self.position(k, s, 0.0)
            return float(x), float(y), float(self.heading_at(k, s))
        ox, oy, dx, dy, h = self._lines[k]
        return ox + s * dx + 0.0 * -dy, oy + s * dy + 0.0 * dx, h

    def heading_at(self, k, s):
        phi = self.cdir[k] * s / self.radius[k] + self.phase0[k]
        return np.where(self.circular[k], phi + np.pi / 2 * self.cdir[k], self.h[k])

    def distance_with_heading(self, k, x, y, h):
        """AbstractLane.distance_with_heading (heading weight 1)."""
        s, r = self.local(k, x, y)
        angle = np.abs(wrap_to_pi(h - self.heading_at(k, s)))
        return np.abs(r) + np.maximum(s - self.length[k], 0) + np.maximum(0 - s, 0) + angle

    def closest(self, x, y, h):
        """RoadNetwork.get_closest_lane_index(position, heading) for arrays of vehicles: the argmin over all lanes
        of distance_with_heading (first lane on ties, as np.argmin). Exact, but only lanes that can win are
        evaluated: the distance is ≥ the Euclidean distance to the lane's centreline (|r| plus the arc or line
        length beyond an end), hence ≥ the distance to its bounding box; lanes whose box is farther than the
        distance to the nearest box's lane cannot be the argmin."""
        shape = np.shape(x)
        x, y, h = np.ravel(x), np.ravel(y), np.ravel(h)
        if "closest" in KERNELS:
            return kernels.closest(self.arr, *(np.ascontiguousarray(a, dtype=float) for a in (x, y, h)),
                                   np.full(x.shape, -1)).reshape(shape)
        bx = np.maximum(np.maximum(self.box[:, 0] - x[:, None], x[:, None] - self.box[:, 2]), 0)
        by = np.maximum(np.maximum(self.box[:, 1] - y[:, None], y[:, None] - self.box[:, 3]), 0)
        lb = np.hypot(bx, by)  # (M, L)
        best = self.distance_with_heading(np.argmin(lb, axis=1), x, y, h)
        m, k = np.nonzero(lb <= best[:, None])
        d = np.full(lb.shape, np.inf)
        d[m, k] = self.distance_with_heading(k, x[m], y[m], h[m])
        return np.argmin(d, axis=1).reshape(shape)


def _centreline_box(lane) -> np.ndarray:
    """Axis-aligned box containing a lane's centreline (an arc's sampled points, grown by the sagitta)."""
    if isinstance(lane, CircularLane):
        n = 256
        phi = np.linspace(lane.start_phase, lane.end_phase, n)
        pts = lane.center + lane.radius * np.stack([np.cos(phi), np.sin(phi)], axis=1)
        pad = lane.radius * (1 - np.cos(abs(lane.end_phase - lane.start_phase) / (n - 1) / 2)) + 1e-6
    else:
        pts, pad = np.array([lane.start, lane.end]), 1e-6
    return np.concatenate([pts.min(axis=0) - pad, pts.max(axis=0) + pad])


@dataclass
class Traffic:
    """The vehicles of B intersections: (B, N) arrays, slot order = ``road.vehicles`` order; ``alive`` marks used
    slots (always a prefix of each row)."""

    tables: LaneTable
    B: int
    N: int = 24
    road_steps: np.ndarray = field(default=None)
    # m: a planner's futures count the ego crashed where another road user comes within this of its box
    # (kernels._near_ego_row; agents/belief.py, ``track_margin``); 0, every real engine's: the contact test only
    ego_margin: float = 0.0

    def __post_init__(self) -> None:
        B, N = self.B, self.N
        z = lambda dt=float: np.zeros((B, N), dtype=dt)  # noqa: E731
        self.alive, self.ego, self.crashed, self.yielding = z(bool), z(bool), z(bool), z(bool)
        # highway-env's plain ``Vehicle`` (the CCFtap target): no controller, its action is kept as it is (zero
        # steering and acceleration until a crash's clip_actions brakes it), no route, never yields
        self.plain = z(bool)
        # an MDPVehicle (the discrete-action ego) never yields in the regulation; the continuous action's ego
        # (RouteFollowingVehicle, a ControlledVehicle) does: its target speed, which it ignores, goes to 0 and back
        self.mdp = z(bool)
        self.x, self.y, self.h, self.v, self.target = z(), z(), z(), z(), z()
        self.steer, self.acc, self.delta = z(), z(), z()
        self.delta[:] = 4.0
        self.impact_x, self.impact_y, self.has_impact = z(), z(), z(bool)
        self.lane, self.tlane = z(int), z(int)
        self.route = np.full((B, N, 3), -1)  # lane ids of the planned route; route[rpos:] is what is left
        self.rpos = z(int)
        # a vehicle's identity, unique in the process (_VEHICLE_IDS), kept through compaction: sensors key on it
        self.vid = z(int)
        if self.road_steps is None:
            self.road_steps = np.zeros(B, dtype=int)

    FIELDS = ("vid", "alive", "ego", "plain", "mdp", "crashed", "yielding", "x", "y", "h", "v", "target", "steer", "acc", "delta",
              "impact_x", "impact_y", "has_impact", "lane", "tlane", "route", "rpos")

    # -------------------------------------------------------------------------------------------- bookkeeping
    def grow(self, n_new: int) -> None:
        for name in self.FIELDS:
            a = getattr(self, name)
            pad = np.zeros((self.B, n_new) + a.shape[2:], dtype=a.dtype)
            if name == "route":
                pad[:] = -1
            setattr(self, name, np.concatenate([a, pad], axis=1))
        self.N += n_new

    def compact(self) -> None:
        """Remove dead slots keeping the order of the others (``road.vehicles = [v for v in ... if ...]``)."""
        order = np.argsort(~self.alive, axis=1, kind="stable")
        for name in self.FIELDS:
            a = getattr(self, name)
            idx = order if a.ndim == 2 else order[..., None]
            setattr(self, name, np.take_along_axis(a, idx, axis=1))

    def cut(self, n: int) -> None:
        """Keep the first ``n`` slots of every env (``n`` >= every env's live vehicles)."""
        if n < self.N:
            for name in self.FIELDS:
                setattr(self, name, np.ascontiguousarray(getattr(self, name)[:, :n]))
            self.N = n

    def trim(self, spare: int = 2) -> None:
        """Drop trailing slots no env uses (the pairwise work is O(N²) in the slot count, not the vehicle count)."""
        n = int(self.alive.sum(axis=1).max()) + spare
        if n < self.N - spare:
            for name in self.FIELDS:
                setattr(self, name, np.ascontiguousarray(getattr(self, name)[:, :n]))
            self.N = n

    def subset(self, rows) -> "Traffic":
        """A new Traffic with the rows ``rows`` of this one (copies)."""
        rows = np.asarray(rows, dtype=int)
        out = Traffic(self.tables, len(rows), N=self.N, road_steps=self.road_steps[rows].copy(),
                      ego_margin=self.ego_margin)
        for name in self.FIELDS:
            setattr(out, name, getattr(self, name)[rows].copy())
        return out

    @staticmethod
    def concat(a: "Traffic", b: "Traffic") -> "Traffic":
        n = max(a.N, b.N)
        out = Traffic(a.tables, a.B + b.B, N=n, road_steps=np.concatenate([a.road_steps, b.road_steps]),
                      ego_margin=a.ego_margin)
        out.put(np.arange(a.B), a)
        out.put(a.B + np.arange(b.B), b)
        return out

    def state_bytes(self) -> int:
        return sum(getattr(self, name).nbytes for name in self.FIELDS) + self.road_steps.nbytes

    def put(self, rows: np.ndarray, other: "Traffic") -> None:
        if other.N > self.N:
            self.grow(other.N - self.N)
        for name in self.FIELDS:
            a, b = getattr(self, name), getattr(other, name)
            a[rows] = 0 if name != "route" else -1
            a[rows, : other.N] = b
        self.road_steps[rows] = other.road_steps

    def settle(self, b: np.ndarray, slots: np.ndarray) -> None:
        """The new vehicles' lane index (RoadObject.__init__: the closest lane), which ControlledVehicle takes as
        its target lane and plan_route_to as its route's first step; one vectorised search for all of them."""
        if len(b):
            lane = self.tables.closest(self.x[b, slots], self.y[b, slots], self.h[b, slots])
            self.lane[b, slots] = self.tlane[b, slots] = self.route[b, slots, 0] = lane

    def add(self, b: int, lane: int, s: float, speed: float, route: list[int], delta: float = 4.0,
            ego: bool = False, target: float | None = None, plain: bool = False, mdp: bool | None = None,
            pose: tuple[float, float, float] | None = None, vid: int | None = None) -> int:
        """``Vehicle.make_on_lane`` + ``plan_route_to`` + append to ``road.vehicles`` in env ``b``; call
        :meth:`settle` on the new slots before the next tick. ``pose``: ``tables.pose(lane, s)`` when the caller
        has it already; ``vid``: an id a kernel reserved (:func:`numbered`), else the next one."""
        slot = int(self.alive[b].sum())
        if slot >= self.N:
            self.grow(8)
        x, y, h = self.tables.pose(lane, s) if pose is None else pose
        self.alive[b, slot], self.ego[b, slot], self.plain[b, slot] = True, ego, plain
        self.mdp[b, slot] = ego if mdp is None else mdp
        self.vid[b, slot] = next(_VEHICLE_IDS) if vid is None else vid
        self.x[b, slot], self.y[b, slot], self.h[b, slot], self.v[b, slot] = x, y, h, speed
        self.target[b, slot] = speed if target is None else target  # ControlledVehicle: target_speed or speed
        self.route[b, slot] = -1
        self.route[b, slot, : len(route)] = route
        self.lane[b, slot] = self.tlane[b, slot] = route[0]  # until settle(): the closest lane
        self.rpos[b, slot] = 0
        self.delta[b, slot] = delta
        for name in ("crashed", "yielding", "has_impact"):
            getattr(self, name)[b, slot] = False
        self.steer[b, slot] = self.acc[b, slot] = self.impact_x[b, slot] = self.impact_y[b, slot] = 0.0
        return slot

    # -------------------------------------------------------------------------------------------- one tick
    def advance(self, dt: float, frames: int, active: np.ndarray | None = None, meta: np.ndarray | None = None,
                speeds: np.ndarray = EGO_TARGET_SPEEDS, ego_acceleration: np.ndarray | None = None,
                clocks: tuple | None = None) -> None:
        """``frames`` ticks (:meth:`act`, then :meth:`step`) of the envs ``active`` (default: all) in one compiled
        call (kernels.advance): the ego's meta-action ``meta`` (B,) at the first tick (None: none), the ego's
        commanded acceleration ``ego_acceleration`` (m/s²; (B,) for every tick, or (frames, B) per tick: the
        continuous ego's command or the AEB shield's brake; NaN: the discrete ego's speed control; None: NaN
        everywhere); ``clocks``: the env's (ticks, time, arrived_time) arrays, ticks counted and arrivals stamped
        per tick as BatchedLeftTurn.step does. Inactive envs are left as they are. ``dt`` in s."""
        B = self.B
        active = np.ones(B, bool) if active is None else np.ascontiguousarray(active, dtype=bool)
        meta = np.full(B, -1) if meta is None else np.ascontiguousarray(meta, dtype=np.int64).reshape(B)
        cmd = np.full(B, np.nan) if ego_acceleration is None else np.asarray(ego_acceleration, dtype=float)
        # a copy, contiguous and writable: a per-tick plan already (frames, B) would pass through as broadcast_to's
        # read-only view and compile a second specialization of kernels.advance (the same floats either way)
        cmd = np.array(np.broadcast_to(cmd, (int(frames), B)), order="C")
        ticks, time, arrived = clocks if clocks is not None else (np.zeros(B, dtype=int), np.zeros(B), np.zeros(B))
        T = self.tables
        prm = _TICK_PARAMS
        if self.ego_margin != 0.0:  # the same float64 array, one compiled signature, the margin's entry set
            prm = _TICK_PARAMS.copy()
            prm[kernels.P_EGO_MARGIN] = float(self.ego_margin)
        kernels.advance(T.arr, T.rules, *_contiguous(self, *_TICK_STATE), active, meta, np.asarray(speeds, float),
                        cmd, int(frames), float(dt), int(1 / dt / 2), REG_TIMES, prm, ticks, time, arrived)

    def act(self, ego_action: np.ndarray | None = None, speeds: np.ndarray = EGO_TARGET_SPEEDS,
            ego_acceleration: np.ndarray | None = None) -> None:
        """``Road.act()`` (and, at a policy step's first tick, the action type's ``MDPVehicle.act(meta)`` over the
        set-points ``speeds``). ``ego_acceleration`` (B,): the ego's commanded acceleration this tick (m/s², the
        continuous action's or the AEB shield's brake), av_gym.envs.vehicles.RouteFollowingVehicle in place of the
        MDPVehicle's speed control; NaN (or None for all): the speed control."""
        T, a = self.tables, self.alive
        if ego_action is not None:  # MDPVehicle.act: FASTER / SLOWER move the index from the *current* speed
            e = self.ego & a
            ts = np.asarray(speeds, dtype=float)
            idx = np.clip(np.round((self.v - ts[0]) / (ts[-1] - ts[0]) * (ts.size - 1)), 0, ts.size - 1)
            step = np.where(ego_action == FASTER, 1, np.where(ego_action == SLOWER, -1, 0))[:, None]
            new = ts[np.clip(idx + step, 0, ts.size - 1).astype(int)]
            self.target = np.where(e & (step != 0), new, self.target)
        self._follow_road()
        steer = np.clip(self._steering(), -MAX_STEERING, MAX_STEERING)
        acc_idm = np.clip(self._idm(), -ACC_MAX, ACC_MAX)
        acc_ego = KP_A * (self.target - self.v)  # ControlledVehicle.speed_control
        if ego_acceleration is not None:  # RouteFollowingVehicle.act: no reversing, a standstill is held
            cmd = np.asarray(ego_acceleration, dtype=float)[:, None]
            acc_ego = np.where(np.isnan(cmd), acc_ego, np.maximum(cmd, -self.v / 0.05))
        # IDMVehicle.act returns early when crashed (action kept); a plain Vehicle's act(None) keeps its action
        live = a & ~self.plain & (~self.crashed | self.ego)
        self.steer = np.where(live, steer, self.steer)
        self.acc = np.where(live, np.where(self.ego, acc_ego, acc_idm), self.acc)

    def _follow_road(self) -> None:
        """ControlledVehicle.follow_road + RoadNetwork.next_lane with a planned route: past a lane's end
        (``after_end``), drop the finished route step and take the next one."""
        T = self.tables
        s, _ = T.local(self.tlane, self.x, self.y)
        over = self.alive & ~self.plain & (~self.crashed | self.ego) \
            & (s > T.length[self.tlane] - VEHICLE_LENGTH / 2)
        if not over.any():
            return
        for b, i in zip(*np.nonzero(over)):
            r, p = self.route[b, i], self.rpos[b, i]
            if p < 3 and r[p] == self.tlane[b, i]:
                p += 1  # "We just finished the first step of the route, drop it."
            if p < 3 and r[p] >= 0 and T.from_node[r[p]] == T.to_node[self.tlane[b, i]]:
                self.tlane[b, i] = r[p]
            self.rpos[b, i] = p
            # (route exhausted: highway-env picks the closest next road; no vehicle here gets there before it
            # is cleared or its episode ends, 80 m into the exit lane)

    def _steering(self) -> np.ndarray:
        """ControlledVehicle.steering_control(target_lane_index)."""
        T, k = self.tables, self.tlane
        s, r = T.local(k, self.x, self.y)
        future_heading = T.heading_at(k, s + self.v * TAU_PURSUIT)
        v_nz = not_zero(self.v)
        heading_cmd = np.arcsin(np.clip(-KP_LATERAL * r / v_nz, -1, 1))
        heading_ref = future_heading + np.clip(heading_cmd, -np.pi / 4, np.pi / 4)
        rate = KP_HEADING * wrap_to_pi(heading_ref - self.h)
        q = np.clip(LENGTH / 2 / v_nz * rate, -1, 1)  # sin(slip)
        with np.errstate(divide="ignore"):  # tan(asin(q)) = q / sqrt(1 - q²), ±inf at |q| = 1 (atan: ±π/2)
            tan_slip = q / np.sqrt(1 - q * q)
        return np.clip(np.arctan(2 * tan_slip), -MAX_STEERING, MAX_STEERING)

    def _front(self, lanes: np.ndarray) -> np.ndarray:
        """Road.neighbour_vehicles(vehicle, lane)[0] for every vehicle: among the other vehicles on ``lane``
        (``on_lane`` with a 1 m margin), the one with the smallest s ≥ the vehicle's own (the last in road order on
        ties, as the stock scan's ``<=``). Returns the front slot (-1: none). Only pairs whose vehicle j is within
        6 m of lane i's centreline box are projected: ``on_lane`` needs |r| ≤ 3 m and s within 5 m of the lane,
        i.e. within √(3² + 5²) < 6 m of the centreline."""
        T, N = self.tables, self.N
        if "front" in KERNELS:
            return kernels.front(T.arr, np.ascontiguousarray(lanes), *_contiguous(self, "x", "y", "alive"),
                                 VEHICLE_LENGTH)
        box = T.box[lanes] + np.array([-6.0, -6.0, 6.0, 6.0])  # (B, i, 4)
        x, y = self.x[:, None, :], self.y[:, None, :]
        cand = (box[..., 0:1] <= x) & (x <= box[..., 2:3]) & (box[..., 1:2] <= y) & (y <= box[..., 3:4])
        cand &= self.alive[:, None, :] & self.alive[:, :, None] & ~np.eye(N, dtype=bool)[None]
        b, i, j = np.nonzero(cand)
        k = lanes[b, i]
        s, r = T.local(k, self.x[b, j], self.y[b, j])
        s_self, _ = T.local(lanes, self.x, self.y)
        ok = (np.abs(r) <= T.width[k] / 2 + 1) & (-VEHICLE_LENGTH <= s) & (s < T.length[k] + VEHICLE_LENGTH) \
            & (s_self[b, i] <= s)
        key = np.full((self.B, N, N), np.inf)
        key[b[ok], i[ok], j[ok]] = s[ok]
        j_front = N - 1 - np.argmin(key[:, :, ::-1], axis=2)  # reversed: the last of equal minima
        return np.where(np.isfinite(key).any(axis=2), j_front, -1)

    def leader_idm(self) -> np.ndarray:
        """IDMVehicle.acceleration (m/s², unclipped) of every slot with its leader on its current lane, from the
        set-points and IDM exponents the arrays hold now: what a driver's acceleration says of its hidden draws."""
        return self._idm_acc(self._front(self.lane))

    def _idm(self) -> np.ndarray:
        """IDMVehicle.act's acceleration: IDM on the current lane's leader, and the min with the target lane's
        leader while the two differ (``lane_distance_to`` stays on the current lane in both)."""
        acc = self._idm_acc(self._front(self.lane))
        changing = self.alive & (self.lane != self.tlane)
        if changing.any():
            acc = np.where(changing, np.minimum(acc, self._idm_acc(self._front(self.tlane))), acc)
        return acc

    def _idm_acc(self, front: np.ndarray) -> np.ndarray:
        """IDMVehicle.acceleration + desired_gap (projected); d = lane_distance_to(front) on the current lane."""
        T = self.tables
        if "idm" in KERNELS:
            return kernels.idm(T.arr, *_contiguous(self, "x", "y", "h", "v", "target", "delta", "lane"),
                               np.ascontiguousarray(front), T.speed_limit, COMFORT_ACC_MAX, COMFORT_ACC_MIN,
                               DISTANCE_WANTED, TIME_WANTED)
        target = np.clip(self.target, 0, T.speed_limit[self.lane])
        acc = COMFORT_ACC_MAX * (1 - np.power(np.maximum(self.v, 0) / np.abs(not_zero(target)), self.delta))
        has = front >= 0
        f = np.maximum(front, 0)
        xf, yf = np.take_along_axis(self.x, f, axis=1), np.take_along_axis(self.y, f, axis=1)
        d = T.local(self.lane, xf, yf)[0] - T.local(self.lane, self.x, self.y)[0]
        c, sn = np.cos(self.h), np.sin(self.h)
        vf, hf = np.take_along_axis(self.v, f, axis=1), np.take_along_axis(self.h, f, axis=1)
        dv = (self.v * c - vf * np.cos(hf)) * c + (self.v * sn - vf * np.sin(hf)) * sn
        ab = -COMFORT_ACC_MAX * COMFORT_ACC_MIN
        d_star = DISTANCE_WANTED + self.v * TIME_WANTED + self.v * dv / (2 * np.sqrt(ab))
        return np.where(has, acc - COMFORT_ACC_MAX * np.power(d_star / not_zero(d), 2), acc)

    def step(self, dt: float) -> None:
        """RegulatedRoad.step: the rules every 1/(dt·2) ticks, Vehicle.step for all, then collisions."""
        self.road_steps += 1
        reg = self.road_steps % int(1 / dt / 2) == 0
        if reg.any():
            self._enforce_road_rules(reg)
        self._kinematics(dt)
        self._collisions(dt)
        if self.ego_margin != 0.0:  # a planner's future: a near miss of the ego is a crash (kernels._near_ego_row)
            kernels.near_ego(*_contiguous(self, "x", "y", "h", "alive", "ego", "crashed"), LENGTH, WIDTH,
                             float(self.ego_margin))

    def _kinematics(self, dt: float) -> None:
        """Vehicle.clip_actions + Vehicle.step (kinematic bicycle) + on_state_update (closest lane)."""
        a = self.alive
        steer = np.where(self.crashed, 0.0, self.steer)
        acc = np.where(self.crashed, -1.0 * self.v, self.acc)
        acc = np.where(self.v > kernels.MAX_SPEED, np.minimum(acc, 1.0 * (kernels.MAX_SPEED - self.v)),
                       np.where(self.v < kernels.MIN_SPEED, np.maximum(acc, 1.0 * (kernels.MIN_SPEED - self.v)), acc))
        self.steer, self.acc = np.where(a, steer, self.steer), np.where(a, acc, self.acc)
        # the slip angle β = atan(tan(steer) / 2) by its cosine and sine, 1 / sqrt(1 + t²) and t / sqrt(1 + t²) of
        # t = tan β, and cos(h + β), sin(h + β) by the sum formulas (kernels._slip_cos_sin: the same arithmetic)
        t = 1 / 2 * np.tan(self.steer)
        cb = 1.0 / np.sqrt(1.0 + t * t)
        sb = t * cb
        c, s = np.cos(self.h), np.sin(self.h)
        x = self.x + self.v * (c * cb - s * sb) * dt
        y = self.y + self.v * (s * cb + c * sb) * dt
        imp = self.has_impact & a
        x, y = np.where(imp, x + self.impact_x, x), np.where(imp, y + self.impact_y, y)
        self.crashed |= imp
        self.has_impact &= ~imp
        h = self.h + self.v * sb / (LENGTH / 2) * dt
        v = self.v + self.acc * dt
        self.x, self.y = np.where(a, x, self.x), np.where(a, y, self.y)
        self.h, self.v = np.where(a, h, self.h), np.where(a, v, self.v)
        b, i = np.nonzero(a)
        self.lane[b, i] = self.tables.closest(self.x[b, i], self.y[b, i], self.h[b, i])

    def _collisions(self, dt: float) -> None:
        """Road.step's ``handle_collisions`` for every pair i < j: RoadObject._is_colliding's spherical pre-check,
        then utils.are_polygons_intersecting (separating axes, with the constant-velocity sweep over dt) on all the
        pairs that pass at once; impacts and crash flags are then assigned in the stock pair order (a later pair's
        impact overwrites an earlier one's, as there)."""
        if "collisions" in KERNELS:
            kernels.collisions(*_contiguous(self, "x", "y", "h", "v", "alive"), dt, LENGTH, WIDTH,
                               *_contiguous(self, "crashed", "has_impact", "impact_x", "impact_y"))
            return
        dist = np.hypot(self.x[:, None, :] - self.x[:, :, None], self.y[:, None, :] - self.y[:, :, None])
        near = dist <= DIAGONAL + self.v[:, :, None] * dt
        near &= self.alive[:, :, None] & self.alive[:, None, :] & np.triu(np.ones((self.N,) * 2, bool), 1)[None]
        if not near.any():
            return
        b, i, j = np.nonzero(near)
        inter, will, tx, ty = _polygons_intersecting(self, b, i, j, dt)
        for n in np.nonzero(inter | will)[0]:  # rare: real contacts, in pair order
            bn, in_, jn = b[n], i[n], j[n]
            if will[n]:
                self.impact_x[bn, in_], self.impact_y[bn, in_] = tx[n] / 2, ty[n] / 2
                self.impact_x[bn, jn], self.impact_y[bn, jn] = -tx[n] / 2, -ty[n] / 2
                self.has_impact[bn, in_] = self.has_impact[bn, jn] = True
            if inter[n]:
                self.crashed[bn, in_] = self.crashed[bn, jn] = True

    def _predict(self, envs: np.ndarray):
        """ControlledVehicle.predict_trajectory_constant_speed(times) along the rest of the route, for every
        vehicle of the envs ``envs``: (b, N, T) positions and headings."""
        T = self.tables
        x, y, v, lane = self.x[envs], self.y[envs], self.v[envs], self.lane[envs]
        route, rpos = self.route[envs], self.rpos[envs]
        s0, _ = T.local(lane, x, y)
        lon = s0[..., None] + v[..., None] * REG_TIMES  # (b, N, T)
        n_left = np.clip(3 - rpos, 0, 3)
        n_left = np.where(np.take_along_axis(route, np.minimum(rpos, 2)[..., None], 2)[..., 0] < 0, 0, n_left)
        # route or [lane_index]
        first = np.where(n_left > 0, np.take_along_axis(route, np.minimum(rpos, 2)[..., None], 2)[..., 0], lane)
        k = np.broadcast_to(first[..., None], lon.shape).copy()
        left = np.broadcast_to(np.maximum(n_left, 1)[..., None], lon.shape).copy()
        pos = np.broadcast_to(rpos[..., None], lon.shape).copy()
        for _ in range(2):  # while len(route) > 1 and longitudinal > lane.length: move on
            move = (left > 1) & (lon > T.length[k])
            if not move.any():
                break
            lon = np.where(move, lon - T.length[k], lon)
            pos = np.where(move, pos + 1, pos)
            left = np.where(move, left - 1, left)
            nxt = np.take_along_axis(route, np.minimum(pos, 2).reshape(pos.shape[0], pos.shape[1], -1), 2)
            k = np.where(move, nxt.reshape(lon.shape), k)
        px, py = T.position(k, lon, 0.0)
        ph = T.heading_at(k, lon)
        plain = self.plain[envs]
        if plain.any():  # Vehicle.predict_trajectory_constant_speed: integrated, zero acceleration; a plain
            # vehicle here never steers (its action keeps steering 0), so a straight line at constant speed
            h = self.h[envs][..., None]
            px = np.where(plain[..., None], x[..., None] + v[..., None] * np.cos(h) * REG_TIMES, px)
            py = np.where(plain[..., None], y[..., None] + v[..., None] * np.sin(h) * REG_TIMES, py)
            ph = np.where(plain[..., None], h, ph)
        return px, py, ph

    def _enforce_road_rules(self, envs_mask: np.ndarray) -> None:
        """RegulatedRoad.enforce_road_rules for the envs in ``envs_mask``."""
        T = self.tables
        envs = np.nonzero(envs_mask)[0]
        # Unfreeze previous yielding vehicles (YIELD_DURATION = 0): back to the lane's speed limit
        unf = self.yielding[envs]
        if unf.any():
            self.target[envs] = np.where(unf, T.speed_limit[self.lane[envs]], self.target[envs])
            self.yielding[envs] = False
        px, py, ph = self._predict(envs)  # (b, N, T)
        alive = self.alive[envs]
        if "conflicts" in KERNELS:
            conflict = kernels.conflicts(*map(np.ascontiguousarray, (px, py, ph, alive)), LENGTH, WIDTH)
        else:
            conflict = _conflicts(px, py, ph, alive)
        for b, i, j in zip(*np.nonzero(conflict)):  # respect_priorities, in pair order
            e = envs[b]
            p1, p2 = T.priority[self.lane[e, i]], T.priority[self.lane[e, j]]
            if p1 > p2:
                y_ = j
            elif p1 < p2:
                y_ = i
            else:  # the vehicle behind yields: front_distance_to
                dxy = np.array([self.x[e, j] - self.x[e, i], self.y[e, j] - self.y[e, i]])
                fi = np.cos(self.h[e, i]) * dxy[0] + np.sin(self.h[e, i]) * dxy[1]
                fj = -(np.cos(self.h[e, j]) * dxy[0] + np.sin(self.h[e, j]) * dxy[1])
                y_ = i if fi > fj else j
            if not (self.mdp[e, y_] or self.plain[e, y_]):  # ControlledVehicles but MDPVehicle yield
                self.target[e, y_] = 0.0
                self.yielding[e, y_] = True


# kernels.advance's state arguments, in its order, and its constants (kernels.P_*)
_TICK_STATE = ("x", "y", "h", "v", "target", "steer", "acc", "delta", "alive", "ego", "plain", "mdp", "crashed",
               "yielding", "impact_x", "impact_y", "has_impact", "lane", "tlane", "route", "rpos", "road_steps")
_TICK_PARAMS = np.array([VEHICLE_LENGTH, LENGTH, WIDTH, COMFORT_ACC_MAX, COMFORT_ACC_MIN, ACC_MAX, DISTANCE_WANTED,
                         TIME_WANTED, TAU_PURSUIT, KP_LATERAL, KP_HEADING, KP_A, MAX_STEERING, EXIT_DISTANCE, 0.0])


def _contiguous(t: Traffic, *names: str) -> list[np.ndarray]:
    """The named state arrays, made C-contiguous in place (no copy when they are: the kernels write into some)."""
    for name in names:
        setattr(t, name, np.ascontiguousarray(getattr(t, name)))
    return [getattr(t, name) for name in names]


def _conflicts(px, py, ph, alive) -> np.ndarray:
    """The regulation's pairwise conflict test on (b, N, T) predictions: (b, N, N), pairs i < j of live vehicles
    whose centres come within LENGTH (the stock pre-check) and whose boxes then intersect at some time."""
    N = alive.shape[1]
    dx = px[:, None, :, :] - px[:, :, None, :]  # (b, i, j, T): j - i
    dy = py[:, None, :, :] - py[:, :, None, :]
    close = np.hypot(dx, dy) <= LENGTH
    pair = alive[:, :, None] & alive[:, None, :] & np.triu(np.ones((N, N), bool), 1)[None]
    close &= pair[..., None]
    conflict = np.zeros_like(pair)
    bb, ii, jj, tt = np.nonzero(close)
    hit = _rects_intersect(px[bb, ii, tt], py[bb, ii, tt], ph[bb, ii, tt],
                           px[bb, jj, tt], py[bb, jj, tt], ph[bb, jj, tt])
    conflict[bb[hit], ii[hit], jj[hit]] = True
    return conflict


def _rect_points(x, y, h, length, width):
    """utils.rect_corners(include_midpoints=True, include_center=True): (M, 9, 2)."""
    hl, hw = length / 2, width / 2
    local = np.array([[-hl, -hw], [-hl, hw], [hl, hw], [hl, -hw], [0, 0], [-hl, 0], [hl, 0], [0, -hw], [0, hw]])
    c, s = np.cos(h)[:, None], np.sin(h)[:, None]
    return np.stack([c * local[:, 0] - s * local[:, 1] + x[:, None], s * local[:, 0] + c * local[:, 1] + y[:, None]],
                    axis=-1)


def _inside(points, x, y, h, length, width):
    """utils.point_in_rotated_rectangle for (M, P, 2) points (its rotation is by +angle, as in highway-env)."""
    c, s = np.cos(h)[:, None], np.sin(h)[:, None]
    dx, dy = points[..., 0] - x[:, None], points[..., 1] - y[:, None]
    ux, uy = c * dx - s * dy, s * dx + c * dy
    return ((-length / 2 <= ux) & (ux <= length / 2) & (-width / 2 <= uy) & (uy <= width / 2)).any(axis=1)


def _rects_intersect(x1, y1, h1, x2, y2, h2):
    """utils.rotated_rectangles_intersect of the regulation's (1.5 L, 0.9 W) boxes, for arrays of pairs."""
    L, W = 1.5 * LENGTH, 0.9 * WIDTH
    return _inside(_rect_points(x1, y1, h1, L, W), x2, y2, h2, L, W) | \
        _inside(_rect_points(x2, y2, h2, L, W), x1, y1, h1, L, W)


def _polygons(t: Traffic, b, i):
    """RoadObject.polygon for vehicles (b, i): (P, 5, 2), closed."""
    local = np.array([[-LENGTH / 2, -WIDTH / 2], [-LENGTH / 2, WIDTH / 2], [LENGTH / 2, WIDTH / 2],
                      [LENGTH / 2, -WIDTH / 2], [-LENGTH / 2, -WIDTH / 2]])
    c, s = np.cos(t.h[b, i])[:, None], np.sin(t.h[b, i])[:, None]
    return np.stack([c * local[:, 0] - s * local[:, 1] + t.x[b, i][:, None],
                     s * local[:, 0] + c * local[:, 1] + t.y[b, i][:, None]], axis=-1)


def _polygons_intersecting(t: Traffic, b, i, j, dt):
    """utils.are_polygons_intersecting(polygon_i, polygon_j, velocity_i dt, velocity_j dt) for arrays of pairs:
    intersecting, will intersect, and the translation (min |distance| axis, first on ties, pointing from j to
    i). The stock loop's early exit only happens once both flags are False, when the translation is unused."""
    pa, pb = _polygons(t, b, i), _polygons(t, b, j)
    da = np.stack([np.cos(t.h[b, i]), np.sin(t.h[b, i])], -1) * (t.v[b, i] * dt)[:, None]
    db = np.stack([np.cos(t.h[b, j]), np.sin(t.h[b, j])], -1) * (t.v[b, j] * dt)[:, None]
    edges = np.concatenate([pa[:, 1:] - pa[:, :-1], pb[:, 1:] - pb[:, :-1]], axis=1)  # (P, 8, 2)
    normal = np.stack([-edges[..., 1], edges[..., 0]], axis=-1)
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    proj_a = np.einsum("pkd,pad->pka", normal, pa)  # (P, 8 axes, 5 points)
    proj_b = np.einsum("pkd,pad->pka", normal, pb)
    min_a, max_a, min_b, max_b = proj_a.min(-1), proj_a.max(-1), proj_b.min(-1), proj_b.max(-1)

    def interval_distance(min_a, max_a, min_b, max_b):
        return np.where(min_a < min_b, min_b - max_a, min_a - max_b)

    intersecting = ~(interval_distance(min_a, max_a, min_b, max_b) > 0).any(axis=1)
    vp = np.einsum("pkd,pd->pk", normal, da - db)
    min_a, max_a = np.where(vp < 0, min_a + vp, min_a), np.where(vp < 0, max_a, max_a + vp)
    distance = interval_distance(min_a, max_a, min_b, max_b)
    will = ~(distance > 0).any(axis=1)
    k = np.argmin(np.abs(distance), axis=1)
    rows = np.arange(len(b))
    axis = normal[rows, k]
    d = pa[:, :-1].mean(axis=1) - pb[:, :-1].mean(axis=1)
    axis = np.where(((d * axis).sum(-1) > 0)[:, None], axis, -axis)
    translation = np.abs(distance[rows, k])[:, None] * axis
    return intersecting, will, translation[:, 0], translation[:, 1]
