"""``TurnFeatures``: a compact, ego-centred observation of the unprotected left turn for learned policies.

Why not highway-env's ``Kinematics`` rows: those are absolute, normalised coordinates of 15 vehicles, and a PPO
agent needs hundreds of thousands of steps to discover from them which car threatens the turn. A driver judges the
turn by a handful of quantities: how far the ego is from the stop line and from the conflict point with the
oncoming lane, and, for each other road user, where it is relative to the ego and when it will pass that conflict
point. This wrapper computes exactly those, from an object list that is either the simulator's vehicles
(``source: truth``, privileged) or the tracker's output (``source: tracks``, perceived: ``obs["tracks"]``).

Ego quantities come from the vehicle itself in both sources (its speed and its position along its own route, which
a car knows from odometry and its map), as the AEB shield does; only the *other* road users are perceived.

``obs["turn"]``: ``Box(-1, 1, (5 + 12·max_objects,))`` float32, every entry scaled to about [-1, 1] (so no running
observation normalisation is needed) and clipped:

- ego (5): speed / 10 m/s, cruise set-point / 10 m/s, distance of the front bumper to the stop line / 30 m,
  distance along the route to the conflict point / 30 m, elapsed time / ``time_scale``;
- per object (12), nearest to the ego first, zero rows for fewer objects: present, position relative to the
  ego in the ego frame (forward, left) / 50 m, velocity relative to the ego in the ego frame / 20 m/s, position
  relative to the oncoming-lane conflict point (world frame) / 50 m, velocity (world) / 15 m/s, and its
  constant-velocity closest approach to the ego's path through the intersection (stop line → turn → 10 m into the
  exit, a point every 2 m): time t* ∈ [0, 10] s / 10, miss distance / 10 m, and where on the path (m past the
  stop line / 30). Crossing traffic from the left and right, not only oncoming cars, hits a turning ego (measured:
  26 of 34 always-proceed collisions on seeds 1000-1059 were with crossing or merging vehicles).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.errors import ConfigError
from av_gym.estimation.driver_intent import DriverIntent
from av_gym.params import ROWS_MAX, Params, param
from av_gym.sensors.base import SensorWrapper, find_wrapper, sim_time
from av_gym.sensors.turn_signal import TurnSignals, TurnSignalsParams

PATH_STEP = 2.0  # m between the points of the ego's path through the intersection that conflicts are checked at
T_MAX = 10.0  # s, horizon of the closest-approach time

# The encoding of obs["turn"]: each feature's name and the scale its value is divided by (then clipped to [-1, 1]).
# The one table of it: both stacks encode with it (:func:`turn_features`) and every reader decodes with it
# (:meth:`TurnEncoding.decode`). ``time``'s scale is the ``time_scale`` parameter.
EGO_SCALES = {"speed": 10.0, "set_point": 10.0, "to_stop_line": 30.0, "to_conflict": 30.0, "time": None}
OBJECT_SCALES = {"present": 1.0, "fwd": 50.0, "left": 50.0, "dv_fwd": 20.0, "dv_left": 20.0, "cx": 50.0, "cy": 50.0,
                 "vx": 15.0, "vy": 15.0, "t_star": T_MAX, "miss": 10.0, "path_s": 30.0}
EGO_FEATURES = tuple(EGO_SCALES)
OBJECT_FEATURES = tuple(OBJECT_SCALES)


@dataclass(frozen=True)
class TurnFeaturesParams(Params):
    source: Literal["truth", "tracks"] = param("truth", doc="the objects described: truth (the simulator's "
                                                            "vehicles, privileged) or tracks (obs['tracks'] from the "
                                                            "tracker, perceived)")
    max_objects: int = param(8, ge=1, le=ROWS_MAX, doc="nearest objects described (12 features each)")
    max_range: float = param(80.0, "m", gt=0, doc="objects farther from the ego are left out (a 60 km/h car 5 s "
                                                  "away is ~80 m out)")
    time_scale: float = param(20.0, "s", gt=0, doc="elapsed time is divided by this (the traffic episode length)")


@dataclass(frozen=True)
class TurnEncoding:
    """``obs["turn"]``'s layout and scales (:data:`EGO_SCALES`, :data:`OBJECT_SCALES`): ``encode`` for the stacks
    that compute the features, ``decode`` for whoever reads them back (meta-actions, rule-based agents), both
    vectorised over any leading axes. Defaults: :class:`TurnFeaturesParams`'."""

    max_objects: int = TurnFeaturesParams().max_objects
    time_scale: float = TurnFeaturesParams().time_scale

    @classmethod
    def of(cls, params: TurnFeaturesParams) -> "TurnEncoding":
        return _encoding(int(params.max_objects), float(params.time_scale))

    @property
    def width(self) -> int:
        return len(EGO_FEATURES) + len(OBJECT_FEATURES) * self.max_objects

    @functools.cached_property
    def ego_scales(self) -> np.ndarray:
        return np.array([self.time_scale if v is None else v for v in EGO_SCALES.values()])

    @functools.cached_property
    def object_scales(self) -> np.ndarray:
        return np.array(list(OBJECT_SCALES.values()))

    def encode(self, ego: np.ndarray, objects: np.ndarray) -> np.ndarray:
        """Raw ``ego`` (..., len(EGO_FEATURES)) and ``objects`` (..., max_objects, len(OBJECT_FEATURES)) values
        (SI units, zero rows for no object) → the feature vectors (..., width) float32 in [-1, 1] (NaN → 0)."""
        obj = objects / self.object_scales
        out = np.concatenate([ego / self.ego_scales, obj.reshape(*obj.shape[:-2], -1)], axis=-1)
        np.clip(out, -1.0, 1.0, out=out)  # ±inf → ±1, as nan_to_num then clip
        out[np.isnan(out)] = 0.0
        return out.astype(np.float32)

    def decode(self, turn: np.ndarray, name: str) -> np.ndarray:
        """Feature ``name`` of ``turn`` (..., width) in SI units: an ego feature (...), an object feature
        (..., objects) (the number of objects from the width). In ``turn``'s precision (a float32 vector decodes
        in float32; pass ``turn.astype(float)`` for doubles)."""
        turn = np.asarray(turn)
        if name in EGO_SCALES:
            scale = EGO_SCALES[name]
            return turn[..., EGO_FEATURES.index(name)] * float(self.time_scale if scale is None else scale)
        objects = turn[..., len(EGO_FEATURES):].reshape(*turn.shape[:-1], -1, len(OBJECT_FEATURES))
        return objects[..., OBJECT_FEATURES.index(name)] * float(OBJECT_SCALES[name])


