"""``belief_lookahead``: the look-ahead planner that knows only what the car can know.

The oracle (:mod:`agents.batched_oracle`) plays the real GO future of an episode: the other drivers' routes, their
IDM draws and the traffic still to spawn are the simulator's own. This planner plays K futures per decision, each
consistent with what the car observes and nothing else, and goes when the share of them that end in a collision is
at most ``threshold``. The gap between the two is the value of the information no sensor has; the gap between this
planner and a student is learning still to do (docs/dagger.md, "Information vs learning").

What a future keeps (observable): every road user's position, heading, speed, its current lane (the closest lane,
a function of the pose), whether it has crashed, the ego's whole state, the clock. What a future redraws (hidden,
the engine's draws in :meth:`av_gym.batched.left_turn.BatchedLeftTurn._spawn`):

- each driver's destination, from its route belief: the shield's Bayes filter over (turn, driver kind)
  (:class:`av_gym.estimation.driver_intent.DriverIntent`) fed with every indicator reading the car got of that driver
  (``obs["intent"][..., 1]``, the turn-signal channel), times the geometry: a driver already inside the
  intersection can only be on a crossing lane whose centreline its pose still fits (``gate``); on the exit road
  the destination is known;
- its IDM exponent ``delta`` ~ U(3.5, 4.5) and its cruise set-point ~ 8 + N(0, 1) m/s, the spawn draws, and no
  regulation yield carried over (the regulation re-decides within 0.5 s on the drawn routes);
- future spawns: the spawn process on a fresh generator per future, never the row's own generator (that one
  holds the real future).

Every draw comes from ``SeedSequence([seed, episode_seed, tick])``: the same episode and decision time give the same
decision whatever the batch, and no draw depends on the hidden state (tests/test_belief.py re-randomises it).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Literal

import gymnasium as gym
import numpy as np

from agents.registry import AgentKind, AgentParams
from agents.track_prior import draw_width  # SLOTS draws per stream: a driver's draws fixed by its place alone
from av_gym.estimation.driver_intent import DriverIntent
from av_gym.params import param
from av_gym.sensors.turn_signal import TurnSignalsParams
from av_gym.sim.batched import SpawnPrior
from av_gym.wrappers import GO, YIELD

__all__ = ["BeliefLookahead", "BeliefLookaheadAgent", "BeliefLookaheadParams", "BeliefPlanner", "EnvView",
           "PlannerOpinion", "belief_lookahead_teacher"]

SPEED_LIMIT = 10.0  # every lane's: a driver the regulation releases takes it as its set-point
P_RELEASED, P_HELD = 0.02, 0.02  # prior shares of drivers released / held by the regulation (validation states)
ACC_SIGMA = 0.3  # m/s², the spread of an observed acceleration about the IDM command of the right behaviour
PARTICLES = 64  # behaviour particles per driver before the resampling
RECHECK_STREAM = 3  # the recheck's futures: SeedSequence([seed, episode, tick, 3]) (1, 2: the tracks' streams)
KEEP_STREAM = 4  # keep_recheck's futures: SeedSequence([seed, episode, tick, 4])


@dataclass(frozen=True)
class BeliefLookaheadParams(AgentParams):
    """The belief-space look-ahead planner (conf/agent/belief_lookahead.yaml)."""

    kind: Literal["belief_lookahead"] = param("belief_lookahead")
    name: str = param("belief_lookahead")
    scenarios: tuple[str, ...] = param(("left_turn",))
    repeat: int = param(5, "env steps", ge=1, doc="env steps between decisions (2 Hz, as the oracle)")
    samples: int = param(16, ge=1, le=256, doc="futures drawn per decision (K), chosen on 300 validation "
                                               "episodes (docs/dagger.md, Information vs learning): 8 / 16 / 32 "
                                               "give 0.067 / 0.053 / 0.047 collisions at 0.83 success; 32 costs "
                                               "twice 16's time for a difference within the noise")
    threshold: float = param(0.05, ge=0, le=1, doc="GO when at most this share of the GO futures collide (with 16 "
                                                   "futures: none of them), chosen on the same episodes: 0.1 / 0.2 "
                                                   "give 0.070 / 0.087 collisions at the same success")
    seed: int = param(0, ge=0, doc="the planner's own seed (with the episode and the decision time)")
    gate: float = param(0.5, "m + rad", gt=0, doc="a crossing lane is still possible for a driver inside the "
                                                  "intersection while its distance_with_heading is within this of "
                                                  "the closest lane's")
    floor: float = param(0.02, gt=0, lt=1, doc="the Bayes filter's likelihood floor (the shield's DriverIntent)")
    commit: Literal["never", "stop", "go"] = param(
        "never", doc="never: every decision is made afresh, a GO taken back (YIELD) whenever the futures of the "
                     "moment say so, as a DAgger teacher labels and its students choose | stop: GO taken back only "
                     "while the ego can still stop before the line at the approach's comfortable deceleration | "
                     "go: GO is final, as the oracle's (whose futures are exact). Chosen on the 300 validation "
                     "episodes at K 16: never 0.010 / 0.857 (collision / success), stop 0.053 / 0.830")
    unseen: float = param(1.0, ge=0, le=10, doc="on tracks (sensors turn_perceived): the density of the road users "
                                                "the tracker has not confirmed, as a multiple of the spawn "
                                                "process's (agents/track_prior.py: the approach lanes out of range, "
                                                "behind confirmed tracks or not yet confirmed, thinned where the "
                                                "sensor looked); 0: what is not confirmed is taken for nobody")
    unseen_ahead: int = param(0, "detector frames", ge=0, le=20, doc="on tracks: a place of the unseen traffic's "
                                                                  "prior that was in view at the last detector "
                                                                  "frame keeps a driver only if the detector would "
                                                                  "miss it in this many frames more (miss_rate ** "
                                                                  "this): the frames before the next decision (5 "
                                                                  "at 10 Hz and 2 Hz decisions), which sees such a "
                                                                  "driver and takes the GO back while the ego can "
                                                                  "stop; 0: only the frames so far")
    track_acc_sigma: float = param(1.6, "m/s²", ge=0, doc="on tracks: the weight of a track's measured "
                                                         "acceleration in the behaviour posterior, as an sd added "
                                                         "in quadrature to the model's 0.3 in the likelihood "
                                                         "(smaller: the measurement counts for more); a setting, "
                                                         "not a measurement: the default is the intent features' "
                                                         "measured error (sd 1.59 m/s² against the simulator's, "
                                                         "19,286 readings of 40 validation episodes)")
    stopped: float = param(1.0, "m/s", ge=0, doc="on tracks: a track slower than this is taken to stay where it is "
                                                 "in the futures, as a crashed car does (the tracks carry no crash "
                                                 "flag); 0: every track drives on")
    stopped_scope: Literal["anywhere", "off_approach"] = param(
        "anywhere", doc="on tracks: where ``stopped`` holds a standing track in place: anywhere, or only off the "
                        "approach lanes and the first 5 m of a crossing lane (off_approach: inside the junction or "
                        "on an exit, a crashed or blocked car); a track standing there waits at its stop line, and "
                        "the futures' regulation and IDM release it (cars standing at their line at the last GO "
                        "pulled away into the ego: validation seeds 1,500,000-1,500,599, benchmarks/"
                        "belief_tracks_diagnose.py)")
    stopped_alone: float = param(0.0, "m", ge=0, le=20, doc="on tracks: a track ``stopped`` (and its scope) would "
                                                        "hold in place stays only where another road user of the "
                                                        "futures' start (a track that is not a ghost or a twin; "
                                                        "not the ego) stands within this many m of it: a crash "
                                                        "leaves two cars in contact, a car the regulation holds "
                                                        "inside the junction stands alone, and the futures' "
                                                        "regulation and IDM release it as the simulator's does "
                                                        "(4 of the last GOs taken back before a collision, "
                                                        "validation 1,953,000-1,953,999 and 1,963,000-1,963,999: "
                                                        "such a track on its crossing lane, held in every future, "
                                                        "the car pulling away at +6 m/s²); 0: off")
    stopped_release: float = param(0.0, ge=0, le=1, doc="on tracks: in this share of the futures, drawn per "
                                                       "future and road user, a track the standing rule "
                                                       "(``stopped``, its scope) holds in place on a crossing lane "
                                                       "is a driver instead, the futures' regulation and IDM "
                                                       "releasing it: the car standing inside the junction is "
                                                       "crashed or held by the regulation, and the tracks do not "
                                                       "tell which (train seeds 200-399, the preset: of such "
                                                       "tracks on a car, 23 % were not crashed, 10.5 % drove off "
                                                       "within 3 s); 4 of the last GOs taken back before a "
                                                       "collision (validation 1,953,000-1,953,999, "
                                                       "1,963,000-1,963,999) had such a car held in all 16 futures "
                                                       "pull away at +6 m/s²; 0: every such track stays")
    tentative: Literal["ignore", "road_user"] = param(
        "ignore", doc="on tracks: a tentative track (fewer than the tracker's min_hits detections) is nobody, as the "
                      "features show it (ignore), or a road user in the futures (road_user)")
    track_heading: Literal["velocity", "detected"] = param(
        "velocity", doc="on tracks: a track's pose for its lane and its futures takes the heading of the filter's "
                        "velocity (above 1 m/s, as obs['tracks']) and its speed (velocity), or the detector's heading "
                        "(the tracker's running mean, sd 0.05 rad a frame) and the speed along it, a track whose "
                        "velocity points backwards standing (detected)")
    ghost: int = param(0, "detector frames", ge=0, doc="on tracks: a track the detector missed in this many frames "
                                                       "running although its place is in view (range, field of "
                                                       "view, not behind a track detected now) is nobody in the "
                                                       "futures (the tracker coasts on it after its car left the "
                                                       "constant-velocity path); 0: every track is a road user")
    track_lag: float = param(0.0, "s", ge=0, le=1, doc="on tracks: a described track's speed is its filter's plus "
                                                       "this times the acceleration the intent features measure: "
                                                       "the constant-velocity filter's speed trails a car "
                                                       "accelerating at a by 0.20 s x a in steady state (the "
                                                       "default tracker at 10 Hz, 10-60 m of range); 0: the "
                                                       "filter's speed")
    track_lag_up: bool = param(False, doc="with ``track_lag`` > 0: the lag is added only where the measured "
                                          "acceleration is positive (a car pulling away, faster than its filter "
                                          "says; the car the collision replays find tracked 1.5 m/s slow when "
                                          "released at +6 m/s²); a braking one keeps its filter's speed, the "
                                          "faster and so the more cautious one; False: both ways")
    track_fit: float = param(0.0, "s", ge=0, le=2, doc="on tracks: a track's speed (along its heading) is the "
                                                      "value now of the planner's own least-squares line through "
                                                      "the detector's velocities of the frames that updated it in "
                                                      "the last this many s (at least 3 frames; agents/"
                                                      "track_prior.py DetectedMotion), not the constant-velocity "
                                                      "filter's, which trails a car pulling away or braking (40 "
                                                      "validation episodes, 0.5 s: bias -0.47 -> -0.14 m/s on cars "
                                                      "accelerating at > 2 m/s², sd 0.36 -> 0.46 m/s over all); 0: "
                                                      "the filter's")
    track_spread: float = param(0.0, "sd", ge=0, le=5, doc="on tracks: each future starts every moving track this "
                                                           "many of its filter's standard deviations off along its "
                                                           "heading, in place and speed (a joint normal draw from "
                                                           "the covariance P projected on the heading), so GO must "
                                                           "be safe against the tracks' own error; 0: every future "
                                                           "starts at the filter's estimate")
    merge: float = param(0.0, "m", ge=0, le=5, doc="on tracks: of two road users (confirmed or tentative tracks) "
                                                   "whose centres are closer than this, only the one the detector "
                                                   "updated last is in the futures (ties: the confirmed, the "
                                                   "nearer): the tracker's twin tracks of one car, which collide "
                                                   "with each other in the futures; 0: every track a road user")
    track_reverse: float = param(0.0, "m/s", ge=0, le=5, doc="on tracks with ``track_heading`` detected: a track "
                                                         "whose filter's speed along its detected heading (before "
                                                         "``track_lag`` and ``track_fit``) is below minus "
                                                         "this is a car backing up and starts its futures at that "
                                                         "negative speed, driven by the engine's IDM as the car is "
                                                         "(highway-env's IDM brakes past 0 into reverse where it "
                                                         "stands closer than its desired gap: its speed is not "
                                                         "clipped, its command only at -6 m/s²), not held standing; "
                                                         "0: every track's speed is kept at or above 0")
    merge_far: float = param(0.0, "m", ge=0, le=6, doc="on tracks with ``merge`` > 0: two road users closer than "
                                                       "this (and farther than ``merge``) are twins too when their "
                                                       "velocities agree within ``merge_agree`` and their detected "
                                                       "headings within 0.5 rad (a car's second track trails or "
                                                       "leads it at its speed; two cars side by side in opposite "
                                                       "lanes do not agree, and a lane's two cars stand >= 6 m "
                                                       "apart); 0: ``merge`` alone")
    merge_agree: float = param(1.0, "m/s", gt=0, le=5, doc="with ``merge_far``: the largest difference of two "
                                                           "tracks' velocity vectors for them to be one car's")
    recall: float = param(0.0, "s", ge=0, le=10, doc="on tracks: a car whose track the tracker dropped (a "
                                                     "tentative one on its first miss, a confirmed one after "
                                                     "max_coast without a detection) stays a road user of the "
                                                     "futures, as a tentative track is, at its last state predicted "
                                                     "on at constant velocity, until a track or detection comes "
                                                     "within 4 m of that place, a detector frame after its death "
                                                     "sees nothing there (in range, field of view, not behind a "
                                                     "track updated then), or this many s have passed "
                                                     "(agents/track_memory.py: the planner's own memory, from the "
                                                     "tracker's tracks and the detections); 0: none")
    recheck: int = param(0, "futures", ge=0, le=256, doc="a GO after a YIELD (or at the first decision) is taken "
                                                         "only when this many more futures, drawn from their own "
                                                         "streams, find GO safe too (at most threshold collide): a "
                                                         "stricter test to start a GO than to keep one, which one "
                                                         "lucky draw of K futures passes right after risky ones; 0: "
                                                         "none")
    recheck_pool: bool = param(False, doc="with ``recheck`` > 0: a GO to start is judged on the decision's K "
                                          "futures and the recheck's pooled (GO when at most ``threshold`` of all "
                                          "K + recheck collide), the recheck asked where the decision's own K could "
                                          "still meet that; a held GO is kept on the K as before: one estimate of "
                                          "GO's collision probability from K + recheck futures has less variance "
                                          "than two tests that each allow none of theirs, so a GO of a small risk "
                                          "is not held back by one unlucky future (the caution benchmarks/"
                                          "belief_tracks_lost.py counts); False: each draw on its own")
    keep_recheck: int = param(0, "futures", ge=0, le=256, doc="a held GO whose decision's K futures find it unsafe "
                                                              "(more than ``threshold`` collide) is taken back only "
                                                              "where the pooled share of those K and this many more, "
                                                              "drawn from their own stream, is above ``threshold`` "
                                                              "too (asked where the K could still pass so): a GO is "
                                                              "kept as ``recheck_pool`` starts one, on one estimate "
                                                              "from K + this futures, not dropped for one unlucky "
                                                              "future of 16; a GO taken back brakes the car in the "
                                                              "crossing, where 12 of 14 collisions after a GO were "
                                                              "hit (validation 1,953,000-1,953,999, benchmarks/"
                                                              "belief_tracks_diagnose.py; two at 1 of 16); 0: a "
                                                              "held GO is kept on its K alone")
    start_brake: float = param(0.0, "m/s²", ge=0, le=10, doc="a GO to start (after a YIELD, or the first) is "
                                                          "taken only where at most ``threshold`` of its futures "
                                                          "(the decision's K and the recheck's, pooled as "
                                                          "``recheck_pool`` says) collide or make another road "
                                                          "user brake harder than this that does not brake so hard "
                                                          "when the ego stops instead (the same future played with "
                                                          "set-point 0): the safe-braking criterion of MOBIL "
                                                          "(Kesting, Treiber, Helbing 2007, b_safe), a gap the ego "
                                                          "takes only where nobody must brake hard or yield for it. "
                                                          "Why: the GOs taken back before collisions had counted on "
                                                          "a car yielding or braking hard for the ego (validation "
                                                          "1,953,000-1,953,999, benchmarks/belief_tracks_takeback.py"
                                                          "), which the real car, or its track half a second later, "
                                                          "did not; a held GO is judged as before; 0: off")
    start_brake_share: float = param(0.0, ge=0, le=1, doc="with ``start_brake``: a GO starts where at most this "
                                                          "share of its futures (pooled as the collisions are) "
                                                          "force such a brake, the collisions judged as before; "
                                                          "0: a forced brake counts as a collision against "
                                                          "``threshold``")
    start_brake_yield: bool = param(False, doc="with ``start_brake``: a road user the regulation holds (yielding) "
                                               "in GO's play and not when the ego stops counts as a forced brake "
                                               "too, whatever its deceleration: a car standing at its line held "
                                               "for the ego's GO brakes at 0 m/s², and four of the takebacks before "
                                               "a collision were such a car pulling away (benchmarks/"
                                               "belief_tracks_takeback.py); False: decelerations alone")
    confirm: int = param(1, "decisions", ge=1, le=10, doc="GO only once this many decisions running found GO safe "
                                                          "(a held GO is kept while it stays safe): a GO that one "
                                                          "draw of K futures finds safe right after risky ones is "
                                                          "often taken back half a second later, the car braking in "
                                                          "the crossing; 1: the decision of the moment")
    confirm_risk: float = param(0.0, ge=0, le=1, doc="with ``confirm`` > 1: a decision counts towards the run of "
                                                     "decisions that found GO safe when GO's collision probability "
                                                     "there was at most this (or ``threshold``, the larger): a GO "
                                                     "is still held after a clearly risky decision, not after a "
                                                     "marginal one; 0: only safe decisions count (``confirm`` as "
                                                     "it is), 1: every decision but the episode's first counts")
    confirm_after: int = param(0, "env steps", ge=0, le=10, doc="with ``confirm`` > 1: a row whose GO is safe "
                                                               "but not yet confirmed decides again this many env "
                                                               "steps later, not at its next regular decision "
                                                               "(``repeat``), so the confirmation takes that long "
                                                               "instead of half a second; 0: at the regular "
                                                               "decision")
    confirm_first: bool = param(False, doc="with ``confirm`` > 1: the episode's first decision goes when it finds "
                                           "GO safe (``recheck`` still asked), as if the decisions before it had: "
                                           "``confirm`` holds a GO right after one found unsafe, and the first "
                                           "has none before it (where the planner on tracks lost arrivals the "
                                           "planner on truth made, 3 of 24 at the truth's first GO were this "
                                           "one: benchmarks/belief_tracks_lost.py); False: it needs ``confirm`` "
                                           "decisions like any other GO")
    committed_choice: bool = param(False, doc="once the ego is past the stop line (by more than "
                                              "``committed_from``), a decision that would YIELD there chooses "
                                              "between carrying on (GO's plan) and stopping (YIELD's: set-point 0, "
                                              "held to the episode's end, standing in the junction), each judged on "
                                              "the same K futures (the decision's own draws): it carries on where "
                                              "GO's collision share is lower than stopping's. Past the line a YIELD "
                                              "brakes the car into the crossing lane (the screen's collision "
                                              "replays, validation seeds 1,930,000-1,930,499: 10 of 12 a GO taken "
                                              "back at the next decision, the ego hit 0.7-12.6 s later braking or "
                                              "standing there); False: YIELD is always the stop")
    committed_from: float = param(0.0, "m", ge=0, le=20, doc="with ``committed_choice``: how far the ego's front "
                                                            "must be past the stop line (stop_line_offset) for the "
                                                            "choice between carrying on and stopping")
    committed_margin: float = param(0.0, ge=0, le=1, doc="with ``committed_choice``: carry on where GO's collision "
                                                         "share is below stopping's plus this (0: strictly lower, "
                                                         "a tie stops; 0.01 at K 16: a tie carries on, both plans "
                                                         "colliding in as many futures, the ego out of the crossing "
                                                         "lane sooner)")
    wait_back: float = param(0.0, "m", ge=0, le=10, doc="YIELD stops this much farther before the stop line than "
                                                       "the approach's 0.5 m (av_gym.wrappers.MARGIN): a waiting ego "
                                                       "at its line has its front 0.7-0.9 m from it, where wrecks of "
                                                       "the crossing traffic sliding into the south exit and a car "
                                                       "straddling the line backing up (highway-env's IDM brakes "
                                                       "into reverse) hit it (benchmarks/belief_tracks_waiting.py); "
                                                       "0: at the line")
    wait_gap: float = param(0.0, "m", ge=0, le=10, doc="YIELD also stops this far behind the nearest road user ahead "
                                                      "of the ego (its centre within 2 m of the ego's axis, 30 m, "
                                                      "any heading), whichever place comes first: the ego's set-point "
                                                      "follows the stop line alone and ran into, or was backed into "
                                                      "by, a car or a wreck standing over the line. It reads where "
                                                      "that road user is now, not its speed, and counts moving "
                                                      "traffic too (a leader driving away, a crossing car passing "
                                                      "in front): YIELD then stops wait_gap behind where it is at "
                                                      "each step, a stop that moves on as it does; 0: the line alone")
    # at most 1.5 m: from 2 m on the grown box reaches every car passing in the adjacent opposite lane (4 m lanes,
    # 2 m wide cars) and a follower queued at highway-env's 2 m gap, so every future would "collide"
    track_margin: float = param(0.0, "m", ge=0, le=1.5, doc="a clearance the futures demand: a future counts as a "
                                                         "collision of the ego where another road user comes within "
                                                         "this of the ego's box (the box grown by it on every side, "
                                                         "av_gym/sim/kernels._near_ego_row), not only where the boxes "
                                                         "touch: a near miss in the model is a miss to avoid, so a "
                                                         "GO must be safe against tracks a little off their true "
                                                         "place and speed (chance-constrained planning's answer to "
                                                         "state error, which a probability threshold, counting "
                                                         "futures, cannot express). The real episode's collision "
                                                         "test and the others' pairs are unchanged; 0: contact only")
    track_margin_scope: Literal["every", "start"] = param(
        "every", doc="where the agent's decisions demand the margin: every decision's futures (every), or only a "
                     "GO to start, a held GO kept on contact alone (start: a GO taken back for a near miss brakes "
                     "the car in the crossing, where the margin at every decision, 0.5 m on validation seeds "
                     "1,944,000-1,944,499, gave 16 collisions against the preset's 13); a teacher's labels and the "
                     "shield's second opinion always demand it")


class BeliefPlanner:
    """The planner for the rows of a :class:`~av_gym.batched.left_turn.BatchedLeftTurn` (traffic mode): the route
    belief of each row's drivers (:meth:`read`, at every env step) and the collision probability of GO now
    (:meth:`go_collision`)."""

    def __init__(self, params: BeliefLookaheadParams | None = None, signals: TurnSignalsParams | None = None,
                 n_rows: int = 0, perception: Any = None) -> None:
        self.params = p = params or BeliefLookaheadParams()
        # on tracks (a batch's BatchedPerception): the road as the tracker has it, and the road users it has not
        # confirmed (agents/track_prior.py); on truth the engine's own vehicles
        self.tracks = None
        if perception is not None:
            from agents.track_prior import TrackBelief

            self.tracks = TrackBelief(p, perception, n_rows)
        self.signals = signals or TurnSignalsParams()
        self.K, self.threshold, self.seed, self.gate = int(p.samples), float(p.threshold), int(p.seed), float(p.gate)
        self.filter = DriverIntent(self.signals, floor=float(p.floor))
        self.counts: list[dict[int, np.ndarray]] = [{} for _ in range(n_rows)]
        self.safe_run = np.zeros(n_rows, dtype=int)  # per row: decisions running that found GO safe (confirm)
        self.safe_run[:] = int(p.confirm) - 1 if p.confirm_first else 0
        self.confirm_at = np.full(n_rows, -1)  # per row: the env step of its early confirming decision, -1: none
        self._tables = None
        self.particles = PARTICLES
        # decisions made, and the wall-clock and CPU seconds of this process spent on them
        self.labelled, self.seconds, self.cpu_seconds = 0, 0.0, 0.0

    # ------------------------------------------------------------------------------------------- the belief
    def reset(self, rows) -> None:
        """Forget the drivers of the rows ``rows`` (their new episodes)."""
        for r in np.asarray(rows, dtype=int):
            while r >= len(self.counts):
                self.counts.append({})
            self.counts[r] = {}
        if len(self.counts) > len(self.safe_run):
            grow = len(self.counts) - len(self.safe_run)
            self.safe_run = np.concatenate([self.safe_run, np.zeros(grow, int)])
            self.confirm_at = np.concatenate([self.confirm_at, np.full(grow, -1)])
        # confirm_first: the episode starts with the run of safe decisions confirm asks for, less this one
        self.safe_run[np.asarray(rows, dtype=int)] = int(self.params.confirm) - 1 if self.params.confirm_first else 0
        self.confirm_at[np.asarray(rows, dtype=int)] = -1
        if self.tracks is not None:
            self.tracks.reset(rows)

    def read(self, engine, rows, intent: np.ndarray) -> None:
        """One indicator reading per driver the car sees: ``intent`` (len(rows), M, 2) is ``obs["intent"]`` of
        ``rows`` (its column 1: the reading attached to each described object), the engine as it was observed.
        A driver beyond the indicator sensor's range gives no reading (its 0 there is not a "none seen")."""
        rows = np.asarray(rows, dtype=int)
        self.reset([r for r in rows if r >= len(self.counts)])
        if self.tracks is not None:  # the engine of the car's tracks (the described ones alive) for the true one
            engine = self.tracks.read(engine, rows, intent)
        slots, present, d = described(engine, rows)
        vid = np.take_along_axis(engine.traffic.vid[rows], slots, 1)
        read = present & (d <= float(self.signals.max_range))
        sig = np.asarray(intent)[:, : slots.shape[1], 1]
        col = np.where(sig < 0, 0, np.where(sig > 0, 2, 1))  # counts of (-1, 0, +1) readings
        for n, m in zip(*np.nonzero(read)):
            c = self.counts[rows[n]].setdefault(int(vid[n, m]), np.zeros(3, dtype=int))
            c[col[n, m]] += 1

    def turn_probabilities(self, rows, vids: np.ndarray) -> np.ndarray:
        """P(turn | readings) (right, straight, left) for vehicles ``vids`` (n, N) of ``rows``: the posterior's
        turn marginal (uniform for a driver never read)."""
        n, N = vids.shape
        counts = np.zeros((n, N, 3))
        for i, r in enumerate(rows):
            known = self.counts[r]
            if known:
                for j, v in enumerate(vids[i]):
                    c = known.get(int(v))
                    if c is not None:
                        counts[i, j] = c
        post = self.filter.posterior(counts.reshape(-1, 3)).reshape(n, N, 3, 3).sum(axis=3)
        return post

    # ------------------------------------------------------------------------------------------- the futures
    def go_collision(self, engine, rows, K: int | None = None, stream: tuple = (),
                     margin: float | None = None) -> np.ndarray:
        """The estimated probability that GO now ends in a collision, for each of ``rows``: the share of K
        futures (drawn as the module docstring says; ``K`` default ``samples``; ``stream``: more entropy appended
        to every seed sequence, for independent futures of the same moment) whose GO play collides."""
        return self._plan_collision(engine, rows, K, stream, play_go_fast, margin)

    def stop_collision(self, engine, rows, K: int | None = None, stream: tuple = (),
                       margin: float | None = None) -> np.ndarray:
        """:meth:`go_collision` for the plan of stopping (YIELD past the stop line: the lowest set-point, held to
        the episode's end) on the same futures (the same ``K`` and ``stream`` draw the same ones)."""
        return self._plan_collision(engine, rows, K, stream, play_stop_fast, margin)

    def _plan_collision(self, engine, rows, K: int | None, stream: tuple, play,
                        margin: float | None = None) -> np.ndarray:
        """The share of K futures of each of ``rows`` that ``play`` (a function of the future engine: which of its
        rows end without a collision) finds colliding."""
        import time

        rows = np.asarray(rows, dtype=int)
        if len(rows) == 0:
            return np.zeros(0)
        start, cpu = time.perf_counter(), time.process_time()
        if self.tracks is not None:
            engine = self.tracks.current(engine)
        K = int(K or self.K)
        f = self.futures(engine, rows, K, stream, margin)
        if self.tracks is not None:
            self.tracks.fill(f, rows, self.seed, K, stream)
        safe = play(f)
        self.labelled += len(rows)
        self.seconds += time.perf_counter() - start
        self.cpu_seconds += time.process_time() - cpu
        return 1.0 - safe.reshape(len(rows), K).mean(axis=1)

    def labels(self, engine, rows) -> np.ndarray:
        """GO where the estimated collision probability of GO is at most ``threshold``, else YIELD."""
        return self.label_of(self.go_collision(engine, rows))

    def label_of(self, p: np.ndarray) -> np.ndarray:
        """The planner's choice for GO collision probabilities ``p`` (:meth:`go_collision`): GO where at most
        ``threshold``, else YIELD."""
        return np.where(np.asarray(p) <= self.threshold + 1e-12, GO, YIELD).astype(np.int64)

    def decide(self, engine, rows, choice: np.ndarray, step: np.ndarray) -> np.ndarray:
        """The held choices (GO / YIELD) of ``rows`` after this env step (``choice``, ``step``: the rows' held
        choices and env steps since their episode began): every ``repeat`` steps the rows decide again unless their
        choice is final (``commit``: never; once GO; or once past the stop line or too fast to stop before it), and
        ``confirm_after`` steps after a GO found safe but not yet confirmed."""
        rows, choice = np.asarray(rows, dtype=int), np.array(choice, copy=True)
        step = np.broadcast_to(np.asarray(step), rows.shape)
        due, final = self.live(engine, rows, choice, step)
        choice[final] = GO
        if due.any():
            r, held = rows[due], choice[due]
            p = self._decision_collision(engine, r, held)
            K, R = self.K, int(self.params.recheck)
            pool = bool(self.params.recheck_pool) and R > 0
            # pooled: a GO to start is safe at this decision where its K futures could still pass with the recheck's
            # R all safe (the pooled share K p / (K + R) at most threshold); a held GO is kept on its K alone
            safe = self.label_of(np.where(held != GO, p * K / (K + R), p) if pool else p) == GO
            new = self.confirmed(r, p, safe)
            early = (new != GO) & safe & (int(self.params.confirm_after) > 0)
            self.confirm_at[r] = np.where(early, step[due] + int(self.params.confirm_after), -1)
            ask = (new == GO) & (held != GO) & (R > 0)
            if ask.any():  # a GO to start: the futures of the recheck's own streams must find it safe too
                p2 = self.go_collision(engine, r[ask], R, (RECHECK_STREAM,))
                new[ask] = self.label_of((K * p[ask] + R * p2) / (K + R) if pool else p2)
            if float(self.params.start_brake) > 0:
                new = self.unforced(engine, r, new, held)
            if int(self.params.keep_recheck) > 0:
                new = self.kept(engine, r, p, new, held)
            if self.params.committed_choice:
                new = self.carry_on(engine, r, p, new, held)
            choice[due] = new
        return choice

    def kept(self, engine, rows: np.ndarray, p: np.ndarray, new: np.ndarray, held: np.ndarray) -> np.ndarray:
        """``keep_recheck``: the choices ``new`` of ``rows`` (GO collision probabilities ``p`` on the decision's K
        futures, held choices ``held``) with a held GO kept where ``new`` takes it back but the pooled share of the
        K and ``keep_recheck`` more futures (:data:`KEEP_STREAM`, judged as a held GO is) is at most ``threshold``;
        a kept GO's run of safe decisions (``confirm``) is kept whole."""
        K, R = self.K, int(self.params.keep_recheck)
        # only where the K alone could still pass with all R safe: K p / (K + R) at most threshold
        back = np.flatnonzero((np.asarray(held) == GO) & (np.asarray(new) != GO)
                              & (np.asarray(p) * K / (K + R) <= self.threshold + 1e-12))
        if len(back) == 0:
            return new
        margin = 0.0 if self.params.track_margin_scope == "start" else None  # a held GO's futures, as p's
        p2 = self.go_collision(engine, rows[back], R, (KEEP_STREAM,), margin=margin)
        keep = back[self.label_of((K * np.asarray(p)[back] + R * p2) / (K + R)) == GO]
        new = np.array(new, copy=True)
        new[keep] = GO
        self.safe_run[rows[keep]] = np.maximum(self.safe_run[rows[keep]], int(self.params.confirm))
        return new

    def unforced(self, engine, rows: np.ndarray, new: np.ndarray, held: np.ndarray) -> np.ndarray:
        """``start_brake``: the choices ``new`` of ``rows`` (held choices ``held``) with a GO to start kept only
        where the share of its futures that collide or force a hard brake (:meth:`forced_share`: the decision's K,
        and with ``recheck`` the recheck's own, pooled under ``recheck_pool``) is at most ``threshold``."""
        start = np.flatnonzero((np.asarray(new) == GO) & (np.asarray(held) != GO))
        if len(start) == 0:
            return new
        K, R = self.K, int(self.params.recheck)
        c, q = self.forced_share(engine, rows[start], K, ())
        if R > 0:
            c2, q2 = self.forced_share(engine, rows[start], R, (RECHECK_STREAM,))
            pool = lambda a, a2: (K * a + R * a2) / (K + R) if self.params.recheck_pool else np.maximum(a, a2)  # noqa
            c, q = pool(c, c2), pool(q, q2)
        share = float(self.params.start_brake_share)
        ok = self.label_of(c + q) == GO if share == 0 else q <= share + 1e-12
        new = np.array(new, copy=True)
        new[start] = np.where(ok, new[start], YIELD)
        return new

    def forced_share(self, engine, rows: np.ndarray, K: int, stream: tuple = ()) -> tuple[np.ndarray, np.ndarray]:
        """The shares of K futures of each of ``rows`` (:meth:`go_collision`'s draws for ``K`` and ``stream``) in
        which GO collides, and in which it does not but some road user brakes harder than ``start_brake`` (m/s²)
        while it brakes less hard in the same future when the ego stops at once (set-point 0): a brake the ego's GO
        forces on it."""
        import time

        rows = np.asarray(rows, dtype=int)
        start, cpu = time.perf_counter(), time.process_time()
        e = self.tracks.current(engine) if self.tracks is not None else engine

        def drawn():  # the same futures each call: every draw from the decision's own seed sequences
            f = self.futures(e, rows, K, stream)
            if self.tracks is not None:
                self.tracks.fill(f, rows, self.seed, K, stream)
            return f

        f = drawn()
        safe, a_go, y_go, steps = play_min_acc(f, float(f.speeds[-1]))
        # stopping over the same window, future by future: a stopped ego's future runs to the time limit, the GO's
        # ends on arrival. Each future's own GO end, not the longest of the call: a row's shares must not depend on
        # which other rows are asked with it (per env and batch decide alike)
        _, a_stop, y_stop, _ = play_min_acc(drawn(), float(f.speeds[0]), steps)
        b = float(self.params.start_brake)
        forced = ((a_go < -b) & (a_stop >= -b)).any(axis=1)
        if self.params.start_brake_yield:
            forced |= (y_go & ~y_stop).any(axis=1)
        self.seconds += time.perf_counter() - start
        self.cpu_seconds += time.process_time() - cpu
        n = len(rows)
        return (~safe).reshape(n, K).mean(axis=1), (safe & forced).reshape(n, K).mean(axis=1)

    def _decision_collision(self, engine, rows: np.ndarray, held: np.ndarray) -> np.ndarray:
        """:meth:`go_collision` of ``rows`` at a decision (``held``: their held choices), judged as
        :meth:`_held_scoped` says."""
        return self._held_scoped(self.go_collision, engine, rows, held)

    def _held_scoped(self, collision, engine, rows: np.ndarray, held: np.ndarray | None) -> np.ndarray:
        """``collision`` (:meth:`go_collision` or :meth:`stop_collision`: which plan is played) of ``rows`` at a
        decision whose held choices are ``held``: under ``track_margin_scope`` start the rows holding GO are judged
        without the clearance margin (on contact alone), the others with it (the same futures either way: a row's
        draws do not depend on the batch it is in); under ``every`` (or ``held`` None) all with it. The one split
        that both the decision's GO and ``committed_choice``'s stopping use, so the two are judged alike."""
        if self.params.track_margin_scope == "every" or held is None:
            return collision(engine, rows)
        p, kept = np.empty(len(rows)), np.asarray(held) == GO
        if kept.any():
            p[kept] = collision(engine, rows[kept], margin=0.0)
        if (~kept).any():
            p[~kept] = collision(engine, rows[~kept])
        return p

    def carry_on(self, engine, rows: np.ndarray, p: np.ndarray, new: np.ndarray,
                 held: np.ndarray | None = None) -> np.ndarray:
        """``committed_choice``: the choices ``new`` of ``rows`` (GO collision probabilities ``p`` at this
        decision, :meth:`_decision_collision` of the held choices ``held``) with GO where the row would YIELD past
        the stop line (by more than ``committed_from``) and stopping there collides in more of the same futures
        than carrying on (``committed_margin``: or in fewer by less than this). Stopping is judged as ``p`` was:
        under ``track_margin_scope`` start a row holding GO on contact alone."""
        back = np.flatnonzero(np.asarray(new) != GO)
        if len(back) == 0:
            return new
        past = engine.truth(rows[back])["stop_line_offset"] > float(self.params.committed_from)
        back = back[past]
        if len(back) == 0:
            return new
        new = np.array(new, copy=True)
        # the decision's own K futures and stream, with the clearance margin where p had it
        p_stop = self._held_scoped(self.stop_collision, engine, rows[back],
                                   None if held is None else np.asarray(held)[back])
        margin = float(self.params.committed_margin)
        new[back] = np.where(np.asarray(p)[back] - p_stop < margin - 1e-12, GO, new[back])
        return new

    def yield_margin(self, engine, rows) -> np.ndarray:
        """How far before the stop line (m, (len(rows),)) YIELD stops for ``rows``: the approach's margin plus
        ``wait_back``, farther where the nearest road user ahead (the planner's own road users: the tracks on
        tracks; any heading, its centre within 2 m of the ego's axis and less than 30 m ahead) leaves less than
        ``wait_gap`` before the line: there YIELD stops ``wait_gap`` behind its rear (taken as ``LENGTH / 2``
        behind its centre along the ego's axis). Measured from the distance to the line that
        :func:`av_gym.wrappers.meta_actions` reads (``obs["turn"]``'s ``to_stop_line``, clipped at its 30 m
        scale), so that the stop falls ``wait_gap`` behind the road user also while the ego is farther out."""
        from av_gym.estimation.turn_features import EGO_SCALES
        from av_gym.sim.batched import LENGTH
        from av_gym.wrappers import MARGIN

        rows = np.asarray(rows, dtype=int)
        p = self.params
        margin = np.full(len(rows), MARGIN + float(p.wait_back))
        if float(p.wait_gap) <= 0 or len(rows) == 0:
            return margin
        e = self.tracks.current(engine) if self.tracks is not None else engine
        t = e.traffic
        s = e.ego_slot(rows)
        ex, ey, eh = t.x[rows, s], t.y[rows, s], t.h[rows, s]
        dx, dy = t.x[rows] - ex[:, None], t.y[rows] - ey[:, None]
        ahead = np.cos(eh)[:, None] * dx + np.sin(eh)[:, None] * dy
        lateral = -np.sin(eh)[:, None] * dx + np.cos(eh)[:, None] * dy
        # any heading: a car held over the line, or a wreck turned across the ego's lane (2 m: two half-widths)
        lead = t.alive[rows] & ~t.ego[rows] & (ahead > 0) & (ahead < 30.0) & (np.abs(lateral) < 2.0)
        # the ego's front to the leader's rear (m), and the ego's front to the stop line
        gap = np.where(lead, ahead - LENGTH, np.inf).min(axis=1)
        # the ego's own state, as meta_actions reads it: the turn features clip to_stop_line at its scale (30 m;
        # the ego starts up to ~40 m out), so a margin from the unclipped distance stopped it up to 10 m short
        scale = EGO_SCALES["to_stop_line"]
        d_stop = np.clip(-engine.truth(rows)["stop_line_offset"], -scale, scale)
        # fmax, not maximum: a NaN distance (a non-finite stop_line_offset) falls back to the line's margin; a NaN
        # margin made meta_actions answer FASTER, so YIELD would have sped up
        return np.fmax(margin, d_stop - (gap - float(p.wait_gap)))

    def meta_actions(self, engine, rows, choice: np.ndarray, turn: np.ndarray) -> np.ndarray:
        """The meta-actions (len(rows),) that move the set-point of ``rows`` towards their ``choice`` (GO or YIELD,
        (len(rows),)) given their ``turn`` features ((len(rows), n)): :func:`av_gym.wrappers.meta_actions` at
        :meth:`yield_margin`, so that YIELD stops where ``wait_back`` / ``wait_gap`` ask. The one place every driver
        of this planner (BeliefLookahead.act, eval.batched, the replay tools in benchmarks/) makes its actions, so a
        replay drives what the preset drives. On tracks, :meth:`read` the rows at this step first."""
        from av_gym.wrappers import meta_actions

        return meta_actions(np.asarray(choice), np.asarray(turn), self.yield_margin(engine, rows))

    def live(self, engine, rows: np.ndarray, choice: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(due, final) masks over ``rows`` at env steps ``step`` (their held choices ``choice``): which rows decide
        now (every ``repeat`` steps, or at their early confirming step), and which of those are made GO for good
        instead of deciding (``final``). Under ``commit: go`` a row holding GO is simply not due (``final`` stays
        all False: its GO is kept, not set); under ``commit: stop`` a due row is final once the ego is over 1 m past
        the stop line, whatever it held (a YIELD there becomes GO), or holds GO too fast to stop before the line
        (:meth:`committed`). Neither kind decides."""
        due = (step % int(self.params.repeat) == 0) | (self.confirm_at[rows] == step)
        final = np.zeros(len(rows), bool)
        if self.params.commit == "go":
            due &= choice != GO
        elif self.params.commit == "stop" and due.any():
            # judged at the stop YIELD would ask for (wait_back / wait_gap move it back), not the line's MARGIN
            final[due] = self.committed(engine, rows[due], choice[due], self.yield_margin(engine, rows[due]))
            due &= ~final
        return due, final

    def confirmed(self, rows: np.ndarray, p: np.ndarray, safe: np.ndarray | None = None) -> np.ndarray:
        """The choices of ``rows`` at a decision whose GO collision probabilities (:meth:`go_collision`) are
        ``p``: GO where GO is safe at this decision (``safe``, default ``p`` at most ``threshold``) and the
        ``confirm`` - 1 before it counted (safe, or at most ``confirm_risk``), else YIELD (a held GO stays while it
        is safe: it was started so)."""
        safe = self.label_of(p) == GO if safe is None else np.asarray(safe, bool)
        counts = safe | (np.asarray(p) <= max(self.threshold, float(self.params.confirm_risk)) + 1e-12)
        self.safe_run[rows] = np.where(counts, self.safe_run[rows] + 1, 0)
        return np.where(safe & (self.safe_run[rows] >= int(self.params.confirm)), GO, YIELD).astype(np.int64)

    @staticmethod
    def committed(engine, rows, choice, margin: np.ndarray | float | None = None) -> np.ndarray:
        """The choice is GO for good: the ego is over 1 m past the stop line (GapAcceptance's commitment: stopping
        inside the intersection puts the car in the crossing traffic's way), or it holds GO and is too fast to stop
        ``margin`` m (one or one per row; default av_gym.wrappers.MARGIN, the line's) before the line at the
        approach's comfortable deceleration (the YIELD set-point av_gym.wrappers.meta_action would ask for could no
        longer be met). :meth:`live` passes :meth:`yield_margin`, where YIELD stops."""
        from av_gym.wrappers import DECEL, MARGIN

        if len(rows) == 0:
            return np.zeros(0, bool)
        tr = engine.truth(np.asarray(rows))
        offset = tr["stop_line_offset"]
        d0 = MARGIN if margin is None else np.asarray(margin, dtype=float)
        v_ok = np.sqrt(2.0 * DECEL * np.maximum(-offset - d0, 0.0))
        return (offset > 1.0) | ((np.asarray(choice) == GO) & (tr["speed"] > v_ok))

    def futures(self, engine, rows: np.ndarray, K: int | None = None, stream: tuple = (),
                margin: float | None = None):
        """A future engine of len(rows)·K rows (``K`` default ``samples``): each row repeated K times, its hidden
        draws replaced (from ``SeedSequence([seed, episode_seed, tick, *stream])``); ``margin``: the clearance
        margin (m) the futures demand, default ``track_margin``."""
        K = int(K or self.K)
        T = engine.T
        if self._tables is not T:
            self._tables = T
            from agents.track_prior import lane_kinds

            self._kind, self._origin, self._dest = lane_kinds(T)
            self._cross = {(int(o), int(d)): k for k, (kd, o, d) in
                           enumerate(zip(self._kind, self._origin, self._dest)) if kd == 1}
            self._approach = {int(o): k for k, (kd, o) in enumerate(zip(self._kind, self._origin)) if kd == 0}
            self._exit = {int(d): k for k, (kd, d) in enumerate(zip(self._kind, self._dest)) if kd == 2}
            # the same maps as arrays over approach / exit indices 0-3 (index -1, "none", gives -1 as .get does)
            self._approach_of, self._exit_of, self._cross_of = np.full(5, -1), np.full(5, -1), np.full((5, 5), -1)
            for table, keys in ((self._approach_of, self._approach), (self._exit_of, self._exit),
                                (self._cross_of, self._cross)):
                for key, k in keys.items():
                    table[key] = k
        n, N = len(rows), engine.traffic.N  # a fork keeps the slot count
        drivers = engine.traffic.alive[rows] & ~engine.traffic.ego[rows] & ~engine.traffic.plain[rows]  # (n, N)
        # every draw of a decision from its own stream: the planner's seed, the episode, the decision's tick
        P = self.particles
        u, u_b = np.zeros((n, K, N)), np.zeros((n, K, N))
        delta, target, hold = np.zeros((n, N, P)), np.zeros((n, N, P)), np.zeros((n, N, P), bool)
        logq = np.zeros((n, N, P))
        spawn_rngs = []
        for i, r in enumerate(rows):
            ss = np.random.SeedSequence([self.seed, int(engine.episode_seed[r]) % 2**63, int(engine.ticks[r]),
                                         *stream])
            child, spawn = ss.spawn(2)
            g = np.random.default_rng(child)
            # a fixed width of draws per stream, so that a driver's draws depend on its place in the road order
            # only, not on how many slots this batch happens to hold (the batch and a one-row view agree)
            W = draw_width(N)
            u[i], u_b[i] = g.random((K, W))[:, :N], g.random((K, W))[:, :N]
            delta[i], target[i], hold[i], logq[i] = (a[:N] for a in self._behaviour_prior(engine.prior, g, (W, P)))
            spawn_rngs += [np.random.Generator(np.random.PCG64(s)) for s in spawn.spawn(K)]
        # the rows' own generators hold the real future: the futures never get them, only fresh spawn streams
        f = engine.fork(rows, K, rngs=spawn_rngs)
        t = f.traffic
        delta, target, hold = self._behaviour_posterior(engine, rows, delta, target, hold, logq, u_b)  # (n, K, N)
        dest = self._destinations(engine, rows, u)  # (n, K, N)
        # the route a spawn gives (o_i → ir_i, ir_i → il_d, il_d → o_d) and where along it the driver is now: the
        # step of its current lane; follow_road moves it on at the next tick when it is already past a lane's end
        src = engine.traffic
        lane = src.lane[rows]
        kind, origin = self._kind[lane], self._origin[lane]
        origin = np.where(kind == 2, (self._dest[lane] + 2) % 4, origin)  # on the exit road the origin is unused
        o = np.broadcast_to(origin[:, None, :], dest.shape)
        appr, cross, exit_ = self._approach_of[o], self._cross_of[o, dest], self._exit_of[dest]
        route = np.stack([appr, cross, exit_], axis=-1).reshape(n * K, N, 3)
        rpos = np.broadcast_to(kind[:, None, :], dest.shape).reshape(n * K, N)
        m = np.repeat(drivers, K, axis=0)  # (n·K, N)
        t.route = np.where(m[..., None], route, t.route)
        t.rpos = np.where(m, rpos, t.rpos)
        t.tlane = np.where(m, np.take_along_axis(t.route, np.clip(t.rpos, 0, 2)[..., None], 2)[..., 0], t.tlane)
        t.delta = np.where(m, delta.reshape(n * K, N), t.delta)
        t.target = np.where(m, target.reshape(n * K, N), t.target)
        t.yielding = np.where(m, hold.reshape(n * K, N), t.yielding)
        t.ego_margin = float(self.params.track_margin if margin is None else margin)  # the futures' clearance (m)
        return f

    def _behaviour_prior(self, spawn: SpawnPrior, g: np.random.Generator, shape: tuple) -> tuple:
        """Particles of a driver's behaviour (IDM exponent, set-point, held by the regulation now) from the
        traffic's own prior (``spawn``, the engine's): a spawn's delta ~ U(3.5, 4.5) and set-point = its spawn
        speed 8 + N(0, 1) m/s; a driver
        the regulation released cruises at the lane's limit instead, one it holds has set-point 0 (each with
        ``P_RELEASED`` / ``P_HELD``, about the shares on validation states). Returns them and their log importance
        weights (prior over proposal)."""
        delta = spawn.deltas(g, shape)
        # stratified: a fixed share of the particles per kind (spawn set-point, released, held), each weighed
        # by its prior over its share, so that the rare kinds are always there for the observation to pick
        P = shape[-1]
        n_rare = max(1, P // 8)
        kind = np.zeros(P, dtype=int)
        kind[P - 2 * n_rare: P - n_rare], kind[P - n_rare:] = 1, 2
        kind = np.broadcast_to(kind, shape)
        target = np.where(kind == 1, SPEED_LIMIT, spawn.speeds(g, shape))
        hold = kind == 2
        share = np.array([(P - 2 * n_rare) / P, n_rare / P, n_rare / P])
        prior = np.array([1.0 - P_RELEASED - P_HELD, P_RELEASED, P_HELD])
        return delta, np.where(hold, 0.0, target), hold, np.log(prior / share)[kind]

    def _behaviour_posterior(self, engine, rows, delta, target, hold, logq, u):
        """Resample the behaviour particles (n, N, P) by the likelihood of each driver's observed acceleration
        (its last command, ``traffic.acc``) under IDM with that particle: ``a = clip(a_max (1 - (v / v0)^delta) -
        a_int)``, the interaction term ``a_int`` computed from the observed leader (it does not depend on the
        driver's own draws), Gaussian noise ``ACC_SIGMA`` (on tracks with ``track_acc_sigma`` added in quadrature);
        then K draws per driver (n, K, N) by inverse CDF."""
        from av_gym.sim.batched import ACC_MAX, COMFORT_ACC_MAX, not_zero

        src = engine.traffic
        sub = src.subset(rows)
        v, lane = sub.v, sub.lane
        limit = engine.T.speed_limit[lane]
        # the leader's term: IDM with the set-point at the speed (free term 0 there), minus that free term
        sub.target = np.maximum(v, 0.0)
        sub.delta = np.full_like(sub.delta, 4.0)  # the free term is 0 at the set-point whatever delta: no hidden draw
        free0 = COMFORT_ACC_MAX * (1 - np.power(np.maximum(v, 0) / np.abs(not_zero(np.clip(sub.target, 0, limit))),
                                                sub.delta))
        a_int = free0 - sub.leader_idm()  # (n, N), >= 0
        v0 = np.abs(not_zero(np.clip(target, 0, limit[..., None])))
        a = COMFORT_ACC_MAX * (1 - np.power(np.maximum(v, 0)[..., None] / v0, delta)) - a_int[..., None]
        a = np.clip(a, -ACC_MAX, ACC_MAX)
        # on tracks the measured acceleration carries the intent features' error besides the model's spread
        sigma = ACC_SIGMA if self.tracks is None else float(np.hypot(ACC_SIGMA, self.params.track_acc_sigma))
        logw = -0.5 * ((a - src.acc[rows][..., None]) / sigma) ** 2
        ok = ~(src.crashed[rows] | src.ego[rows] | ~src.alive[rows])
        logw = np.where(ok[..., None], logw, 0.0) + logq
        w = np.exp(logw - logw.max(axis=-1, keepdims=True))
        cdf = np.cumsum(w, axis=-1)
        cdf /= cdf[..., -1:]
        k = (u[..., None] >= np.swapaxes(cdf, 0, 0)[:, None]).sum(axis=-1)  # (n, K, N)
        k = np.minimum(k, w.shape[-1] - 1)
        pick = lambda a_: np.take_along_axis(np.broadcast_to(a_[:, None], (*u.shape, a_.shape[-1])),  # noqa: E731
                                             k[..., None], -1)[..., 0]
        return pick(delta), pick(target), pick(hold)

    def _destinations(self, engine, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Each driver's destination per future (n, K, N), drawn by inverse CDF from the uniforms ``u``:
        P(turn | readings) on the approach; that times the crossing lanes its pose still fits inside the
        intersection; the exit it is on after it."""
        src, T = engine.traffic, engine.T
        lane = src.lane[rows]  # (n, N): the closest lane, a function of the pose
        kind, origin = self._kind[lane], self._origin[lane]
        p_turn = self.turn_probabilities(rows, src.vid[rows])  # (n, N, 3): right, straight, left
        # destinations in the same order: right (o-1), straight (o+2), left (o+1)
        cand = (origin[..., None] + np.array([-1, 2, 1])) % 4  # (n, N, 3)
        p = p_turn.copy()
        inside = kind == 1
        if inside.any():
            b, j = np.nonzero(inside)
            x, y, h = src.x[rows][b, j], src.y[rows][b, j], src.h[rows][b, j]
            lanes = self._cross_of[origin[b, j][:, None], cand[b, j]]
            d = np.stack([T.distance_with_heading(lanes[:, k], x, y, h) for k in range(3)], axis=1)
            fits = d <= d.min(axis=1, keepdims=True) + self.gate
            q = p[b, j] * fits
            q = np.where(q.sum(axis=1, keepdims=True) > 0, q, fits.astype(float))
            p[b, j] = q
        p = p / p.sum(axis=-1, keepdims=True)
        cdf = np.cumsum(p, axis=-1)  # (n, N, 3)
        k = (u[..., None] >= cdf[:, None, :, :2]).sum(axis=-1)  # (n, K, N) in {0, 1, 2}
        dest = np.take_along_axis(np.broadcast_to(cand[:, None], (*u.shape, 3)), k[..., None], -1)[..., 0]
        on_exit = np.broadcast_to((kind == 2)[:, None, :], dest.shape)
        return np.where(on_exit, np.broadcast_to(self._dest[lane][:, None, :], dest.shape), dest)


def play_go_fast(f) -> np.ndarray:
    """Whether each row of the future engine ``f`` ends without a collision when the ego goes (GO at every env
    step, to the episode's end): :func:`agents.batched_oracle.play_go` without its features and margins. GO's
    meta-action needs only the ego's set-point (GO asks for the top one; meta_action: FASTER below it, SLOWER
    above, IDLE at it), so no feature is computed."""
    return play_set_point_fast(f, float(f.speeds[-1]))


def play_stop_fast(f) -> np.ndarray:
    """:func:`play_go_fast` for stopping: the lowest set-point (0 m/s) held to the episode's end, what YIELD asks
    for once the ego is past the stop line (meta_actions: no speed stops it before the line there)."""
    return play_set_point_fast(f, float(f.speeds[0]))


def set_point_meta(f, top: float) -> np.ndarray:
    """The meta-actions, one per row of the future engine ``f``, that move the ego's set-point towards ``top``
    (m/s): FASTER below it, SLOWER above, IDLE at it (1 mm/s apart counts as at it)."""
    from av_gym.sim.batched import FASTER, IDLE, SLOWER

    sp = f.traffic.target[np.arange(f.B), f.ego_slot()]
    return np.where(top > sp + 1e-3, FASTER, np.where(top < sp - 1e-3, SLOWER, IDLE))


def play_set_point_fast(f, top: float) -> np.ndarray:
    """Whether each row of the future engine ``f`` ends without a collision when the ego asks for the set-point
    ``top`` (m/s) at every env step to the episode's end (:func:`set_point_meta`)."""
    safe = np.ones(f.B, bool)
    idx = np.arange(f.B)  # the rows of the original future that ``f`` still holds
    live = np.ones(f.B, bool)  # the rows of ``f`` still playing
    while live.any():
        n = f.B
        _, terminated, truncated = f.step(set_point_meta(f, top), active=live)  # the ended rows wait as they are
        ended = (terminated | truncated) & live
        if ended.any():
            e = np.nonzero(ended)[0]
            safe[idx[e]] = ~f.traffic.crashed[e, f.ego_slot(e)]
            live &= ~ended
            if 0 < live.sum() <= n // 2:  # drop the ended rows once they are half: a copy per halving, not per end
                keep = np.nonzero(live)[0]
                idx, f, live = idx[keep], f.keep(keep), np.ones(len(keep), bool)
    return safe


def play_min_acc(f, top: float, horizon: int | np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`play_set_point_fast` of the future engine ``f`` at set-point ``top`` (m/s), also returning each road
    user's hardest command (the lowest ``traffic.acc``, m/s²; +inf where it never drove uncrashed) over the play
    and whether the regulation held it (``yielding``) after any step, each (B, N) in the slots of ``f``'s start,
    followed by vid (slots shift as vehicles leave); the ego and the vehicles that enter later are left out (+inf,
    False); and the policy steps each row played, (B,) (to its end, or to its horizon). ``horizon``: stop each row
    after this many steps, one for all or (B,) one per row (the rows still playing then count as uncrashed): a
    row's window is its own, whatever the other rows of ``f`` do."""
    t = f.traffic
    vids = np.where(t.alive & ~t.ego, t.vid, -1)  # (B, N) the start's road users
    low, held = np.full(vids.shape, np.inf), np.zeros(vids.shape, bool)
    safe = np.ones(f.B, bool)
    idx = np.arange(f.B)  # the rows of the original future that ``f`` still holds
    live = np.ones(f.B, bool)  # the rows of ``f`` still playing
    limit = np.full(f.B, np.iinfo(np.int64).max) if horizon is None else \
        np.broadcast_to(np.asarray(horizon, dtype=np.int64), (f.B,))  # each original row's own last step
    played = np.zeros(f.B, dtype=np.int64)
    steps = 0
    while True:
        live &= steps < limit[idx]  # a row past its own horizon waits as an ended one does
        if not live.any():
            break
        steps += 1
        _, terminated, truncated = f.step(set_point_meta(f, top), active=live)
        played[idx[live]] = steps
        t, v = f.traffic, vids[idx]
        driving = t.alive & ~t.ego & ~t.crashed & live[:, None]
        same = (t.vid[:, :, None] == v[:, None, :]) & driving[:, :, None] & (v[:, None, :] >= 0)
        low[idx] = np.minimum(low[idx], np.where(same, t.acc[:, :, None], np.inf).min(axis=1))
        held[idx] |= (same & t.yielding[:, :, None]).any(axis=1)
        ended = (terminated | truncated) & live
        if ended.any():
            e = np.flatnonzero(ended)
            safe[idx[e]] = ~t.crashed[e, f.ego_slot(e)]
            live &= ~ended
            if 0 < live.sum() <= f.B // 2:  # drop the ended rows once they are half, as play_set_point_fast does
                keep = np.flatnonzero(live)
                idx, f, live = idx[keep], f.keep(keep), np.ones(len(keep), bool)
    return safe, low, held, played


def described(engine, rows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The slots ``obs["turn"]`` describes for ``rows``, nearest first (BatchedLeftTurn.observe's order: a stable
    sort of the others' distances, the first ``max_objects``), whether each is within ``max_range``, and its
    distance (m)."""
    t = engine.traffic
    rows = np.asarray(rows, dtype=int)
    e = engine.ego_slot(rows)
    ex, ey = t.x[rows, e], t.y[rows, e]
    other = t.alive[rows] & ~t.ego[rows]
    d = np.where(other, np.hypot(t.x[rows] - ex[:, None], t.y[rows] - ey[:, None]), np.inf)
    order = np.argsort(d, axis=1, kind="stable")[:, : engine.max_objects]
    dn = np.take_along_axis(d, order, 1)
    max_range = getattr(engine, "max_range", None)  # the engine's own, or its TurnFeaturesParams'
    max_range = float(engine.features.max_range if max_range is None else max_range)
    return order, dn <= max_range, dn


class BeliefLookahead:
    """``belief_lookahead`` as an agent: GO when the planner finds GO safe enough, decided every ``repeat`` env
    steps until the choice is final (``commit``).
    On the batch (``vec_env=batched``) :mod:`eval.batched` drives :class:`BeliefPlanner` for every row at once; on
    the per-env stack each decision builds a one-row engine from the env's observable state
    (:func:`engine_from_env`)."""

    def __init__(self, env: gym.Env | None, params: BeliefLookaheadParams | None = None, **overrides: Any) -> None:
        p = self.params = BeliefLookaheadParams.build(params, **overrides)
        self.env, self.repeat = env, int(p.repeat)
        self.planner = BeliefPlanner(p, n_rows=1)
        self.tracks = None  # on tracks: the env's tracker as the planner reads it (at the first observation)
        self.reset()

    def reset(self) -> None:
        self._t, self._choice = 0, YIELD
        self.planner.reset([0])
        if getattr(self, "view", None) is None:
            self.view = EnvView()
        self.view.reset()

    def act(self, obs) -> int:
        engine = self.view.engine(self.env, obs)
        if self.tracks is None and _on_tracks(self.env):  # the planner on the tracker's tracks, as on the batch
            from agents.track_prior import EnvTracks

            self.tracks = EnvTracks(self.env)
            self.tracks.update(engine)
            self.planner = BeliefPlanner(self.params, n_rows=1, perception=self.tracks)
        if self.tracks is not None:
            self.tracks.update(engine)
        self.planner.read(engine, [0], obs["intent"][None])
        self._choice = int(self.planner.decide(engine, [0], np.array([self._choice]), np.array([self._t]))[0])
        self._t += 1
        return int(self.planner.meta_actions(engine, [0], np.array([self._choice]), np.asarray(obs["turn"])[None])[0])


def _on_tracks(env: gym.Env) -> bool:
    """Whether the env's turn features describe the tracker's tracks (sensors turn_perceived)."""
    from av_gym.estimation.turn_features import TurnFeatures
    from av_gym.sensors.base import find_wrapper

    features = find_wrapper(env, TurnFeatures)
    return features is not None and features.source == "tracks"


def belief_lookahead_teacher(params: BeliefLookaheadParams, actions: str, scenario: str | None = None,
                             action_repeat: int = 1) -> Any:
    """A teacher whose labels depend only on what the student could know (see :data:`agents.registry.TEACHERS`):
    GO when none (at most ``threshold``) of its K futures collide. Per state on a per-env training env (its belief
    from the readings at the states it is asked about, a one-row :class:`EnvView` of the env); on the batch
    ``train/dagger.py``'s BatchedLabels runs a :class:`BeliefPlanner` for every row (``label.belief``)."""
    from agents.go_yield import _go_yield_only

    _go_yield_only(params, actions)
    planner, view = BeliefPlanner(params, n_rows=1), EnvView()
    episode: list = [None]

    def label(env, obs, info) -> int:
        u = env.unwrapped
        key = (int(u.episode_seed), id(u))
        if key != episode[0] or float(u.time) == 0.0:  # a new episode: forget its drivers
            planner.reset([0])
            view.reset()
            episode[0] = key
        engine = view.engine(env, obs)
        planner.read(engine, [0], obs["intent"][None])
        return int(planner.labels(engine, [0])[0])

    label.belief = params
    return label


class PlannerOpinion:
    """The planner as the AEB shield's second opinion (:attr:`av_gym.shields.aeb.AEBShield.opinion`): before a
    brake at the stop line, the shield asks whether going on is safe, and the planner answers with its K futures of
    GO from the car's information (GO's estimated collision probability at most ``threshold``). Emergency brakes
    are never asked about. It reads the indicators at every observation, as the agent does; the shield's env must
    carry the turn features (``obs["intent"]``: sensors turn_truth or turn_perceived)."""

    def __init__(self, params: BeliefLookaheadParams | None = None) -> None:
        self.params = params or BeliefLookaheadParams()
        self.planner, self.view = BeliefPlanner(self.params, n_rows=1), EnvView()
        self._engine = None
        self.asked = 0  # questions answered this episode

    def reset(self) -> None:
        self.planner.reset([0])
        self.view.reset()
        self._engine, self.asked = None, 0

    def observe(self, env: gym.Env, obs) -> None:
        if not isinstance(obs, dict) or "intent" not in obs:
            from av_gym.errors import ConfigError

            raise ConfigError("shield.second_opinion belief_lookahead reads obs['intent']; run the agent with "
                              "sensors turn_truth or turn_perceived (or their _memory presets)")
        self._engine = self.view.engine(env, obs)
        self.planner.read(self._engine, [0], obs["intent"][None])

    def go_is_safe(self, env: gym.Env) -> bool:
        # the engine observe() built from the state the shield now decides on (nothing moved since)
        self.asked += 1
        return bool(self.planner.labels(self._engine, [0])[0] == GO)


class BeliefLookaheadAgent(AgentKind):
    Params = BeliefLookaheadParams

    @classmethod
    def build(cls, params: BeliefLookaheadParams, env: gym.Env, label: str) -> BeliefLookahead:
        from av_gym.errors import ConfigError

        for key in ("turn", "intent"):
            if key not in env.observation_space.spaces:
                raise ConfigError(f"agent {label!r} reads obs[{key!r}]; use sensors=turn_truth or turn_perceived")
        return BeliefLookahead(env, params)


class EnvView:
    """A one-row :class:`~av_gym.batched.left_turn.BatchedLeftTurn` holding what the car observes of a per-env
    left turn: the ego's own state, and the other road users as the turn features describe them: the simulator's
    vehicles (``turn_features.source: truth``) or the tracker's tracks (``tracks``: their position, velocity and
    heading; the closest lane from that pose; the acceleration the intent features measure; no crash flag). The
    hidden fields are left at neutral values: :meth:`BeliefPlanner.futures` redraws them all. Identities (the
    belief's keys) are the vehicle objects on truth, the tracker's track ids on tracks."""

    def __init__(self) -> None:
        self._engine, self._ids, self._next = None, {}, 1

    def reset(self) -> None:
        self._ids, self._next = {}, 1

    def _id(self, key) -> int:
        if key not in self._ids:
            self._ids[key], self._next = self._next, self._next + 1
        return self._ids[key]

    def engine(self, env: gym.Env, obs) -> Any:
        from av_gym.batched.left_turn import BatchedLeftTurn
        from av_gym.estimation.turn_features import TurnFeatures
        from av_gym.sensors.base import find_wrapper
        from av_gym.sim.batched import Traffic

        u = env.unwrapped
        if self._engine is None:
            self._engine = BatchedLeftTurn(1, {k: v for k, v in u.config.items() if k != "observation"})
        e = self._engine
        T = e.T
        features = find_wrapper(env, TurnFeatures)
        ego = u.vehicle
        others = self._others(env, u, features, obs)  # (n, 7): x, y, h, v, acc, crashed, id
        t = Traffic(T, 1, N=len(others) + 3)
        t.road_steps[:] = int(u.road.steps)
        slot_of_ego = self._ego_slot(u)
        rows = list(others)
        rows.insert(min(slot_of_ego, len(rows)), None)
        for j, o in enumerate(rows):
            if o is None:  # the ego, as it knows itself
                lane = T.id[tuple(ego.lane_index[:2]) + (0,)]
                route = [int(k) for k in e.route]  # the ego's route is its own: the engine's
                tl = T.id[tuple(ego.target_lane_index[:2]) + (0,)]
                t.alive[0, j], t.ego[0, j], t.mdp[0, j] = True, True, not e.continuous
                t.x[0, j], t.y[0, j] = ego.position
                t.h[0, j], t.v[0, j], t.target[0, j] = ego.heading, ego.speed, getattr(ego, "target_speed", ego.speed)
                t.lane[0, j], t.tlane[0, j], t.route[0, j] = lane, tl, route
                t.rpos[0, j] = route.index(tl) if tl in route else 0
                t.crashed[0, j] = ego.crashed
                t.steer[0, j], t.acc[0, j] = ego.action.get("steering", 0.0), ego.action.get("acceleration", 0.0)
                t.vid[0, j] = 0
            else:
                x, y, h, v, acc, crashed, key = o
                t.alive[0, j] = True
                t.x[0, j], t.y[0, j], t.h[0, j], t.v[0, j], t.target[0, j] = x, y, h, v, v
                t.lane[0, j] = t.tlane[0, j] = t.route[0, j, 0] = T.closest(np.array([x]), np.array([y]),
                                                                            np.array([h]))[0]
                t.acc[0, j], t.crashed[0, j], t.vid[0, j] = acc, bool(crashed), int(key)
        return e.observed(t, [float(u.time)], [int(u.steps)], [int(u.episode_seed)])

    @staticmethod
    def _ego_slot(u) -> int:
        return next(i for i, v in enumerate(u.road.vehicles) if v is u.vehicle)

    def _others(self, env, u, features, obs) -> list:
        """The road users the features describe from, in their order: (x, y, heading, speed, acceleration,
        crashed, identity)."""
        from av_gym.estimation.object_tracking import ObjectTracker
        from av_gym.estimation.turn_features import ACC_SCALE
        from av_gym.sensors.base import find_wrapper

        if features.source == "truth":
            return [(*v.position, v.heading, v.speed, v.action.get("acceleration", 0.0), v.crashed, self._id(v))
                    for v in u.road.vehicles if v is not u.vehicle]
        tracker = find_wrapper(env, ObjectTracker)
        rows = tracker._last[tracker._last[:, 0] > 0]
        internal = tracker.tracker.tracks()
        ids = tracker.tracker.track_ids()
        acc = np.zeros(len(rows))
        described = features.described  # rows of features.others (= rows here) in obs["intent"]'s order
        acc[described] = np.asarray(obs["intent"])[: len(described), 0] * ACC_SCALE
        out = []
        for k, r in enumerate(rows):
            key = -1
            if len(internal):
                m = int(np.argmin(np.hypot(internal[:, 0] - r[1], internal[:, 1] - r[2])))
                key = ("track", int(ids[m]))
            out.append((float(r[1]), float(r[2]), float(r[5]), float(np.hypot(r[3], r[4])), float(acc[k]), False,
                        self._id(key)))
        return out
