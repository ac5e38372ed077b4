"""``av_gym/UnprotectedLeftTurn-v0``: highway-env's four-way intersection, ego from the south turning left
across the oncoming lane (digest 003 §9.1 for the geometry).

Modes:
- ``traffic``: highway-env's random IDM traffic and "challenger" (for RL training), spawn rate kept per second
  (stock tries one spawn per second with probability 0.6; we try every policy step with 0.6 / policy_frequency).
- ``ccftap``: Euro NCAP car-to-car front turn-across-path (digest 003 §3.2–3.3): the ego approaches at
  ``ccftap_ego_speed`` and a single non-reactive target drives straight at ``ccftap_target_speed`` in the oncoming
  lane, timed to reach the conflict point ``ccftap_dt`` seconds after the ego would (0 = they meet there). The
  episode runs on after the ego stops (to the time limit, long enough for the target to pass), so an ego parked
  in its path is hit; it ends, as in traffic mode, when the ego arrives (25 m into the exit lane, beyond the
  target's reach) or crashes.

Geometry (highway-env 1.12.1, verified in digest 003): south approach ``o0→ir0`` along x = +2 m driving −y, stop
line at y = 11 m, left-turn arc ``ir0→il1`` (centre (−11, 11), R = 13 m), exit ``il1→o1``. Oncoming lane
x ∈ [−4, 0]; the ego's arc crosses its centreline at the conflict point (−2, 1.62), 10.48 m of arc past the line.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Literal

import numpy as np
from highway_env import utils
from highway_env.envs.common.action import DiscreteMetaAction
from highway_env.envs.common.observation import KinematicObservation
from highway_env.envs.intersection_env import IntersectionEnv
from highway_env.vehicle.kinematics import Vehicle

from av_gym.envs.base import ScenarioMixin, ScenarioParams
from av_gym.sim.vehicles import ego_kinematics
from av_gym.envs.lane_path import LanePath
from av_gym.envs.observations import FastKinematics, StateDict
from av_gym.envs.vehicles import FastDiscreteMetaAction, LongitudinalAction
from av_gym.params import Params, param
from av_gym.geometry import NO_OTHERS, box_corners, constant_velocity_ttc
from av_gym.sim.fast_network import FastRoadNetwork
from av_gym.sim.road import FastRegulatedRoad
from av_gym.sim.vehicles import FastVehicle

STOCK_IDM = "highway_env.vehicle.behavior.IDMVehicle"
FAST_IDM = "av_gym.sim.vehicles.FastIDMVehicle"
ROUTE = [("o0", "ir0", 0), ("ir0", "il1", 0), ("il1", "o1", 0)]
ONCOMING_NEAR_EDGE_X = 0.0  # m, the oncoming lane spans x in [-4, 0]
CONFLICT_POINT = np.array([-2.0, 11.0 - np.sqrt(13.0**2 - 9.0**2)])  # (-2, 1.62) m, see module docstring


@dataclass(frozen=True)
class LeftTurnRewards(Params):
    """What PPO optimises; metrics never depend on it (they come from truth)."""

    collision: float = param(-5.0, doc="once, on collision (stock)")
    arrived: float = param(3.0, doc="once, on reaching the exit (stock: 1). At 1, waiting at the line until the time "
                                    "limit (~1.2 of progress) was worth about as much as a gap-acceptance driver's mix "
                                    "of arrivals and collisions, and PPO drifted to never turning (measured)")
    high_speed: float = param(0.0, "1/s", doc="per second spent at 7-9 m/s (stock: 1.0 per 1 Hz step). Off: at 1/s an "
                                              "always-proceed driver earns ~6 from speed and loses ~2.6 (0.52 x 5) to "
                                              "collisions, so PPO learnt never to yield (measured); at 0.1/s "
                                              "and no progress term it learnt to wait forever")
    progress: float = param(2.0, ge=0, doc="in total over the route to the arrival point: dense, rate-free, zero "
                                           "when waiting")
    comfort: float = param(0.01, "1/s", ge=0, doc="per second at 3 m/s² (quadratic in acceleration): discourages "
                                                  "SLOWER/FASTER chatter")


@dataclass(frozen=True)
class CCFtapParams(Params):
    """Euro NCAP car-to-car front turn-across-path (digest 003 §3.2-3.3)."""

    ego_speed_kmh: float = param(15.0, "km/h", ge=1, le=100, doc="VUT speed: Euro NCAP 10 / 15 / 20 (below 1 km/h "
                                                  "the ego takes minutes to arrive; no turn is driven at 100)")
    target_speed_kmh: float = param(45.0, "km/h", ge=1, le=144, doc="GVT speed: Euro NCAP 30 / 45 / 60 (bounds: "
                                                  "the episode lasts until it clears the junction; highway-env "
                                                  "caps a vehicle at Vehicle.MAX_SPEED = 40 m/s = 144 km/h, so a "
                                                  "faster target would never drive its set speed and would reach "
                                                  "the conflict point late)")
    dt: float = param(0.0, "s", ge=-30, le=30, doc="the target reaches the conflict point this long after the ego (0 = "
                                                 "they meet); the episode lasts until it clears, so |dt| is "
                                                 "bounded (Euro NCAP uses a few s; 1e9 hung)")


@dataclass(frozen=True)
class LeftTurnParams(ScenarioParams):
    """``env=left_turn``: highway-env's four-way intersection, ego from the south turning left. These defaults are
    the task the harness trains and reports, and the registered id's defaults; :data:`STOCK_CONFIG` restores
    highway-env's own episode length and rewards."""

    name: Literal["left_turn"] = param("left_turn")
    mode: Literal["traffic", "ccftap"] = param("traffic", doc="traffic (random IDM traffic, for RL) | ccftap (Euro "
                                                             "NCAP turn-across-path test)")
    action: Literal["discrete", "continuous"] = param("discrete", doc="discrete {SLOWER, IDLE, FASTER} over "
                                                                      "target_speeds_kmh | continuous acceleration")
    duration: float = param(20.0, "s", gt=0, le=600, doc="traffic-mode time limit (<= 10 min: a turn takes ~9 s, "
                                                         "a waiting policy steps until the limit). Stock: 13 s, "
                                                         "which leaves an always-proceed driver (exit at ~8.7 s) 4 s "
                                                         "of slack: too little to yield to a stream of oncoming cars "
                                                         "and still exit")
    spawn_probability: float = param(0.6, "1/s", ge=0, le=1, doc="expected new traffic vehicles per second (stock "
                                                                 "highway-env's rate)")
    target_speeds_kmh: tuple[float, float, float] = param((0.0, 16.2, 32.4), "km/h", ge=0,
                                                          doc="discrete set-points = stock 0 / 4.5 / 9 m/s")
    acceleration_range: tuple[float, float] = param((-8.0, 3.0), "m/s²", doc="continuous action -1..1 maps onto this")
    rewards: LeftTurnRewards = param(LeftTurnRewards())
    ccftap: CCFtapParams = param(CCFtapParams())
    compare: tuple[str, ...] = param(
        ("always_proceed", "always_proceed+aeb", "gap_acceptance", "gap_acceptance+aeb", "ppo_turn", "ppo_turn+aeb",
         "ppo_turn_shielded", "ppo_turn_shielded+aeb", "ppo_turn_perceived", "ppo_turn_perceived+aeb"),
        doc="python -m eval env=left_turn with no agents=: the headline comparison, each agent with and "
            "without the AEB shield")

    CONFIG_KEYS = {**ScenarioParams.CONFIG_KEYS, "mode": "mode", "action.type": "action",
                   "action.target_speeds": "target_speeds_kmh", "action.acceleration_range": "acceleration_range",
                   "duration": "duration", "spawn_probability": "spawn_probability",
                   "ccftap_ego_speed": "ccftap.ego_speed_kmh", "ccftap_target_speed": "ccftap.target_speed_kmh",
                   "ccftap_dt": "ccftap.dt", "collision_reward": "rewards.collision",
                   "arrived_reward": "rewards.arrived", "high_speed_reward": "rewards.high_speed",
                   "progress_reward": "rewards.progress", "comfort_reward": "rewards.comfort"}

    def relations(self) -> list[str]:
        lo, hi = self.acceleration_range
        if not lo < hi:  # the continuous action -1..1 maps linearly onto [lo, hi]: an empty range divides by zero
            return [f"@acceleration_range must be [min, max] with min < max (m/s²), got [{lo:g}, {hi:g}]"]
        speeds = self.target_speeds_kmh
        if not all(a < b for a, b in zip(speeds, speeds[1:])):
            # highway-env's SLOWER/FASTER step down/up this list by index: out of order, FASTER slows the ego down
            return [f"@target_speeds_kmh must be strictly increasing [SLOWER, IDLE, FASTER] set-points (km/h), got "
                    f"[{', '.join(f'{v:g}' for v in speeds)}]"]
        return super().relations()


