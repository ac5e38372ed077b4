"""The AEB shield's parameters (module docstring of :mod:`av_gym.shields.aeb`): the brake actuator's, the
common :class:`AEBParams` and one Params class per variant, each field with its unit, default and reason; the
decision stages and the shield's own perception defaults."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from av_gym.estimation.tracker import TrackerParams
from av_gym.params import Params, check, param
from av_gym.sensors.detector import DetectorParams
from av_gym.sensors.turn_signal import TurnSignalsParams


STOP_SPEED = 0.1  # m/s, standstill (as av_gym.metrics.left_turn.STOP_SPEED)
SETOFF_ACCEL_TIME = 3.0  # s, how long the set-off rule's standing road user keeps setoff_accel (both stacks read it)


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
target 1.5 s behind a 10 km/h ego is ~110 m away when the ego must decide (docs/shield.md; 100 m gives 4/99
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
    """The ``improved`` variant, our design: the ego predicted along its planned route, others
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
                        "(av_gym.shields.conflicts.ConflictModel). The default: always_proceed+aeb on "
                        "seeds 1000-1099, 4 collisions / 87 arrivals against cv's 8 / 81 and map's 4 / 81")
    hypothesis_min_p: float = param(0.1, ge=0, le=1, doc="target_model conflict: a path hypothesis less likely than "
                                                         "this is dropped (uniform over the continuations: 1/3 "
                                                         "each at the intersection, so only a turn signal prunes)")
    signals: bool = param(True, doc="target_model conflict: read the other drivers' indicators through the shield's "
                                    "own indicator channel (signal_channel), each driver's readings accumulated in a "
                                    "Bayes filter over its turn (av_gym.estimation.driver_intent). The default: "
                                    "always_proceed+aeb on seeds 1000-1499, fewer collisions, more "
                                    "arrivals and fewer unneeded brakes than without (docs/shield.md)")
    signal_channel: TurnSignalsParams = param(
        TurnSignalsParams(), doc="signals: the shield's indicator channel (av_gym.sensors.turn_signal's model and "
                                 "defaults: 25 % of drivers never indicate, 5 % the wrong side, 10 % of readings "
                                 "missed, 60 m); all three rates 0 = every driver's intent known (an upper bound: "
                                 "what perfect intent would buy)")
    release_hold: float = param(0.3, "s", ge=0, doc="the release test must pass this long before the brake lets go")
    emergency_accel_time: float = param(
        1.5, "s", ge=0, doc="the emergency test (past the stop-line trigger point) also predicts every road user that "
                            "is braking keeping its measured deceleration this long along each path hypothesis (a "
                            "braking car stops, it never reverses), beside the constant-speed prediction ("
                            "a crossing car braking hard in front of the ego, or two cars colliding there, "
                            "were braked for 0.2-0.3 s late, when the constant-speed footprints first touched); 0 = "
                            "constant speed only (the rule before)")
    release_accel_time: float = param(
        0.0, "s", ge=0, doc="the release test also predicts every road user that is speeding up keeping its "
                            "measured acceleration this long along each path hypothesis, beside the constant-speed "
                            "prediction, so a car setting off again after slowing holds the brake; 0 = constant "
                            "speed only, the default: measured with 1.5 s (always_proceed+aeb "
                            "on seeds 1000-1499) it prevented one collision (seed 1298) and added two (1185, 1231)")
    setoff_speed: float = param(
        2.0, "m/s", ge=0, doc="before the stop line, a road user slower than this in the box (on a lane through "
                              "it) that was faster within setoff_recent s is also predicted setting off along each "
                              "path hypothesis (from 0.5 m/s at setoff_accel), for the stop-line trigger and the "
                              "release test (seed 1215, an oncoming car standing in the box set "
                              "off as the unbraked ego entered it at 9 m/s); 0 = off (the rule before)")
    setoff_accel: float = param(3.0, "m/s²", gt=0, doc="see setoff_speed")
    setoff_recent: float = param(3.0, "s", gt=0, doc="only a road user that was faster than setoff_speed within "
                                                    "this many seconds may set off (a wreck, or a car parked in "
                                                    "the box for long, does not hold the ego at the line)")
    setoff_horizon: float = param(3.0, "s", gt=0, doc="only a conflict with a setting-off car within this many "
                                                      "seconds counts (see setoff_speed)")
    release_standing: float = param(
        1.0, "m/s", ge=0, doc="gridlock release: with the ego braked to a standstill in the "
                              "box (front past the stop line, turn not cleared), the release test predicts every road "
                              "user slower than this standing where it is, not along its path hypotheses, so the ego "
                              "clears the box when what it braked for stands or yields to it; 0 = off (the rule "
                              "before)")
    feasibility: bool = param(True, doc="no braking when it would leave the ego parked in the target's path "
                                        "(003 §9.7)")
    second_opinion: str = param(
        "none", doc="the second opinion this shield needs before a brake at the stop line (never an emergency "
                    "brake): its owner installs it (AEBShield.opinion, an av_gym.shields.Opinion) and names it "
                    "here, and the shield refuses to run without one; none = it runs without (an opinion installed "
                    "is still asked). The names are the owner's: python -m eval installs the one "
                    "conf/shield/aeb_belief.yaml names")
    go_speed: float = param(4.5, "m/s", gt=0, doc="speed assumed for setting off when the ego has no cruise "
                                                  "set-point (commanded acceleration)")
    warn_ttc: float = param(2.5, "s", gt=0, doc="outside the turn window: forward-collision warning at TTC <= this")
    check_action: bool = param(True, doc="predict the ego under the action the agent proposes for this step (its new "
                                         "set-point, or its commanded acceleration), as a safety filter checks the "
                                         "action it is given; false: under the set-point before it, "
                                         "which brakes an agent that has just "
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
