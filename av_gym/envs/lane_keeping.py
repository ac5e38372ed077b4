"""``av_gym/LaneKeepingLap-v0``: one lap of a closed circuit, steering only, speed held by a controller.

The metric is the cross-track error (CTE): signed lateral offset of the vehicle's reference point from the lane
centreline, + = right of centre (paper 001's convention). Because the circuit is made of straight and circular
lanes, CTE is exact (perpendicular distance), unlike highway-env's sine lane whose "lateral" is along the chord
normal (digest 001 §8.1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from highway_env import utils
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.road.road import Road

from av_gym.envs.base import ScenarioMixin, ScenarioParams
from av_gym.sim.vehicles import ego_kinematics
from av_gym.envs.observations import LaneKeepingState, StateDict
from av_gym.envs.track import Track, build_track
from av_gym.sim import fmath
from av_gym.sim import lanes as fast_lanes
from av_gym.sim.fast_network import FastRoadNetwork
from av_gym.envs.vehicles import SpeedHeldVehicle, SteeringAction
from av_gym.geometry import NO_OTHERS
from av_gym.params import param


_FAST_TRACKS: dict = {}  # (layout, lane width) -> (Track, FastRoadNetwork), shared by fast envs


@dataclass(frozen=True)
class LaneKeepingParams(ScenarioParams):
    """``env=lane_keeping``: one lap of a closed circuit, steering only, speed held by a controller; the
    registered id's defaults too."""

    name: Literal["lane_keeping"] = param("lane_keeping")
    track: Literal["A", "B"] = param("A", doc="layout: A (training) | B (held out: never used for training data)")
    target_speed_kmh: float = param(36.0, "km/h", ge=1, le=200, doc="10 m/s, held by the speed controller (the default "
                                                                  "time limit is twice a lap at this speed)")
    lane_width: float = param(4.0, "m", gt=0, doc="highway-env's default lane width")
    max_steering_deg: float = param(25.0, "deg", gt=0, lt=90, doc="action ±1 maps to ±25° (Udacity's, digest "
                                                                  "001 §8.0)")
    offroad_margin: float = param(1.0, "m", gt=0, doc="beyond the lane edge at which the car has left the road "
                                                      "(half a car width)")
    time_limit: float | None = param(None, "s", gt=0, le=3600, doc="null = twice the nominal lap time (<= 1 h: the "
                                                                  "episode steps until it)")
    initial_lateral_std: float = param(0.2, "m", ge=0, doc="seeded start offset from the centre line, so seeds "
                                                           "differ without sensor noise (our choice)")
    initial_heading_std_deg: float = param(1.15, "deg", ge=0, doc="seeded start heading error (~0.02 rad)")
    compare: tuple[str, ...] = param(
        ("pid_paper", "pid_tuned", "pid_localized", "pilotnet", "ppo_lane_localized", "ppo_lane_camera"),
        doc="python -m eval env=lane_keeping with no agents=: every lane-keeping agent")

    CONFIG_KEYS = {**ScenarioParams.CONFIG_KEYS, "track": "track", "lane_width": "lane_width",
                   "target_speed": "target_speed_kmh", "max_steering": "max_steering_deg",
                   "offroad_margin": "offroad_margin", "time_limit": "time_limit",
                   "initial_lateral_std": "initial_lateral_std", "initial_heading_std": "initial_heading_std_deg"}

    def relations(self) -> list[str]:
        width = SpeedHeldVehicle.WIDTH  # the ego (fast or not); the lane-departure metric needs it to fit its lane
        if not self.lane_width > width:
            return [f"@lane_width must be wider than the ego vehicle's width, {width} m, got {self.lane_width:g}"]
        return super().relations()


