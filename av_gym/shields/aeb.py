"""Predictive automatic emergency braking (AEB) shield for the unprotected left turn (digest 003).

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
    the action the agent proposes for this step, held (``check_action``: a safety filter checks the
    action it is given, so an agent that has just chosen to stop is not braked): highway-env's cruise-control
    response through the set-points FASTER/SLOWER step to (discrete actions), or the commanded acceleration
    for 1 s (continuous);
  * the others on every way the road network lets them continue, each hypothesis with its probability, at
    constant speed on the path highway-env's controller drives (``target_model: conflict``, the default:
    :class:`av_gym.shields.conflicts.ConflictModel`), or constant-velocity (``cv``), constant-acceleration
    (``ca``), CV along each lane continuation plus the plain CV hypothesis (``map``);
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
  * with ``target_model: conflict``, the emergency test also predicts a braking road user
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
braking would park the ego in the target's path), ``aeb_brake_time`` (s, first brake command this episode;
:data:`NOT_YET` = inf before), ``aeb_stop_position`` (m, front bumper past the stop line at the first standstill
under braking; :data:`NOT_YET` = inf before), ``aeb_action`` (the action passed on to the env: an int, or with
continuous actions a float32 array of the action's shape; at reset :data:`NO_ACTION` = -1, or NaNs),
``aeb_withheld`` (stop-line brake decisions a second opinion withheld this episode: :attr:`AEBShield.opinion`, an
:class:`~av_gym.shields.opinion.Opinion` its owner installs). Every key has one type at reset and in every step,
so ``gymnasium.make_vec(..., vectorization_mode="sync"/"async")`` batches each into a typed array whichever env
just reset (None beside an int raised in Gymnasium's ``_add_info``); inf, not NaN, for "not yet", so that identical
runs' infos compare equal (``check_env``).

The code, by seam: the parameters (:mod:`av_gym.shields.aeb_params`), the brake actuator
(:mod:`av_gym.shields.actuator`), the shared base and the variant registry (:mod:`av_gym.shields.aeb_base`), and
one module per variant (``aeb_paper``, ``aeb_standard``, ``aeb_improved``). This module re-exports their public
names and registers the variants, so ``av_gym.shields.aeb`` is where a caller imports them from.
"""

from __future__ import annotations

from av_gym.shields.actuator import BrakeActuator
from av_gym.shields.aeb_base import AEB_VARIANTS, NO_ACTION, NOT_YET, AEBShield, _route_tables, find_shield
from av_gym.shields.aeb_params import (BRAKE, CONFIG_SECTION_KEYS, MONITOR, SHIELD_DETECTOR, STOP_SPEED,
                                      TRACKER_FOLLOWS_DETECTOR, WARN, AEBParams, BrakeParams, ImprovedParams,
                                      PaperParams, StandardParams, TurnParams)
# the variants, re-exported here (AEB_VARIANTS names them in its own order)
from av_gym.shields.aeb_paper import PaperAEB  # isort: skip
from av_gym.shields.aeb_improved import ImprovedAEB  # isort: skip
from av_gym.shields.aeb_standard import StandardAEB  # isort: skip

__all__ = ["AEB_VARIANTS", "AEBParams", "AEBShield", "BRAKE", "BrakeActuator", "BrakeParams", "CONFIG_SECTION_KEYS",
           "ImprovedAEB", "ImprovedParams", "MONITOR", "NOT_YET", "NO_ACTION", "PaperAEB", "PaperParams",
           "SHIELD_DETECTOR", "STOP_SPEED", "StandardAEB", "StandardParams", "TRACKER_FOLLOWS_DETECTOR", "TurnParams",
           "WARN", "_route_tables", "find_shield"]