@functools.lru_cache(maxsize=None)
def _encoding(max_objects: int, time_scale: float) -> TurnEncoding:  # one per layout: its scale arrays made once
    return TurnEncoding(max_objects, time_scale)


TURN = TurnEncoding()  # the default layout; decode("time") of a non-default time_scale needs its own TurnEncoding


def turn_path(turn_lane, exit_lane) -> tuple[np.ndarray, np.ndarray]:
    """The ego's path through the intersection, from the stop line along ``turn_lane`` and 10 m into ``exit_lane``
    (highway-env lanes), a point every ``PATH_STEP`` m: where crossing, oncoming and merging traffic can meet it.
    Returns the points (P, 2) and their distance past the stop line (P,)."""
    s_turn = np.arange(0.0, turn_lane.length, PATH_STEP)
    s_exit = np.arange(0.0, 10.0 + 1e-9, PATH_STEP)
    path = np.array([turn_lane.position(s, 0.0) for s in s_turn] + [exit_lane.position(s, 0.0) for s in s_exit])
    return path, np.concatenate([s_turn, turn_lane.length + s_exit])


class TurnFeatures(SensorWrapper):
    """Adds ``obs["turn"]`` (see the module docstring); parameters: :class:`TurnFeaturesParams`."""

    key = "turn"
    Params = TurnFeaturesParams

    def __init__(self, env: gym.Env, params: TurnFeaturesParams | None = None, **overrides) -> None:
        p = self.params = TurnFeaturesParams.build(params, **overrides)
        if env.unwrapped.scenario != "left_turn":
            raise ConfigError(f"sensors.turn_features is for env=left_turn, not env={env.unwrapped.scenario}")
        if p.source == "tracks" and "tracks" not in env.observation_space.spaces:
            raise ConfigError("sensors.turn_features.source=tracks needs a tracker below it (`tracker:` in the "
                              "sensors preset, after `detector:`)")
        self.source, self.max_objects = p.source, int(p.max_objects)
        self.max_range, self.time_scale = float(p.max_range), float(p.time_scale)
        super().__init__(env)
        self.conflict = env.unwrapped.CONFLICT_POINT
        network = env.unwrapped.road.network  # the road is fixed: the path is computed once
        self.path, self.path_s = turn_path(network.get_lane(("ir0", "il1", 0)), network.get_lane(("il1", "o1", 0)))
        self._last = np.zeros(self.sensor_space().shape, dtype=np.float32)
        self.others = np.zeros((0, 4))  # the objects of the last call, (N, 4) [x, y, vx, vy] (world, m, m/s)
        self.described = np.zeros(0, dtype=int)  # rows of ``others`` described, in feature order (nearest first)

    def sensor_space(self) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, shape=(TurnEncoding.of(self.params).width,), dtype=np.float32)

    # The ego part reads info["truth"] (the ego's own state), so this wrapper hooks reset/step, not observation().
    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._step_faults = 0
        obs = self._add(obs, info)
        return obs, self._reported(info)

    def step(self, action):
        self._step_faults = 0
        obs, reward, terminated, truncated, info = self.env.step(action)
        obs = self._add(obs, info)
        return obs, reward, terminated, truncated, self._reported(info)

    def _add(self, obs: dict, info: dict) -> dict:
        truth = info["truth"]
        others = truth["others"][:, :4] if self.source == "truth" else \
            obs["tracks"][obs["tracks"][:, 0] > 0, 1:5].astype(float)
        self._last = self._guarded(self.features(truth, others))  # no NaN/inf reaches the agent; counted in info
        return {**obs, self.key: self._last}

    def features(self, truth: dict, others: np.ndarray) -> np.ndarray:
        """The feature vector for the ego in ``truth`` and ``others`` (N, ≥4) ``[x, y, vx, vy]`` (world, m, m/s):
        :func:`turn_features` on a batch of one."""
        others = others[np.isfinite(others).all(axis=1), :4] if len(others) else np.zeros((0, 4))
        values = np.array([[self._set_point() if k == "set_point" else truth[k] for k in EGO_INPUTS]], dtype=float)
        ego = dict(zip(EGO_INPUTS, values.T))
        out, order, present = turn_features(ego, others[None], np.ones((1, len(others)), bool), self.path,
                                            self.path_s, self.conflict, self.params)
        self.others, self.described = others, order[0][present[0]]
        return out[0]

    def _set_point(self) -> float:
        ego = self.env.unwrapped.vehicle
        return float(getattr(ego, "target_speed", ego.speed))

    def measure(self) -> np.ndarray:
        return self._last.copy()


