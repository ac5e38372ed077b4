"""What both scenarios share on top of highway-env's ``AbstractEnv``: a per-tick hook and an episode seed for
everything outside the simulator (sensor noise, the roadside world)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from av_gym.sim import fmath


class ScenarioMixin:
    """Mix in before ``AbstractEnv``.

    - ``tick_listeners``: callables ``f(env)`` run after every simulation tick (sensors that sample faster than
      the policy, e.g. the IMU, record there; highway-env only exposes the state at policy steps).
    - ``episode_seed``: drawn from the env's own generator at the end of every reset, so all sensor noise and the
      roadside world follow from ``reset(seed=...)`` and are independent of the wrapper order.
    """

    scenario: str = ""

    def _init_scenario_state(self) -> None:
        if not hasattr(self, "tick_listeners"):
            self.tick_listeners: list[Callable] = []

    def _finish_reset(self) -> None:
        self._init_scenario_state()
        self.episode_seed = int(self.np_random.integers(2**63 - 1))

    def _simulate(self, action=None) -> None:
        self._init_scenario_state()
        frames = int(self.config["simulation_frequency"] // self.config["policy_frequency"])
        for frame in range(frames):
            if action is not None and frame == 0 and not self.config["manual_control"]:
                self.action_type.act(action)
            self.road.act()
            self.road.step(1 / self.config["simulation_frequency"])
            self.steps += 1
            self._on_tick()
            for listener in self.tick_listeners:
                listener(self)
            if frame < frames - 1:
                self._automatic_rendering()
        self.enable_auto_render = False

    def _on_tick(self) -> None:
        """Scenario bookkeeping after each tick (lap progress, arrival time)."""

    def _info(self, obs, action=None) -> dict:
        info = super()._info(obs, action)
        info["truth"] = self.truth()
        return info


def ego_kinematics(vehicle) -> dict:
    """Applied steering (rad), acceleration (m/s²) and the kinematic bicycle's yaw rate (rad/s, + = right turn:
    ψ̇ = v·sin β / (L/2), β = atan(tan δ / 2), highway-env's model) of a vehicle."""
    action = vehicle.action or {}
    steering = float(action.get("steering", 0.0))
    beta = fmath.atan(0.5 * fmath.tan(steering))  # = np.arctan(0.5 * np.tan(steering)), see av_gym.sim.fmath
    return {"steering": steering, "acceleration": float(action.get("acceleration", 0.0)),
            "yaw_rate": float(vehicle.speed * fmath.sin(beta) / (vehicle.LENGTH / 2))}
