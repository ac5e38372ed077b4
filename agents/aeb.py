"""Predictive automatic emergency braking (AEB) shield for the unprotected left turn (issue 5; digest 003).

:class:`AEBShield` is a ``gymnasium.Wrapper`` that sits between any agent and the left-turn env (it wraps the
sensed env, see :func:`av_gym.make.add_shield`). It never needs the agent's cooperation: every policy step (10 Hz,
T = 0.1 s) it predicts the ego and the other vehicles, decides a stage — 0 monitor, 1 warn, 2 brake — and while
braking it cuts the throttle in the agent's action and applies a :class:`BrakeActuator` directly to the ego
vehicle, whatever the agent commands.

Variants (``variant``):

- ``paper`` — faithful to digest 003 §4.1–4.8: constant-acceleration prediction of ego and targets in fixed,
  approach-aligned axes with the literal ``(V0 + A0·t)·t`` (``half_accel_term`` False), accelerations from finite
  differences low-passed by an EMA (α = 0.5), constant-yaw-rate ego heading (eq. 9), the collision limits of eqs.
  (7)–(8), horizon map 10/15/20 km/h → 4/3/2 s (clamped), warning while TTC ≤ H, braking at TTC ≤ 1.5 s, latched
  until standstill. The paper says nothing about what follows; we hold the standstill ``standstill_hold`` s (2 s,
  a typical AEB brake-hold before handing back to the driver; ``null`` holds it as long as the function is
  active, as digest 003's prototype did; 0 releases at once), then go back to monitoring. Minimum TTC
  over all targets. Active from ``activation_distance`` before the stop line until the ego has cleared the turn
  (our stand-in for "left indicator on").
- ``improved`` — our design, aimed at the paper's intended outcome (stop *before leaving its own lane*):

  * the ego predicted **along its planned route**, where it will actually drive: highway-env's route-following
    controller cuts the turn by up to 0.6 m and lags 10° in heading, so :class:`agents.aeb_predict.DrivenPath`
    replays that controller (tabulated per speed) instead of assuming the lane centreline; longitudinally the
    vehicle's own cruise-control response to its set-point (discrete actions), or its current acceleration for
    1 s (continuous);
  * the others constant-velocity (``target_model: cv``, default), constant-acceleration (``ca``) or on every way
    the map lets them continue (``map``: CV along each lane continuation plus the plain CV hypothesis);
  * footprints as oriented boxes, the ego's grown by ``margin`` m, overlap by the separating-axis test, over a
    **geometry horizon**: the time to clear the turn, clipped to [``horizon_min``, ``horizon_max``];
  * a **stop-line-aware trigger**: while a conflict is predicted, brake once the distance from the front bumper
    to the stop line has come down to the actuator's stopping distance (delay and jerk included) plus one
    decision period and ``stop_margin``, so the car stops just behind the line; otherwise (past that point, or
    outside the turn window, where the shield acts as a forward AEB on the predicted footprints) only an
    emergency brake at TTC ≤ ``ttc_brake`` on the unmargined footprints;
  * a **brake-feasibility check** (003 §9.7): no braking if the braking profile predicts the ego standing still
    in a target's path when it is hit (a hit while still moving does not stop the brake: it mitigates);
  * a **release rule**: once latched, the brake lets go when the ego setting off again (or carrying on, for a
    continuous agent both) is predicted conflict-free with the larger ``release_margin`` for ``release_hold`` s.
  * Vehicles following the ego in its lane are ignored (they are responsible for their own gap).
- ``standard`` — the baseline of paper 003 §2: ``TTC = Δx/Δv`` for targets ahead in the ego's corridor only,
  warn at TTC ≤ ``warn_ttc``, brake at TTC ≤ ``ttc_brake``, latched until standstill (and held like the paper
  variant), optionally inhibited above
  a steering angle (``steering_inhibit_deg``; off by default, i.e. the most generous standard AEB). Always active.

Modes (``mode``): ``ground_truth`` reads the other vehicles from the simulator; ``perceived`` builds its **own**
:class:`av_gym.sensors.detector.Detector` (from the ``detector`` sub-config, world frame, its own random stream
``"aeb_detector"`` from the episode seed) and a :class:`av_gym.estimation.MultiObjectTracker` (``tracker``
sub-config) and uses the confirmed tracks. The shield owns its perception so it works whatever sensors the agent
has (an agent with only cameras, or with the privileged state) and the agent's observation is left untouched; a
vehicle has a dedicated AEB sensor in the same way. The ego's own state (position on its route, speed,
acceleration, yaw rate) is read from the vehicle in both modes: the shield is part of the ego's own stack.

The brake override: while braking the agent's action passes with its throttle cut (FASTER → IDLE, continuous
acceleration capped at 0), and the :class:`BrakeActuator` sets the ego's acceleration on every simulation tick
(the ego instance's ``act`` is patched at reset: it works for MDPVehicle's speed controller and for
RouteFollowingVehicle's commanded acceleration alike). The agent's set-point is kept for after the release.

``info`` each step: ``aeb_stage`` (0/1/2), ``aeb_ttc`` (s, inf when none), ``aeb_horizon`` (s), ``aeb_override``
and ``shield_override`` (bool: the action was overridden by braking), ``aeb_target_id`` (index in the simulator's
vehicle list minus the ego, or track id; -1), ``aeb_active``, ``aeb_infeasible`` (a conflict was predicted but
braking would park the ego in the target's path), ``aeb_brake_time`` (s, first brake command this episode, NaN),
``aeb_stop_position`` (m, front bumper past the stop line at the first standstill under braking, NaN before),
``aeb_action`` (the action passed on to the env).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from agents.aeb_predict import (DrivenPath, LaneHypotheses, RouteTable, cruise_profile, footprint_ttc,
                                go_profile, object_predict, paper_horizon, paper_ttc, profile_speeds,
                                standard_ttc)
from av_gym.sensors.base import sensor_rng

VARIANTS = ("paper", "improved", "standard")
MODES = ("ground_truth", "perceived")
TARGET_MODELS = ("cv", "ca", "map")
STOP_SPEED = 0.1  # m/s, standstill (as av_gym.metrics.left_turn.STOP_SPEED)
MONITOR, WARN, BRAKE = 0, 1, 2


# ----------------------------------------------------------------------------------------------- actuator
@dataclass
class BrakeActuator:
    """Brake actuator: after a command, nothing happens for ``delay`` s, then the deceleration ramps up at
    ``jerk`` m/s³ (0 = a step) to ``decel`` m/s² and is held, never reversing the car; applied every simulation
    tick. Defaults after digest 003 §9.4 (none is in the paper): 8 m/s² (≈ 0.8 g, a typical AEB peak on a dry
    road), 0.15 s (middle of the 0.1–0.2 s suggested), 30 m/s³."""

    decel: float = 8.0
    delay: float = 0.15
    jerk: float = 30.0

    def __post_init__(self) -> None:
        if not self.decel > 0:
            raise ValueError(f"shield.brake.decel must be > 0 m/s², got {self.decel}")
        if not self.delay >= 0:
            raise ValueError(f"shield.brake.delay must be >= 0 s, got {self.delay}")
        if not self.jerk >= 0:
            raise ValueError(f"shield.brake.jerk must be >= 0 m/s³ (0 = step), got {self.jerk}")
        self.engaged_at: float | None = None

    def engage(self, t: float) -> None:
        if self.engaged_at is None:
            self.engaged_at = float(t)

    def release(self) -> None:
        self.engaged_at = None

    def deceleration(self, elapsed: float, dt: float) -> float | None:
        """Deceleration (m/s², > 0) during the tick that starts ``elapsed`` s after the command; None in the
        delay (the vehicle's own control acts)."""
        if elapsed < self.delay - 1e-9:
            return None
        return self.decel if self.jerk <= 0 else min(self.decel, self.jerk * (elapsed - self.delay + dt))

    def command(self, t: float, speed: float, dt: float) -> float | None:
        """Acceleration (m/s²) to apply in the tick starting at ``t``, or None when not braking."""
        if self.engaged_at is None:
            return None
        d = self.deceleration(t - self.engaged_at, dt)
        return None if d is None else max(-d, -max(speed, 0.0) / dt)

    def profile(self, v0: float, a_before: float, duration: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Distance (m) and speed (m/s) after each tick of ``dt`` s over ``duration`` s when the brake is commanded
        now at speed ``v0`` and the vehicle keeps ``a_before`` (m/s²) during the delay; integrated like
        highway-env's ``Vehicle.step`` (position with the speed before the update)."""
        n = int(np.ceil(duration / dt - 1e-9))
        x, v = 0.0, max(float(v0), 0.0)
        xs, vs = np.empty(n), np.empty(n)
        for i in range(n):
            d = self.deceleration(i * dt, dt)
            a = a_before if d is None else max(-d, -v / dt)
            x += v * dt
            v = max(v + a * dt, 0.0)
            xs[i], vs[i] = x, v
        return xs, vs

    def stopping_distance(self, v0: float, a_before: float, dt: float) -> tuple[float, float]:
        """Distance (m) and time (s) to standstill when braking is commanded now."""
        if v0 <= 0:
            return 0.0, 0.0
        a_before = max(a_before, 0.0)
        t_max = self.delay + 1.0 / max(self.jerk, 1e-6) * self.decel + (v0 + a_before * self.delay) / self.decel + 1.0
        xs, vs = self.profile(v0, a_before, t_max, dt)
        i = int(np.argmax(vs <= 0.0)) if (vs <= 0.0).any() else len(vs) - 1
        return float(xs[i]), float((i + 1) * dt)


# ----------------------------------------------------------------------------------------------- shield
_ROUTE_CACHE: dict[tuple, tuple[RouteTable, DrivenPath]] = {}


def _route_tables(lanes) -> tuple[RouteTable, DrivenPath]:
    """Centreline table and driven-path model of a route (the turn: lane 1), cached by the route's geometry."""
    key = tuple((type(lane).__name__, round(lane.length, 6), *np.round(lane.position(0, 0), 6),
                 *np.round(lane.position(lane.length, 0), 6)) for lane in lanes)
    if key not in _ROUTE_CACHE:
        route = RouteTable(lanes)
        turn_end = route.starts[2] if len(route.starts) > 2 else route.length
        _ROUTE_CACHE[key] = (route, DrivenPath(route, route.starts[min(1, len(route.starts) - 1)], turn_end))
    return _ROUTE_CACHE[key]


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


class _ActuatedAct:
    """The ego's ``act`` followed by the shield's brake actuator (:meth:`AEBShield._install_actuator`). An object,
    not a closure: ``copy.deepcopy`` of the env stack (the lookahead oracle plays futures on copies) copies its
    references, so the copied ego runs its own controller and the copied shield's actuator; a closure would be
    shared and drive the original vehicle."""

    def __init__(self, original, vehicle, shield: "AEBShield") -> None:
        self.original, self.vehicle, self.shield = original, vehicle, shield

    def __call__(self, action=None) -> None:
        self.original(action)
        u, shield = self.shield.env.unwrapped, self.shield
        t = u.steps / float(u.config["simulation_frequency"])
        a = shield.actuator.command(t, self.vehicle.speed, shield.sim_dt)
        if a is not None:
            self.vehicle.action["acceleration"] = a


class AEBShield(gym.Wrapper):
    """Predictive AEB safety shield; see the module docstring for variants, modes and ``info`` keys.

    Parameters (all SI): ``variant``, ``mode``; ``step`` prediction slice T (0.1 s); ``ttc_brake`` (1.5 s);
    ``brake`` dict for :class:`BrakeActuator`; ``detector``/``tracker`` dicts for the perceived mode;
    ``activation_distance`` (m before the stop line at which paper/improved engage, 50);
    paper: ``half_accel_term`` (False), ``limits`` (``paper`` eqs. 7–8 | ``aabb`` corrected), ``accel_alpha``
    (EMA of the finite-difference accelerations, 0.5); improved: ``margin`` (0.3 m), ``release_margin`` (0.6 m),
    ``stop_margin`` (0.3 m), ``horizon_min``/``horizon_max`` (2/8 s), ``target_model`` (cv), ``release_hold``
    (0.3 s), ``feasibility`` (True), ``go_speed`` (m/s the ego is assumed to set off to when its own set-point is
    unknown, 4.5); standard: ``warn_ttc`` (2.5 s), ``steering_inhibit_deg`` (None), ``lateral_margin`` (0.2 m);
    paper and standard: ``standstill_hold`` (2 s; None = while active).
    """

    def __init__(self, env: gym.Env, variant: str = "improved", mode: str = "ground_truth", step: float = 0.1,
                 ttc_brake: float = 1.5, brake: dict | None = None, detector: dict | None = None,
                 tracker: dict | None = None, activation_distance: float = 50.0,
                 half_accel_term: bool = False, limits: str = "paper", accel_alpha: float = 0.5,
                 margin: float = 0.3, release_margin: float = 0.6, stop_margin: float = 0.3,
                 horizon_min: float = 2.0, horizon_max: float = 8.0, target_model: str = "cv",
                 release_hold: float = 0.3, feasibility: bool = True, go_speed: float = 4.5,
                 warn_ttc: float = 2.5, steering_inhibit_deg: float | None = None,
                 lateral_margin: float = 0.2, standstill_hold: float | None = 2.0,
                 ignore_rear: bool = False) -> None:
        super().__init__(env)
        if getattr(env.unwrapped, "scenario", None) != "left_turn":
            raise ValueError(f"shield.kind aeb works on the left_turn scenario only, not "
                             f"{getattr(env.unwrapped, 'scenario', '?')!r}")
        if variant not in VARIANTS:
            raise ValueError(f"shield.variant must be one of {list(VARIANTS)}, got {variant!r}")
        if mode not in MODES:
            raise ValueError(f"shield.mode must be one of {list(MODES)}, got {mode!r}")
        if target_model not in TARGET_MODELS:
            raise ValueError(f"shield.target_model must be one of {list(TARGET_MODELS)}, got {target_model!r}")
        if limits not in ("paper", "aabb"):
            raise ValueError(f"shield.limits must be one of ['paper', 'aabb'], got {limits!r}")
        for name, value in (("step", step), ("ttc_brake", ttc_brake), ("horizon_min", horizon_min),
                            ("horizon_max", horizon_max), ("warn_ttc", warn_ttc), ("go_speed", go_speed),
                            ("activation_distance", activation_distance)):
            if not value > 0:
                raise ValueError(f"shield.{name} must be > 0, got {value}")
        for name, value in (("margin", margin), ("release_margin", release_margin), ("stop_margin", stop_margin),
                            ("release_hold", release_hold), ("lateral_margin", lateral_margin)):
            if not value >= 0:
                raise ValueError(f"shield.{name} must be >= 0, got {value}")
        if standstill_hold is not None and not standstill_hold >= 0:
            raise ValueError(f"shield.standstill_hold must be >= 0 s or null, got {standstill_hold}")
        if not 0 < accel_alpha <= 1:
            raise ValueError(f"shield.accel_alpha must be in (0, 1], got {accel_alpha}")
        if horizon_max < horizon_min:
            raise ValueError(f"shield.horizon_max ({horizon_max}) must be >= shield.horizon_min ({horizon_min})")
        self.variant, self.mode, self.T, self.ttc_brake = variant, mode, float(step), float(ttc_brake)
        try:
            self.actuator = BrakeActuator(**(brake or {}))
        except TypeError as exc:
            raise ValueError(f"shield.brake: {exc}") from None
        self.activation_distance = float(activation_distance)
        self.half_accel_term, self.limits, self.accel_alpha = bool(half_accel_term), limits, float(accel_alpha)
        self.margin, self.release_margin, self.stop_margin = float(margin), float(release_margin), float(stop_margin)
        self.horizon_min, self.horizon_max, self.target_model = float(horizon_min), float(horizon_max), target_model
        self.release_hold, self.feasibility, self.go_speed = float(release_hold), bool(feasibility), float(go_speed)
        self.warn_ttc, self.lateral_margin = float(warn_ttc), float(lateral_margin)
        self.standstill_hold = None if standstill_hold is None else float(standstill_hold)
        self.ignore_rear = bool(ignore_rear)
        self._hypotheses: LaneHypotheses | None = None
        self.steering_inhibit = None if steering_inhibit_deg is None else np.radians(float(steering_inhibit_deg))
        self.detector = self.tracker = None
        self._lanes: list = []
        if mode == "perceived":
            self._build_perception(detector or {}, tracker or {})

    # ------------------------------------------------------------------------------------------- perception
    def _build_perception(self, det_cfg: dict, trk_cfg: dict) -> None:
        import inspect

        from av_gym.estimation import MultiObjectTracker
        from av_gym.sensors.detector import Detector

        det_cfg = {k: v for k, v in dict(det_cfg).items() if k != "frame"}
        allowed = [p for p in inspect.signature(Detector.__init__).parameters if p not in ("self", "env", "frame")]
        bad = sorted(set(det_cfg) - set(allowed))
        if bad:
            raise ValueError(f"shield.detector.{bad[0]} is not a parameter of Detector; allowed: {allowed}")
        try:
            # Around the bare scenario env: its own sensor, independent of the agent's sensor stack.
            self.detector = Detector(self.env.unwrapped, frame="world", **det_cfg)
        except ValueError as exc:
            raise ValueError(str(exc).replace("sensors.detector", "shield.detector")) from None
        trk_defaults = {"sigma_pos0": det_cfg.get("sigma_pos0", 0.3), "sigma_pos_k": det_cfg.get("sigma_pos_k", 0.01),
                        "sigma_vel": det_cfg.get("sigma_vel", 0.5)}
        try:
            self.tracker = MultiObjectTracker(**{**trk_defaults, **dict(trk_cfg)})
        except TypeError as exc:
            raise ValueError(f"shield.tracker: {exc}") from None
        except ValueError as exc:
            raise ValueError(f"shield.{exc}") from None

    # ------------------------------------------------------------------------------------------- episode
    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        u = self.env.unwrapped
        self.sim_dt = 1.0 / float(u.config["simulation_frequency"])
        lanes = u.route.lanes if hasattr(u, "route") else [u.road.network.get_lane(i) for i in u.vehicle.route]
        self.route, self.driven = _route_tables(lanes)
        self.stop_line_s = float(self.route.starts[1])
        self.clear_s = float(self.route.starts[2]) if len(self.route.starts) > 2 else self.route.length
        self.approach_heading = float(self.route.heading[0])
        self._route_k = 0
        self._latched = False
        self._clear_for = 0.0
        self._stopped_at = None
        self._ema: dict[Any, np.ndarray] = {}
        self._prev_v: dict[Any, np.ndarray] = {}
        self._prev_t = None
        self._brake_time = float("nan")
        self._stop_position = float("nan")
        self.actuator.release()
        self._install_actuator(u.vehicle)
        if self.target_model == "map":
            if self._hypotheses is None:
                self._hypotheses = LaneHypotheses(u.road.network)
            self._hypotheses.network = u.road.network
        if self.detector is not None:
            self.detector.rng = sensor_rng(self.env, "aeb_detector")
            self.detector.on_reset()
            self.tracker.reset()
        self._info = self._make_info(MONITOR, float("inf"), 0.0, -1, False, False, None)
        info.update(self._info)
        return obs, info

    def _install_actuator(self, vehicle) -> None:
        """Patch this ego instance so that, while the brake is commanded, every simulation tick ends with the
        actuator's acceleration, whatever the vehicle's own controller (MDPVehicle's speed controller for
        discrete actions, RouteFollowingVehicle's commanded acceleration for continuous) asked for."""
        vehicle.act = _ActuatedAct(vehicle.act, vehicle, self)

    def step(self, action):
        stage, ttc, horizon, target, active, infeasible = self._decide()
        override = stage == BRAKE
        applied = self._throttle_cut(action) if override else action
        obs, reward, terminated, truncated, info = self.env.step(applied)
        ego = self.env.unwrapped.vehicle
        if override and np.isnan(self._stop_position) and ego.speed < STOP_SPEED:
            self._stop_position = self._front_past_line()
        self._info = self._make_info(stage, ttc, horizon, target, active, infeasible, applied)
        info.update(self._info)
        return obs, reward, terminated, truncated, info

    def _make_info(self, stage, ttc, horizon, target, active, infeasible, applied) -> dict:
        return {"aeb_stage": int(stage), "aeb_ttc": float(ttc), "aeb_horizon": float(horizon),
                "aeb_override": bool(stage == BRAKE), "shield_override": bool(stage == BRAKE),
                "aeb_target_id": int(target), "aeb_active": bool(active), "aeb_infeasible": bool(infeasible),
                "aeb_brake_time": self._brake_time, "aeb_stop_position": self._stop_position,
                "aeb_action": None if applied is None else (np.asarray(applied).tolist())}

    def _throttle_cut(self, action):
        """While braking the agent may not accelerate: FASTER becomes IDLE (its set-point is kept for after the
        release), a continuous command is capped at zero acceleration. The deceleration itself comes from the
        actuator, after its delay."""
        u = self.env.unwrapped
        if isinstance(action, (int, np.integer)) or np.ndim(action) == 0:
            return 1 if int(action) == 2 else action
        cruise = u.cruise_action()
        return np.minimum(np.asarray(action, dtype=np.float32), cruise)

    # ------------------------------------------------------------------------------------------- state
    def _time(self) -> float:
        u = self.env.unwrapped
        return u.steps / float(u.config["simulation_frequency"])

    def _ego(self) -> dict:
        ego = self.env.unwrapped.vehicle
        self._route_k, s_lane, lat = self.env.unwrapped.route.locate(ego.position, self._route_k) \
            if hasattr(self.env.unwrapped, "route") else (0, 0.0, 0.0)
        s = float(self.route.starts[self._route_k] + s_lane)
        steering = float(ego.action.get("steering", 0.0)) if ego.action else 0.0
        beta = np.arctan(0.5 * np.tan(steering))
        return {"xy": np.array(ego.position, dtype=float), "heading": float(ego.heading),
                "speed": float(ego.speed), "velocity": np.array(ego.velocity, dtype=float),
                "accel": float(ego.action.get("acceleration", 0.0)) if ego.action else 0.0,
                "yaw_rate": float(ego.speed * np.sin(beta) / (ego.LENGTH / 2)), "steering": steering,
                "size": (float(ego.LENGTH), float(ego.WIDTH)), "s": s, "lane": self._route_k,
                "set_speed": float(ego.target_speed) if hasattr(ego, "speed_index") else None,
                "speed_limit": float(getattr(ego.lane, "speed_limit", None) or self.go_speed)}

    def _objects(self, ego: dict) -> tuple[np.ndarray, list, list]:
        """Other vehicles ``(N, 7)`` [x, y, vx, vy, heading, length, width], a persistent key per row (for the
        finite differences) and the id reported in ``info`` (index in ``truth["others"]``, or the track id)."""
        u = self.env.unwrapped
        if self.mode == "ground_truth":
            vehicles = [v for v in u.road.vehicles if v is not u.vehicle]
            rows = [[v.position[0], v.position[1], v.velocity[0], v.velocity[1], v.heading, v.LENGTH, v.WIDTH]
                    for v in vehicles]
            self._lanes = [getattr(v, "lane_index", None) for v in vehicles]
            # Keyed by the vehicle objects, not id(): a deep copy of the stack (the lookahead oracle) then maps the
            # history to the copied vehicles, and a removed vehicle's id can never hand its history to a new one.
            return np.array(rows, dtype=float).reshape(-1, 7), vehicles, list(range(len(vehicles)))
        rows = self.detector.measure()
        tracks = self.tracker.step(rows, self._time(), ego["xy"])
        ids = [int(i) for i in self.tracker.track_ids()]
        if self.target_model == "map":  # map matching of each track, as highway-env does for its vehicles
            net = u.road.network
            self._lanes = [net.get_closest_lane_index(tr[0:2], tr[4]) for tr in tracks]
        return tracks, [("track", i) for i in ids], ids

    def _accelerations(self, keys: list, velocities: np.ndarray, t: float) -> np.ndarray:
        """Finite-difference accelerations (m/s², world frame) low-passed by an EMA, per object key."""
        out = np.zeros((len(keys), 2))
        dt = None if self._prev_t is None else t - self._prev_t
        for i, (k, v) in enumerate(zip(keys, velocities)):
            if dt and dt > 1e-9 and k in self._prev_v:
                raw = (v - self._prev_v[k]) / dt
                self._ema[k] = self.accel_alpha * raw + (1 - self.accel_alpha) * self._ema.get(k, np.zeros(2))
            out[i] = self._ema.get(k, np.zeros(2))
            self._prev_v[k] = np.array(v, dtype=float)
        present = set(keys)
        for store in (self._prev_v, self._ema):
            for k in [k for k in store if k not in present]:
                del store[k]
        return out

    def _front_past_line(self) -> float:
        ego = self._ego()
        return ego["s"] + 0.5 * ego["size"][0] - self.stop_line_s

    def _is_active(self, ego: dict) -> bool:
        if self.variant == "standard":
            return True
        front_to_line = self.stop_line_s - (ego["s"] + 0.5 * ego["size"][0])
        return ego["s"] < self.clear_s and front_to_line <= self.activation_distance

    # ------------------------------------------------------------------------------------------- decision
    def _decide(self):
        """``(stage, ttc, horizon, target, active, infeasible)`` for the state at the start of this step."""
        t = self._time()
        ego = self._ego()
        others, keys, out_ids = self._objects(ego)
        ego_key = "__ego__"
        accels = self._accelerations([ego_key, *keys], np.vstack([ego["velocity"][None], others[:, 2:4]]), t)
        self._prev_t = t
        active = self._is_active(ego)
        if not active and self.variant != "improved":
            self._release()
            return MONITOR, float("inf"), 0.0, -1, False, False
        if self.variant == "paper":
            out = self._decide_paper(ego, others, accels[0], accels[1:], t)
        elif self.variant == "standard":
            out = self._decide_standard(ego, others, t)
        else:
            out = self._decide_improved(ego, others, accels[1:], t, active)
        stage, ttc, horizon, target, infeasible = out
        if stage == BRAKE and np.isnan(self._brake_time):
            self._brake_time = t
        target_key = out_ids[target] if 0 <= target < len(out_ids) else -1
        return stage, ttc, horizon, target_key, active, infeasible

    def _latch(self, t: float) -> None:
        self._latched = True
        self._clear_for = 0.0
        self._stopped_at = None
        self.actuator.engage(t)

    def _release(self) -> None:
        self._latched = False
        self._clear_for = 0.0
        self._stopped_at = None
        self.actuator.release()

    def _latched_until_standstill(self, speed: float, t: float) -> bool:
        """Paper/standard latch: brake until standstill, then hold it ``standstill_hold`` s (None: as long as
        the function is active); True while the brake stays on."""
        if speed >= STOP_SPEED and self._stopped_at is None:
            return True
        if self._stopped_at is None:
            self._stopped_at = t
        if self.standstill_hold is None or t - self._stopped_at < self.standstill_hold - 1e-9:
            return True
        self._release()
        return False

    # paper ------------------------------------------------------------------------------------------------
    def _decide_paper(self, ego, others, a_ego, a_others, t):
        horizon = paper_horizon(ego["speed"])
        ttc, target = float("inf"), -1
        if len(others):
            c, s = np.cos(self.approach_heading), np.sin(self.approach_heading)
            rot = np.array([[c, s], [-s, c]])  # world → approach frame (x along the approach)
            rel = (others[:, 0:2] - ego["xy"]) @ rot.T
            phi0 = -_wrap(ego["heading"] - self.approach_heading)  # + = turning left (heading decreases here)
            ttc, target = paper_ttc(rel, rot @ ego["velocity"], rot @ a_ego, others[:, 2:4] @ rot.T,
                                    a_others @ rot.T, others[:, 5:7], ego["size"], phi0, -ego["yaw_rate"],
                                    horizon, self.T, self.half_accel_term, self.limits)
        if self._latched and self._latched_until_standstill(ego["speed"], t):
            return BRAKE, ttc, horizon, target, False
        if ttc <= self.ttc_brake:
            self._latch(t)
            return BRAKE, ttc, horizon, target, False
        return (WARN if ttc <= horizon else MONITOR), ttc, horizon, target, False

    # standard ---------------------------------------------------------------------------------------------
    def _decide_standard(self, ego, others, t):
        ttc, target = standard_ttc(ego["xy"], ego["heading"], ego["speed"], ego["size"], others,
                                   self.lateral_margin)
        if self.steering_inhibit is not None and abs(ego["steering"]) > self.steering_inhibit:
            ttc, target = float("inf"), -1
        if self._latched and self._latched_until_standstill(ego["speed"], t):
            return BRAKE, ttc, self.warn_ttc, target, False
        if ttc <= self.ttc_brake:
            self._latch(t)
            return BRAKE, ttc, self.warn_ttc, target, False
        return (WARN if ttc <= self.warn_ttc else MONITOR), ttc, self.warn_ttc, target, False

    # improved ---------------------------------------------------------------------------------------------
    def _relevant(self, ego, others) -> np.ndarray:
        """Mask of objects that matter: not a vehicle following the ego in its lane."""
        if not len(others):
            return np.zeros(0, dtype=bool)
        c, s = np.cos(ego["heading"]), np.sin(ego["heading"])
        rel = others[:, 0:2] - ego["xy"]
        x_rel, y_rel = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
        same_dir = np.abs((others[:, 4] - ego["heading"] + np.pi) % (2 * np.pi) - np.pi) < np.radians(45)
        follower = same_dir & (x_rel < -0.5 * ego["size"][0]) & (np.abs(y_rel) < 2.5)
        return ~follower

    def _horizon(self, s0: float, ds: np.ndarray, t: np.ndarray) -> float:
        """Time (s) until the ego's centre has passed the end of the turn (the conflict zone is cleared) under the
        distance profile ``ds`` at times ``t``, plus one slice, clipped to [horizon_min, horizon_max]."""
        reached = s0 + ds >= self.clear_s
        h = t[int(np.argmax(reached))] + self.T if reached.any() else self.horizon_max
        return float(np.clip(h, self.horizon_min, self.horizon_max))

    def _decide_improved(self, ego, others, a_others, t, in_turn: bool = True):
        """Outside the turn window (``in_turn`` False: far up the approach, or past the turn) only the emergency
        part runs — a forward AEB on the predicted footprints (the paper's function also sat inside the car's
        existing AEB) — so, e.g., a slower car ahead on the exit lane is still braked for."""
        keep = self._relevant(ego, others)
        others, a_others = others[keep], a_others[keep]
        v, a, s0 = ego["speed"], ego["accel"], ego["s"]
        t_long = self.T * np.arange(1, int(round(max(self.horizon_max, 4.0 + self.horizon_min) / self.T)) + 1)
        if self.target_model == "map":
            lanes = [lane for lane, k in zip(self._lanes, keep) if k]
            obj_xy, obj_h, owner, turn = self._hypotheses.predict(others, lanes, t_long)
            # A vehicle that would turn into the ego's lane behind it has to yield to the ego: its map
            # hypotheses never count as running into the ego from behind.
            rear = turn | self.ignore_rear
        else:
            obj_xy, obj_h = object_predict(others, t_long, a_others if self.target_model == "ca" else None)
            owner = np.arange(len(others))
            rear = np.full(len(owner), self.ignore_rear)
        idx = np.flatnonzero(keep)[owner]  # hypothesis → row of the full object list
        size = np.asarray(others[owner, 5:7], dtype=float).reshape(-1, 2)

        def ttc_of(ds: np.ndarray, n: int, margin: float) -> tuple[float, int]:
            xy, h = self.driven.poses(s0, ds[:n], profile_speeds(ds[:n], t_long[:n], v))
            return footprint_ttc(xy, h, ego["size"], obj_xy[:n], obj_h[:n], size, t_long[:n], margin, rear)

        ds_cruise = self._continue_profile(ego, t_long)
        horizon = self._horizon(s0, ds_cruise, t_long)
        n = int(round(horizon / self.T))
        ttc, target = ttc_of(ds_cruise, n, self.margin)
        target_out = int(idx[target]) if target >= 0 else -1

        if self._latched:
            # Release rule: the ego setting off again (or carrying on, if still rolling) must be predicted
            # conflict-free, with the larger release margin (hysteresis), for release_hold s.
            ttc_go, tgo = float("inf"), -1
            profiles = [ds_cruise] if ego["set_speed"] is not None else [ds_cruise, self._go_profile(ego, t_long)]
            for ds_p in profiles:  # commanded acceleration: safe whether the agent holds its speed or sets off
                n_p = int(round(self._horizon(s0, ds_p, t_long) / self.T))
                ttc_p, tg_p = ttc_of(ds_p, n_p, self.release_margin)
                if ttc_p < ttc_go:
                    ttc_go, tgo = ttc_p, tg_p
            self._clear_for = self._clear_for + self.T if not np.isfinite(ttc_go) else 0.0
            if not np.isfinite(ttc_go) and self._clear_for + 1e-9 >= self.release_hold:
                self._release()
            else:
                t_out = int(idx[tgo]) if tgo >= 0 else target_out
                return BRAKE, min(ttc, ttc_go), horizon, t_out, False
        if not np.isfinite(ttc):
            return MONITOR, ttc, horizon, -1, False

        front_to_line = self.stop_line_s - (s0 + 0.5 * ego["size"][0])
        d_stop, _ = self.actuator.stopping_distance(v, a, self.sim_dt)
        stop_line_trigger = in_turn and 0.0 <= front_to_line <= d_stop + v * self.T + self.stop_margin
        emergency = False
        if ttc <= self.ttc_brake:
            ttc_raw, _ = ttc_of(ds_cruise, n, 0.0)
            emergency = ttc_raw <= self.ttc_brake
        if not (stop_line_trigger or emergency):
            return (WARN if in_turn or ttc <= self.warn_ttc else MONITOR), ttc, horizon, target_out, False
        if self.feasibility and self._parked_in_path(v, a, s0, ego, obj_xy, obj_h, size, t_long, rear):
            return WARN, ttc, horizon, target_out, True
        self._latch(t)
        return BRAKE, ttc, horizon, target_out, False

    def _continue_profile(self, ego: dict, t: np.ndarray) -> np.ndarray:
        """Distance (m) along the route at times ``t`` if the ego carries on as it is driven now: for a vehicle
        with a cruise set-point (MDPVehicle, discrete actions) highway-env's first-order speed response to that
        set-point (exact for its controller, including setting off from a standstill); otherwise (commanded
        acceleration) its current acceleration for 1 s, the speed capped at the lane's speed limit (or
        ``go_speed`` from a standstill), never reversing."""
        if ego["set_speed"] is not None:
            return go_profile(ego["speed"], ego["set_speed"], t)
        v_cap = max(ego["speed"], self.go_speed, ego["speed_limit"])
        a = ego["accel"] if ego["speed"] > STOP_SPEED else max(ego["accel"], 0.0)
        return cruise_profile(ego["speed"], a, t, v_max=v_cap)

    def _go_profile(self, ego: dict, t: np.ndarray) -> np.ndarray:
        """Distance (m) at times ``t`` if the brake is released now: the first-order speed response to the
        vehicle's cruise set-point, or to ``go_speed`` (at least the current speed) when it has none — an agent
        commanding acceleration is assumed to set off again."""
        v_set = ego["set_speed"] if ego["set_speed"] is not None else max(self.go_speed, ego["speed"])
        return go_profile(ego["speed"], v_set, t)

    def _parked_in_path(self, v, a, s0, ego, obj_xy, obj_h, size, t_long, rear) -> bool:
        """Brake-feasibility check (digest 003 §9.7): would braking now leave the ego standing where a target
        will hit it? A collision that happens while the ego is still moving is not a reason to hold off (braking
        still mitigates it); one after standstill is."""
        ticks = int(round(self.T / self.sim_dt))
        xs, vs = self.actuator.profile(v, a, t_long[-1] + 1e-9, self.sim_dt)
        ds = xs[ticks - 1::ticks][: len(t_long)]
        stopped = vs[ticks - 1::ticks][: len(t_long)] <= 0.0
        xy, h = self.driven.poses(s0, ds, profile_speeds(ds, t_long[: len(ds)], v))
        ttc, _ = footprint_ttc(xy, h, ego["size"], obj_xy[: len(ds)], obj_h[: len(ds)], size, t_long[: len(ds)],
                               self.margin, rear)
        if not np.isfinite(ttc):
            return False
        k = int(round(ttc / self.T)) - 1
        return bool(stopped[k])


def build_shield(env: gym.Env, params: dict) -> gym.Env:
    """Builder for :func:`av_gym.make.add_shield` (``kind: aeb``): ``params`` are :class:`AEBShield`'s keyword
    arguments (the shield config minus ``name``/``kind``)."""
    import inspect

    allowed = [p for p in inspect.signature(AEBShield.__init__).parameters if p not in ("self", "env")]
    bad = sorted(set(params) - set(allowed))
    if bad:
        raise ValueError(f"shield.{bad[0]} is not a parameter of the AEB shield; allowed: {allowed}")
    return AEBShield(env, **params)