INTENT_FEATURES = ("acc", "signal")
MEMORY_FEATURES = ("p_right", "p_straight", "p_left")  # TurnIntentParams.memory: the turn belief, in [0, 1]
ACC_SCALE = 5.0  # m/s², a firm brake; IDM drivers here brake at up to ~5 m/s² and accelerate at up to 3 m/s²


@dataclass(frozen=True)
class TurnIntentParams(Params):
    history: float = param(0.5, "s", gt=0, doc="the object's velocity now against its velocity this long ago")
    gate: float = param(2.0, "m", gt=0, doc="the object then is the one within this of where it is now, moved back")
    signal_gate: float = param(3.0, "m", gt=0, doc="a turn-signal reading belongs to the object this close to it")
    memory: bool = param(False, doc="add each object's turn belief P(right, straight, left) from every indicator "
                                    "reading on it so far (3 columns, IntentHistory): what the shield's and "
                                    "belief_lookahead's Bayes filter knows, which one frame's reading does not")
    read_period: float = param(0.5, "s", gt=0, doc="memory: at most one reading counted per this long, so the "
                                                   "per-env stack (observed every 0.1 s) counts the readings the "
                                                   "batch (observed at each 0.5 s decision) does")


def intent_features(params: TurnIntentParams) -> tuple[str, ...]:
    """The columns of ``obs["intent"]`` under ``params``."""
    return INTENT_FEATURES + (MEMORY_FEATURES if params.memory else ())