STOCK_CONFIG = {"duration": 13.0, "arrived_reward": 1.0, "high_speed_reward": 1.0, "progress_reward": 0.0,
                "comfort_reward": 0.0}
"""highway-env's own intersection episode (13 s, its rewards): ``gym.make("av_gym/UnprotectedLeftTurn-v0",
config=STOCK_CONFIG)``. The registered id otherwise defaults to :class:`LeftTurnParams`, the harness's task."""


class UnprotectedLeftTurnEnv(ScenarioMixin, IntersectionEnv):
    """Unprotected left turn across oncoming traffic; the agent controls only the ego's speed.

    Action (``action``): ``discrete`` = highway-env's longitudinal meta-actions {0: SLOWER, 1: IDLE, 2: FASTER}
    over ``target_speeds`` (m/s); ``continuous`` = ``Box(-1, 1, (1,))`` mapped to ``acceleration_range`` (m/s²).
    The ego follows its route laterally in both. Observation: ``Dict(state=Box(15, 7))``, highway-env's Kinematics
    (presence, x, y, vx, vy, cos_h, sin_h; absolute, normalised). Rewards are rates per second so they do not
    depend on the policy frequency: ``high_speed_reward`` per second in ``reward_speed_range``, plus one-off
    ``collision_reward`` and ``arrived_reward``. ``info["truth"]`` carries ground truth for metrics.
    """

    scenario = "left_turn"
    # read through the env by estimation.turn_features (below envs, so it may not import this module)
    CONFLICT_POINT = CONFLICT_POINT
    Params = LeftTurnParams

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update({  # what LeftTurnParams does not hold; every other key comes from it, below
            "ttc_horizon": 5.0,  # s, horizon of the constant-velocity TTC reported in truth
            "ccftap_lead_time": 5.0,  # s, the ego starts this long (at its speed) before the stop line, >= 25 m
        })
        config.update(LeftTurnParams().env_config())  # the harness's task; STOCK_CONFIG = highway-env's
        return config

    # ----------------------------------------------------------------------------------------------- spaces
    def define_spaces(self) -> None:
        self._check_config()
        obs_config = {k: v for k, v in self.config["observation"].items() if k != "type"}
        fast = bool(self.config["fast"])
        kinematics = FastKinematics if fast else KinematicObservation
        self.observation_type = StateDict(self, kinematics(self, **obs_config))
        a = self.config["action"]
        if a["type"] == "discrete":
            speeds = [0.0, float(self.config["ccftap_ego_speed"])] if self.config["mode"] == "ccftap" \
                else a["target_speeds"]
            meta = FastDiscreteMetaAction if fast else DiscreteMetaAction
            self.action_type = meta(self, longitudinal=True, lateral=False, target_speeds=speeds)
        else:
            self.action_type = LongitudinalAction(self, acceleration_range=tuple(a["acceleration_range"]), fast=fast)
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

    def cruise_action(self):
        """The action that keeps the current speed: IDLE, or zero acceleration (used by always-proceed)."""
        if isinstance(self.action_type, DiscreteMetaAction):
            return 1
        lo, hi = self.action_type.acceleration_range
        return np.array([utils.lmap(0.0, [lo, hi], [-1.0, 1.0])], dtype=np.float32)

    # ----------------------------------------------------------------------------------------------- scene
    def _reset(self) -> None:
        self._make_road()
        if self.config["fast"]:  # same road and rules, faster (av_gym.sim)
            self.road = FastRegulatedRoad.from_road(self.road, FastRoadNetwork.from_network(self.road.network))
        self.route = LanePath([self.road.network.get_lane(i) for i in ROUTE])
        if self.config["mode"] == "traffic":
            self._make_vehicles(self.config["initial_vehicle_count"])
        else:
            self._make_ccftap()
        self._route_k = 0
        self._arrived_time = None
        self._finish_reset()
        self._progress_s = self._route_s()
        # Route position where highway-env counts the ego as arrived: 25 m into the exit lane.
        self._progress_total = max(1.0, self.route.starts[2] + 25.0 - self._progress_s)

    def _make_ccftap(self) -> None:
        """Ego and one constant-speed target timed by ``ccftap_dt`` (digest 003 §3.3, §9.8)."""
        v_e, v_t = float(self.config["ccftap_ego_speed"]), float(self.config["ccftap_target_speed"])
        approach = self.road.network.get_lane(ROUTE[0])
        d_start = max(25.0, v_e * float(self.config["ccftap_lead_time"]))  # m before the stop line
        s0 = approach.length - d_start
        ego = self.action_type.vehicle_class(self.road, approach.position(s0, 0.0), approach.heading_at(s0), v_e)
        ego.plan_route_to("o1")
        if hasattr(ego, "speed_index"):
            ego.speed_index = ego.speed_to_index(v_e)
            ego.target_speed = ego.index_to_speed(ego.speed_index)
        turn = self.road.network.get_lane(ROUTE[1])
        s_conflict, _ = turn.local_coordinates(CONFLICT_POINT)
        self.ccftap_ego_arrival = (d_start + s_conflict) / v_e  # s, ego centre at the conflict point
        t_target = self.ccftap_ego_arrival + float(self.config["ccftap_dt"])
        target_class = FastVehicle if self.config["fast"] else Vehicle
        target = target_class(self.road, CONFLICT_POINT - np.array([0.0, v_t * t_target]), heading=np.pi / 2,
                              speed=v_t)
        self.road.vehicles += [ego, target]
        self.controlled_vehicles = [ego]
        self.ccftap_target = target
        # Long enough for the ego to exit and the target to clear the intersection, with slack for a stop.
        t_clear = max(self.ccftap_ego_arrival + 25.0 / v_e, t_target + 30.0 / v_t)
        self._ccftap_time_limit = t_clear + 8.0

    @contextlib.contextmanager
    def _traffic_class(self):
        """fast: highway-env's traffic code builds ``config["other_vehicles_type"]``; while it runs, the stock IDM
        class is swapped for ``FastIDMVehicle`` (same model, same trajectories)."""
        stock = self.config["other_vehicles_type"]
        if self.config["fast"] and stock == STOCK_IDM:
            self.config["other_vehicles_type"] = FAST_IDM
        try:
            yield
        finally:
            self.config["other_vehicles_type"] = stock

    def _make_vehicles(self, n_vehicles: int = 10) -> None:
        with self._traffic_class():
            super()._make_vehicles(n_vehicles)

    def _spawn_vehicle(self, *args, **kwargs):
        with self._traffic_class():
            return super()._spawn_vehicle(*args, **kwargs)

    def _step(self, action):
        if self.config["mode"] == "traffic" and self.steps > 0:
            # Stock highway-env clears and spawns traffic right *after* computing the observation, so wrappers
            # reading the road later would see another scene than the observation and info["truth"]. Doing it
            # at the start of the next step keeps the same sequence of scenes and random draws.
            self._clear_vehicles()
            # Stock tries one spawn per policy step at 1 Hz: 0.6 vehicles/s expected. Keep that expected rate.
            self._spawn_vehicle(spawn_probability=self.config["spawn_probability"] / self.config["policy_frequency"])
        return super(IntersectionEnv, self).step(action)  # AbstractEnv.step: IntersectionEnv.step would spawn

    def _on_tick(self) -> None:
        if self._arrived_time is None and self.has_arrived(self.vehicle):
            self._arrived_time = float(self.time)

    # ----------------------------------------------------------------------------------------------- episode
    def _target_passed(self) -> bool:
        # The ego can only be in the oncoming lane on its turn arc, which ends below y = 11 m; a target whose rear
        # is beyond that can no longer reach it.
        t = self.ccftap_target
        return t.position[1] - t.LENGTH / 2 > 12.0

    def _route_s(self) -> float:
        """Ego position along its route (m), with the route-lane hint kept up to date."""
        self._route_k, s, _ = self.route.locate(self.vehicle.position, self._route_k)
        return self.route.path_s(self._route_k, s)

    def _reward(self, action) -> float:
        """Per step: speed (rate per second in ``reward_speed_range``), progress (``progress_reward`` spread over the
        route from the start to the arrival point, so standing still earns nothing and each metre earns the same),
        comfort (``-comfort_reward`` × (a / 3 m/s²)² per second), and the one-off collision and arrival terms."""
        ego = self.vehicle
        dt = 1.0 / self.config["policy_frequency"]
        speed_term = np.clip(utils.lmap(ego.speed, self.config["reward_speed_range"], [0, 1]), 0, 1)
        reward = self.config["high_speed_reward"] * speed_term * dt
        if self.config["progress_reward"]:
            s = self._route_s()
            reward += self.config["progress_reward"] * max(0.0, s - self._progress_s) / self._progress_total
            self._progress_s = max(s, self._progress_s)
        if self.config["comfort_reward"]:
            reward -= self.config["comfort_reward"] * (ego.action.get("acceleration", 0.0) / 3.0) ** 2 * dt
        if ego.crashed:
            reward += self.config["collision_reward"]
        elif self.has_arrived(ego):
            reward += self.config["arrived_reward"]
        return float(reward)

    def _is_terminated(self) -> bool:
        ego = self.vehicle
        if ego.crashed:
            return True
        # Arrival ends every episode, in both modes and action types: the arrival reward is one-off, and an ego 25 m
        # into the exit lane (x <= -36 m) is out of the CCFtap target's reach (its lane is x in [-4, 0]), so the
        # test has nothing left to score. A CCFtap ego that has not arrived (stopped, or slow) runs on until the
        # time limit, so one parked in the target's path is hit. Before, a CCFtap ego arriving before the target
        # had passed (continuous acceleration, or a large dt) was paid the arrival every step and drove off the end
        # of the exit lane, where the batch's lane following differs.
        return bool(self.has_arrived(ego))

    def _is_truncated(self) -> bool:
        limit = self._ccftap_time_limit if self.config["mode"] == "ccftap" else self.config["duration"]
        return bool(self.time >= limit)

    def truth(self) -> dict:
        """Ground truth for metrics and tests (never part of the observation). SI units throughout."""
        ego = self.vehicle
        self._route_k, s, lat = self.route.locate(ego.position, self._route_k)
        route_s = self.route.path_s(self._route_k, s)
        stop_line_s = self.route.starts[1]
        kin = ego_kinematics(ego)
        others = [v for v in self.road.vehicles if v is not ego]
        others_arr = np.array([[v.position[0], v.position[1], v.velocity[0], v.velocity[1], v.heading,
                                v.LENGTH, v.WIDTH] for v in others]) if others else NO_OTHERS.copy()
        ego_arr = np.array([*ego.position, *ego.velocity, ego.heading, ego.LENGTH, ego.WIDTH])
        corners = box_corners(ego.position, ego.heading, ego.LENGTH, ego.WIDTH)
        conflict_s = stop_line_s + self.route.lanes[1].local_coordinates(CONFLICT_POINT)[0]
        return {
            "time": float(self.time),
            "x": float(ego.position[0]),
            "y": float(ego.position[1]),
            "heading": float(ego.heading),
            "speed": float(ego.speed),
            "yaw_rate": kin["yaw_rate"],
            "acceleration": kin["acceleration"],
            "steering": kin["steering"],
            "route_s": route_s,
            "cte": lat,
            "stop_line_offset": route_s + ego.LENGTH / 2 - stop_line_s,
            "distance_to_conflict": conflict_s - route_s,
            "oncoming_gap": float(corners[:, 0].min() - ONCOMING_NEAR_EDGE_X),
            "collision": bool(ego.crashed),
            "arrived": bool(self.has_arrived(ego)),
            "arrived_time": self._arrived_time,
            "others": others_arr,
            "ttc": constant_velocity_ttc(ego_arr, others_arr, horizon=float(self.config["ttc_horizon"])),
        }
