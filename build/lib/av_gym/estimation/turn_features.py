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

from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.errors import ConfigError
from av_gym.params import ROWS_MAX, Params, param
from av_gym.sensors.base import SensorWrapper, find_wrapper, sim_time

EGO_FEATURES = ("speed", "set_point", "to_stop_line", "to_conflict", "time")
OBJECT_FEATURES = ("present", "fwd", "left", "dv_fwd", "dv_left", "cx", "cy", "vx", "vy", "t_star", "miss",
                   "path_s")
PATH_STEP = 2.0  # m between the points of the ego's path through the intersection that conflicts are checked at
T_MAX = 10.0  # s, horizon of the closest-approach time


@dataclass(frozen=True)
class TurnFeaturesParams(Params):
    source: Literal["truth", "tracks"] = param("truth", doc="the objects described: truth (the simulator's "
                                                            "vehicles, privileged) or tracks (obs['tracks'] from the "
                                                            "tracker, perceived)")
    max_objects: int = param(8, ge=1, le=ROWS_MAX, doc="nearest objects described (12 features each)")
    max_range: float = param(80.0, "m", gt=0, doc="objects farther from the ego are left out (a 60 km/h car 5 s "
                                                  "away is ~80 m out)")
    time_scale: float = param(20.0, "s", gt=0, doc="elapsed time is divided by this (the traffic episode length)")


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
        # The ego's path through the intersection, from the stop line along the turn and 10 m into the exit: where
        # crossing, oncoming and merging traffic can meet it (the road is fixed, so computed once).
        turn, exit_lane = env.unwrapped.road.network.get_lane(("ir0", "il1", 0)), \
            env.unwrapped.road.network.get_lane(("il1", "o1", 0))
        s_turn = np.arange(0.0, turn.length, PATH_STEP)
        s_exit = np.arange(0.0, 10.0 + 1e-9, PATH_STEP)
        self.path = np.array([turn.position(s, 0.0) for s in s_turn] + [exit_lane.position(s, 0.0) for s in s_exit])
        self.path_s = np.concatenate([s_turn, turn.length + s_exit])  # m past the stop line
        self._last = np.zeros(self.sensor_space().shape, dtype=np.float32)
        self.others = np.zeros((0, 4))  # the objects of the last call, (N, 4) [x, y, vx, vy] (world, m, m/s)
        self.described = np.zeros(0, dtype=int)  # rows of ``others`` described, in feature order (nearest first)

    def sensor_space(self) -> spaces.Box:
        n = len(EGO_FEATURES) + len(OBJECT_FEATURES) * self.max_objects
        return spaces.Box(-1.0, 1.0, shape=(n,), dtype=np.float32)

    # The ego part reads info["truth"] (the ego's own state), so this wrapper hooks reset/step, not observation().
    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        return self._add(obs, info), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._add(obs, info), reward, terminated, truncated, info

    def _add(self, obs: dict, info: dict) -> dict:
        truth = info["truth"]
        others = truth["others"][:, :4] if self.source == "truth" else \
            obs["tracks"][obs["tracks"][:, 0] > 0, 1:5].astype(float)
        self._last = self.features(truth, others)
        return {**obs, self.key: self._last}

    def features(self, truth: dict, others: np.ndarray) -> np.ndarray:
        """The feature vector for the ego in ``truth`` and ``others`` (N, ≥4) ``[x, y, vx, vy]`` (world, m, m/s)."""
        ego = np.array([truth["speed"] / 10.0, self._set_point() / 10.0, -truth["stop_line_offset"] / 30.0,
                        truth["distance_to_conflict"] / 30.0, truth["time"] / self.time_scale])
        obj = np.zeros((self.max_objects, len(OBJECT_FEATURES)))
        p_ego = np.array([truth["x"], truth["y"]])
        psi = truth["heading"]
        v_ego = truth["speed"] * np.array([np.cos(psi), np.sin(psi)])
        others = others[np.isfinite(others).all(axis=1)] if len(others) else np.zeros((0, 4))
        d = np.hypot(*(others[:, :2] - p_ego).T) if len(others) else np.zeros(0)
        near = np.argsort(d)[: self.max_objects]
        near = near[d[near] <= self.max_range]
        self.others, self.described = others, near
        if len(near):
            p, v = others[near, :2], others[near, 2:4]
            c, s = np.cos(psi), np.sin(psi)
            to_ego = np.array([[c, s], [-s, c]])  # world → ego frame (x forward, y left)
            rel_p, rel_v = (p - p_ego) @ to_ego.T, (v - v_ego) @ to_ego.T
            pc = p - self.conflict
            t_star, miss, path_s = self._path_conflict(p, v)
            obj[: len(near)] = np.column_stack([np.ones(len(near)), rel_p / 50.0, rel_v / 20.0, pc / 50.0,
                                                v / 15.0, t_star / T_MAX, miss / 10.0, path_s / 30.0])
        out = np.concatenate([ego, obj.ravel()])
        return np.clip(np.nan_to_num(out, nan=0.0), -1.0, 1.0).astype(np.float32)

    def _path_conflict(self, p: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return path_conflict(p, v, self.path, self.path_s)

    def _set_point(self) -> float:
        ego = self.env.unwrapped.vehicle
        return float(getattr(ego, "target_speed", ego.speed))

    def measure(self) -> np.ndarray:
        return self._last.copy()


INTENT_FEATURES = ("acc", "signal")
ACC_SCALE = 5.0  # m/s², a firm brake; IDM drivers here brake at up to ~5 m/s² and accelerate at up to 3 m/s²


@dataclass(frozen=True)
class TurnIntentParams(Params):
    history: float = param(0.5, "s", gt=0, doc="the object's velocity now against its velocity this long ago")
    gate: float = param(2.0, "m", gt=0, doc="the object then is the one within this of where it is now, moved back")
    signal_gate: float = param(3.0, "m", gt=0, doc="a turn-signal reading belongs to the object this close to it")


class TurnIntent(SensorWrapper):
    """Adds ``obs["intent"]``: ``Box(-1, 1, (max_objects, 2))``, one row per object of ``obs["turn"]`` in the same
    order (zero rows where ``obs["turn"]`` has none): what the other drivers are about to do, from sensors a car has.

    - ``acc``: the object's longitudinal acceleration / 5 m/s², from its own short history: its velocity now
      against its velocity ``history`` seconds ago (the object then is the one nearest to where it is now, moved
      back at its current velocity, within ``gate`` m; 0 when none). Braking (< 0) is how a driver who yields to
      the ego shows it (docs/agents.md: the other drivers slow down for the ego, which constant-velocity features miss).
      From the simulator's vehicles with ``turn_features.source=truth``, from the Kalman tracks with ``tracks``.
    - ``signal``: the direction indicator the turn-signal sensor (``obs["signals"]``,
      :class:`av_gym.sensors.turn_signal.TurnSignals`) reads on the vehicle at the object's position (within
      ``signal_gate`` m): +1 left, -1 right, 0 none (or no reading, or no turn-signal sensor in the stack).

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
        self._past: list[tuple[float, np.ndarray]] = []  # (time s, objects (N, 4)) of the last `history` seconds
        self._last = np.zeros(self.sensor_space().shape, dtype=np.float32)

    def sensor_space(self) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, shape=(self.features_wrapper.max_objects, len(INTENT_FEATURES)),
                          dtype=np.float32)

    def on_reset(self) -> None:
        self._past = []

    def observation(self, observation: dict) -> dict:
        now = sim_time(self.env)
        turn = self.features_wrapper
        objects = turn.others[turn.described]
        out = np.zeros(self.sensor_space().shape)
        if len(objects):
            out[: len(objects), 0] = self._acceleration(objects, now) / ACC_SCALE
            if "signals" in observation:
                out[: len(objects), 1] = signals_at(objects, observation["signals"], self.signal_gate)
        self._past = [(t, o) for t, o in self._past if now - t < self.history - 1e-9] + [(now, turn.others)]
        self._last = np.clip(np.nan_to_num(out), -1.0, 1.0).astype(np.float32)
        return {**observation, self.key: self._guarded(self._last)}

    def _acceleration(self, objects: np.ndarray, now: float) -> np.ndarray:
        """Longitudinal acceleration (m/s²) of each row of ``objects`` (N, 4), from the oldest kept past."""
        if not self._past or not len(self._past[0][1]):
            return np.zeros(len(objects))
        t_then, then = self._past[0]
        dt = now - t_then
        if dt <= 0:
            return np.zeros(len(objects))
        return acceleration(objects, then, np.ones(len(then), dtype=bool), np.asarray(dt), self.gate)

    def measure(self) -> np.ndarray:
        return self._last.copy()


# The models both stacks run: the per-env wrappers above call them with one env's arrays, the batched left turn
# (av_gym/batched/left_turn.py) with a leading batch axis (tests/test_one_model.py).
def path_conflict(p: np.ndarray, v: np.ndarray, path: np.ndarray,
                  path_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per object (positions ``p``, velocities ``v``, (..., N, 2)): the constant-velocity closest approach to the
    ego's ``path`` (P, 2), ``t* = clip(-(p - c)·v / |v|², 0, T)`` and ``miss = |p + v t* - c|`` for every path
    point ``c``; returns t* (s), miss (m) and the path point's ``path_s`` (m past the stop line) at the smallest
    miss, each (..., N). Exact ties in miss (an object driving along the exit) go to the first point."""
    d = p[..., :, None, :] - path  # (..., N, P, 2)
    vv = np.maximum((v * v).sum(axis=-1), 1e-6)[..., None]
    t = np.clip(-(d * v[..., :, None, :]).sum(axis=-1) / vv, 0.0, T_MAX)  # (..., N, P)
    q = d + v[..., :, None, :] * t[..., None]
    miss = np.hypot(q[..., 0], q[..., 1])
    j = np.argmin(miss, axis=-1)[..., None]
    return np.take_along_axis(t, j, -1)[..., 0], np.take_along_axis(miss, j, -1)[..., 0], path_s[j[..., 0]]


def acceleration(objects: np.ndarray, then: np.ndarray, then_valid: np.ndarray, dt: np.ndarray,
                 gate: float) -> np.ndarray:
    """Longitudinal acceleration (m/s²) of ``objects`` (..., N, 4) ``[x, y, vx, vy]`` against the objects ``then``
    (..., K, 4) (``then_valid`` (..., K)) ``dt`` (...) s ago: the one nearest to where each object was had it kept
    its velocity, within ``gate`` m; 0 when none."""
    dt = np.asarray(dt, dtype=float)
    back = objects[..., :2] - objects[..., 2:4] * dt[..., None, None]
    d = np.hypot(back[..., :, None, 0] - then[..., None, :, 0], back[..., :, None, 1] - then[..., None, :, 1])
    d = np.where(then_valid[..., None, :], d, np.inf)  # (..., N, K)
    j = np.argmin(d, axis=-1)[..., None]
    matched = np.take_along_axis(d, j, -1)[..., 0] <= gate
    speed = np.hypot(objects[..., 2], objects[..., 3])
    heading = objects[..., 2:4] / np.maximum(speed, 1e-6)[..., None]
    v_then = np.take_along_axis(then[..., 2:4], j, -2)
    acc = ((objects[..., 2:4] - v_then) * heading).sum(axis=-1) / dt[..., None]
    return np.where(matched, acc, 0.0)


def signals_at(objects: np.ndarray, signals: np.ndarray, gate: float) -> np.ndarray:
    """The turn signal read on each of ``objects`` (..., N, ≥2) ``[x, y, ...]``: that of the nearest reading of
    ``signals`` (..., S, 4) (``obs["signals"]`` rows ``[present, x, y, signal]``) within ``gate`` m, else 0."""
    valid = signals[..., 0] > 0
    d = np.hypot(objects[..., :, None, 0] - signals[..., None, :, 1],
                 objects[..., :, None, 1] - signals[..., None, :, 2])
    d = np.where(valid[..., None, :], d, np.inf)  # (..., N, S): the nearest seen reading, first on ties
    if d.shape[-1] == 0:
        return np.zeros(d.shape[:-1])
    j = np.argmin(d, axis=-1)[..., None]
    near = np.take_along_axis(d, j, -1)[..., 0] <= gate
    read = np.take_along_axis(np.broadcast_to(signals[..., None, :, 3], d.shape), j, -1)[..., 0]
    return np.where(near, read, 0.0)
