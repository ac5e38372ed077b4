"""The AEB shield (``shield=aeb``: the ``improved`` variant, ground-truth or perceived mode) for every env of a
:class:`~av_gym.batched.left_turn.BatchedLeftTurn`.

The per-env shield (:class:`~av_gym.shields.aeb_improved.ImprovedAEB`) stays the reference and is what decides
here: each env of the batch has its own ImprovedAEB, built around a :class:`RowEnv`, a read-only view of that env's
row of the batch's arrays with the attributes the shield reads of highway-env's env (the ego, the road's vehicles in
road order, the road network, the route, the clock, the action type). So every decision (the conflict model, the
driven path, the stop-line trigger, feasibility, release, the indicator channel and its Bayes filter) is the per-env
shield's code on the per-env shield's inputs: one implementation, nothing to keep in step.

What the batch does itself:

- **perception** (``mode: perceived``): the shield's own detector and tracker for all envs at once
  (:class:`~av_gym.batched.perception.BatchedDetector` on each env's ``episode_rng(seed, "aeb_detector")``, the
  per-env shield's stream, and :class:`~av_gym.batched.perception.BatchedTracker`, the per-env
  ``MultiObjectTracker``'s arithmetic); each env's shield reads its confirmed tracks.
- **the conflict model's prediction** (ground-truth mode): what each row's shield asks the conflict model first in a
  decision (its kept road users' path hypotheses) for all rows in one compiled call
  (:meth:`~av_gym.shields.conflicts.ConflictModel.predict_rows`: each row :func:`~av_gym.shields.kernels.
  conflict_predict` on its own inputs, the same floats as the shield's own call), handed to the shield as its road
  users' rows are; the rules that predict again (set-off, release, emergency) call the model themselves.
- **the brake actuator**: the per-env shield patches the ego's ``act`` so that every 20 Hz tick ends with the
  actuator's acceleration. On the batch the engine's step takes that acceleration per tick as the ego's commanded
  one (:meth:`BatchedShield.brake_plan`, (frames, B), handed to ``BatchedLeftTurn.step``; the engine's
  ``max(a, -v / 0.05)`` is the actuator's own no-reversing clamp at 20 Hz).

Not on the batch (refused in one line by :func:`check_batched_shield`): the ``paper`` and ``standard`` variants, a
second opinion (``aeb_belief``: the planner it asks plays the per-env stack's copies), and a simulation frequency
other than 20 Hz.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
from highway_env.envs.common.action import DiscreteMetaAction
from highway_env.vehicle.controller import MDPVehicle

from av_gym.batched.left_turn import tables
from av_gym.envs.lane_path import LanePath
from av_gym.envs.left_turn import ROUTE, UnprotectedLeftTurnEnv
from av_gym.errors import ConfigError
from av_gym.estimation.driver_intent import DriverIntent
from av_gym.params import ParamError
from av_gym.sensors.base import episode_rng
from av_gym.sensors.turn_signal import (DRIVER_DRAWS, DriverDraws, first_sighting, fit_ids, node_index, reported,
                                        route_origin, turn_signal)
from av_gym.shields.aeb_improved import GO_TAU, ImprovedAEB, _go_rise, followers, long_times
from av_gym.shields.aeb_params import BRAKE, MONITOR, SETOFF_ACCEL_TIME, STOP_SPEED, WARN, ImprovedParams
from av_gym.shields.conflicts import ConflictModel
from av_gym.shields.locate_rows import locate_rows
from av_gym.shields.predict import setpoint_steps
from av_gym.shields.setoff_rows import box_lanes, predict_rows_following, setoff_slow, setoff_start
from av_gym.sim.fast_network import FastRoadNetwork
from av_gym.sim.batched import LENGTH, WIDTH

SIM_HZ = 20  # the engine's commanded acceleration clamps a standstill at v / 0.05 s, the actuator at v / sim_dt
SCREEN = True  # False: every row's decision by its shield's own code (BatchedShield._screen; A/B checks, tests)
SCREEN_CHECK = False  # True: each screened row's own decision runs too and must be the screen's (tests)


def shield_kind(shield_cfg: Mapping | None) -> str:
    """The ``kind`` of a shield section (``none`` when there is none)."""
    s = shield_cfg or {}
    return str(s.get("kind", s.get("name", "none")) or "none")


def check_batched_shield(shield_cfg: Mapping | None, env_cfg: Mapping | None = None) -> ImprovedParams | None:
    """The shield's parameters if the batch can run this ``shield`` section (None for no shield), else one
    ConfigError line naming the field and what the batch runs."""
    kind = shield_kind(shield_cfg)
    if kind == "none":
        return None
    if kind != "aeb":
        raise ConfigError(f"shield.kind={kind} is not available with agent.vec_env=batched (it runs shield=aeb, "
                          f"the improved variant); use agent.vec_env=subproc")
    values = {k: v for k, v in dict(shield_cfg).items() if k not in ("name", "kind", "variant")}
    variant = dict(shield_cfg).get("variant", "improved")
    if variant != "improved":
        raise ConfigError(f"shield.variant={variant} is not available with agent.vec_env=batched (it runs the "
                          f"improved variant: shield=aeb); use agent.vec_env=subproc")
    try:
        p = ImprovedParams.from_mapping(values, "shield", what="a parameter of the AEB shield's improved variant")
    except ParamError as exc:
        raise ConfigError(str(exc)) from None
    if p.second_opinion != "none":
        raise ConfigError(f"shield.second_opinion={p.second_opinion} is not available with agent.vec_env=batched "
                          f"(its planner plays copies of the per-env stack); use agent.vec_env=subproc, or "
                          f"shield=aeb")
    hz = ((env_cfg or {}).get("simulation_frequency") if env_cfg else None) or SIM_HZ
    if int(hz) != SIM_HZ:
        raise ConfigError(f"env.simulation_frequency={hz} with shield=aeb is not available with "
                          f"agent.vec_env=batched (its brake actuator runs at {SIM_HZ} Hz); use agent.vec_env=subproc")
    return p


# ----------------------------------------------------------------------------------------------- one env's view
class _Vehicle:
    """What the shield reads of a highway-env vehicle, for one slot of the batch (one object per vehicle for the
    whole episode, as highway-env's: the shield keys its per-object memory by it)."""

    LENGTH, WIDTH = LENGTH, WIDTH

    def __init__(self, vid: int) -> None:
        self.vid = int(vid)
        self.action: dict = {}

    def act(self, action=None) -> None:
        """The per-env shield wraps the ego's ``act`` with its actuator; on the batch the actuator runs in
        :meth:`BatchedShield.brake_plan`."""

    # MDPVehicle's set-point arithmetic, on this view's target_speeds (the ego's, discrete actions)
    speed_to_index = MDPVehicle.speed_to_index
    index_to_speed = MDPVehicle.index_to_speed


class _Road:
    def __init__(self, network) -> None:
        self.network = network
        self.vehicles: list[_Vehicle] = []


class RowEnv(gym.Env):
    """The scenario env of one row of a :class:`BatchedLeftTurn` as the AEB shield reads it: ``vehicle`` (the ego),
    ``road.vehicles`` (road order) and ``road.network``, ``route``, ``steps``, ``config``, ``episode_seed``,
    ``action_type`` and ``cruise_action``. :meth:`refresh` reads the row's state now (SI units)."""

    scenario = "left_turn"

    def __init__(self, engine, row: int, template: UnprotectedLeftTurnEnv, network, route: LanePath) -> None:
        self.e, self.row, self.template = engine, int(row), template
        self.action_space, self.observation_space = template.action_space, template.observation_space
        self.action_type, self.config, self.route = template.action_type, engine.config, route
        self.road = _Road(network)
        self.vehicle: _Vehicle | None = None
        self._by_vid: dict[int, _Vehicle] = {}
        # the shield's road-user rows and accelerations, set by the batch before each decision (None: computed by
        # the shield's own code, perceived mode)
        self.objects: np.ndarray | None = None
        self.accels: np.ndarray | None = None
        self.relevant: np.ndarray | None = None
        self.lanes: list = []  # their lane indices and keys (vehicle ids), with ``objects``
        self.keys: list = []
        # the indicator channel's turn weights of the kept road users, and who moved lately (ground-truth mode)
        self.intent: np.ndarray | None = None
        self.recent: np.ndarray | None = None
        # the conflict model's paths of the kept road users (ConflictModel.predict's tuple), None: the shield's own,
        # and how many road users the batch kept for it
        self.predicted: tuple | None = None
        self.predicted_n = 0

    def cruise_action(self):
        return self.template.cruise_action()

    @property
    def steps(self) -> int:
        return int(self.e.ticks[self.row])

    @property
    def episode_seed(self) -> int:
        return int(self.e.episode_seed[self.row])

    def reset(self, **kwargs):
        self._by_vid = {}
        self.refresh()
        return {}, {}

    def refresh(self, ego_only: bool = False) -> None:
        """Every alive vehicle of the row, in road order, as the shield reads it now; ``ego_only``: the ego alone
        (``road.vehicles`` then holds only it), where the batch hands the shield its road users' rows, lanes and keys
        (ground-truth mode: :meth:`BatchedShield._kinematics`)."""
        t, r = self.e.traffic, self.row
        slots = np.flatnonzero(t.alive[r] & t.ego[r] if ego_only else t.alive[r])
        # the row's numbers as Python floats and ints at once (the same values as one element at a time)
        self.read(zip(slots.tolist(), t.vid[r, slots].tolist(), t.x[r, slots].tolist(), t.y[r, slots].tolist(),
                      t.v[r, slots].tolist(), t.h[r, slots].tolist(), t.lane[r, slots].tolist(),
                      t.route[r, slots].tolist(), t.ego[r, slots].tolist()), ego_only)

    def read(self, columns, ego_only: bool = False) -> None:
        """The vehicles of ``columns`` (per vehicle: slot, id, x, y, speed, heading, lane id, route lane ids, is the
        ego; Python numbers, road order) as :meth:`refresh` reads them."""
        index, r = self.e.T.index, self.row
        by_vid, vehicles, known = {}, [], self._by_vid
        for i, vid, x, y, speed, heading, lane, route, ego in columns:
            v = known.get(vid) or _Vehicle(vid)
            v.position = np.array([x, y])
            v.speed, v.heading = speed, heading
            v.lane_index = index[lane]
            v.route = [index[k] for k in route if k >= 0] or None
            by_vid[vid] = v
            vehicles.append(v)
            if ego:
                self._ego(v, r, i)
        # ego alone: the vehicles read before keep their objects (a full read later updates the same ones)
        self._by_vid, self.road.vehicles = {**known, **by_vid} if ego_only else by_vid, vehicles

    def _ego(self, v: _Vehicle, r: int, i: int) -> None:
        """The ego's own state: velocity, last commanded steering and acceleration, set-point, lane."""
        e, t = self.e, self.e.traffic
        v.velocity = v.speed * np.array([np.cos(v.heading), np.sin(v.heading)])
        v.action = {"steering": float(t.steer[r, i]), "acceleration": float(t.acc[r, i])}
        v.lane = self.road.network.get_lane(v.lane_index)
        if not e.continuous:  # an MDPVehicle (hasattr speed_index: the shield's test for a cruise set-point)
            v.target_speeds, v.target_speed, v.speed_index = e.speeds, float(t.target[r, i]), 0
        self.vehicle = v


# ----------------------------------------------------------------------------------------------- perception
class _Tracks:
    """The per-env shield's ``detector`` and ``tracker`` for one row: the batch's readings, measured for every row
    before the decisions (:meth:`BatchedShield._perceive`)."""

    def __init__(self) -> None:
        self.rows, self.ids = np.zeros((0, 7)), np.zeros(0, dtype=int)
        self.rng = None

    def on_reset(self) -> None:
        pass

    def reset(self) -> None:
        pass

    def measure(self) -> None:
        return None

    def step(self, detections, t: float, ego_xy) -> np.ndarray:
        return self.rows

    def track_ids(self) -> np.ndarray:
        return self.ids


# ----------------------------------------------------------------------------------------------- the batch
def _row_shield_class():
    """ImprovedAEB on a :class:`RowEnv` whose road users' state rows and accelerations the batch computed for all
    rows at once (ground-truth mode: :class:`_Kinematics`); where it did not (perceived mode: tracks) the per-env
    code runs."""

    class RowAEB(ImprovedAEB):
        def _objects(self, ego: dict) -> tuple[np.ndarray, list, list]:
            view = self.env
            if view.objects is None:
                return super()._objects(ego)
            self._lanes = view.lanes
            return view.objects, view.keys, list(range(len(view.keys)))

        def _decision_accels(self, ego: dict, others: np.ndarray, keys: list, t: float) -> np.ndarray:
            view = self.env
            return super()._decision_accels(ego, others, keys, t) if view.accels is None else view.accels

        def _relevant(self, ego: dict, others: np.ndarray) -> np.ndarray:
            view = self.env
            return super()._relevant(ego, others) if view.relevant is None else view.relevant

        def _intent(self, others: np.ndarray, keys: list) -> np.ndarray | None:
            view = self.env
            return super()._intent(others, keys) if view.intent is None else view.intent

        def _recently_moved(self, others: np.ndarray, t: float) -> np.ndarray | None:
            view = self.env
            return super()._recently_moved(others, t) if view.recent is None else view.recent

        def _scene_conflicts(self, others: np.ndarray, lanes: list, a_others: np.ndarray, t_long: np.ndarray,
                             intent: np.ndarray | None) -> tuple:
            view = self.env
            if view.predicted is None:
                return super()._scene_conflicts(others, lanes, a_others, t_long, intent)
            if len(others) != view.predicted_n:  # the batch's prediction is for another set of road users than it keeps
                raise RuntimeError(f"row {view.row}: the batch's prediction holds {view.predicted_n} road users, "
                                   f"the shield keeps {len(others)}")
            return view.predicted

    return RowAEB


class _Kinematics:
    """What the per-env shield's ``_objects`` and ``_accelerations`` compute in ground-truth mode, for every row
    at once from the engine's arrays (the ego's slot among the others): each road user's state row
    ``[x, y, vx, vy, heading, length, width]`` (velocity ``speed * [cos, sin](heading)``, the same products), and
    the finite-difference accelerations low-passed by the EMA, remembered per vehicle id (the engine's slots move
    when it compacts them) and forgotten, as the per-env shield's dicts drop a key, once that vehicle is not there
    at a decision. Element by element the per-env shield's operations: the same numbers."""

    def __init__(self, B: int, alpha: float) -> None:
        self.alpha = float(alpha)
        self.prev_t = np.full(B, np.nan)  # s, the row's last decision (NaN: none this episode)
        # per row, the vehicles of its last decision (-1: none; one empty slot to start: argmax needs a column),
        # their velocities (m/s) and EMAs (m/s²)
        self.vid = np.full((B, 1), -1, dtype=np.int64)
        self.prev_v, self.ema, self.has_ema = np.zeros((B, 1, 2)), np.zeros((B, 1, 2)), np.zeros((B, 1), bool)

    def reset(self, rows: np.ndarray) -> None:
        """New episodes in ``rows``: nothing remembered (the per-env shield's reset)."""
        self.prev_t[rows], self.vid[rows] = np.nan, -1

    def update(self, engine, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The decision of the envs ``rows`` now: every slot's state row (n, S, 7) and its acceleration (n, S, 2)
        (zero where the shield has none), the memory moved on to this decision."""
        t = engine.traffic
        alive, h, v = t.alive[rows], t.h[rows], t.v[rows]
        state = np.empty((*alive.shape, 7))
        state[..., 0], state[..., 1] = t.x[rows], t.y[rows]
        state[..., 2], state[..., 3] = v * np.cos(h), v * np.sin(h)
        state[..., 4], state[..., 5], state[..., 6] = h, LENGTH, WIDTH
        vel, now = state[..., 2:4], engine.ticks[rows] / float(engine.config["simulation_frequency"])
        vid = np.where(alive, t.vid[rows], -1)
        same = (vid[:, :, None] == self.vid[rows][:, None, :]) & (vid[:, :, None] >= 0)  # (n, S, last's slots)
        match, j = same.any(axis=2), same.argmax(axis=2)  # in the last decision, and its slot there
        prev_v = np.take_along_axis(self.prev_v[rows], j[..., None], axis=1)
        known = match & np.take_along_axis(self.has_ema[rows], j, axis=1)
        ema = np.where(known[..., None], np.take_along_axis(self.ema[rows], j[..., None], axis=1), 0.0)
        dt = now - self.prev_t[rows]
        ok = dt > 1e-9  # the per-env ``if dt and dt > 1e-9`` (no decision before: NaN)
        seen = match & ok[:, None]
        with np.errstate(invalid="ignore", divide="ignore"):  # rows without a previous decision: not used
            raw = (vel - prev_v) / dt[:, None, None]
        alpha = self.alpha
        ema = np.where(seen[..., None], alpha * raw + (1 - alpha) * ema, ema)
        has = np.where(ok[:, None], match, known)
        out = np.where(has[..., None], ema, 0.0)
        self._keep(rows, vid, vel, out, has)
        self.prev_t[rows] = now
        return state, out

    def _keep(self, rows: np.ndarray, vid: np.ndarray, vel: np.ndarray, ema: np.ndarray, has: np.ndarray) -> None:
        """This decision's vehicles of ``rows`` for the next one (the memory widened to the engine's slots)."""
        S = vid.shape[1]
        if S > self.vid.shape[1]:
            grow = S - self.vid.shape[1]
            B = len(self.vid)
            self.vid = np.concatenate([self.vid, np.full((B, grow), -1, np.int64)], axis=1)
            self.prev_v = np.concatenate([self.prev_v, np.zeros((B, grow, 2))], axis=1)
            self.ema = np.concatenate([self.ema, np.zeros((B, grow, 2))], axis=1)
            self.has_ema = np.concatenate([self.has_ema, np.zeros((B, grow), bool)], axis=1)
        self.vid[rows] = -1
        self.vid[rows, :S], self.prev_v[rows, :S], self.ema[rows, :S], self.has_ema[rows, :S] = vid, vel, ema, has


class _Channel:
    """ImprovedAEB's own indicator channel and Bayes filter (``_intent``, ground-truth mode) for every row at once:
    per row its own generator (``episode_rng(seed, "aeb_signals")``, the per-env shield's stream) drawn as the
    per-env shield draws it (per decision the first sightings' ``DRIVER_DRAWS`` uniforms per new driver in reading
    order, then one per reading: one ``uniform(size=...)`` call gives the numbers of the two), the per-driver draws
    and reading counts in arrays by vehicle id (unique in the process, so a new episode needs no clearing), the
    intended indicator from each slot's lane and route (``intended_signal``'s rule), and each row's turn weights
    from its kept drivers' counts in one :meth:`DriverIntent.weights` per row (the per-env grouping: a matrix
    product's last bit may depend on how many rows it has)."""

    def __init__(self, engine, params: ImprovedParams) -> None:
        self.e, self.p = engine, params.signal_channel
        T = engine.T
        self.origin = np.array([route_origin(f, t) for f, t, _ in T.index])
        self.dest = np.array([node_index(t, "o") for _, t, _ in T.index])
        self.draws = DriverDraws()
        self.counts = np.zeros((64, 3), dtype=np.int64)  # readings right, none, left per vehicle id
        self.beliefs = DriverIntent(self.p)
        self.rngs: list = [None] * engine.B

    def reset(self, rows: np.ndarray) -> None:
        for r in rows.tolist():
            self.rngs[r] = episode_rng(int(self.e.episode_seed[r]), "aeb_signals")

    def _intended(self, rows: np.ndarray) -> np.ndarray:
        """(n, S) :func:`intended_signal` of every slot: its lane's approach and its route's last lane's exit."""
        t = self.e.traffic
        route = t.route[rows]
        last = np.where(route[..., 2] >= 0, route[..., 2], np.where(route[..., 1] >= 0, route[..., 1], route[..., 0]))
        return turn_signal(self.origin[t.lane[rows]], np.where(last >= 0, self.dest[last], -1))

    def _read(self, rows: np.ndarray, vid: np.ndarray, in_range: np.ndarray) -> None:
        """This decision's readings of the drivers ``in_range`` (n, S) of the envs ``rows``, counted."""
        known = self.draws.get(vid)[0]
        fresh = in_range & ~known
        n_fresh, n_read = (DRIVER_DRAWS * fresh.sum(axis=1)).tolist(), in_range.sum(axis=1).tolist()
        first, seen = [], []
        for r, f, k in zip(rows.tolist(), n_fresh, n_read):
            if k:
                u = self.rngs[r].uniform(size=f + k)
                first.append(u[:f])
                seen.append(u[f:])
        if not seen:
            return
        if fresh.any():
            self.draws.keep(vid[fresh], *first_sighting(np.concatenate(first).reshape(-1, DRIVER_DRAWS), self.p))
        _, indicates, wrong = self.draws.get(vid[in_range])
        readings = reported(self._intended(rows)[in_range], indicates, wrong, np.concatenate(seen), self.p)
        ids = vid[in_range]
        self.counts = fit_ids(self.counts, ids, 0)
        self.counts[ids, np.where(readings < 0, 0, np.where(readings == 0, 1, 2))] += 1

    def weights(self, rows: np.ndarray, state: np.ndarray, kept: np.ndarray, ego: np.ndarray) -> list[np.ndarray]:
        """Per env of ``rows``, the turn weights (its kept road users in road order, 3) of ``_intent`` after this
        decision's readings: ``state`` (n, S, 7) every slot's row, ``kept`` (n, S) the relevant road users, ``ego``
        (n,) the ego's slot; NaN rows for drivers never read."""
        t = self.e.traffic
        vid = t.vid[rows]
        at = np.arange(len(rows))
        dx, dy = state[..., 0] - state[at, ego, 0][:, None], state[..., 1] - state[at, ego, 1][:, None]
        self._read(rows, vid, kept & (dx * dx + dy * dy <= self.p.max_range**2))  # np.square(.).sum(): the same
        ever = self.draws.get(vid)[0] & kept
        out = np.full((int(kept.sum()), 3), np.nan)  # every env's kept road users, one env after the other
        out[ever[kept]] = self._posteriors(self.counts[vid[ever]], ever.sum(axis=1))
        return np.split(out, np.cumsum(kept.sum(axis=1))[:-1]) if len(rows) else []

    def _posteriors(self, counts: np.ndarray, per_env: np.ndarray) -> np.ndarray:
        """``DriverIntent.weights`` of each env's drivers read so far as the per-env shield groups them (one call
        per decision with that decision's drivers): ``counts`` (N, 3) every env's drivers one env after the other,
        ``per_env`` (n,) how many are each env's. The envs with as many drivers are one stack (S, m, 3), one (m, 3)
        product per env: the numbers of its own call bit for bit as observed here with numpy 2.4's OpenBLAS 0.3.31,
        not promised by numpy (another BLAS may round a last bit apart; the tests allow for that)."""
        out = np.empty((len(counts), 3))
        start = np.cumsum(per_env) - per_env
        for m in np.unique(per_env[per_env > 0]).tolist():
            at = (start[per_env == m][:, None] + np.arange(m)).reshape(-1)
            out[at] = self.beliefs.weights(counts[at].reshape(-1, m, 3)).reshape(-1, 3)
        return out


class _Moved:
    """ImprovedAEB's ``_recently_moved`` for every row at once: when each vehicle id was last faster than
    ``setoff_speed`` (s; -inf: never), in an array by vehicle id (unique in the process)."""

    def __init__(self, params: ImprovedParams) -> None:
        self.speed, self.window = float(params.setoff_speed), float(params.setoff_recent)
        self.at = np.full(64, -np.inf)

    def recent(self, vid: np.ndarray, state: np.ndarray, others: np.ndarray, now: np.ndarray) -> np.ndarray:
        """(n, S): the road users ``others`` that were faster than ``setoff_speed`` within ``setoff_recent`` s of
        ``now`` (n,) s, those moving now recorded first (the per-env order)."""
        self.at = fit_ids(self.at, vid, -np.inf)
        fast = others & (np.hypot(state[..., 2], state[..., 3]) >= self.speed)
        self.at[vid[fast]] = np.broadcast_to(now[:, None], fast.shape)[fast]
        return others & (now[:, None] - self.at[vid] <= self.window + 1e-9)


def _followers(state: np.ndarray, ego: np.ndarray) -> np.ndarray:
    """ImprovedAEB._relevant's follower test for every slot of every row at once: (n, S) bool (``state`` (n, S, 7)
    :class:`_Kinematics`' rows, ``ego`` (n,) the ego's slot)."""
    at = np.arange(len(ego))
    return followers(state[at, ego, 0:2], state[at, ego, 4], LENGTH, state)


class BatchedShield:
    """``shield=aeb`` for every env of ``engine``: per env the per-env shield deciding on its :class:`RowEnv`;
    :meth:`decide` before a step (the applied actions), :meth:`brake_plan` for the engine's step, :meth:`after`
    after it; per episode ``brake_time`` (s), ``stop_position`` (m past the stop line), ``overrides`` (the steps it
    overrode)."""

    def __init__(self, engine, params: ImprovedParams) -> None:
        self.e, self.p = engine, params
        B = engine.B
        cfg = {k: v for k, v in engine.config.items() if k != "observation"}
        template = UnprotectedLeftTurnEnv(config=cfg)
        network = tables()[1]  # the intersection's highway-env road network, built once per process
        if engine.config.get("fast", True):  # the per-env env's own (UnprotectedLeftTurnEnv._reset): its lanes' floats
            network = FastRoadNetwork.from_network(network)
        route = LanePath([network.get_lane(i) for i in ROUTE])
        self.route = route  # the ego's LanePath, shared by every row's view
        self.views = [RowEnv(engine, r, template, network, route) for r in range(B)]
        self.shields = []
        row_shield = _row_shield_class()
        for view in self.views:
            s = row_shield(view, dataclasses.replace(params, mode="ground_truth"))
            s.p = params  # the section's mode: its perception is the batch's (_Tracks)
            if params.mode == "perceived":
                s.detector, s.tracker = _Tracks(), _Tracks()
            self.shields.append(s)
        self.perception = _shield_perception(engine, params) if params.mode == "perceived" else None
        # ground truth: the road users' rows and accelerations for all rows at once (perceived: the tracks')
        self.kinematics = _Kinematics(B, params.accel_alpha) if params.mode == "ground_truth" else None
        truth = params.mode == "ground_truth"
        self.channel = _Channel(engine, params) if truth and params.target_model == "conflict" and params.signals \
            else None
        self.moved = _Moved(params) if truth and params.setoff_speed > 0 else None
        # the conflict model's prediction for all rows at once (ground truth: the batch has the road users' rows)
        self.conflicts = ConflictModel(network, min_p=params.hypothesis_min_p) \
            if truth and params.target_model == "conflict" else None
        self.t_long = long_times(params)  # s, the shields' long prediction
        self.override = np.zeros(B, bool)
        self.steps = np.zeros(B, dtype=int)
        self.overrides: list[list[int]] = [[] for _ in range(B)]
        self._brake_from: np.ndarray | None = None
        self._flat: SimpleNamespace | None = None  # this decision's kept road users and prediction for the screen
        self.in_box = box_lanes(engine.T.index)  # per engine lane id: through the box (the set-off rule's lanes)

    def reset(self, rows) -> None:
        """New episodes in the envs ``rows`` (after the engine started them): the per-env shield's reset."""
        rows = np.asarray(rows, dtype=int)
        if self.perception is not None:
            self.perception.detector.reset(rows, self.e.episode_seed[rows])
            self.perception.tracker.reset(rows)
        if self.kinematics is not None:
            self.kinematics.reset(rows)
        if self.channel is not None:
            self.channel.reset(rows)
        for r in rows.tolist():
            self.shields[r].reset()
            self.override[r], self.steps[r], self.overrides[r] = False, 0, []

    def decide(self, rows: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """The shield's decision for the envs ``rows`` before their step under the env actions ``actions`` (B,)
        (meta-actions, or the continuous command in [-1, 1]); returns the actions applied (the throttle cut while
        braking) and sets :attr:`override`."""
        rows = np.asarray(rows, dtype=int)
        if self.kinematics is not None:  # its road users from _kinematics: each view reads its ego alone
            self._read_egos(rows)
        else:
            for r in rows.tolist():
                self.views[r].refresh()
        if self.perception is not None:
            self._perceive(rows)
        else:
            self._kinematics(rows)
        applied = np.array(actions, copy=True)
        screened = self._screen(rows, actions)
        for n, r in enumerate(rows.tolist()):
            if screened is not None and screened[n]:  # the screen decided it (no brake), its state moved on
                self.override[r] = False
                continue
            s = self.shields[r]
            action = self._env_action(actions[r])
            s._proposed = action
            stage, *_ = s._decide()
            self.override[r] = stage == BRAKE
            if self.override[r]:
                self.overrides[r].append(int(self.steps[r]))
                applied[r] = np.asarray(s._throttle_cut(action)).reshape(-1)[0]
        self.steps[rows] += 1
        return applied

    def _read_egos(self, rows: np.ndarray) -> None:
        """:meth:`RowEnv.refresh` with ``ego_only`` for the envs ``rows``, their egos' numbers read for all at once."""
        t = self.e.traffic
        slot = self.e.ego_slot(rows)
        columns = zip(slot.tolist(), t.vid[rows, slot].tolist(), t.x[rows, slot].tolist(), t.y[rows, slot].tolist(),
                      t.v[rows, slot].tolist(), t.h[rows, slot].tolist(), t.lane[rows, slot].tolist(),
                      t.route[rows, slot].tolist(), (t.alive[rows, slot] & t.ego[rows, slot]).tolist())
        for r, (i, vid, x, y, speed, heading, lane, route, alive) in zip(rows.tolist(), columns):
            view = self.views[r]
            if alive:
                view.read([(i, vid, x, y, speed, heading, lane, route, True)], ego_only=True)
            else:  # no ego on the road (argmax's slot 0 is then no ego; refresh finds none)
                view.refresh(ego_only=True)

    def _kinematics(self, rows: np.ndarray) -> None:
        """Each row's road users (its alive slots but the ego's, in road order) and their accelerations, the ego's
        first, for its shield's ``_objects`` and ``_accelerations`` (:class:`_Kinematics`, all rows at once)."""
        state, accel = self.kinematics.update(self.e, rows)
        e, t = self.e, self.e.traffic
        alive, ego, slot = t.alive[rows], t.ego[rows], e.ego_slot(rows)
        relevant = ~_followers(state, slot)
        others = alive & ~ego
        now = e.ticks[rows] / float(e.config["simulation_frequency"])
        recent = self.moved.recent(t.vid[rows], state, others, now) if self.moved is not None else None
        kept = others & relevant
        intent = self.channel.weights(rows, state, kept, slot) if self.channel is not None else None
        index, lanes, vids = e.T.index, t.lane[rows], t.vid[rows]
        n_kept = kept.sum(axis=1)
        predicted = self._predict(state, kept, n_kept, lanes, accel, intent)
        if self._flat is not None and recent is not None:  # the set-off rule's ``recent`` for the screen
            self._flat.recent = recent[kept]
        # every row's road users one row after the other (boolean masks keep row-major order), each view a slice:
        # the values of ``state[n, others[n]]`` and the like, without ~8 masked copies per row
        n_others = others.sum(axis=1)
        cut = np.concatenate([[0], np.cumsum(n_others)]).tolist()
        flat_state, flat_relevant = state[others], relevant[others]
        flat_lanes = [index[k] for k in lanes[others].tolist()]
        flat_keys = vids[others].tolist()
        # the shield's accelerations (N + 1, 2): each row's ego slot first, then its road users in slot order
        with_ego = others | ego
        row_of, slot_of = np.nonzero(with_ego)
        order = np.argsort(row_of * (with_ego.shape[1] + 1) + np.where(ego[row_of, slot_of], 0, slot_of + 1),
                           kind="stable")
        flat_accel = accel[row_of[order], slot_of[order]]
        cut_accel = np.concatenate([[0], np.cumsum(with_ego.sum(axis=1))]).tolist()
        flat_recent = None if recent is None else recent[others]
        for n, r in enumerate(rows.tolist()):
            view, a, b = self.views[r], cut[n], cut[n + 1]
            view.objects, view.relevant = flat_state[a:b], flat_relevant[a:b]
            view.lanes, view.keys = flat_lanes[a:b], flat_keys[a:b]
            view.accels = flat_accel[cut_accel[n]:cut_accel[n + 1]]
            view.recent = None if flat_recent is None else flat_recent[a:b]
            view.intent = None if intent is None else intent[n]
            view.predicted, view.predicted_n = predicted[n], int(n_kept[n])

    def _predict(self, state: np.ndarray, kept: np.ndarray, n_kept: np.ndarray, lanes: np.ndarray,
                 accel: np.ndarray, intent: list[np.ndarray] | None) -> list[tuple | None]:
        """Per decision the conflict model's paths of its kept road users (``kept`` (n, S): relevant, not the ego;
        ``n_kept`` (n,) how many per decision; ``state`` (n, S, 7), ``lanes`` (n, S) lane ids, ``accel`` (n, S, 2)
        m/s², ``intent`` per decision its kept road users' turn weights or None), what its shield's
        ``_predict_scene`` asks the conflict model, for all decisions in one compiled call
        (:meth:`ConflictModel.predict_rows`; None for a decision it does not serve: the shield's own call)."""
        self._flat = None
        if self.conflicts is None:
            return [None] * len(kept)
        index = self.e.T.index
        row_off = np.concatenate([[0], np.cumsum(n_kept)])
        weights = None
        if intent is not None:  # each decision's (its kept road users, 3) weights, one after the other
            weights = np.concatenate([w.reshape(-1, 3) for w in intent]) if len(intent) else np.zeros((0, 3))
        others = state[kept]
        flat = self.conflicts.predict_rows_flat(others, row_off, [index[k] for k in lanes[kept].tolist()],
                                                accel[kept], self.t_long, weights)
        if flat is not None:  # for the screen (:meth:`_screen`): the kept road users by decision, and the buffers
            self._flat = SimpleNamespace(row_off=row_off, others=others, lane=lanes[kept], weights=weights,
                                         buffers=flat, recent=None)
        return self.conflicts.split_rows(flat, len(self.t_long), len(kept))

    def _screen(self, rows: np.ndarray, actions: np.ndarray) -> np.ndarray | None:
        """(n,) bool: the decisions of the envs ``rows`` that end, by the row's own rules, in MONITOR with no
        conflict or in a warning, decided here for all rows at once, their shields' state moved on as their own
        ``_decide`` moves it (None: none screened).

        Which: ground-truth mode on the batch's prediction, discrete actions, not latched, and the first test of
        ImprovedAEB._decide_improved (the ego carrying on, its TTC against the kept road users' hypotheses) finds

        - no conflict (TTC infinite) while the set-off rule cannot act (outside it, or not at the stop-line trigger
          point): the row returns ``(MONITOR, inf, horizon, -1, active, False)``;
        - a conflict later than ``ttc_brake`` (so no emergency test) with the ego not at the stop-line trigger point
          (the set-off rule is asked only with no conflict): ``_warn_or_brake`` returns ``(WARN if active or TTC <=
          warn_ttc else MONITOR, TTC, horizon, its target, active, False)``;
        - no conflict at the stop-line trigger point while the set-off rule finds nothing (:meth:`_screen_setoff`:
          no standing road user in the box that moved lately, or none of their set-off hypotheses met within
          ``setoff_horizon``): the quiet row's MONITOR too.

        The row's code changes only its route lane hint (``_ego``), ``_lanes``, ``_keys``, ``_prev_t`` and
        ``target_xy`` then: these are set here. The same floats by construction (:meth:`_screen_egos`,
        :meth:`_screen_ttc`, :meth:`_screen_trigger`). With :data:`SCREEN_CHECK` each screened row's own
        ``_decide`` runs too and must agree. Why: ~97 % of the decisions end here (33,204 of 34,121 over 250
        validation episodes), and the rows' Python around the first TTC was most of their cost."""
        flat, self._flat = self._flat, None
        if not SCREEN or flat is None or self.e.continuous or not len(rows):
            return None
        from av_gym.shields.predict import FOOTPRINT_KERNEL, DrivenPath

        first = self.shields[int(rows[0])]
        if not (DrivenPath.kernel and FOOTPRINT_KERNEL and first.driven._register() >= 0):
            return None
        shields = [self.shields[r] for r in rows.tolist()]
        g = self._screen_egos(rows, actions, shields, flat.buffers[1])
        missing, k, m = self._screen_ttc(g, flat, first)
        p = self.p
        ttc = np.where(k >= 0, self.t_long[np.maximum(k, 0)], np.inf)
        quiet = g.cand & (missing == 0) & (k < 0)
        warn = g.cand & (missing == 0) & (k >= 0) & (ttc > p.ttc_brake)
        # the stop-line trigger point: a warning's _warn_or_brake asks it, a quiet row's set-off rule (if on)
        setoff_rule = p.setoff_speed > 0 and p.target_model == "conflict"
        ask = (warn | (quiet & setoff_rule)) & g.active & (g.front_to_line >= 0)
        at = self._screen_trigger(g, ask, shields, first)
        decided = (quiet | warn) & ~at
        if setoff_rule:  # a quiet row at the trigger point whose set-off rule finds nothing: MONITOR as well
            decided |= self._screen_setoff(g, quiet & at, flat, first)
        stage = np.where(warn & (g.active | (ttc <= p.warn_ttc)), WARN, MONITOR)
        self._screen_apply(rows, actions, shields, g, decided, stage, ttc, np.where(warn, m, -1), flat)
        return decided

    def _screen_egos(self, rows: np.ndarray, actions: np.ndarray, shields: list, n_h: np.ndarray) -> SimpleNamespace:
        """:meth:`_screen`'s candidates (``cand`` (n,): an ego on the road, the batch's prediction, not latched) and
        per decision what the row's own ``_ego``, ``_is_active``, ``_continue_profile`` and ``_horizon`` compute:
        ``route_k``, ``s0`` (m), ``speed`` (m/s), ``accel`` (m/s²), ``now`` (s), ``front_to_line`` (m), ``active``,
        ``ds`` (n, K) m, ``horizon`` (s), ``n_slices``. The route position by
        :func:`~av_gym.shields.locate_rows.locate_rows` from each row's own hint (the method's walk and floats), the
        profile, horizon and front-to-line distance element by element as the row computes them (under a FASTER /
        SLOWER the row's own :func:`setpoint_steps`)."""
        p, e, t = self.p, self.e, self.e.traffic
        first = shields[0]
        route, driven = first.route, first.driven
        slot = e.ego_slot(rows)
        g = SimpleNamespace(speed=t.v[rows, slot], accel=t.acc[rows, slot],
                            now=e.ticks[rows] / float(e.config["simulation_frequency"]))
        set_speed = t.target[rows, slot]
        g.cand = (t.alive[rows, slot] & t.ego[rows, slot]) & (n_h >= 0) & np.array(
            [not sh._latched and sh.route is route and sh.driven is driven for sh in shields], dtype=bool)
        at = np.flatnonzero(g.cand)
        g.route_k, s_lane = np.zeros(len(rows), np.int64), np.zeros(len(rows))
        hint = np.array([shields[n]._route_k for n in at.tolist()], dtype=np.int64)
        g.route_k[at], s_lane[at], _ = locate_rows(self.route, t.x[rows[at], slot[at]], t.y[rows[at], slot[at]], hint)
        g.s0 = route.starts[g.route_k] + s_lane
        g.front_to_line = first.stop_line_s - (g.s0 + 0.5 * LENGTH)
        g.active = (g.s0 < first.clear_s) & (g.front_to_line <= p.activation_distance)
        # the ego carrying on (ImprovedAEB._continue_profile): go_profile's expression, or setpoint_steps
        t_long, rise = self.t_long, _go_rise(p)
        g.ds = set_speed[:, None] * t_long[None, :] + ((g.speed - set_speed) * GO_TAU)[:, None] * rise[None, :]
        if p.check_action:  # FASTER (+1) / SLOWER (-1) repeated
            names = self.views[int(rows[0])].action_type.actions
            step = {a: 1 if name == "FASTER" else -1 for a, name in names.items() if name in ("FASTER", "SLOWER")}
            for n in at.tolist():
                s = step.get(int(actions[rows[n]]))
                if s is not None:
                    g.ds[n] = setpoint_steps(float(g.speed[n]), self.views[int(rows[n])].vehicle.target_speeds, s,
                                             t_long, dt=first.sim_dt)
        # ImprovedAEB._horizon, element by element
        reached = g.s0[:, None] + g.ds >= first.clear_s
        h = np.where(reached.any(axis=1), t_long[np.argmax(reached, axis=1)] + p.step, p.horizon_max)
        g.horizon = np.minimum(np.maximum(h, p.horizon_min), p.horizon_max)
        g.n_slices = np.rint(g.horizon / p.step).astype(np.int64)
        return g

    def _screen_ttc(self, g: SimpleNamespace, flat: SimpleNamespace, first) -> tuple[np.ndarray, ...]:
        """The first TTC of every candidate at once (ImprovedAEB._ttc_of with the scene's hypotheses and
        ``p.margin``): per decision (missing speed bins, slice, hypothesis) of :meth:`_rows_ttc` on
        :meth:`ConflictModel.predict_rows_flat`'s buffers (``flat.buffers``)."""
        n_h = np.where(g.cand, flat.buffers[1], -1)
        return self._rows_ttc(g.s0, g.ds, g.n_slices, flat.buffers, n_h, flat.others[:, 5:7], flat.row_off, first)

    def _rows_ttc(self, s0: np.ndarray, ds: np.ndarray, n: np.ndarray, buffers: tuple, n_h: np.ndarray,
                  size: np.ndarray, row_off: np.ndarray, first) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ImprovedAEB._ttc_of (margin ``p.margin``) of R decisions at once: decision r's ego from route position
        ``s0[r]`` (m) on the profile ``ds[r, :n[r]]`` (m) against its ``n_h[r]`` hypotheses (-1: none tested) of
        the flat prediction ``buffers`` (``(h_off, n_h, xy, hh, owner, is_map, prob)``, owners rows of ``size``
        (., 2) m from ``row_off[r]``), by :func:`~av_gym.shields.kernels.driven_ttc_rows` (each decision the
        row's :func:`driven_ttc` kernel on its slices). Per decision (missing speed bins, slice, hypothesis)."""
        from av_gym.shields.kernels import driven_ttc_rows
        from av_gym.shields.predict import DRIVEN_SPEEDS, _footprint_args, _store

        p = self.p
        h_off, _, xy, hh, owner, is_map, _ = buffers
        row_of = np.repeat(np.arange(len(s0)), np.diff(h_off))
        valid = np.arange(int(h_off[-1])) - h_off[row_of] < n_h[row_of]
        osize, rear = np.zeros((len(valid), 2)), np.zeros(len(valid), bool)
        osize[valid] = size[row_off[row_of[valid]] + owner[valid]]
        rear[valid] = is_map[valid] | p.ignore_rear
        length, width, xy, hh, osize, reach, rear = _footprint_args((float(LENGTH), float(WIDTH)), xy, hh, osize,
                                                                    p.margin, rear)
        st, need = _store(), np.zeros((len(s0), len(DRIVEN_SPEEDS)), dtype=np.bool_)
        return driven_ttc_rows(st.data, st.route, st.limits, st.bins, st.grid_table, first.driven.store_id, s0,
                               np.ascontiguousarray(ds), n, self.t_long, length, width, xy, hh, h_off, n_h, osize,
                               reach, rear, need)

    def _screen_setoff(self, g: SimpleNamespace, which: np.ndarray, flat: SimpleNamespace, first) -> np.ndarray:
        """(n,) bool: of the quiet decisions ``which`` at the stop-line trigger point, those whose set-off rule
        finds nothing, so that the row returns MONITOR as a quiet one: no kept road user the rule predicts
        (:func:`~av_gym.shields.setoff_rows.setoff_slow`: standing on a lane through the box, moving lately), or
        the ego carrying on for ``setoff_horizon`` s meets none of their set-off hypotheses
        (:meth:`ImprovedAEB._setoff_stop`'s TTC infinite; :func:`~av_gym.shields.setoff_rows.
        predict_rows_following` with ``_accel_predict``'s arguments, :meth:`_rows_ttc`). A decision whose
        prediction is not served (a speed bin missing) or that would brake is left to its row."""
        p, out = self.p, np.zeros(len(which), bool)
        if not which.any() or flat.recent is None:
            return out
        row_of = np.repeat(np.arange(len(which)), np.diff(flat.row_off))
        slow = setoff_slow(flat.others, self.in_box[flat.lane], flat.recent, p.setoff_speed) & which[row_of]
        n_slow = np.bincount(row_of[slow], minlength=len(which))
        out[which & (n_slow == 0)] = True
        at = np.flatnonzero(which & (n_slow > 0))
        if not len(at):
            return out
        mod, accels = setoff_start(flat.others[slow], p.setoff_accel)
        row_off = np.concatenate([[0], np.cumsum(n_slow[at])])
        index = self.e.T.index
        buffers = predict_rows_following(self.conflicts, mod, row_off, [index[k] for k in flat.lane[slow].tolist()],
                                         accels, self.t_long, None if flat.weights is None else flat.weights[slow],
                                         SETOFF_ACCEL_TIME)
        if buffers is None:
            return out
        n_h = buffers[1]
        n_set = np.minimum(g.n_slices[at], int(round(p.setoff_horizon / p.step)))
        missing, k, _ = self._rows_ttc(g.s0[at], g.ds[at], n_set, buffers, n_h, mod[:, 5:7], row_off, first)
        out[at[(n_h >= 0) & (missing == 0) & (k < 0)]] = True
        return out

    def _screen_trigger(self, g: SimpleNamespace, ask: np.ndarray, shields: list, first) -> np.ndarray:
        """(n,) bool: of the decisions ``ask`` (in the turn window, not past the line), those at the stop-line
        trigger point (the row's own ``_at_trigger_point``). Beyond :meth:`BrakeActuator.stopping_bounds` (the
        per-row upper bound, for all rows at once, the same floats) plus one decision period and ``stop_margin``
        the answer is False without the ticks, as the row's own; the rest ask their row."""
        p = self.p
        at = np.zeros(len(ask), bool)
        reach = first.actuator.stopping_bounds(g.speed, g.accel, first.sim_dt) + (g.speed * p.step + p.stop_margin)
        for n in np.flatnonzero(ask & ~(g.front_to_line > reach)).tolist():
            sc = SimpleNamespace(in_turn=True, front_to_line=float(g.front_to_line[n]), v=float(g.speed[n]),
                                 a=float(g.accel[n]))
            at[n] = shields[n]._at_trigger_point(sc)
        return at

    def _screen_apply(self, rows: np.ndarray, actions: np.ndarray, shields: list, g: SimpleNamespace,
                      decided: np.ndarray, stage: np.ndarray, ttc: np.ndarray, hit: np.ndarray,
                      flat: SimpleNamespace) -> None:
        """The state of the ``decided`` rows moved on as their own ``_decide`` moves it: route lane, road users'
        lanes and keys, decision time, and ``target_xy`` (the road user of hypothesis ``hit`` (n,; -1: none) of the
        row's block of ``flat``, NaN for none)."""
        h_off, owner = flat.buffers[0], flat.buffers[4]
        for n in np.flatnonzero(decided).tolist():
            r = int(rows[n])
            sh, view = shields[n], self.views[r]
            target = -1
            if hit[n] >= 0:  # ImprovedAEB's sc.idx[target]: the kept road user's row among all the row's road users
                target = int(np.flatnonzero(view.relevant)[owner[h_off[n] + hit[n]]])
            sh._proposed = self._env_action(actions[r])
            if SCREEN_CHECK:
                want = (int(stage[n]), float(ttc[n]), float(g.horizon[n]), target, bool(g.active[n]), False)
                _check_screened(sh, want, int(g.route_k[n]), float(g.now[n]))
            sh._route_k, sh._lanes, sh._keys, sh._prev_t = int(g.route_k[n]), view.lanes, view.keys, float(g.now[n])
            sh.target_xy = view.objects[target, 0:2].copy() if target >= 0 else np.full(2, np.nan)

    def _env_action(self, a):
        """One env's action as the per-env env takes it: a meta-action int, or the continuous (1,) float32."""
        return np.array([a], dtype=np.float32) if self.e.continuous else int(a)

    def _perceive(self, rows: np.ndarray) -> None:
        """The shield's own detector frame and tracker step for the envs ``rows``; each row's confirmed tracks and
        their ids for its shield (``MultiObjectTracker.tracks`` / ``track_ids``)."""
        e, seen = self.e, self.perception
        tr = e.truth(rows)
        now = e.ticks[rows] / e.config["simulation_frequency"]
        ego = np.stack([tr["x"], tr["y"], tr["heading"]], axis=1)
        det = seen.detector.measure(rows, now, ego, *seen.others(rows))
        seen.tracker.step(rows, det, now, ego[:, :2])
        tracks, shown = seen.tracker.tracks(rows)
        for n, r in enumerate(rows.tolist()):
            src = self.shields[r].tracker
            src.rows = tracks[n][shown[n]]
            src.ids = seen.tracker.id[r, : shown.shape[1]][shown[n]].astype(int)

    def brake_plan(self, rows: np.ndarray) -> np.ndarray | None:
        """(frames, B) the ego's acceleration (m/s²) on each tick of the coming step of the envs ``rows`` whose
        actuator is engaged: its deceleration after its delay, as the per-env shield's patched ``act`` sets it (NaN
        where the ego's own control acts); None when no env brakes. The engine's step takes it
        (``BatchedLeftTurn.step``'s ``ego_acceleration``: ``max(a, -v / 0.05)``, the actuator's own no-reversing
        clamp at 20 Hz)."""
        braking = [r for r in np.asarray(rows, dtype=int).tolist() if self.shields[r].actuator.engaged_at is not None]
        if not braking:
            return None
        e = self.e
        dt = 1.0 / e.config["simulation_frequency"]
        plan = np.full((e.frames, e.B), np.nan)
        for r in braking:
            act = self.shields[r].actuator
            for f in range(e.frames):
                d = act.deceleration((e.ticks[r] + f) * dt - act.engaged_at, dt)
                plan[f, r] = np.nan if d is None else -d
        return plan

    def after(self, rows: np.ndarray) -> None:
        """After the step of the envs ``rows``: where a braking ego came to a standstill, its stop position."""
        for r in np.asarray(rows, dtype=int).tolist():
            s = self.shields[r]
            if not self.override[r] or not np.isnan(s._stop_position):
                continue
            e = self.e
            if e.traffic.v[r, e.ego_slot([r])[0]] < STOP_SPEED:
                self.views[r].refresh(ego_only=self.kinematics is not None)
                s._stop_position = s._front_past_line()

    def episode(self, r: int) -> dict:
        """Env ``r``'s episode so far: ``brake_time`` (s, first brake; inf if none, the per-env shield's
        ``aeb.NOT_YET``), ``stop_position`` (m past the stop line at the first standstill under braking; inf if none),
        ``overrides`` (the steps it braked)."""
        info = self.shields[r]._make_info(0, float("inf"), 0.0, -1, False, False, None)
        return {"brake_time": info["aeb_brake_time"], "stop_position": info["aeb_stop_position"],
                "overrides": list(self.overrides[r])}


def _check_screened(shield, want: tuple, route_k: int, now: float) -> None:
    """:data:`SCREEN_CHECK`: the row's own decision from the state the screen found is the screen's ``want``
    (stage, TTC s, horizon s, target, active, infeasible), and moves its state as the screen does (an AssertionError
    naming what differs)."""
    got = shield._decide()
    assert got == want and shield._route_k == route_k and shield._prev_t == now, \
        f"screened row {shield.env.row}: its own decision {got}, route lane {shield._route_k}, time " \
        f"{shield._prev_t}; the screen's {want}, {route_k}, {now}"


def _shield_perception(engine, params: ImprovedParams):
    """The shield's own detector (world frame, its ``aeb_detector`` stream) and tracker for the batch."""
    from types import SimpleNamespace

    from av_gym.batched.perception import BatchedDetector, BatchedTracker, others_state

    det = BatchedDetector(engine.B, dataclasses.replace(params.detector, frame="world"), stream="aeb_detector")
    return SimpleNamespace(detector=det, tracker=BatchedTracker(engine.B, params.tracker),
                           others=lambda rows: others_state(engine, rows))
