"""Predictive automatic emergency braking (AEB) shield for the unprotected left turn (issue 5; digest 003).

:class:`AEBShield` is a ``gymnasium.Wrapper`` that sits between any agent and the left-turn env (it wraps the
sensed env, see :func:`av_gym.make.add_shield`). It never needs the agent's cooperation: every policy step (10 Hz,
T = 0.1 s) it predicts the ego and the other vehicles, decides a stage — 0 monitor, 1 warn, 2 brake — and while
braking it cuts the throttle in the agent's action and applies a :class:`BrakeActuator` directly to the ego
vehicle, whatever the agent commands.

Variants (``variant``): one wrapper class each, registered in :data:`AEB_VARIANTS` (:class:`PaperAEB`,
:class:`ImprovedAEB`, :class:`StandardAEB`), each with its own parameters (:class:`PaperParams`,
:class:`ImprovedParams`, :class:`StandardParams`: the fields it reads, defaults and reasons) on a common
:class:`AEBParams` (mode, ``ttc_brake``, the brake actuator, the perceived mode's detector and tracker). The
config section ``shield`` (``kind: aeb``, ``variant: ...``) builds one through :meth:`AEBShield.from_config`.


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
    controller cuts the turn by up to 0.6 m and lags 10° in heading, so :class:`av_gym.shields.predict.DrivenPath`
    replays that controller (tabulated per speed) instead of assuming the lane centreline; longitudinally under
    the action the agent proposes for this step, held (``check_action``, issue 17: a safety filter checks the
    action it is given, so an agent that has just chosen to stop is not braked): highway-env's cruise-control
    response through the set-points FASTER/SLOWER step to (discrete actions), or the commanded acceleration
    for 1 s (continuous);
  * the others on every way the road network lets them continue, each hypothesis with its probability, at
    constant speed on the path highway-env's controller drives (``target_model: conflict``, the default since
    issue 17: :class:`av_gym.shields.conflicts.ConflictModel`), or constant-velocity (``cv``, the default
    before), constant-acceleration (``ca``), CV along each lane continuation plus the plain CV hypothesis
    (``map``);
  * footprints as oriented boxes, the ego's grown by ``margin`` m, overlap by the separating-axis test, over a
    **geometry horizon**: the time to clear the turn, clipped to [``horizon_min``, ``horizon_max``];
  * a **stop-line-aware trigger**: while a conflict is predicted, brake once the distance from the front bumper
    to the stop line has come down to the actuator's stopping distance (delay and jerk included) plus one
    decision period and ``stop_margin``, so the car stops just behind the line; otherwise (past that point, or
    outside the turn window, where the shield acts as a forward AEB on the predicted footprints) only an
    emergency brake at TTC ≤ ``ttc_brake`` on the unmargined footprints;
  * a **brake-feasibility check** (003 §9.7): no braking if the braking profile predicts the ego standing still
    in the path of the object braked for when it is hit (a hit while still moving does not stop the brake: it
    mitigates; another road user reaching the standing ego later is a later conflict);
  * a **release rule**: once latched, the brake lets go when the ego setting off again (or carrying on, for a
    continuous agent both) is predicted conflict-free with the larger ``release_margin`` for ``release_hold`` s;
    standing in the box, road users slower than ``release_standing`` count as standing where they are;
  * issue 17's third pass (``target_model: conflict``): the emergency test also predicts a braking road user
    keeping its deceleration (``emergency_accel_time``), and before the line a road user that stands in the box
    after moving may set off (``setoff_speed``: for the stop-line trigger and the release test).
  * Vehicles following the ego in its lane are ignored (they are responsible for their own gap).
- ``standard`` — the baseline of paper 003 §2: ``TTC = Δx/Δv`` for targets ahead in the ego's corridor only,
  warn at TTC ≤ ``warn_ttc``, brake at TTC ≤ ``ttc_brake``, latched until standstill (and held like the paper
  variant), optionally inhibited above
  a steering angle (``steering_inhibit_deg``; off by default, i.e. the most generous standard AEB). Always active.

Modes (``mode``): ``ground_truth`` reads the other vehicles from the simulator; ``perceived`` builds its **own**
:class:`av_gym.sensors.detector.Detector` (the ``detector`` section, world frame, its own random stream
``"aeb_detector"`` from the episode seed) and a :class:`av_gym.estimation.MultiObjectTracker` (``tracker``
section) and uses the confirmed tracks. The shield owns its perception so it works whatever sensors the agent
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

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import gymnasium as gym
import numpy as np

from av_gym.estimation.tracker import TrackerParams
from av_gym.geometry import wrap_angle
from av_gym.params import ParamError, Params, check, param
from av_gym.registry import Registry
from av_gym.sensors.base import sensor_rng
from av_gym.sensors.detector import DetectorParams
from av_gym.sensors.turn_signal import DRIVER_DRAWS, TurnSignalsParams, first_sighting, intended_signal, reported
from av_gym.shields.conflicts import ConflictModel
from av_gym.shields.intent import DriverIntent
from av_gym.shields.predict import (DrivenPath, LaneHypotheses, RouteTable, cruise_profile, footprint_ttc,
                                    go_profile, object_predict, paper_horizon, paper_ttc, profile_speeds,
                                    setpoint_profile, standard_ttc)

STOP_SPEED = 0.1  # m/s, standstill (as av_gym.metrics.left_turn.STOP_SPEED)
_NO_ACCEL = np.zeros(2)  # an object's acceleration before its second sighting (never written to)
MONITOR, WARN, BRAKE = 0, 1, 2


# ----------------------------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class BrakeParams(Params):
    """The brake actuator (digest 003 §9.4 suggestions; none of it is in the paper). The same for every variant,
    so that only the decision logic differs between them."""

    decel: float = param(8.0, "m/s²", gt=0, doc="full AEB braking, ≈ 0.8 g: a typical AEB peak on a dry road")
    delay: float = param(0.15, "s", ge=0, doc="command to onset of deceleration (middle of the 0.1-0.2 s suggested)")
    jerk: float = param(30.0, "m/s³", ge=0, doc="ramp to full deceleration; 0 = a step")


SHIELD_DETECTOR = DetectorParams(miss_rate=0.3, burst_length=5.0, max_range=150.0)
"""The shield's own detector: :class:`DetectorParams` defaults except a miss rate of 30 % of frames per vehicle in
bursts of 5 frames (0.5 s) on average (Gilbert-Elliott chain) and a long (radar-class) range of 150 m: a 60 km/h
target 1.5 s behind a 10 km/h ego is ~110 m away when the ego must decide (docs/aeb.md; 100 m gives 4/99
collisions)."""

TRACKER_FOLLOWS_DETECTOR = ("sigma_pos0", "sigma_pos_k", "sigma_vel")
"""The tracker's measurement noise: the shield's detector's values unless the ``tracker`` section sets them."""

