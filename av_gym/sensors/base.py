"""What every sensor wrapper shares: its key in the ``Dict`` observation, a per-episode seeded generator, and
read access to the true simulator state.

A sensor is a ``gymnasium.ObservationWrapper`` that *adds* one key (``self.key``) to the observation dict and
leaves every other key, and ``info["truth"]``, untouched. Sensors therefore compose in any order. Each draws its
randomness from its own generator, seeded from the env's ``episode_seed`` (itself drawn from ``reset(seed=...)``)
and the sensor's key, so adding or reordering sensors never changes another sensor's readings.
"""

from __future__ import annotations

import functools
import inspect
import zlib

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.geometry import NO_OTHERS


def sensor_rng(env: gym.Env, key: str) -> np.random.Generator:
    """The generator for sensor ``key`` in the current episode of ``env``."""
    return episode_rng(env.unwrapped.episode_seed, key)


def episode_rng(episode_seed: int, key: str) -> np.random.Generator:
    """The generator for sensor ``key`` in the episode of ``episode_seed`` (the batched stack's envs too)."""
    return np.random.default_rng(np.random.SeedSequence([int(episode_seed), zlib.crc32(key.encode())]))


def ego_pose(env: gym.Env) -> np.ndarray:
    """True ego ``[x, y, heading, speed]`` (m, m, rad, m/s)."""
    ego = env.unwrapped.vehicle
    return np.array([ego.position[0], ego.position[1], ego.heading, ego.speed], dtype=float)


def others_state(env: gym.Env) -> np.ndarray:
    """True state of every other vehicle, ``(N, 7)`` ``[x, y, vx, vy, heading, length, width]``."""
    unwrapped = env.unwrapped
    ego = unwrapped.vehicle
    rows = []
    for v in unwrapped.road.vehicles:
        if v is not ego:
            velocity = v.velocity  # a property that builds its array: read once
            rows.append([v.position[0], v.position[1], velocity[0], velocity[1], v.heading, v.LENGTH, v.WIDTH])
    return np.array(rows, dtype=float) if rows else NO_OTHERS.copy()


def find_wrapper(env: gym.Env, cls: type):
    """The outermost wrapper of type ``cls`` in ``env``'s stack (``env`` itself included), or ``None``: how an
    estimator finds the sensor below it whose model or state it reads."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, cls):
            return env
        env = env.env
    return None


def sim_time(env: gym.Env) -> float:
    """Simulation time (s) since the start of the episode, at tick resolution."""
    unwrapped = env.unwrapped
    return unwrapped.steps / unwrapped.config["simulation_frequency"]


class SensorWrapper(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """Base class: subclasses set ``key``, implement :meth:`sensor_space` and :meth:`measure`, and may override
    :meth:`on_reset` (per-episode state such as biases), all using ``self.rng``."""

    key: str = ""

    def __init_subclass__(cls, **kwargs) -> None:
        # Record every subclass's constructor arguments, as Gymnasium's own wrappers do by hand, so that
        # ``env.spec`` can rebuild the whole stack (``check_env`` and vector envs rely on it).
        super().__init_subclass__(**kwargs)
        init = cls.__init__
        signature = inspect.signature(init)

        @functools.wraps(init)
        def recorded_init(self, *args, **kw):
            bound = signature.bind(self, *args, **kw)
            bound.apply_defaults()
            recorded = {k: v for k, v in bound.arguments.items() if k not in ("self", "env")}
            for name, param in signature.parameters.items():  # **kwargs are recorded as the keywords they hold
                if param.kind is param.VAR_KEYWORD:
                    recorded.update(recorded.pop(name, {}))
            gym.utils.RecordConstructorArgs.__init__(self, **recorded)
            init(self, *args, **kw)

        cls.__init__ = recorded_init

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        if not isinstance(env.observation_space, spaces.Dict):
            raise TypeError(f"{type(self).__name__} needs a Dict observation space, got {env.observation_space}")
        if self.key in env.observation_space.spaces:
            raise ValueError(f"observation key {self.key!r} is already provided by an inner wrapper")
        self.observation_space = spaces.Dict({**env.observation_space.spaces, self.key: self.sensor_space()})
        self.rng = np.random.default_rng(0)
        self.faults = 0  # readings that held NaN/inf, over the wrapper's life (see _guarded)
        self._step_faults = 0

    def sensor_space(self) -> spaces.Space:
        raise NotImplementedError

    def on_reset(self) -> None:
        """Draw per-episode quantities (biases, outage windows) from ``self.rng``."""

    def measure(self):
        raise NotImplementedError

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.rng = sensor_rng(self.env, self.key)
        self.on_reset()
        self._step_faults = 0
        obs = self.observation(obs)
        return obs, self._reported(info)

    def observation(self, observation: dict) -> dict:
        return {**observation, self.key: self._guarded(self.measure())}

    def _guarded(self, value):
        """The reading with any NaN/inf replaced (NaN → 0, ±inf → the space's bound, then clipped into it), so that
        nothing non-finite ever reaches an agent or a network, then marked not usable by ``invalidate`` (a bare 0
        must not read as a confident value, e.g. a valid GNSS fix at the origin); each such reading is counted and
        reported in ``info["sensor_faults"][key]``. A sensor's model should never produce one: this is the last
        line, after the sensors' own checks (e.g. a GNSS fix that is not finite is dropped like one lost in an
        outage)."""
        bad = count_nonfinite(value)
        if bad:
            self.faults += 1
            self._step_faults += bad
            value = self.invalidate(value, _finite(value, self.observation_space[self.key]))
        return value

    def invalidate(self, raw, clean):
        """``clean`` (the finite, in-space copy of a reading ``raw`` that held NaN/inf) marked as not usable, in the
        sensor's own terms: GNSS clears its fresh/valid flags, the detector drops the rows, the lidar reads the
        beams as no return. This default, for sensors with no such flag (IMU, cameras, estimators), keeps
        ``clean`` as it is: the faulty entries read 0 (or the bound for ±inf) and only
        ``info["sensor_faults"]`` says so."""
        return clean

    def step(self, action):
        self._step_faults = 0
        obs, reward, terminated, truncated, info = self.env.step(action)
        obs = self.observation(obs)
        return obs, reward, terminated, truncated, self._reported(info)

    def _reported(self, info: dict) -> dict:
        """``info`` with this reading's non-finite entries, if any, under ``info["sensor_faults"][key]`` (the first
        reading of an episode, at reset, too: EpisodeMetrics sums them into the episode's ``sensor_faults``)."""
        if not self._step_faults:
            return info
        return {**info, "sensor_faults": {**info.get("sensor_faults", {}), self.key: self._step_faults}}