class TurnIntent(SensorWrapper):
    """Adds ``obs["intent"]``: ``Box(-1, 1, (max_objects, 2))`` (5 columns with ``memory``), one row per object of
    ``obs["turn"]`` in the same order (zero rows where ``obs["turn"]`` has none): what the other drivers are about to
    do, from sensors a car has.

    - ``acc``: the object's longitudinal acceleration / 5 m/s², from its own short history: its velocity now
      against its velocity ``history`` seconds ago (the object then is the one nearest to where it is now, moved
      back at its current velocity, within ``gate`` m; 0 when none). Braking (< 0) is how a driver who yields to
      the ego shows it (docs/agents.md: the other drivers slow down for the ego, which constant-velocity features miss).
      From the simulator's vehicles with ``turn_features.source=truth``, from the Kalman tracks with ``tracks``.
    - ``signal``: the direction indicator the turn-signal sensor (``obs["signals"]``,
      :class:`av_gym.sensors.turn_signal.TurnSignals`) reads on the vehicle at the object's position (within
      ``signal_gate`` m): +1 left, -1 right, 0 none (or no reading, or no turn-signal sensor in the stack).
    - with ``memory``: ``p_right``, ``p_straight``, ``p_left``, the object's turn belief after every reading on it so
      far (at most one per ``read_period``), carried along the object from observation to observation
      (:class:`IntentHistory`); 1/3 each before its first reading.

    Stack it after ``turn_features`` (config ``sensors.turn_intent``); parameters: :class:`TurnIntentParams`."""

    key = "intent"
    Params = TurnIntentParams

    def __init__(self, env: gym.Env, params: TurnIntentParams | None = None, **overrides) -> None:
        p = self.params = TurnIntentParams.build(params, **overrides)
        self.features_wrapper = find_wrapper(env, TurnFeatures)
        if self.features_wrapper is None:
            raise ConfigError("sensors.turn_intent needs turn_features below it (add `turn_features:` to the "
                              "preset)")
        self.history, self.gate, self.signal_gate = float(p.history), float(p.gate), float(p.signal_gate)
        super().__init__(env)
        signals = find_wrapper(env, TurnSignals)
        # the objects of the last `history` seconds: a batch of one env
        self.past = IntentHistory(1, p, signals.params if signals is not None else None)
        self._last = np.zeros(self.sensor_space().shape, dtype=np.float32)

    def sensor_space(self) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, shape=(self.features_wrapper.max_objects, len(intent_features(self.params))),
                          dtype=np.float32)

    def on_reset(self) -> None:
        self.past.clear([0])

    def observation(self, observation: dict) -> dict:
        turn = self.features_wrapper
        M, k = turn.max_objects, len(turn.described)
        objects = np.zeros((1, M, 4))
        objects[0, :k] = turn.others[turn.described]
        described = np.arange(M)[None] < k
        signals = observation["signals"][None] if "signals" in observation else None
        self._last = self.past.observe([0], np.array([sim_time(self.env)]), objects, described, turn.others[None],
                                       np.ones((1, len(turn.others)), bool), signals)[0]
        return {**observation, self.key: self._guarded(self._last)}

    def measure(self) -> np.ndarray:
        return self._last.copy()


# The models both stacks run: the per-env wrappers above call them with one env's arrays, the batched left turn
# (av_gym/batched/left_turn.py) with a leading batch axis (tests/test_one_model.py).
EGO_INPUTS = ("x", "y", "heading", "speed", "set_point", "stop_line_offset", "distance_to_conflict", "time")