CONFIG_SECTION_KEYS = {"detector": ("miss_rate", "burst_length", "max_range"),
                       "tracker": ("sigma_acc", "min_hits", "max_coast")}
"""The detector and tracker fields the Hydra defaults (``conf/shield/aeb*.yaml`` via ``/aeb/<variant>``) list, so
``shield.detector.miss_rate=0.5`` works on the command line; any other field of theirs is added with
``+shield.detector.<field>=...`` (as before the params port)."""


def _standstill_hold() -> Any:
    return param(2.0, "s", ge=0, doc="how long the brake stays on after standstill before the function hands back "
                                     "to the driver (not in the paper: a typical AEB brake-hold); null = as long "
                                     "as the function is active, as digest 003's prototype; 0 = released at once, "
                                     "the most literal reading")


@dataclass(frozen=True)
class AEBParams(Params):
    """What every AEB variant reads. A partial ``brake``/``detector``/``tracker`` mapping is completed from these
    defaults (the shield's, not the component's own), and the tracker's measurement noise follows the detector's
    unless set (:meth:`with_section_defaults`)."""

    mode: Literal["ground_truth", "perceived"] = param(
        "ground_truth", doc="ground_truth: reads the simulator's vehicles | perceived: its own detector + tracker")
    ttc_brake: float = param(1.5, "s", gt=0, doc="brake at TTC <= this (003 §4.7: the paper triggered at exactly "
                                                 "1.5 s, the 15th slice); improved: the emergency brake past the "
                                                 "stop-line trigger point")
    brake: BrakeParams = param(BrakeParams(), doc="the brake actuator")
    detector: DetectorParams = param(
        SHIELD_DETECTOR, doc="perceived mode only: the shield's OWN detector (world frame, own random stream), so it "
                             "works whatever sensors the agent has and never touches the agent's observation, as a "
                             "car's AEB has its own sensor; defaults: SHIELD_DETECTOR (30 % misses in 5-frame bursts, "
                             "150 m range)")
    tracker: TrackerParams = param(
        TrackerParams(), doc="perceived mode only: the shield's CV Kalman tracker (Hungarian association) on its "
                             "detector; measurement noise = the detector's unless set")

    @classmethod
    def with_section_defaults(cls, values: Mapping) -> dict:
        """``values`` with each partial ``brake``/``detector``/``tracker`` mapping completed from this class's
        defaults, and the tracker's measurement noise (:data:`TRACKER_FOLLOWS_DETECTOR`) from the detector unless
        the tracker section sets it. Values that are not mappings are left to the checks."""
        out = dict(values)
        base = cls()
        for key in ("brake", "detector", "signal_channel"):
            if isinstance(out.get(key), Mapping) and hasattr(base, key):
                out[key] = {**getattr(base, key).as_dict(), **out[key]}
        det = out.get("detector", base.detector)
        det = det.as_dict() if isinstance(det, Params) else det
        trk = out.get("tracker", {})
        if isinstance(det, Mapping) and isinstance(trk, Mapping):
            follow = {k: det[k] for k in TRACKER_FOLLOWS_DETECTOR if k in det}
            out["tracker"] = {**base.tracker.as_dict(), **follow, **trk}
        return out

    @classmethod
    def from_mapping(cls, values: Mapping | None = None, where: str = "", what: str | None = None,
                     **overrides: Any):
        return super().from_mapping(cls.with_section_defaults({**(values or {}), **overrides}), where, what)

    @classmethod
    def problems_of(cls, values: Mapping, where: str = "", what: str | None = None) -> list[str]:
        """:func:`av_gym.params.check` of a config section as :meth:`from_mapping` will build it."""
        if not isinstance(values, Mapping):
            return check(cls, values, where, what)
        return check(cls, cls.with_section_defaults(values), where, what)


@dataclass(frozen=True)
class TurnParams(AEBParams):
    """What the turn-window variants (paper, improved) read besides :class:`AEBParams`."""

    step: float = param(0.1, "s", gt=0, doc="prediction slice T (digest 003 §4.3; the paper's 15th slice = 1.5 s), "
                                            "and the decision period: the 10 Hz policy step")
    activation_distance: float = param(50.0, "m", gt=0, doc="before the stop line at which the turn function "
                                                            "engages: our stand-in for 'left indicator on'")
    accel_alpha: float = param(0.5, gt=0, le=1, doc="EMA of the finite-difference accelerations (003 §9.3); "
                                                    "improved: only for target_model ca")