def count_nonfinite(value) -> int:
    """How many entries of a reading (an array, or a dict of them) are NaN or ±inf."""
    if isinstance(value, dict):
        return sum(count_nonfinite(v) for v in value.values())
    a = np.asarray(value)
    return int(a.size - np.count_nonzero(np.isfinite(a))) if a.dtype.kind in "fc" else 0


def guarded_rows(values: np.ndarray, space: spaces.Box, invalidate=None) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`SensorWrapper._guarded` for a batch of readings, ``values`` (n, *space.shape) (one env's reading per
    row, av_gym/batched): each row holding NaN/inf made finite and in ``space`` as the per-env guard makes it, then
    ``invalidate(raw_row, clean_row)`` (the per-env sensor's :meth:`SensorWrapper.invalidate`; None: kept as it
    is). Rows without one are returned untouched. Returns the readings and each row's count of non-finite entries
    (n,), what the per-env sensor reports in ``info["sensor_faults"][key]``."""
    a = np.asarray(values)
    if a.dtype.kind not in "fc" or not len(a):
        return values, np.zeros(len(a), dtype=int)
    flat = a.reshape(len(a), -1)
    counts = flat.shape[1] - np.count_nonzero(np.isfinite(flat), axis=1)
    bad = np.flatnonzero(counts)
    if not len(bad):
        return values, counts
    out = a.copy()
    for i in bad.tolist():
        clean = _finite(a[i], space)
        out[i] = clean if invalidate is None else invalidate(a[i], clean)
    return out, counts


def _finite(value, space: spaces.Space):
    if isinstance(value, dict):
        return {k: _finite(v, space[k]) for k, v in value.items()}
    a = np.asarray(value)
    if a.dtype.kind not in "fc" or not isinstance(space, spaces.Box):
        return value
    low = np.broadcast_to(space.low, a.shape)
    high = np.broadcast_to(space.high, a.shape)
    out = np.where(np.isnan(a), 0.0, a)
    out = np.where(np.isposinf(out), high, np.where(np.isneginf(out), low, out))
    return np.clip(out, low, high).astype(a.dtype)
