"""IMU: body-frame longitudinal and lateral acceleration and yaw rate at the simulation rate.

Truth comes from the simulated kinematics, sampled every tick: a_long = dv/dt, yaw rate r = dψ/dt (finite
differences over one tick) and a_lat = v·r (the centripetal term; the kinematic bicycle has no side slip rate
worth modelling). Noise model per channel c ∈ {a_long, a_lat, r} and sample k (dt = one tick)::

    z_k = sat( (1 + s_c)·truth_k + b_k + n_k ),   n_k ~ N(0, σ_c²)
    b_k = b_{k−1} + σ_rw,c·sqrt(dt)·w_k,          b_0 ~ N(0, σ_b0,c²)        (bias instability as a random walk)

Observation ``Box(K, 3)`` with K = simulation_frequency / policy_frequency samples per policy step, oldest first,
columns ``[a_long (m/s²), a_lat (m/s², + = towards the right), yaw_rate (rad/s, + = turning right)]`` in
highway-env's convention (y down on screen, so a right turn increases the heading).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from highway_env import utils

from av_gym.params import Params, param
from av_gym.sensors.base import SensorWrapper

G = 9.80665  # m/s²


@dataclass(frozen=True)
class IMUParams(Params):
    """IMU noise (digest 000 §5.2 / 002 §4.2 suggestions: neither paper gives IMU numbers)."""

    accel_sigma: float = param(0.05, "m/s²", ge=0, doc="white noise per sample")
    gyro_sigma: float = param(0.01, "rad/s", ge=0, doc="white noise per sample")
    accel_bias_sigma: float = param(0.05, "m/s²", ge=0, doc="per-episode initial bias std")
    gyro_bias_sigma: float = param(0.005, "rad/s", ge=0, doc="per-episode initial bias std")
    accel_bias_walk: float = param(0.002, "m/s²/√s", ge=0, doc="bias random walk (bias instability)")
    gyro_bias_walk: float = param(0.0001, "rad/s/√s", ge=0, doc="bias random walk (bias instability)")
    scale_error: float = param(0.01, ge=0, doc="per-episode scale-factor error std (1 %)")
    accel_range: float = param(156.9064, "m/s²", gt=0, doc="saturation (16 g)")
    gyro_range: float = param(4.3633231, "rad/s", gt=0, doc="saturation (250 °/s)")
    saturate: bool = param(True, doc="clip at the ranges (the observation space is bounded by them either way)")


class IMU(SensorWrapper):
    """Adds ``obs["imu"]``; parameters: :class:`IMUParams`.

    Example: one row per simulation tick of the policy step (15 Hz simulation, 5 Hz decisions on the lap: 3 rows),
    columns ``[a_long (m/s²), a_lat (m/s²), yaw_rate (rad/s)]``:

        >>> import gymnasium as gym
        >>> import av_gym
        >>> from av_gym.sensors.imu import IMU
        >>> env = IMU(gym.make("av_gym/LaneKeepingLap-v0"))
        >>> obs, info = env.reset(seed=0)
        >>> obs, reward, terminated, truncated, info = env.step([0.0])
        >>> obs["imu"].shape == (env.unwrapped.config["simulation_frequency"]
        ...                      // env.unwrapped.config["policy_frequency"], 3)
        True
    """

    key = "imu"
    Params = IMUParams

    def __init__(self, env: gym.Env, params: IMUParams | None = None, **overrides) -> None:
        p = self.params = IMUParams.build(params, **overrides)
        accel_sigma, gyro_sigma, accel_range, gyro_range = p.accel_sigma, p.gyro_sigma, p.accel_range, p.gyro_range
        u = env.unwrapped
        self.samples = int(u.config["simulation_frequency"] // u.config["policy_frequency"])
        self.dt = 1.0 / u.config["simulation_frequency"]
        self.sigma = np.array([accel_sigma, accel_sigma, gyro_sigma])
        self.bias_sigma = np.array([p.accel_bias_sigma, p.accel_bias_sigma, p.gyro_bias_sigma])
        self.bias_walk = np.array([p.accel_bias_walk, p.accel_bias_walk, p.gyro_bias_walk])
        self.scale_error = p.scale_error
        self.limits = np.array([accel_range, accel_range, gyro_range]) if p.saturate else np.full(3, np.inf)
        self._space_limit = np.array([accel_range, accel_range, gyro_range])
        super().__init__(env)

    def sensor_space(self) -> spaces.Box:
        high = np.tile(self._space_limit, (self.samples, 1)).astype(np.float32)
        return spaces.Box(-high, high, dtype=np.float32)

    def on_reset(self) -> None:
        unwrapped = self.env.unwrapped
        if self._tick not in unwrapped.tick_listeners:
            unwrapped.tick_listeners.append(self._tick)
        self.bias = self.rng.normal(0.0, self.bias_sigma)
        self.scale = 1.0 + self.rng.normal(0.0, self.scale_error, 3)
        ego = unwrapped.vehicle
        self._prev = (ego.speed, ego.heading)
        # Before the first tick the car is in steady motion: report its commanded acceleration and model yaw rate.
        steering = float(ego.action.get("steering", 0.0)) if ego.action else 0.0
        r0 = ego.speed * np.sin(np.arctan(0.5 * np.tan(steering))) / (ego.LENGTH / 2)
        a0 = float(ego.action.get("acceleration", 0.0)) if ego.action else 0.0
        self._buffer = [self._sample(np.array([a0, ego.speed * r0, r0])) for _ in range(self.samples)]

    def _tick(self, unwrapped) -> None:
        ego = unwrapped.vehicle
        v0, psi0 = self._prev
        r = utils.wrap_to_pi(ego.heading - psi0) / self.dt
        truth = np.array([(ego.speed - v0) / self.dt, ego.speed * r, r])
        self._prev = (ego.speed, ego.heading)
        self._buffer.append(self._sample(truth))

    def _sample(self, truth: np.ndarray) -> np.ndarray:
        self.bias = self.bias + self.bias_walk * np.sqrt(self.dt) * self.rng.normal(size=3)
        z = self.scale * truth + self.bias + self.rng.normal(0.0, self.sigma)
        return np.minimum(np.maximum(z, -self.limits), self.limits)  # np.clip's values, without its dispatch

    def measure(self) -> np.ndarray:
        out = np.array(self._buffer[-self.samples:])
        self._buffer = self._buffer[-self.samples:]
        return np.minimum(np.maximum(out, -self._space_limit), self._space_limit).astype(np.float32)