@dataclass(frozen=True)
class PaperParams(TurnParams):
    """The ``paper`` variant, faithful to paper 003 (digest 003 §4.1-4.8), to reproduce it and show where it falls
    short in highway-env's geometry."""

    half_accel_term: bool = param(False, doc="false = the literal X0 + (V0 + A0 t) t of eqs. (2)-(5); true = the "
                                             "kinematic 1/2 A t²")
    limits: Literal["paper", "aabb"] = param("paper", doc="paper = eqs. (7)-(8) as printed | aabb = corrected "
                                                          "half-extents")
    standstill_hold: float | None = _standstill_hold()


@dataclass(frozen=True)
class ImprovedParams(TurnParams):
    """The ``improved`` variant, our design (issue 5): the ego predicted along its planned route, others
    constant-velocity, oriented-box overlap with a margin, a stop-line-aware brake trigger, a brake-feasibility
    check and a release rule."""

    margin: float = param(0.3, "m", ge=0, doc="the ego footprint is grown by this on every side for the conflict "
                                              "test")
    release_margin: float = param(0.6, "m", ge=0, doc="the larger margin the release test uses (hysteresis)")
    stop_margin: float = param(0.3, "m", ge=0, doc="the stop-line trigger aims this far behind the line")
    horizon_min: float = param(2.0, "s", gt=0, doc="the geometry horizon (time to clear the turn) is clipped to "
                                                   "[horizon_min, horizon_max]")
    horizon_max: float = param(8.0, "s", gt=0, doc="see horizon_min")
    target_model: Literal["cv", "ca", "map", "conflict"] = param(
        "conflict", doc="cv: constant velocity | ca: constant acceleration for 1.5 s (EMA finite differences) | map: "
                        "CV along every lane continuation the road network allows, plus CV | conflict: every lane "
                        "continuation with its probability (turn signals when `signals`), at constant speed on the "
                        "path highway-env's controller drives, CV only off the map "
                        "(av_gym.shields.conflicts.ConflictModel). Default since issue 17: always_proceed+aeb on "
                        "seeds 1000-1099, 4 collisions / 87 arrivals against cv's 8 / 81 and map's 4 / 81")
    hypothesis_min_p: float = param(0.1, ge=0, le=1, doc="target_model conflict: a path hypothesis less likely than "
                                                         "this is dropped (uniform over the continuations: 1/3 "
                                                         "each at the intersection, so only a turn signal prunes)")
    signals: bool = param(True, doc="target_model conflict: read the other drivers' indicators through the shield's "
                                    "own indicator channel (signal_channel), each driver's readings accumulated in a "
                                    "Bayes filter over its turn (av_gym.shields.intent). Default since issue 17's "
                                    "fourth pass: always_proceed+aeb on seeds 1000-1499, fewer collisions, more "
                                    "arrivals and fewer unneeded brakes than without (docs/aeb.md)")
    signal_channel: TurnSignalsParams = param(
        TurnSignalsParams(), doc="signals: the shield's indicator channel (av_gym.sensors.turn_signal's model and "
                                 "defaults: 25 % of drivers never indicate, 5 % the wrong side, 10 % of readings "
                                 "missed, 60 m); all three rates 0 = every driver's intent known (an upper bound: "
                                 "what perfect intent would buy)")
    release_hold: float = param(0.3, "s", ge=0, doc="the release test must pass this long before the brake lets go")
    emergency_accel_time: float = param(
        1.5, "s", ge=0, doc="the emergency test (past the stop-line trigger point) also predicts every road user that "
                            "is braking keeping its measured deceleration this long along each path hypothesis (a "
                            "braking car stops, it never reverses), beside the constant-speed prediction (issue 17, "
                            "third pass: a crossing car braking hard in front of the ego, or two cars colliding there, "
                            "were braked for 0.2-0.3 s late, when the constant-speed footprints first touched); 0 = "
                            "constant speed only (the rule before)")
    release_accel_time: float = param(
        0.0, "s", ge=0, doc="the release test also predicts every road user that is speeding up keeping its "
                            "measured acceleration this long along each path hypothesis, beside the constant-speed "
                            "prediction, so a car setting off again after slowing holds the brake; 0 = constant "
                            "speed only, the default: measured with 1.5 s (issue 17, third pass, always_proceed+aeb "
                            "on seeds 1000-1499) it prevented one collision (seed 1298) and added two (1185, 1231)")
    setoff_speed: float = param(
        2.0, "m/s", ge=0, doc="before the stop line, a road user slower than this in the box (on a lane through "
                              "it) that was faster within setoff_recent s is also predicted setting off along each "
                              "path hypothesis (from 0.5 m/s at setoff_accel), for the stop-line trigger and the "
                              "release test (issue 17, third pass: seed 1215, an oncoming car standing in the box set "
                              "off as the unbraked ego entered it at 9 m/s); 0 = off (the rule before)")
    setoff_accel: float = param(3.0, "m/s²", gt=0, doc="see setoff_speed")
    setoff_recent: float = param(3.0, "s", gt=0, doc="only a road user that was faster than setoff_speed within "
                                                    "this many seconds may set off (a wreck, or a car parked in "
                                                    "the box for long, does not hold the ego at the line)")
    setoff_horizon: float = param(3.0, "s", gt=0, doc="only a conflict with a setting-off car within this many "
                                                      "seconds counts (see setoff_speed)")
    release_standing: float = param(
        1.0, "m/s", ge=0, doc="gridlock release (issue 17, third pass): with the ego braked to a standstill in the "
                              "box (front past the stop line, turn not cleared), the release test predicts every road "
                              "user slower than this standing where it is, not along its path hypotheses, so the ego "
                              "clears the box when what it braked for stands or yields to it; 0 = off (the rule "
                              "before)")
    feasibility: bool = param(True, doc="no braking when it would leave the ego parked in the target's path "
                                        "(003 §9.7)")
    go_speed: float = param(4.5, "m/s", gt=0, doc="speed assumed for setting off when the ego has no cruise "
                                                  "set-point (commanded acceleration)")
    warn_ttc: float = param(2.5, "s", gt=0, doc="outside the turn window: forward-collision warning at TTC <= this")
    check_action: bool = param(True, doc="predict the ego under the action the agent proposes for this step (its new "
                                         "set-point, or its commanded acceleration), as a safety filter checks the "
                                         "action it is given; false: under the set-point before it (the default "
                                         "before issue 17's second pass), which brakes an agent that has just "
                                         "chosen to stop at the line")
    ignore_rear: bool = param(False, doc="never count a hit from behind (a vehicle running into the ego)")

    def relations(self) -> list[str]:
        if self.horizon_max < self.horizon_min:
            return [f"@horizon_max ({self.horizon_max}) must be >= @horizon_min ({self.horizon_min})"]
        return []