class LaneKeepingLapEnv(ScenarioMixin, AbstractEnv):
    """Drive one lap of track ``config["track"]`` as close to the lane centre as possible.

    Action: ``Box(-1, 1, (1,))`` steering, mapped linearly to ±``max_steering`` rad (+ = right).
    Observation: ``Dict(state=Box(10,))``, see :class:`LaneKeepingState` (privileged; sensor wrappers add more).
    Episode: ``terminated`` on lap completion (``info["truth"]["lap_completed"]``) or when |CTE| exceeds
    half the lane width plus ``offroad_margin`` (left the road); ``truncated`` at ``time_limit`` s.
    Reward: ``1 - (cte / (lane_width/2))**2`` each step (clipped at -1), ``offroad_reward`` when leaving the road.
    """

    scenario = "lane_keeping"
    # the lane state's layout (features, preview distances, bounds): read through the env by
    # estimation.lane_features, which sits below envs and may not import it (tests/test_imports.py)
    STATE = LaneKeepingState
    Params = LaneKeepingParams

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update({  # what LaneKeepingParams does not hold; every other key comes from it, below
            "offroad_reward": -10.0,
            "start_s": 0.0,  # m along the lap where the car starts
            "screen_width": 600,
            "screen_height": 600,
            "centering_position": [0.5, 0.5],
            "scaling": 4.0,
        })
        config.update(LaneKeepingParams().env_config())  # the harness's task
        return config

    # ----------------------------------------------------------------------------------------------- spaces
    def define_spaces(self) -> None:
        self.observation_type = StateDict(self, LaneKeepingState(self))
        m = float(self.config["max_steering"])
        self.action_type = SteeringAction(self, steering_range=(-m, m), target_speed=float(self.config["target_speed"]),
                                          fast=bool(self.config["fast"]))
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

    # ----------------------------------------------------------------------------------------------- scene
    def _reset(self) -> None:
        self._check_config()
        if self.config["fast"]:
            # The track and its lane index are immutable: build them once per layout, not at every reset.
            key = (self.config["track"], float(self.config["lane_width"]))
            if key not in _FAST_TRACKS:
                track = build_track(key[0], lane_width=key[1])
                _FAST_TRACKS[key] = (track, FastRoadNetwork.from_network(track.network))
            self.track, network = _FAST_TRACKS[key]
        else:
            self.track: Track = build_track(self.config["track"], lane_width=float(self.config["lane_width"]))
            network = self.track.network
        self.road = Road(network=network, np_random=self.np_random,
                         record_history=self.config["show_trajectories"])
        start_s = float(self.config["start_s"]) % self.track.length
        k = int(np.searchsorted(self.track.starts, start_s, side="right") - 1)
        lane = self.track.lanes[k]
        s_local = start_s - self.track.starts[k]
        lat0, psi0 = np.clip(self.np_random.normal(size=2), -3, 3) * [self.config["initial_lateral_std"],
                                                                        self.config["initial_heading_std"]]
        ego = self.action_type.vehicle_class(self.road, lane.position(s_local, lat0), lane.heading_at(s_local) + psi0,
                                             float(self.config["target_speed"]))
        self.road.vehicles.append(ego)
        self.controlled_vehicles = [ego]
        self._lane_k = k
        self._lap_s = start_s
        self._progress = 0.0
        self._time_limit = (float(self.config["time_limit"]) if self.config["time_limit"]
                            else 2.0 * self.track.length / float(self.config["target_speed"]))
        self._finish_reset()

    # ----------------------------------------------------------------------------------------------- dynamics
    def step(self, action):
        # fast: the lane-relative state is computed once per policy step (observation, reward, termination and
        # truth each asked for it, up to six times) -- valid from the end of the simulation to the end of step().
        self._lane_state_cache = None
        try:
            return super().step(action)
        finally:
            self._lane_state_cache = None

    def _simulate(self, action=None) -> None:
        self._lane_state_cache = None
        super()._simulate(action)
        if self.config["fast"]:
            self._lane_state_cache = {}

    def _on_tick(self) -> None:
        # Lap progress is accumulated every tick, so a fast car cannot skip a lane between policy steps.
        if self.config["fast"]:  # the same arithmetic on floats
            position = self.vehicle.position
            k, s, _ = fast_lanes.locate(self.track, float(position[0]), float(position[1]), self._lane_k)
            length = self.track.length
            lap_s = float(self.track.starts[k]) + s
            ds = lap_s - self._lap_s
            ds -= length * float(round(ds / length))  # round() and np.round both round half to even
            self._progress += ds
            self._lane_k, self._lap_s = k, lap_s
            return
        else:
            k, s, _ = self.track.locate(self.vehicle.position, self._lane_k)
        lap_s = self.track.starts[k] + s
        ds = lap_s - self._lap_s
        ds -= self.track.length * np.round(ds / self.track.length)  # across the start line
        self._progress += ds
        self._lane_k, self._lap_s = k, lap_s

    def lane_state(self) -> dict:
        """Lane-relative ego state (SI units), shared by the observation and ``info["truth"]``."""
        cache = getattr(self, "_lane_state_cache", None)
        if cache:
            return dict(cache)
        state = self._lane_state()
        if cache is not None:
            cache.update(state)
        return state

    def _lane_state(self) -> dict:
        ego = self.vehicle
        lane = self.track.lanes[self._lane_k]
        if self.config["fast"]:  # the same formulas on floats (av_gym.sim.lanes)
            s, cte = fast_lanes.local_coordinates(lane, float(ego.position[0]), float(ego.position[1]))
            heading_error = fmath.wrap_to_pi(ego.heading - fast_lanes.heading_at(lane, s))
        else:
            s, cte = lane.local_coordinates(ego.position)
            heading_error = utils.wrap_to_pi(ego.heading - lane.heading_at(s))
        kin = ego_kinematics(ego)
        return {
            "cte": float(cte),
            "heading_error": float(heading_error),
            "speed": float(ego.speed),
            "yaw_rate": kin["yaw_rate"],
            "steering": kin["steering"],
            "lap_s": float(self._lap_s),
        }

    # ----------------------------------------------------------------------------------------------- episode
    def _offroad(self, cte: float | None = None) -> bool:
        cte = self.lane_state()["cte"] if cte is None else cte
        return abs(cte) > self.config["lane_width"] / 2 + self.config["offroad_margin"]

    def _lap_completed(self) -> bool:
        return self._progress >= self.track.length

    def _reward(self, action) -> float:
        cte = self.lane_state()["cte"]
        if self._offroad(cte):
            return float(self.config["offroad_reward"])
        return float(max(-1.0, 1.0 - (cte / (self.config["lane_width"] / 2)) ** 2))

    def _is_terminated(self) -> bool:
        return bool(self._lap_completed() or self._offroad() or self.vehicle.crashed)

    def _is_truncated(self) -> bool:
        return bool(self.time >= self._time_limit)

    def truth(self) -> dict:
        """Ground truth for metrics and tests (never part of the observation). SI units throughout."""
        ego = self.vehicle
        t = self.lane_state()
        t.update({
            "time": float(self.time),
            "x": float(ego.position[0]),
            "y": float(ego.position[1]),
            "heading": float(ego.heading),
            "acceleration": float((ego.action or {}).get("acceleration", 0.0)),  # = ego_kinematics(ego)[...]
            "progress": float(self._progress),
            "lap_length": float(self.track.length),
            "lap_completed": bool(self._lap_completed()),
            "on_road": not self._offroad(t["cte"]),
            "lane_width": float(self.config["lane_width"]),
            "vehicle_width": float(ego.WIDTH),
            "collision": bool(ego.crashed),
            "others": NO_OTHERS.copy(),
            "ttc": float("inf"),
        })
        return t


__all__ = ["LaneKeepingLapEnv", "SpeedHeldVehicle"]
