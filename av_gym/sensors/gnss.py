"""GNSS receiver: position and velocity fixes with white noise, a slowly varying multipath bias, outages and
latency, held between fixes.

Noise model (per horizontal axis, at each fix k taken at time t_k, of the true state delayed by ``latency``)::

    p̃_k = p(t_k − latency) + b_k + n_k,       n_k ~ N(0, sigma²)
    b_k = φ_k b_{k−1} + sigma_bias·sqrt(1 − φ_k²)·w_k,  φ_k = exp(−(t_k − t_{k−1}) / bias_tau),  w_k ~ N(0, 1)
    ṽ_k = v(t_k − latency) + m_k,            m_k ~ N(0, velocity_sigma²)

The bias is a first-order Gauss–Markov process (stationary std ``sigma_bias``, correlation time ``bias_tau``),
the usual model of multipath (digest 000 §5.1). During an outage no fix is produced: the last one is held and
the ``valid`` flag is 0, so nothing downstream ever sees NaN.

Observation ``Box(7,)``: ``[x, y, vx, vy, fresh, valid, age]`` — world frame m and m/s; ``fresh`` = 1 on the step
a new fix arrived; ``valid`` = 0 while in an outage (or before the first fix); ``age`` = s since the held fix.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.params import RATE_MAX_HZ, Params, param
from av_gym.sensors.base import SensorWrapper, sim_time

BOUND = 1e5  # m, m/s: far beyond any scenario, keeps the Box finite


@dataclass(frozen=True)
class GNSSParams(Params):
    """GNSS receiver noise (digest 000 §5.1, 002 §4.2; suggestions: neither paper gives values)."""

    rate_hz: float = param(10.0, "Hz", gt=0, le=RATE_MAX_HZ, doc="fix rate, held between fixes (1-10 Hz suggested; thesis 002 "
                                                  "used 1 Hz)")
    sigma: float = param(1.5, "m", ge=0, doc="white position noise per axis (consumer grade 1-3 m)")
    sigma_bias: float = param(0.5, "m", ge=0, doc="multipath Gauss-Markov bias, stationary std (open road)")
    bias_tau: float = param(30.0, "s", gt=0, doc="bias correlation time (10-60 s)")
    velocity_sigma: float = param(0.1, "m/s", ge=0, doc="Doppler velocity noise (0.05-0.2)")
    latency: float = param(0.1, "s", ge=0, doc="fix latency (50-200 ms)")
    outage: Literal["none", "random", "scripted"] = param("none", doc="outage model")
    outage_rate: float = param(0.01, "1/s", ge=0, doc="random outage entry rate (highway value)")
    outage_mean: float = param(5.0, "s", gt=0, doc="mean random outage duration")
    outage_windows: tuple[tuple[float, float], ...] = param(
        (), "s", ge=0, doc="scripted outages, [[start, end], ...], e.g. [[10, 30]] for a 20 s tunnel")

    def relations(self) -> list[str]:
        if any(end < start for start, end in self.outage_windows):
            return [f"@outage_windows must be [start, end] pairs with end >= start, got "
                    f"{[list(w) for w in self.outage_windows]}"]
        return []


class GNSS(SensorWrapper):
    """Adds ``obs["gnss"]``; parameters: :class:`GNSSParams`. ``outage``: ``"none"``; ``"random"`` (two-state
    Markov chain, entry rate ``outage_rate`` and mean duration ``outage_mean``, 000 §5.1 highway values);
    ``"scripted"`` with ``outage_windows`` (002's motivation: a tunnel).

    Example (any field of :class:`GNSSParams` as a keyword, SI units):

        >>> import gymnasium as gym
        >>> import av_gym
        >>> from av_gym.sensors.gnss import GNSS
        >>> env = GNSS(gym.make("av_gym/LaneKeepingLap-v0"), sigma=1.5, outage="none")
        >>> obs, info = env.reset(seed=0)
        >>> obs["gnss"].shape  # [x, y, vx, vy, fresh, valid, age]
        (7,)
        >>> bool(obs["gnss"][5])  # a fix is valid from the first step (no outage)
        True
    """

    key = "gnss"
    Params = GNSSParams

    def __init__(self, env: gym.Env, params: GNSSParams | None = None, **overrides) -> None:
        p = self.params = GNSSParams.build(params, **overrides)
        self.rate_hz, self.sigma, self.sigma_bias, self.bias_tau = p.rate_hz, p.sigma, p.sigma_bias, p.bias_tau
        self.velocity_sigma, self.latency, self.outage = p.velocity_sigma, p.latency, p.outage
        self.outage_rate, self.outage_mean = p.outage_rate, p.outage_mean
        self.outage_windows = np.array(p.outage_windows, dtype=float).reshape(-1, 2)
        super().__init__(env)
        self._history: deque = deque()
        space = self.observation_space[self.key]
        self._low, self._high = space.low, space.high  # the reading is clipped into the space every step

    def sensor_space(self) -> spaces.Box:
        low = np.array([-BOUND] * 4 + [0, 0, 0], dtype=np.float32)
        high = np.array([BOUND] * 4 + [1, 1, BOUND], dtype=np.float32)
        return spaces.Box(low, high, dtype=np.float32)

    # ------------------------------------------------------------------------------------------- episode state
    def on_reset(self) -> None:
        unwrapped = self.env.unwrapped
        if self._record not in unwrapped.tick_listeners:
            unwrapped.tick_listeners.append(self._record)
        self._history.clear()
        self._record(unwrapped)
        self._bias = self.rng.normal(0.0, self.sigma_bias, size=2)
        self._last_fix_time: float | None = None
        self._fix = np.zeros(4)
        self._fix_time = 0.0
        self._fix_index = 0  # fixes are at k / rate_hz: counted, not accumulated, so no float drift
        self._in_outage = False
        self._outage_until = 0.0
        self._fix_dropped = False

    def _record(self, unwrapped) -> None:
        ego = unwrapped.vehicle
        t = unwrapped.steps / unwrapped.config["simulation_frequency"]
        self._history.append((t, ego.position[0], ego.position[1], ego.velocity[0], ego.velocity[1]))
        while len(self._history) > 2 and self._history[1][0] <= t - self.latency - 1.0:
            self._history.popleft()

    def _true_state(self, t: float) -> np.ndarray:
        """True [x, y, vx, vy] at time t (linear interpolation in the recorded ticks; clamped at the ends)."""
        h = np.array(self._history)
        return np.array([np.interp(t, h[:, 0], h[:, j]) for j in range(1, 5)])

    def _outage_at(self, t: float, dt: float) -> bool:
        if self.outage == "scripted":
            return bool(np.any((self.outage_windows[:, 0] <= t) & (t < self.outage_windows[:, 1])))
        if self.outage == "random":
            if self._in_outage and t >= self._outage_until:
                self._in_outage = False
            if not self._in_outage and self.rng.random() < 1.0 - np.exp(-self.outage_rate * dt):
                self._in_outage = True
                self._outage_until = t + self.rng.exponential(self.outage_mean)
            return self._in_outage
        return False

    # ------------------------------------------------------------------------------------------- measurement
    def invalidate(self, raw: np.ndarray, clean: np.ndarray) -> np.ndarray:
        """A reading that held NaN/inf (see ``SensorWrapper._guarded``) is not a fix: fresh = valid = 0, so that
        the 0 put in place of the NaN is never read as a confident fix at the origin."""
        out = np.array(clean, dtype=np.float32)
        out[4] = out[5] = 0.0
        return out

    def measure(self) -> np.ndarray:
        t = sim_time(self.env)
        fresh = False
        period = 1.0 / self.rate_hz
        while self._fix_index * period <= t + 1e-9:  # every fix time that has passed since the last step
            t_fix = round(self._fix_index * period, 9)
            self._fix_index += 1
            if self._outage_at(t_fix, period):
                continue
            dt = period if self._last_fix_time is None else t_fix - self._last_fix_time
            phi = np.exp(-dt / self.bias_tau)
            self._bias = phi * self._bias + self.sigma_bias * np.sqrt(1 - phi**2) * self.rng.normal(size=2)
            truth = self._true_state(t_fix - self.latency)
            noise = np.concatenate([self.rng.normal(0, self.sigma, 2), self.rng.normal(0, self.velocity_sigma, 2)])
            fix = truth + np.concatenate([self._bias, [0.0, 0.0]]) + noise
            if not np.all(np.isfinite(fix)):  # a receiver reports no fix rather than a wrong one: held, as in an outage
                self._bias = np.where(np.isfinite(self._bias), self._bias, 0.0)
                self.faults += 1
                self._step_faults += int(np.count_nonzero(~np.isfinite(fix)))  # info["sensor_faults"], as the guard
                self._fix_dropped = True
                continue
            self._fix, self._fix_dropped = fix, False
            self._fix_time = self._last_fix_time = t_fix
            fresh = True
        valid = self._last_fix_time is not None and not self._in_outage_now(round(t, 9)) and not self._fix_dropped
        age = 0.0 if self._last_fix_time is None else t - self._fix_time
        out = np.empty(7)
        out[:4], out[4], out[5], out[6] = self._fix, float(fresh), float(valid), age
        # np.clip's values by minimum/maximum, without its per-call dispatch (this runs every step)
        return np.minimum(np.maximum(out, self._low), self._high).astype(np.float32)

    def _in_outage_now(self, t: float) -> bool:
        if self.outage == "scripted":
            return bool(np.any((self.outage_windows[:, 0] <= t) & (t < self.outage_windows[:, 1])))
        return self.outage == "random" and self._in_outage