@dataclass(frozen=True)
class StandardParams(AEBParams):
    """The ``standard`` variant: the standard AEB baseline of paper 003 §2, always active."""

    warn_ttc: float = param(2.5, "s", gt=0, doc="forward-collision warning at TTC <= this")
    lateral_margin: float = param(0.2, "m", ge=0, doc="added to the corridor half-width")
    steering_inhibit_deg: float | None = param(None, "deg", gt=0, doc="production cars inhibit AEB above a steering "
                                                                      "angle; null = never inhibited (the most "
                                                                      "generous standard AEB)")
    standstill_hold: float | None = _standstill_hold()


# ----------------------------------------------------------------------------------------------- actuator
class BrakeActuator:
    """Brake actuator (:class:`BrakeParams`): after a command, nothing happens for ``delay`` s, then the
    deceleration ramps up at ``jerk`` m/s³ (0 = a step) to ``decel`` m/s² and is held, never reversing the car;
    applied every simulation tick."""

    Params = BrakeParams

    def __init__(self, params: BrakeParams | None = None, **overrides) -> None:
        p = self.params = BrakeParams.build(params, **overrides)
        self.decel, self.delay, self.jerk = p.decel, p.delay, p.jerk
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


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _wrap(a: float) -> float:
    return float(wrap_angle(a))


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


def find_shield(env: gym.Env) -> "AEBShield | None":
    """The AEB shield in a wrapped env stack (None if there is none)."""
    e = env
    while e is not None:
        if isinstance(e, AEBShield):
            return e
        e = getattr(e, "env", None)
    return None


AEB_VARIANTS = Registry("variant")
"""``shield.variant`` → the AEB wrapper class with that decision logic; its ``Params`` is the section's fields."""


class AEBShield(gym.Wrapper):
    """Predictive AEB safety shield, the machinery every variant shares (perception, ego state, actuator, latch,
    ``info``); the decision logic is a subclass per variant, registered in :data:`AEB_VARIANTS`. See the module
    docstring for variants, modes and ``info`` keys.

    ``ImprovedAEB(env, params=None, **overrides)`` (likewise each variant) with its own Params; from a config
    section (``variant`` + fields) :meth:`from_config`, as :func:`av_gym.make.add_shield` does."""

    Params: ClassVar[type[AEBParams]] = AEBParams
    variant: ClassVar[str] = ""
    decides_outside_window: ClassVar[bool] = False  # improved: a forward AEB outside the turn window
    needs_lanes: bool = False  # the objects' lane indices (improved with target_model map)
    accel_alpha: float | None = None  # EMA of the finite-difference accelerations; None: not computed
    # The counterfactual labeller's handles (eval/interventions.py); neither changes a decision.
    on_intervention: Any = None  # called as on_intervention(shield, action) when a brake starts, before the step
    bypass: bool = False  # True: pass the agent's action through untouched and decide nothing
    target_xy: np.ndarray | None = None  # position of the object the last decision named (NaN when none)
    _proposed: Any = None  # the agent's action for the step being decided (the improved variant's check_action)

    # ------------------------------------------------------------------------------------------- config
    @classmethod
    def variant_class(cls, variant: str, where: str = "") -> type["AEBShield"]:
        """The wrapper class of ``variant`` (a :class:`ParamError` naming the allowed ones otherwise)."""
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
        p = self.params = self.Params.build(params, **overrides)
        super().__init__(env)
        if getattr(env.unwrapped, "scenario", None) != "left_turn":
            raise ParamError(f"kind aeb works on the left_turn scenario only, not "
                             f"{getattr(env.unwrapped, 'scenario', '?')!r}")
        self.mode, self.ttc_brake = p.mode, p.ttc_brake
        self.actuator = BrakeActuator(p.brake)
        self.detector = self.tracker = None
        self._lanes: list = []
        if self.mode == "perceived":
            self._build_perception(p.detector, p.tracker)

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
                "speed_limit": getattr(ego.lane, "speed_limit", None)}

    def _objects(self, ego: dict) -> tuple[np.ndarray, list, list]:
        """Other vehicles ``(N, 7)`` [x, y, vx, vy, heading, length, width], a persistent key per row (for the
        finite differences) and the id reported in ``info`` (index in ``truth["others"]``, or the track id)."""
        u = self.env.unwrapped
        if self.mode == "ground_truth":
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
                self._ema.update(zip([keys[i] for i in seen], self.accel_alpha * raw + (1 - self.accel_alpha) * ema))
        out = np.array([self._ema.get(k, _NO_ACCEL) for k in keys], dtype=float).reshape(-1, 2)
        self._prev_v = dict(zip(keys, velocities))  # keys no longer present are dropped, as from the EMA
        self._ema = {k: self._ema[k] for k in keys if k in self._ema}
        return out

    def _front_past_line(self) -> float:
        ego = self._ego()
        return ego["s"] + 0.5 * ego["size"][0] - self.stop_line_s

    def _is_active(self, ego: dict) -> bool:
        """Inside the turn window: from ``activation_distance`` before the stop line until the turn is cleared."""
        front_to_line = self.stop_line_s - (ego["s"] + 0.5 * ego["size"][0])
        return ego["s"] < self.clear_s and front_to_line <= self.activation_distance

    # ------------------------------------------------------------------------------------------- decision
    def _decide(self):
        """``(stage, ttc, horizon, target, active, infeasible)`` for the state at the start of this step."""
        t = self._time()
        ego = self._ego()
        others, keys, out_ids = self._objects(ego)
        self._keys = keys  # a persistent key per row of ``others`` (for a variant's own per-object memory)
        ego_key = "__ego__"
        if self.accel_alpha is not None:
            accels = self._accelerations([ego_key, *keys], np.vstack([ego["velocity"][None], others[:, 2:4]]), t)
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
        if self.standstill_hold is None or t - self._stopped_at < self.standstill_hold - 1e-9:
            return True
        self._release()
        return False


