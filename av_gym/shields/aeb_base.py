""":class:`AEBShield`: what every AEB variant shares (config plumbing, perception, ego state, actuator, latch,
``info``) and the variant registry :data:`AEB_VARIANTS`; the variants are in ``aeb_paper``, ``aeb_standard`` and
``aeb_improved`` (see :mod:`av_gym.shields.aeb` for the design)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from av_gym.actions import check_action
from av_gym.estimation.tracker import TrackerParams
from av_gym.geometry import wrap_angle
from av_gym.params import ParamError, Params
from av_gym.registry import Registry
from av_gym.sensors.base import sensor_rng
from av_gym.sensors.detector import DetectorParams
from av_gym.shields.predict import DrivenPath, RouteTable
from av_gym.shields.actuator import BrakeActuator, _ActuatedAct
from av_gym.shields.aeb_params import _NO_ACCEL, BRAKE, CONFIG_SECTION_KEYS, MONITOR, STOP_SPEED, AEBParams
from av_gym.shields.opinion import Opinion, check_opinion


# ----------------------------------------------------------------------------------------------- info sentinels
NOT_YET = math.inf
"""``info["aeb_brake_time"]`` / ``info["aeb_stop_position"]`` before the event (s / m): a float, so that a vector env
batches the key into a float array whichever env comes first (None raised in Gymnasium's ``_add_info``), and not
NaN, so that two identical runs' infos compare equal (Gymnasium's ``check_env``; NaN != NaN). A time at infinity:
the brake has not come."""
NO_ACTION = -1
"""``info["aeb_action"]`` (discrete actions) at reset, before any action was passed on: an int like the actions."""


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


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _wrap(a: float) -> float:
    return float(wrap_angle(a))


def find_shield(env: gym.Env) -> "AEBShield | None":
    """The AEB shield in a wrapped env stack (None if there is none)."""
    e = env
    while e is not None:
        if isinstance(e, AEBShield):
            return e
        e = getattr(e, "env", None)
    return None


AEB_VARIANTS = Registry("variant", {
    "paper": "av_gym.shields.aeb_paper:PaperAEB",
    "improved": "av_gym.shields.aeb_improved:ImprovedAEB",
    "standard": "av_gym.shields.aeb_standard:StandardAEB",
})
"""``shield.variant`` → the AEB wrapper class with that decision logic; its ``Params`` is the section's fields.
Named as ``"module:Class"`` strings (as the sensor registry names its kinds): the base imports no variant (the
variants import the base), the order of the names is this table's whatever was imported first, and a variant's
module is loaded when the variant is first asked for."""


class AEBShield(gym.Wrapper):
    """Predictive AEB safety shield, the machinery every variant shares (perception, ego state, actuator, latch,
    ``info``); the decision logic is a subclass per variant, registered in :data:`AEB_VARIANTS`. See the module
    docstring for variants, modes and ``info`` keys.

    ``ImprovedAEB(env, params=None, **overrides)`` (likewise each variant) with its own Params; from a config
    section (``variant`` + fields) :meth:`from_config`, as :func:`av_gym.make.add_shield` does."""

    Params: ClassVar[type[AEBParams]] = AEBParams
    variant: ClassVar[str] = ""
    decides_outside_window: ClassVar[bool] = False  # improved: a forward AEB outside the turn window
    p: AEBParams  # the parameters: every decision reads them here (a field copied onto self would be a second copy)
    # The counterfactual labeller's handles (eval/interventions.py); neither changes a decision.
    on_intervention: Any = None  # called as on_intervention(shield, action) when a brake starts, before the step
    bypass: bool = False  # True: pass the agent's action through untouched and decide nothing
    target_xy: np.ndarray | None = None  # position of the object the last decision named (NaN when none)
    _opinion: Opinion | None = None
    withheld: int = 0  # stop-line brakes the opinion withheld this episode
    _proposed: Any = None  # the agent's action for the step being decided (the improved variant's check_action)

    # ------------------------------------------------------------------------------------------- config
    @classmethod
    def variant_class(cls, variant: str, where: str = "") -> type["AEBShield"]:
        """The wrapper class of ``variant`` (a :class:`ParamError` naming the allowed ones otherwise): the
        variants registered so far, each by its own module; :mod:`av_gym.shields.aeb` imports them all."""
        if variant not in AEB_VARIANTS:
            raise ParamError(f"{_join(where, 'variant')} must be one of {AEB_VARIANTS.names()}, got {variant!r}")
        return AEB_VARIANTS.get(variant)

    @classmethod
    def _split(cls, section: Mapping) -> tuple[str, dict]:
        values = {k: v for k, v in section.items() if k not in ("name", "kind", "variant")}
        return section.get("variant", "improved"), values

    @classmethod
    def from_config(cls, env: gym.Env, section: Mapping, where: str = "") -> "AEBShield":
        """The shield a ``shield`` config section asks for: ``variant`` (default ``improved``) picks the class, the
        other fields (``name``/``kind`` aside) are its Params. A :class:`ParamError` names the field under
        ``where`` (the section's config path, e.g. ``shield``)."""
        variant, values = cls._split(section)
        sub = cls.variant_class(variant, where)
        params = sub.Params.from_mapping(values, where, what=f"a parameter of the AEB shield's {variant} variant")
        try:
            return sub(env, params)
        except ParamError as exc:  # the scenario check: a field-relative message
            raise ParamError(_join(where, str(exc))) from None

    @classmethod
    def config_problems(cls, section: Mapping, where: str = "") -> list[str]:
        """Every problem of a ``shield`` section (``kind: aeb``), one line each naming the field under ``where``;
        what :meth:`from_config` would refuse."""
        variant, values = cls._split(section)
        try:
            sub = cls.variant_class(variant, where)
        except ParamError as exc:
            return [str(exc)]
        return sub.Params.problems_of(values, where, what=f"a parameter of the AEB shield's {variant} variant")

    @classmethod
    def config_defaults(cls) -> dict:
        """This variant's Hydra defaults (``/aeb/<variant>``, conf/__init__.py): its Params' values, the detector
        and tracker sections with the fields in :data:`CONFIG_SECTION_KEYS`."""
        node = cls.Params().as_dict()
        for key, keep in CONFIG_SECTION_KEYS.items():
            node[key] = {k: node[key][k] for k in keep}
        return node

    # ------------------------------------------------------------------------------------------- construction
    def __init__(self, env: gym.Env, params: AEBParams | None = None, **overrides) -> None:
        if type(self) is AEBShield:
            raise TypeError("AEBShield is the variants' base: use AEBShield.from_config(env, section) or a variant "
                            f"class ({AEB_VARIANTS.names()} in AEB_VARIANTS)")
        p = self.p = self.Params.build(params, **overrides)
        super().__init__(env)
        if getattr(env.unwrapped, "scenario", None) != "left_turn":
            raise ParamError(f"kind aeb works on the left_turn scenario only, not "
                             f"{getattr(env.unwrapped, 'scenario', '?')!r}")
        self.actuator = BrakeActuator(p.brake)
        self.detector = self.tracker = None
        self._lanes: list = []
        if p.mode == "perceived":
            self._build_perception(p.detector, p.tracker)

    @property
    def params(self) -> AEBParams:
        """The parameters the shield was built with (:attr:`p`), under the constructor's name."""
        return self.p

    @property
    def ttc_brake(self) -> float:
        """s, the emergency threshold (``p.ttc_brake``): what a caller compares an ``aeb_ttc`` with."""
        return self.p.ttc_brake

    @property
    def opinion(self) -> Opinion | None:
        """The second opinion asked before a brake at the stop line (never before an emergency brake): an
        :class:`~av_gym.shields.opinion.Opinion`, whose ``go_is_safe`` True withholds the brake. Installed by
        whoever builds the shield: the library has none of its own."""
        return self._opinion

    @opinion.setter
    def opinion(self, opinion: Opinion | None) -> None:
        check_opinion(opinion)
        self._opinion = opinion

    @property
    def needs_lanes(self) -> bool:
        """Whether the decision reads the objects' lane indices (the improved variant's map-based models)."""
        return False

    # ------------------------------------------------------------------------------------------- perception
    def _build_perception(self, detector: DetectorParams, tracker: TrackerParams) -> None:
        from av_gym.estimation import MultiObjectTracker
        from av_gym.sensors.detector import Detector

        # Around the bare scenario env: its own sensor, independent of the agent's sensor stack; world frame
        # whatever the section says (the tracker and the prediction work in world coordinates).
        self.detector = Detector(self.env.unwrapped, dataclasses.replace(detector, frame="world"))
        self.tracker = MultiObjectTracker(tracker)

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
        self._on_reset(u)
        if self.detector is not None:
            self.detector.rng = sensor_rng(self.env, "aeb_detector")
            self.detector.on_reset()
            self.tracker.reset()
        self.withheld = 0
        if self.opinion is not None:
            self.opinion.reset()
            self.opinion.observe(self.env, obs)
        self._info = self._make_info(MONITOR, float("inf"), 0.0, -1, False, False, None)
        info.update(self._info)
        return obs, info

    def _on_reset(self, u) -> None:
        """A variant's own episode start (``u``: the scenario env, reset)."""

    def _install_actuator(self, vehicle) -> None:
        """Patch this ego instance so that, while the brake is commanded, every simulation tick ends with the
        actuator's acceleration, whatever the vehicle's own controller (MDPVehicle's speed controller for
        discrete actions, RouteFollowingVehicle's commanded acceleration for continuous) asked for."""
        vehicle.act = _ActuatedAct(vehicle.act, vehicle, self)

    def step(self, action):
        check_action(self.action_space, action)  # before _decide: a NaN would crash its numba predictor
        if self.bypass:  # a counterfactual replay (eval/interventions.py): the agent's action, no shield
            obs, reward, terminated, truncated, info = self.env.step(action)
            self._info = self._make_info(MONITOR, float("inf"), 0.0, -1, False, False, action)
            info.update(self._info)
            return obs, reward, terminated, truncated, info
        self._proposed = action  # what the agent asks for this step (an action filter checks what it is given)
        stage, ttc, horizon, target, active, infeasible = self._decide()
        override = stage == BRAKE
        if override and not self._info["aeb_override"] and self.on_intervention is not None:
            # before the env steps: the hook may copy the whole stack and replay this step without the brake
            self.on_intervention(self, action)
        applied = self._throttle_cut(action) if override else action
        obs, reward, terminated, truncated, info = self.env.step(applied)
        if self.opinion is not None:
            self.opinion.observe(self.env, obs)
        ego = self.env.unwrapped.vehicle
        if override and np.isnan(self._stop_position) and ego.speed < STOP_SPEED:
            self._stop_position = self._front_past_line()
        self._info = self._make_info(stage, ttc, horizon, target, active, infeasible, applied)
        info.update(self._info)
        return obs, reward, terminated, truncated, info

    def switch_off(self) -> None:
        """Bypass this shield from now on and let go of any brake: the driver alone (a counterfactual replay, or
        an oracle's own simulated future, on a deep copy of the stack)."""
        self.on_intervention, self.bypass = None, True
        self.actuator.release()

    def _make_info(self, stage, ttc, horizon, target, active, infeasible, applied) -> dict:
        """The shield's ``info`` keys (:mod:`av_gym.shields.aeb`), each with one type in every step and at reset:
        Gymnasium's vector envs batch a key into an array typed by the first env's value, so None beside a number
        (one env just reset, the other driving) raised a TypeError in ``_add_info``."""
        return {"aeb_stage": int(stage), "aeb_ttc": float(ttc), "aeb_horizon": float(horizon),
                "aeb_override": bool(stage == BRAKE), "shield_override": bool(stage == BRAKE),
                "aeb_target_id": int(target), "aeb_active": bool(active), "aeb_infeasible": bool(infeasible),
                "aeb_brake_time": _or_not_yet(self._brake_time), "aeb_stop_position": _or_not_yet(self._stop_position),
                "aeb_action": self._action_info(applied), "aeb_withheld": int(self.withheld)}

    def _action_info(self, applied) -> int | np.ndarray:
        """``info["aeb_action"]``: the action passed on to the env, an int (discrete actions; :data:`NO_ACTION`
        before the first step) or a float32 array of the action space's shape (continuous; NaN before the first
        step, an info the determinism check never compares)."""
        space = self.action_space
        if isinstance(space, gym.spaces.Discrete):
            return NO_ACTION if applied is None else int(applied)
        if applied is None:
            return np.full(space.shape, np.nan, dtype=np.float32)
        return np.asarray(applied, dtype=np.float32).reshape(space.shape)

    def _second_opinion_withholds(self) -> bool:
        """Whether the second opinion (if any) finds going on safe, so that a stop-line brake is withheld."""
        if self.opinion is None or not self.opinion.go_is_safe(self.env):
            return False
        self.withheld += 1
        return True

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
                "speed_limit": getattr(ego.lane, "speed_limit", None)}

    def _objects(self, ego: dict) -> tuple[np.ndarray, list, list]:
        """Other vehicles ``(N, 7)`` [x, y, vx, vy, heading, length, width], a persistent key per row (for the
        finite differences) and the id reported in ``info`` (index in ``truth["others"]``, or the track id)."""
        u = self.env.unwrapped
        if self.p.mode == "ground_truth":
            vehicles = [v for v in u.road.vehicles if v is not u.vehicle]
            state = np.array([(v.position[0], v.position[1], v.speed, v.heading, v.LENGTH, v.WIDTH)
                              for v in vehicles], dtype=float).reshape(-1, 6)
            # highway-env's Vehicle.velocity (speed x [cos, sin] of the heading) for all at once: the same products
            # (numpy's cos/sin give an array the values they give each element), without ~20 property calls
            speed, heading = state[:, 2:3], state[:, 3]
            rows = np.hstack([state[:, 0:2], speed * np.stack([np.cos(heading), np.sin(heading)], axis=1),
                              state[:, 3:6]])
            self._lanes = [getattr(v, "lane_index", None) for v in vehicles]
            # Keyed by the vehicle objects, not id(): a deep copy of the stack (the lookahead oracle) then maps the
            # history to the copied vehicles, and a removed vehicle's id can never hand its history to a new one.
            return rows, vehicles, list(range(len(vehicles)))
        rows = self.detector.measure()
        tracks = self.tracker.step(rows, self._time(), ego["xy"])
        ids = [int(i) for i in self.tracker.track_ids()]
        if self.needs_lanes:  # map matching of each track, as highway-env does for its vehicles
            net = u.road.network
            self._lanes = [net.get_closest_lane_index(tr[0:2], tr[4]) for tr in tracks]
        return tracks, [("track", i) for i in ids], ids

    def _accelerations(self, keys: list, velocities: np.ndarray, t: float) -> np.ndarray:
        """Finite-difference accelerations (m/s², world frame) low-passed by an EMA, per object key (all keys at once:
        the same element-wise arithmetic as one key at a time, without ~20 small numpy calls per decision)."""
        velocities = np.array(velocities, dtype=float).reshape(-1, 2)
        dt = None if self._prev_t is None else t - self._prev_t
        if dt and dt > 1e-9:
            seen = [i for i, k in enumerate(keys) if k in self._prev_v]
            if seen:
                prev = np.array([self._prev_v[keys[i]] for i in seen])
                ema = np.array([self._ema.get(keys[i], _NO_ACCEL) for i in seen])
                raw = (velocities[seen] - prev) / dt
                alpha = self.p.accel_alpha
                self._ema.update(zip([keys[i] for i in seen], alpha * raw + (1 - alpha) * ema))
        out = np.array([self._ema.get(k, _NO_ACCEL) for k in keys], dtype=float).reshape(-1, 2)
        self._prev_v = dict(zip(keys, velocities))  # keys no longer present are dropped, as from the EMA
        self._ema = {k: self._ema[k] for k in keys if k in self._ema}
        return out

    def _decision_accels(self, ego: dict, others: np.ndarray, keys: list, t: float) -> np.ndarray:
        """(N + 1, 2) m/s²: the ego's EMA acceleration, then each road user's (:meth:`_accelerations`)."""
        return self._accelerations(["__ego__", *keys], np.vstack([ego["velocity"][None], others[:, 2:4]]), t)

    def _front_past_line(self) -> float:
        ego = self._ego()
        return ego["s"] + 0.5 * ego["size"][0] - self.stop_line_s

    def _is_active(self, ego: dict) -> bool:
        """Inside the turn window: from ``activation_distance`` before the stop line until the turn is cleared."""
        front_to_line = self.stop_line_s - (ego["s"] + 0.5 * ego["size"][0])
        return ego["s"] < self.clear_s and front_to_line <= self.p.activation_distance

    # ------------------------------------------------------------------------------------------- decision
    def _decide(self):
        """``(stage, ttc, horizon, target, active, infeasible)`` for the state at the start of this step."""
        t = self._time()
        ego = self._ego()
        others, keys, out_ids = self._objects(ego)
        self._keys = keys  # a persistent key per row of ``others`` (for a variant's own per-object memory)
        if hasattr(self.p, "accel_alpha"):  # the turn-window variants' EMA (TurnParams)
            accels = self._decision_accels(ego, others, keys, t)
        else:  # a variant that reads no accelerations
            accels = np.zeros((len(others) + 1, 2))
        self._prev_t = t
        active = self._is_active(ego)
        if not active and not self.decides_outside_window:
            self._release()
            return MONITOR, float("inf"), 0.0, -1, False, False
        stage, ttc, horizon, target, infeasible = self._decide_variant(ego, others, accels[0], accels[1:], t, active)
        if stage == BRAKE and np.isnan(self._brake_time):
            self._brake_time = t
        target_key = out_ids[target] if 0 <= target < len(out_ids) else -1
        self.target_xy = others[target, 0:2].copy() if 0 <= target < len(others) else np.full(2, np.nan)
        return stage, ttc, horizon, target_key, active, infeasible

    def _decide_variant(self, ego, others, a_ego, a_others, t, active):
        """The variant's decision: ``(stage, ttc, horizon, target row, infeasible)``; ``a_ego``/``a_others``: the
        EMA finite-difference accelerations (zeros where the variant reads none); ``active``: inside the turn
        window (always True for a variant that decides only there)."""
        raise NotImplementedError

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
        hold = self.p.standstill_hold
        if hold is None or t - self._stopped_at < hold - 1e-9:
            return True
        self._release()
        return False


def _or_not_yet(value: float) -> float:
    """``value`` as a float, :data:`NOT_YET` where it is NaN (not yet happened)."""
    return NOT_YET if np.isnan(value) else float(value)