def turn_features(ego: dict, others: np.ndarray, valid: np.ndarray, path: np.ndarray, path_s: np.ndarray,
                  conflict: np.ndarray, params: TurnFeaturesParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``obs["turn"]`` (the module docstring) for n egos at once. ``ego``: arrays (n,) of :data:`EGO_INPUTS`
    (``info["truth"]``'s fields, SI; ``set_point`` the ego's cruise set-point); ``others`` (n, N, ≥4)
    ``[x, y, vx, vy]`` (world) with ``valid`` (n, N) marking the rows that are road users; the ego's ``path``
    through the intersection (:func:`turn_path`) and the oncoming-lane ``conflict`` point.

    Returns the features (n, width) float32, and which rows of ``others`` they describe: ``order`` (n,
    min(max_objects, N)) indices, nearest first (ties in row order), and ``present`` (n, same): that row is a road
    user within ``max_range`` (a described object). Both stacks run it compiled (av_gym.sim.kernels.turn_features,
    the same formulas) while ``av_gym.sim.batched.KERNELS`` names "turn_features"; the numpy code below stays its
    reference (tests/test_kernels.py compares them)."""
    enc = TurnEncoding.of(params)
    from av_gym.sim import batched as _batched

    if "turn_features" in _batched.KERNELS:  # the same formulas compiled (av_gym.sim.kernels.turn_features)
        from av_gym.sim import kernels

        inputs = np.stack([np.asarray(ego[k], dtype=float) for k in EGO_INPUTS], axis=1)
        return kernels.turn_features(inputs, np.ascontiguousarray(others, dtype=float),
                                     np.ascontiguousarray(valid, dtype=bool), path, path_s,
                                     np.asarray(conflict, dtype=float), enc.max_objects, float(params.max_range),
                                     enc.ego_scales, enc.object_scales, T_MAX)
    M, n = enc.max_objects, len(others)
    ex, ey = ego["x"][:, None], ego["y"][:, None]
    d = np.where(valid, np.hypot(others[..., 0] - ex, others[..., 1] - ey), np.inf)
    order = np.argsort(d, axis=1, kind="stable")[:, :M]
    env = np.arange(n)[:, None]
    present = d[env, order] <= params.max_range
    near = others[env, order, :4]  # (n, m, 4), nearest first
    ox, oy, ovx, ovy = near[..., 0], near[..., 1], near[..., 2], near[..., 3]
    psi = ego["heading"][:, None]
    c, s = np.cos(psi), np.sin(psi)
    rx, ry = ox - ex, oy - ey  # relative position and velocity, turned into the ego frame (x forward, y left)
    rvx, rvy = ovx - ego["speed"][:, None] * c, ovy - ego["speed"][:, None] * s
    objects = np.zeros((n, M, len(OBJECT_FEATURES)))
    m = order.shape[1]
    rows = objects[:, :m]
    rows[..., 0] = 1.0
    rows[..., 1], rows[..., 2] = rx * c + ry * s, rx * -s + ry * c
    rows[..., 3], rows[..., 4] = rvx * c + rvy * s, rvx * -s + rvy * c
    rows[..., 5], rows[..., 6] = ox - conflict[0], oy - conflict[1]
    rows[..., 7:9] = near[..., 2:4]
    rows[..., 9], rows[..., 10], rows[..., 11] = path_conflict(near[..., :2], near[..., 2:4], path, path_s)
    rows[~present] = 0.0
    raw_ego = np.stack([ego["speed"], ego["set_point"], -ego["stop_line_offset"], ego["distance_to_conflict"],
                        ego["time"]], axis=1)
    return enc.encode(raw_ego, objects), order, present


class IntentHistory:
    """``obs["intent"]`` (:class:`TurnIntent`) for n envs at once, with each env's past: up to H snapshots of its
    objects (times ``t`` (n, H), NaN = empty; ``objects`` (n, H, K, 4) ``[x, y, vx, vy]`` with ``valid`` (n, H, K)),
    kept while younger than ``history`` s. The per-env wrapper holds one of one env, the batched left turn one of
    all its envs.

    With ``memory``, also each object's indicator readings so far: counts of (-1, 0, +1) readings per object of the
    last observation (``counts`` (n, K, 3)), carried to the object of this observation that was there had it kept
    its velocity (within ``gate`` m, the acceleration's association), plus this observation's reading when
    ``read_period`` s have passed since the last one counted. Counts are what the Bayes filter over (turn, driver
    kind) needs (:class:`~av_gym.estimation.driver_intent.DriverIntent`: the readings of one driver are independent
    given its hidden state), so a stacked history of readings would carry nothing more; their posterior's turn
    marginal is the feature. Why by hand: the association must run on the batch's arrays and on one env's alike,
    with no track ids on the truth stack."""

    def __init__(self, n: int, params: TurnIntentParams, channel: TurnSignalsParams | None = None) -> None:
        self.params = params
        self.t = np.full((n, 2), np.nan)
        self.objects = np.full((n, 2, 0, 4), np.nan)
        self.valid = np.zeros((n, 2, 0), bool)
        self.width = len(intent_features(params))
        self.filter = DriverIntent(channel or TurnSignalsParams()) if params.memory else None
        self.last_t, self.read_t = np.full(n, np.nan), np.full(n, np.nan)  # last observation, last reading counted
        self.last = np.full((n, 0, 4), np.nan)  # the objects of the last observation and their counts
        self.counts = np.zeros((n, 0, 3))

    def clear(self, rows) -> None:
        """Forget the past of the envs ``rows`` (a new episode)."""
        rows = np.asarray(rows, dtype=int)
        self.t[rows] = np.nan
        self.last_t[rows], self.read_t[rows] = np.nan, np.nan

    def observe(self, rows, now: np.ndarray, objects: np.ndarray, described: np.ndarray, snapshot: np.ndarray,
                snapshot_valid: np.ndarray, signals: np.ndarray | None) -> np.ndarray:
        """The intent rows (len(rows), M, 2 or 5) float32 of the described ``objects`` (n, M, 4) (``described`` (n, M)
        marks the rows that are objects) of the envs ``rows`` at times ``now`` (n,): each object's acceleration
        against the oldest kept snapshot, the turn signal of ``signals`` (n, S, 4) (``obs["signals"]``; None:
        no turn-signal sensor) read on it and, with ``memory``, its turn belief. Then keeps ``snapshot`` (n, N, 4)
        (every object now, ``snapshot_valid`` (n, N)) as the envs' newest past."""
        p, rows = self.params, np.asarray(rows, dtype=int)
        n, M = len(rows), objects.shape[1]
        t = self.t[rows]
        oldest = np.where(np.isnan(t), np.inf, t).argmin(axis=1)
        t_then = t[np.arange(n), oldest]
        then, then_valid = self.objects[rows, oldest], self.valid[rows, oldest]  # (n, K, 4), (n, K)
        dt = now - t_then
        usable = (dt > 0) & then_valid.any(axis=1)  # false for an empty past (NaN)
        out = np.zeros((n, M, self.width))
        if usable.any():
            acc = acceleration(objects, then, then_valid & usable[:, None], np.where(usable, dt, 1.0), p.gate)
            out[..., 0] = np.where(usable[:, None] & described, acc, 0.0) / ACC_SCALE
        if signals is not None:
            out[..., 1] = np.where(described, signals_at(objects, signals, p.signal_gate), 0.0)
        if self.filter is not None:
            out[..., 2:] = self._belief(rows, now, objects, described, snapshot, snapshot_valid, signals)
        self._keep(rows, now, snapshot, snapshot_valid)
        np.clip(out, -1.0, 1.0, out=out)  # ±inf → ±1, NaN → 0, as nan_to_num then clip
        out[np.isnan(out)] = 0.0
        return out.astype(np.float32)

    def _belief(self, rows: np.ndarray, now: np.ndarray, objects: np.ndarray, described: np.ndarray,
                snapshot: np.ndarray, valid: np.ndarray, signals: np.ndarray | None) -> np.ndarray:
        """P(right, straight, left) (n, M, 3) of the described ``objects`` after their readings so far; carries the
        counts from the last observation's objects to ``snapshot``'s and keeps those as the last."""
        n, N, M = len(rows), snapshot.shape[1], objects.shape[1]
        last, last_valid = self.last[rows], ~np.isnan(self.last[rows, :, 0])
        counts = np.zeros((n, N, 3))
        if last.shape[1]:
            dt = now - self.last_t[rows]
            seen = np.isfinite(dt) & (dt > 0)
            j, matched = associate(snapshot, last, last_valid & seen[:, None], np.where(seen, dt, 1.0),
                                   self.params.gate)
            carried = np.take_along_axis(self.counts[rows], j[..., None], axis=1)
            counts = np.where((matched & valid)[..., None], carried, 0.0)
        due = ~(now - self.read_t[rows] < self.params.read_period - 1e-9)  # NaN (no reading yet) compares false
        if signals is not None and due.any():
            reading, near = signal_readings(snapshot, signals, self.params.signal_gate)
            col = np.where(reading < 0, 0, np.where(reading > 0, 2, 1))
            add = (near & valid & due[:, None])[..., None] & (col[..., None] == np.arange(3))
            counts = counts + add
            self.read_t[rows[due]] = now[due]
        self._keep_counts(rows, now, np.where(valid[..., None], snapshot, np.nan), counts)
        if N == 0:  # no road user at all: nothing described either
            return np.zeros((n, M, 3))
        # the described objects are rows of the snapshot: find each one's by its position
        d = np.hypot(objects[..., :, None, 0] - snapshot[..., None, :, 0],
                     objects[..., :, None, 1] - snapshot[..., None, :, 1])
        d = np.where(valid[:, None, :], d, np.inf)
        own = np.take_along_axis(counts, np.argmin(d, axis=-1)[..., None], 1)
        post = self.filter.posterior(own.reshape(-1, 3)).reshape(n, M, 3, 3).sum(axis=3)
        return np.where(described[..., None], post, 0.0)

    def _keep_counts(self, rows: np.ndarray, now: np.ndarray, snapshot: np.ndarray, counts: np.ndarray) -> None:
        N = snapshot.shape[1]
        if N > self.last.shape[1]:
            k = self.last.shape[1]
            grown = np.full((len(self.last), N, 4), np.nan)
            grown[:, :k] = self.last
            grown_counts = np.zeros((len(self.last), N, 3))
            grown_counts[:, :k] = self.counts
            self.last, self.counts = grown, grown_counts
        self.last[rows] = np.nan
        self.last[rows, :N] = snapshot
        self.counts[rows] = 0.0
        self.counts[rows, :N] = counts
        self.last_t[rows] = now

    def _keep(self, rows: np.ndarray, now: np.ndarray, snapshot: np.ndarray, valid: np.ndarray) -> None:
        """Drop what is no longer younger than ``history`` (TurnIntent's rule: ``now - t < history``), add now."""
        n, N = len(rows), snapshot.shape[1]
        t = self.t[rows]
        t[~(now[:, None] - t < self.params.history - 1e-9)] = np.nan  # (NaN compares false: stays empty)
        free = np.isnan(t)
        full = not free.any(axis=1).all()
        if full or N > self.objects.shape[2]:  # room for one more snapshot of N objects
            h, k = self.objects.shape[1:3]
            H, K = h + full, max(N, k)
            grown = np.full((len(self.t), H, K, 4), np.nan)
            grown_valid = np.zeros((len(self.t), H, K), bool)
            grown[:, :h, :k], grown_valid[:, :h, :k] = self.objects, self.valid
            self.t = np.concatenate([self.t, np.full((len(self.t), H - h), np.nan)], axis=1)
            self.objects, self.valid = grown, grown_valid
            t = np.concatenate([t, np.full((n, H - h), np.nan)], axis=1)
            free = np.isnan(t)
        slot = np.argmax(free, axis=1)
        t[np.arange(n), slot] = now
        self.t[rows] = t
        self.objects[rows, slot] = np.nan
        self.objects[rows, slot, :N] = snapshot
        self.valid[rows, slot] = False
        self.valid[rows, slot, :N] = valid


def path_conflict(p: np.ndarray, v: np.ndarray, path: np.ndarray,
                  path_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per object (positions ``p``, velocities ``v``, (..., N, 2)): the constant-velocity closest approach to the
    ego's ``path`` (P, 2), ``t* = clip(-(p - c)·v / |v|², 0, T)`` and ``miss = |p + v t* - c|`` for every path
    point ``c``; returns t* (s), miss (m) and the path point's ``path_s`` (m past the stop line) at the smallest
    miss, each (..., N). Exact ties in miss (an object driving along the exit) go to the first point.
    (n, N, 2) inputs run as av_gym.sim.kernels.path_conflict, the same arithmetic compiled, while the batch's
    kernel switch names it (``av_gym.sim.batched.KERNELS``: "path_conflict"); tests/test_kernels.py compares them.)"""
    from av_gym.sim import batched as _batched

    if p.ndim == 3 and "path_conflict" in _batched.KERNELS:
        from av_gym.sim import kernels

        return kernels.path_conflict(*(np.ascontiguousarray(a, dtype=float) for a in (p, v, path, path_s)), T_MAX)
    d = p[..., :, None, :] - path  # (..., N, P, 2)
    vv = np.maximum((v * v).sum(axis=-1), 1e-6)[..., None]
    t = np.clip(-(d * v[..., :, None, :]).sum(axis=-1) / vv, 0.0, T_MAX)  # (..., N, P)
    q = d + v[..., :, None, :] * t[..., None]
    miss = np.hypot(q[..., 0], q[..., 1])
    j = np.argmin(miss, axis=-1)[..., None]
    return np.take_along_axis(t, j, -1)[..., 0], np.take_along_axis(miss, j, -1)[..., 0], path_s[j[..., 0]]


def associate(objects: np.ndarray, then: np.ndarray, then_valid: np.ndarray, dt: np.ndarray,
              gate: float) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``objects`` (..., N, 4) ``[x, y, vx, vy]``: the index (..., N) of the nearest of the objects
    ``then`` (..., K, ≥2) (``then_valid`` (..., K)) ``dt`` (...) s ago to where it was had it kept its velocity, and
    whether that one is within ``gate`` m."""
    dt = np.asarray(dt, dtype=float)
    back = objects[..., :2] - objects[..., 2:4] * dt[..., None, None]
    d = np.hypot(back[..., :, None, 0] - then[..., None, :, 0], back[..., :, None, 1] - then[..., None, :, 1])
    d = np.where(then_valid[..., None, :], d, np.inf)  # (..., N, K)
    j = np.argmin(d, axis=-1)
    return j, np.take_along_axis(d, j[..., None], -1)[..., 0] <= gate


def acceleration(objects: np.ndarray, then: np.ndarray, then_valid: np.ndarray, dt: np.ndarray,
                 gate: float) -> np.ndarray:
    """Longitudinal acceleration (m/s²) of ``objects`` (..., N, 4) ``[x, y, vx, vy]`` against the objects ``then``
    (..., K, 4) (``then_valid`` (..., K)) ``dt`` (...) s ago: the one nearest to where each object was had it kept
    its velocity, within ``gate`` m; 0 when none."""
    dt = np.asarray(dt, dtype=float)
    j, matched = associate(objects, then, then_valid, dt, gate)
    speed = np.hypot(objects[..., 2], objects[..., 3])
    heading = objects[..., 2:4] / np.maximum(speed, 1e-6)[..., None]
    v_then = np.take_along_axis(then[..., 2:4], j[..., None], -2)
    acc = ((objects[..., 2:4] - v_then) * heading).sum(axis=-1) / dt[..., None]
    return np.where(matched, acc, 0.0)


def signal_readings(objects: np.ndarray, signals: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
    """The turn signal read on each of ``objects`` (..., N, ≥2) ``[x, y, ...]``: that of the nearest reading of
    ``signals`` (..., S, 4) (``obs["signals"]`` rows ``[present, x, y, signal]``) within ``gate`` m (else 0), and
    whether there was one (a 0 reading is "no indicator seen"; no reading is no information)."""
    valid = signals[..., 0] > 0
    d = np.hypot(objects[..., :, None, 0] - signals[..., None, :, 1],
                 objects[..., :, None, 1] - signals[..., None, :, 2])
    d = np.where(valid[..., None, :], d, np.inf)  # (..., N, S): the nearest seen reading, first on ties
    if d.shape[-1] == 0:
        return np.zeros(d.shape[:-1]), np.zeros(d.shape[:-1], bool)
    j = np.argmin(d, axis=-1)[..., None]
    near = np.take_along_axis(d, j, -1)[..., 0] <= gate
    read = np.take_along_axis(np.broadcast_to(signals[..., None, :, 3], d.shape), j, -1)[..., 0]
    return np.where(near, read, 0.0), near


def signals_at(objects: np.ndarray, signals: np.ndarray, gate: float) -> np.ndarray:
    """The turn signal read on each of ``objects`` (:func:`signal_readings`'s reading, 0 where there is none)."""
    return signal_readings(objects, signals, gate)[0]