@AEB_VARIANTS.register("paper")
class PaperAEB(AEBShield):
    """``paper``: the predictive AEB of digest 003 §4.1-4.8 (module docstring); parameters :class:`PaperParams`."""

    Params = PaperParams
    variant = "paper"

    def __init__(self, env: gym.Env, params: PaperParams | None = None, **overrides) -> None:
        super().__init__(env, params, **overrides)
        p = self.params
        self.T, self.activation_distance, self.accel_alpha = p.step, p.activation_distance, p.accel_alpha
        self.half_accel_term, self.limits, self.standstill_hold = p.half_accel_term, p.limits, p.standstill_hold

    def _decide_variant(self, ego, others, a_ego, a_others, t, active):
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


@AEB_VARIANTS.register("improved")
class ImprovedAEB(AEBShield):
    """``improved``: our design (module docstring); parameters :class:`ImprovedParams`."""

    Params = ImprovedParams
    variant = "improved"
    decides_outside_window = True

    def __init__(self, env: gym.Env, params: ImprovedParams | None = None, **overrides) -> None:
        super().__init__(env, params, **overrides)
        p = self.params
        self.T, self.activation_distance, self.accel_alpha = p.step, p.activation_distance, p.accel_alpha
        self.margin, self.release_margin, self.stop_margin = p.margin, p.release_margin, p.stop_margin
        self.horizon_min, self.horizon_max, self.target_model = p.horizon_min, p.horizon_max, p.target_model
        self.release_hold, self.feasibility, self.go_speed = p.release_hold, p.feasibility, p.go_speed
        self.release_standing, self.emergency_accel_time = p.release_standing, p.emergency_accel_time
        self.release_accel_time = p.release_accel_time
        self.setoff_speed, self.setoff_accel, self.setoff_horizon = p.setoff_speed, p.setoff_accel, p.setoff_horizon
        self.setoff_recent = p.setoff_recent
        self._moved_at: dict = {}
        self.warn_ttc, self.ignore_rear, self.check_action = p.warn_ttc, p.ignore_rear, p.check_action
        self.needs_lanes = self.target_model in ("map", "conflict")
        self._hypotheses: LaneHypotheses | None = None
        self._conflicts: ConflictModel | None = None
        self.hypothesis_min_p, self.signals = p.hypothesis_min_p, p.signals
        self._signal_params = p.signal_channel
        self._signal_channel: dict = {}
        self._intended_at: dict = {}  # vehicle -> (lane index, the indicator its route asks for there)
        self._beliefs = DriverIntent(p.signal_channel)

    def _on_reset(self, u) -> None:
        if self.target_model == "map":
            if self._hypotheses is None:
                self._hypotheses = LaneHypotheses(u.road.network)
            self._hypotheses.network = u.road.network
        if self.target_model == "conflict":
            if self._conflicts is None:
                self._conflicts = ConflictModel(u.road.network, min_p=self.hypothesis_min_p)
            self._conflicts.network = u.road.network
            self._signal_channel, self._intended_at = {}, {}
            self._beliefs.clear()
            self._signal_rng = sensor_rng(self.env, "aeb_signals")
        self._moved_at = {}

    def _intent(self, others: np.ndarray, keys: list) -> np.ndarray | None:
        """The weight of each turn (right, straight, left) of each object from every indicator reading of its
        driver so far (:class:`av_gym.shields.intent.DriverIntent`); a NaN row for a driver never read.

        A reading comes through the shield's own indicator channel (``signal_channel``; its own random stream:
        per driver when first read, does it indicate and on which side; per reading, is it missed) and belongs to
        the true vehicle: the object itself in ground-truth mode (``keys``), the vehicle within 2 m of the track
        in perceived mode (none elsewhere). None beyond the channel's range; what was read stays known."""
        if not self.signals:
            return None
        u, sp = self.env.unwrapped, self._signal_params
        if self.mode == "ground_truth":
            drivers = list(keys)
        else:
            vehicles = [v for v in u.road.vehicles if v is not u.vehicle]
            drivers = [None] * len(others)
            if vehicles and len(others):
                pos = np.array([v.position for v in vehicles], dtype=float)
                d = np.hypot(*(others[:, None, 0:2] - pos[None]).transpose(2, 0, 1))  # (objects, vehicles)
                nearest = np.argmin(d, axis=1)
                drivers = [vehicles[k] if d[m, k] <= 2.0 else None for m, k in enumerate(nearest)]
        in_range = (np.square(others[:, 0:2] - u.vehicle.position).sum(axis=1) <= sp.max_range**2).tolist()
        read = [v for v, r in zip(drivers, in_range) if r and v is not None]
        if read:
            for v in read:
                if v not in self._signal_channel:  # first reading: does this driver indicate, and on which side?
                    self._signal_channel[v] = first_sighting(self._signal_rng.uniform(size=DRIVER_DRAWS), sp)
            u_seen = self._signal_rng.uniform(size=len(read))
            channel = np.array([self._signal_channel[v] for v in read], dtype=bool).reshape(-1, 2)
            readings = reported([self._intended(v) for v in read], channel[:, 0], channel[:, 1], u_seen, sp)
            self._beliefs.update(read, readings.tolist())
        return self._beliefs.turn_weights(drivers)

    def _intended(self, vehicle) -> float:
        """:func:`intended_signal` of ``vehicle``, recomputed only when it changes lanes (its route is fixed)."""
        lane = vehicle.lane_index
        held = self._intended_at.get(vehicle)
        if held is None or held[0] != lane:
            held = self._intended_at[vehicle] = (lane, intended_signal(vehicle))
        return held[1]

    def _decide_variant(self, ego, others, a_ego, a_others, t, active):
        return self._decide_improved(ego, others, a_others, t, active)

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
        recent = None
        if self.setoff_speed > 0:  # when each object was last faster than setoff_speed
            keys = getattr(self, "_keys", None) or [None] * len(others)
            fast = np.hypot(others[:, 2], others[:, 3]) >= self.setoff_speed if len(others) else np.zeros(0, bool)
            for key, f in zip(keys, fast):
                if f and key is not None:
                    self._moved_at[key] = t
            recent = np.array([key is not None and t - self._moved_at.get(key, -np.inf) <= self.setoff_recent + 1e-9
                               for key in keys], dtype=bool)[keep] if len(others) else np.zeros(0, bool)
        others, a_others = others[keep], a_others[keep]
        v, a, s0 = ego["speed"], ego["accel"], ego["s"]
        t_long = self.T * np.arange(1, int(round(max(self.horizon_max, 4.0 + self.horizon_min) / self.T)) + 1)
        lanes, intent = None, None
        if self.target_model == "map":
            lanes = [lane for lane, k in zip(self._lanes, keep) if k]
            obj_xy, obj_h, owner, turn = self._hypotheses.predict(others, lanes, t_long)
            # A vehicle that would turn into the ego's lane behind it has to yield to the ego: its map
            # hypotheses never count as running into the ego from behind.
            rear = turn | self.ignore_rear
        elif self.target_model == "conflict":
            lanes = [lane for lane, k in zip(self._lanes, keep) if k]
            intent = self._intent(others, [k for k, kept in zip(self._keys, keep) if kept])
            obj_xy, obj_h, owner, turn, _ = self._conflicts.predict(others, lanes, a_others, t_long, intent)
            rear = turn | self.ignore_rear
        else:
            obj_xy, obj_h = object_predict(others, t_long, a_others if self.target_model == "ca" else None)
            owner = np.arange(len(others))
            rear = np.full(len(owner), self.ignore_rear)
        idx = np.flatnonzero(keep)[owner]  # hypothesis → row of the full object list
        size = np.asarray(others[owner, 5:7], dtype=float).reshape(-1, 2)

        def ttc_of(ds: np.ndarray, n: int, margin: float, xy_o=obj_xy, h_o=obj_h, size_o=size,
                   rear_o=rear) -> tuple[float, int]:
            xy, h = self.driven.poses(s0, ds[:n], profile_speeds(ds[:n], t_long[:n], v))
            return footprint_ttc(xy, h, ego["size"], xy_o[:n], h_o[:n], size_o, t_long[:n], margin, rear_o)

        ds_cruise = self._continue_profile(ego, t_long)
        horizon = self._horizon(s0, ds_cruise, t_long)
        n = int(round(horizon / self.T))
        ttc, target = ttc_of(ds_cruise, n, self.margin)
        target_out = int(idx[target]) if target >= 0 else -1
        front_to_line = self.stop_line_s - (s0 + 0.5 * ego["size"][0])

        def at_trigger_point() -> bool:
            """The stop-line trigger: the front bumper within the stopping distance (+ one decision period and
            stop_margin) of the line, not past it."""
            if not (in_turn and 0.0 <= front_to_line):
                return False
            d_stop, _ = self.actuator.stopping_distance(v, a, self.sim_dt)
            return front_to_line <= d_stop + v * self.T + self.stop_margin

        # A car standing in the box that may set off (before the line only): checked where it can make a
        # difference, in the release test and at the stop-line trigger point (it never warns or brakes elsewhere)
        setoff_rule = self.setoff_speed > 0 and self.target_model == "conflict" and in_turn and front_to_line >= 0.0
        setoff = None
        if setoff_rule and (self._latched or (not np.isfinite(ttc) and at_trigger_point())):
            setoff = self._setoff_predict(others, lanes, t_long, intent, recent)

        if self._latched:
            # Release rule: the ego setting off again (or carrying on, if still rolling) must be predicted
            # conflict-free, with the larger release margin (hysteresis), for release_hold s.
            ttc_go, tgo = float("inf"), -1
            profiles = [ds_cruise] if ego["set_speed"] is not None else [ds_cruise, self._go_profile(ego, t_long)]
            predictions = [(obj_xy, obj_h)]
            speeding_up = self._along_accel(others, a_others, sign=1.0)
            if self.release_accel_time > 0 and self.target_model == "conflict" and speeding_up.any():
                accel_xy, accel_h, _, _ = self._accel_predict(others, lanes, speeding_up, t_long, intent,
                                                              self.release_accel_time)
                predictions.append((accel_xy, accel_h))
            for p_xy, p_h in predictions:
                xy_r, h_r = self._release_objects(ego, others, owner, p_xy, p_h)
                for ds_p in profiles:  # commanded acceleration: safe whether the agent holds its speed or sets off
                    n_p = int(round(self._horizon(s0, ds_p, t_long) / self.T))
                    ttc_p, tg_p = ttc_of(ds_p, n_p, self.release_margin, xy_r, h_r)
                    if ttc_p < ttc_go:
                        ttc_go, tgo = ttc_p, tg_p
            if setoff is not None:  # a car standing in the box that may set off (before the line only)
                for ds_p in profiles:
                    n_p = int(round(self._horizon(s0, ds_p, t_long) / self.T))
                    n_p = min(n_p, int(round(self.setoff_horizon / self.T)))
                    ttc_p, _ = ttc_of(ds_p, n_p, self.release_margin, *setoff[:2], *setoff[3:])
                    ttc_go = min(ttc_go, ttc_p)
            self._clear_for = self._clear_for + self.T if not np.isfinite(ttc_go) else 0.0
            if not np.isfinite(ttc_go) and self._clear_for + 1e-9 >= self.release_hold:
                self._release()
            else:
                t_out = int(idx[tgo]) if tgo >= 0 else target_out
                return BRAKE, min(ttc, ttc_go), horizon, t_out, False
        if not np.isfinite(ttc) and setoff is not None and at_trigger_point():
            # a standing car that may set off: a reason to stop at the line, never an emergency
            n_set = min(n, int(round(self.setoff_horizon / self.T)))
            ttc_set, k = ttc_of(ds_cruise, n_set, self.margin, *setoff[:2], *setoff[3:])
            if np.isfinite(ttc_set):
                self._latch(t)
                return BRAKE, ttc_set, horizon, int(np.flatnonzero(keep)[setoff[2][k]]), False
        if not np.isfinite(ttc):
            return MONITOR, ttc, horizon, -1, False
        stop_line_trigger = at_trigger_point()
        emergency = False
        if ttc <= self.ttc_brake:
            ttc_raw, _ = ttc_of(ds_cruise, n, 0.0)
            emergency = ttc_raw <= self.ttc_brake
            if not emergency and self.emergency_accel_time > 0 and self.target_model == "conflict":
                emergency = self._braking_ttc(ego, ds_cruise, n, others, lanes, a_others, t_long,
                                              intent) <= self.ttc_brake
        if not (stop_line_trigger or emergency):
            return (WARN if in_turn or ttc <= self.warn_ttc else MONITOR), ttc, horizon, target_out, False
        # Feasibility against the object braked for (any of its path hypotheses) only: another road user that
        # would reach the standing ego seconds later is a later conflict (it can brake, the ego can set off),
        # not a reason to drive into this one (seed 1019: a rear-end at TTC 1.3 s went unbraked because a car
        # merging into the exit lane was predicted through the stopped ego 5.9 s later).
        mine = owner == owner[target]
        if self.feasibility and self._parked_in_path(v, a, s0, ego, obj_xy[:, mine], obj_h[:, mine], size[mine],
                                                     t_long, np.broadcast_to(rear, owner.shape)[mine]):
            return WARN, ttc, horizon, target_out, True
        self._latch(t)
        return BRAKE, ttc, horizon, target_out, False

    @staticmethod
    def _along_accel(others: np.ndarray, a_others: np.ndarray, sign: float) -> np.ndarray:
        """``a_others`` (M, 2) kept for the road users whose acceleration along their velocity has the sign
        ``sign`` (-1 braking, +1 speeding up), zero for the others."""
        if len(others) == 0:
            return np.zeros((0, 2))
        speed = np.hypot(others[:, 2], others[:, 3])
        along = np.einsum("mi,mi->m", a_others, others[:, 2:4]) / np.maximum(speed, 1e-6)
        return np.where((sign * along > 0.0)[:, None], a_others, 0.0)

    def _setoff_predict(self, others, lanes, t_long, intent, recent):
        """Positions (K, H, 2), headings (K, H), owners (H,: rows of ``others``), sizes (H, 2) and rear flags (H,)
        of the path hypotheses of every road user slower than ``setoff_speed`` on a lane through the box, setting
        off from 0.5 m/s at ``setoff_accel`` (for 3 s); None when there is none."""
        box = np.array([lane is not None and str(lane[0]).startswith("ir") for lane in lanes], dtype=bool)
        speed = np.hypot(others[:, 2], others[:, 3]) if len(others) else np.zeros(0)
        slow = box & (speed < self.setoff_speed) & recent
        if not slow.any():
            return None
        idx = np.flatnonzero(slow)
        mod = others[idx].copy()
        direction = np.stack([np.cos(mod[:, 4]), np.sin(mod[:, 4])], 1)
        mod[:, 2:4] = 0.5 * direction
        sub_lanes = [lanes[i] for i in idx]
        sub_intent = None if intent is None else intent[idx]
        xy, h, owner, turn = self._accel_predict(mod, sub_lanes, self.setoff_accel * direction, t_long,
                                                 sub_intent, 3.0)
        return xy, h, idx[owner], np.asarray(others[idx[owner], 5:7], dtype=float).reshape(-1, 2), \
            turn | self.ignore_rear

    def _accel_predict(self, others, lanes, accels, t_long, intent, accel_time):
        """The conflict model's path hypotheses (same ones, same order) with each road user keeping the
        acceleration ``accels`` (M, 2, world frame; along its path) for ``accel_time`` s, never reversing."""
        model = self._conflicts
        saved = model.accel_time
        model.accel_time = accel_time
        try:
            obj_xy, obj_h, owner, turn, _ = model.predict(others, lanes, accels, t_long, intent)
        finally:
            model.accel_time = saved
        return obj_xy, obj_h, owner, turn

    def _braking_ttc(self, ego, ds, n, others, lanes, a_others, t_long, intent) -> float:
        """Unmargined TTC of the ego on the profile ``ds`` against every road user that is braking (along its
        path) predicted keeping that deceleration for ``emergency_accel_time`` s along each of its path
        hypotheses, the others at constant speed as in the conflict test (:class:`ConflictModel` with
        ``accel_time``; the accelerations are the finite-difference EMA the shield keeps per object)."""
        braking = self._along_accel(others, a_others, sign=-1.0)
        if not braking.any():
            return float("inf")
        obj_xy, obj_h, owner, turn = self._accel_predict(others, lanes, braking, t_long, intent,
                                                         self.emergency_accel_time)
        v, s0 = ego["speed"], ego["s"]
        xy, h = self.driven.poses(s0, ds[:n], profile_speeds(ds[:n], t_long[:n], v))
        size_b = np.asarray(others[owner, 5:7], dtype=float).reshape(-1, 2)
        ttc, _ = footprint_ttc(xy, h, ego["size"], obj_xy[:n], obj_h[:n], size_b, t_long[:n], 0.0,
                               turn | self.ignore_rear)
        return ttc

    def _release_objects(self, ego: dict, others: np.ndarray, owner: np.ndarray, obj_xy: np.ndarray,
                         obj_h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The predicted objects the release test checks: all path hypotheses, except (``release_standing``) with
        the ego standing in the box, where every road user slower than ``release_standing`` is predicted standing
        at its current place and heading. Why: braked to a standstill in the box, the ego would otherwise wait for
        a car that is barely moving there itself (one yielding, creeping, or sliding to a stop after a collision
        with another car) whose path hypotheses at that speed cross the ego's, until the time-out or until a third
        car runs into the standing ego; a car that does set off again is still met by the emergency brake."""
        if self.release_standing <= 0 or ego["speed"] > STOP_SPEED or len(owner) == 0:
            return obj_xy, obj_h
        front_to_line = self.stop_line_s - (ego["s"] + 0.5 * ego["size"][0])
        if front_to_line >= 0.0 or ego["s"] >= self.clear_s:
            return obj_xy, obj_h
        slow = np.hypot(others[owner, 2], others[owner, 3]) < self.release_standing
        if not slow.any():
            return obj_xy, obj_h
        xy, h = obj_xy.copy(), obj_h.copy()
        xy[:, slow] = others[owner[slow], 0:2][None]
        h[:, slow] = others[owner[slow], 4][None]
        return xy, h

    def _continue_profile(self, ego: dict, t: np.ndarray) -> np.ndarray:
        """Distance (m) along the route at times ``t`` if the ego carries on as it is driven now: for a vehicle
        with a cruise set-point (MDPVehicle, discrete actions) highway-env's first-order speed response to that
        set-point (exact for its controller, including setting off from a standstill); otherwise (commanded
        acceleration) its current acceleration for 1 s, the speed capped at the lane's speed limit (or
        ``go_speed`` from a standstill), never reversing.

        With ``check_action``, under the agent's proposed action instead, held over the horizon (a policy step is
        the decision period): FASTER/SLOWER repeated (the set-point moves one step from the one nearest the speed
        at every step, :func:`setpoint_profile`), IDLE the set-point kept, a commanded acceleration held for 1 s."""
        action = self._proposed if self.check_action else None
        u = self.env.unwrapped
        if ego["set_speed"] is not None:
            name = u.action_type.actions.get(int(action)) if action is not None and np.ndim(action) == 0 else None
            if name in ("FASTER", "SLOWER"):
                vehicle, step = u.vehicle, 1 if name == "FASTER" else -1
                top = len(vehicle.target_speeds) - 1

                def set_at(v: float) -> float:  # MDPVehicle.act for this action
                    return float(vehicle.index_to_speed(int(np.clip(int(vehicle.speed_to_index(v)) + step, 0, top))))
                return setpoint_profile(ego["speed"], set_at, t, dt=self.sim_dt)
            return go_profile(ego["speed"], ego["set_speed"], t)
        accel = ego["accel"] if action is None else u.action_type.acceleration(action)
        v_cap = max(ego["speed"], self.go_speed, ego["speed_limit"] or self.go_speed)
        a = accel if ego["speed"] > STOP_SPEED else max(accel, 0.0)
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


@AEB_VARIANTS.register("standard")
class StandardAEB(AEBShield):
    """``standard``: the standard AEB of paper 003 §2 (``TTC = Δx/Δv`` on targets ahead in the ego's corridor),
    always active; parameters :class:`StandardParams`."""

    Params = StandardParams
    variant = "standard"

    def __init__(self, env: gym.Env, params: StandardParams | None = None, **overrides) -> None:
        super().__init__(env, params, **overrides)
        p = self.params
        self.warn_ttc, self.lateral_margin, self.standstill_hold = p.warn_ttc, p.lateral_margin, p.standstill_hold
        self.steering_inhibit = None if p.steering_inhibit_deg is None else np.radians(p.steering_inhibit_deg)

    def _is_active(self, ego: dict) -> bool:
        return True

    def _decide_variant(self, ego, others, a_ego, a_others, t, active):
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
