"""The ``improved`` AEB variant, our design (see :mod:`av_gym.shields.aeb` for what it predicts and why)."""

from __future__ import annotations

from types import SimpleNamespace


import gymnasium as gym
import numpy as np

from av_gym.params import Params
from av_gym.sensors.base import sensor_rng
from av_gym.sensors.turn_signal import DRIVER_DRAWS, DriverDraws, first_sighting, intended_signal, reported
from av_gym.shields.conflicts import ConflictModel
from av_gym.estimation.driver_intent import DriverIntent
from av_gym.shields.predict import (LaneHypotheses, cruise_profile, driven_ttc, go_profile, object_predict,
                                    setpoint_steps)
from av_gym.shields.aeb_base import AEBShield
from av_gym.shields.aeb_params import BRAKE, MONITOR, SETOFF_ACCEL_TIME, STOP_SPEED, WARN, ImprovedParams


def followers(xy, heading, length: float, others: np.ndarray) -> np.ndarray:
    """(..., M) bool: the road users ``others`` (..., M, 7) ``[x, y, vx, vy, heading, ...]`` following an ego at
    ``xy`` (..., 2) m with ``heading`` (...) rad and ``length`` m in its lane: behind it, within 2.5 m of its axis,
    heading within 45° of its heading. One ego (the per-env shield) or one per row of a batch, element by element
    the same operations."""
    xy = np.asarray(xy)
    h = heading if np.ndim(heading) == 0 else np.asarray(heading)[..., None]
    c, s = np.cos(h), np.sin(h)
    rel_x, rel_y = others[..., 0] - xy[..., 0:1], others[..., 1] - xy[..., 1:2]
    x_rel, y_rel = rel_x * c + rel_y * s, -rel_x * s + rel_y * c
    same_dir = np.abs((others[..., 4] - h + np.pi) % (2 * np.pi) - np.pi) < np.radians(45)
    return same_dir & (x_rel < -0.5 * length) & (np.abs(y_rel) < 2.5)


_LONG_TIMES: dict[tuple[float, float, float], np.ndarray] = {}
_GO_RISE: dict[tuple[float, float, float], np.ndarray] = {}
GO_TAU = 0.6  # s, highway-env's cruise controller (TAU_ACC): go_profile's default


def long_times(p: ImprovedParams) -> np.ndarray:
    """The times (s) of the shield's long prediction: every ``step`` up to the longer of ``horizon_max`` and
    ``4 + horizon_min`` s. One array per (step, horizon_max, horizon_min), the same object every call (every
    decision reads it; nobody writes it): the same floats without ~3 us per decision."""
    key = (p.step, p.horizon_max, p.horizon_min)
    t = _LONG_TIMES.get(key)
    if t is None:
        t = p.step * np.arange(1, int(round(max(p.horizon_max, 4.0 + p.horizon_min) / p.step)) + 1)
        t.flags.writeable = False  # shared by every decision of the process: a write would corrupt all later ones
        _LONG_TIMES[key] = t
    return t


def _go_rise(p: ImprovedParams) -> np.ndarray:
    """``1 - exp(-t / tau)`` over :func:`long_times` (go_profile's decay, the same expression), kept per times."""
    key = (p.step, p.horizon_max, p.horizon_min)
    rise = _GO_RISE.get(key)
    if rise is None:
        rise = 1.0 - np.exp(-np.asarray(long_times(p), dtype=float) / GO_TAU)
        rise.flags.writeable = False  # shared, as long_times
        _GO_RISE[key] = rise
    return rise


class ImprovedAEB(AEBShield):
    """``improved``: our design (module docstring); parameters :class:`ImprovedParams`."""

    Params = ImprovedParams
    p: ImprovedParams
    variant = "improved"
    decides_outside_window = True

    def __init__(self, env: gym.Env, params: ImprovedParams | None = None, **overrides) -> None:
        super().__init__(env, params, **overrides)
        self._moved_at: dict = {}
        self._hypotheses: LaneHypotheses | None = None
        self._conflicts: ConflictModel | None = None
        self._drivers = DriverDraws()  # the shield's own channel's per-driver draws, keyed by the vehicle
        self._intended_at: dict = {}  # vehicle -> (lane index, the indicator its route asks for there)
        self._beliefs = DriverIntent(self.p.signal_channel)

    @property
    def needs_lanes(self) -> bool:
        return self.p.target_model in ("map", "conflict")

    def _on_reset(self, u) -> None:
        if self.p.second_opinion != "none" and self.opinion is None:
            from av_gym.errors import ConfigError

            raise ConfigError(f"shield.second_opinion={self.p.second_opinion!r} is the harness's planner and none is "
                              f"installed: python -m eval installs it; from your own code install an opinion, an "
                              f"object with reset(), observe(env, obs) and go_is_safe(env) (av_gym.shields.Opinion), "
                              f"as find_shield(env).opinion, or set shield.second_opinion=none")
        if self.p.target_model == "map":
            if self._hypotheses is None:
                self._hypotheses = LaneHypotheses(u.road.network)
            self._hypotheses.network = u.road.network
        if self.p.target_model == "conflict":
            if self._conflicts is None:
                self._conflicts = ConflictModel(u.road.network, min_p=self.p.hypothesis_min_p)
            self._conflicts.network = u.road.network
            self._drivers.clear()
            self._intended_at = {}
            self._beliefs.clear()
            self._signal_rng = sensor_rng(self.env, "aeb_signals")
        self._moved_at = {}

    def _intent(self, others: np.ndarray, keys: list) -> np.ndarray | None:
        """The weight of each turn (right, straight, left) of each object from every indicator reading of its
        driver so far (:class:`av_gym.estimation.driver_intent.DriverIntent`); a NaN row for a driver never read.

        A reading comes through the shield's own indicator channel (``signal_channel``; its own random stream:
        per driver when first read, does it indicate and on which side; per reading, is it missed) and belongs to
        the true vehicle: the object itself in ground-truth mode (``keys``), the vehicle within 2 m of the track
        in perceived mode (none elsewhere). None beyond the channel's range; what was read stays known."""
        if not self.p.signals:
            return None
        u, sp = self.env.unwrapped, self.p.signal_channel
        if self.p.mode == "ground_truth":
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
            rows = self._drivers.rows(read)
            first = np.sort(np.unique(rows, return_index=True)[1])  # a driver read twice (two tracks) draws once
            fresh = rows[first][~self._drivers.get(rows[first])[0]]
            if len(fresh):  # first reading: does this driver indicate, and on which side? (in reading order)
                self._drivers.keep(fresh, *first_sighting(self._signal_rng.uniform(size=(len(fresh), DRIVER_DRAWS)),
                                                          sp))
            u_seen = self._signal_rng.uniform(size=len(read))
            _, indicates, wrong = self._drivers.get(rows)
            readings = reported([self._intended(v) for v in read], indicates, wrong, u_seen, sp)
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
        return ~followers(ego["xy"], ego["heading"], ego["size"][0], others)

    def _horizon(self, s0: float, ds: np.ndarray, t: np.ndarray) -> float:
        """Time (s) until the ego's centre has passed the end of the turn (the conflict zone is cleared) under the
        distance profile ``ds`` at times ``t``, plus one slice, clipped to [horizon_min, horizon_max]."""
        reached = s0 + ds >= self.clear_s
        h = t[int(np.argmax(reached))] + self.p.step if reached.any() else self.p.horizon_max
        return float(min(max(h, self.p.horizon_min), self.p.horizon_max))  # np.clip's value, without its ~3.5 us

    def _decide_improved(self, ego, others, a_others, t, in_turn: bool = True):
        """Outside the turn window (``in_turn`` False: far up the approach, or past the turn) only the emergency
        part runs — a forward AEB on the predicted footprints (the paper's function also sat inside the car's
        existing AEB) — so, e.g., a slower car ahead on the exit lane is still braked for. The steps: predict the
        relevant road users (:meth:`_predict_scene`), the ego's TTC carrying on, then, in this order, the release
        test while latched (:meth:`_release_test`), a standing car that may set off (:meth:`_setoff_stop`), and
        the warn / brake / infeasible choice (:meth:`_warn_or_brake`)."""
        sc = self._predict_scene(ego, others, a_others, t, in_turn)
        sc.ds_cruise = self._continue_profile(ego, sc.t_long)
        sc.horizon = self._horizon(sc.s0, sc.ds_cruise, sc.t_long)
        sc.n = int(round(sc.horizon / self.p.step))
        ttc, target = self._ttc_of(sc, sc.ds_cruise, sc.n, self.p.margin)
        sc.target_out = int(sc.idx[target]) if target >= 0 else -1
        # A car standing in the box that may set off (before the line only): checked where it can make a
        # difference, in the release test and at the stop-line trigger point (it never warns or brakes elsewhere)
        p = self.p
        setoff_rule = p.setoff_speed > 0 and p.target_model == "conflict" and in_turn and sc.front_to_line >= 0
        setoff = None
        if setoff_rule and (self._latched or (not np.isfinite(ttc) and self._at_trigger_point(sc))):
            setoff = self._setoff_predict(sc.others, sc.lanes, sc.t_long, sc.intent, sc.recent)
        if self._latched:
            held = self._release_test(sc, ttc, setoff)
            if held is not None:
                return held
        if not np.isfinite(ttc) and setoff is not None and self._at_trigger_point(sc):
            stop = self._setoff_stop(sc, setoff, t)
            if stop is not None:
                return stop
        if not np.isfinite(ttc):
            return MONITOR, ttc, sc.horizon, -1, False
        return self._warn_or_brake(sc, ttc, target, t)

    def _recently_moved(self, others: np.ndarray, t: float) -> np.ndarray | None:
        """Per object, whether it was faster than ``setoff_speed`` within the last ``setoff_recent`` s (None when
        the set-off rule is off); also records who is moving now."""
        if self.p.setoff_speed <= 0:
            return None
        keys = getattr(self, "_keys", None) or [None] * len(others)
        fast = np.hypot(others[:, 2], others[:, 3]) >= self.p.setoff_speed if len(others) else np.zeros(0, bool)
        for key, f in zip(keys, fast):
            if f and key is not None:
                self._moved_at[key] = t
        return np.array([key is not None and t - self._moved_at.get(key, -np.inf) <= self.p.setoff_recent + 1e-9
                         for key in keys], dtype=bool) if len(others) else np.zeros(0, bool)

    def _predict_scene(self, ego, others, a_others, t, in_turn: bool) -> SimpleNamespace:
        """The relevant road users (:meth:`_relevant`) predicted over the long horizon by ``target_model``: their
        footprints per hypothesis (``obj_xy``, ``obj_h``, ``size``; ``owner``: hypothesis → kept object, ``idx``:
        → row of the full list), which may not count as hitting the ego from behind (``rear``), plus the ego's
        state the later steps read."""
        keep = self._relevant(ego, others)
        recent = self._recently_moved(others, t)
        recent = recent[keep] if recent is not None else None
        others, a_others = others[keep], a_others[keep]
        p = self.p
        t_long = long_times(p)
        lanes, intent = None, None
        if self.p.target_model == "map":
            lanes = [lane for lane, k in zip(self._lanes, keep) if k]
            obj_xy, obj_h, owner, turn = self._hypotheses.predict(others, lanes, t_long)
            # A vehicle that would turn into the ego's lane behind it has to yield to the ego: its map
            # hypotheses never count as running into the ego from behind.
            rear = turn | self.p.ignore_rear
        elif self.p.target_model == "conflict":
            lanes = [lane for lane, k in zip(self._lanes, keep) if k]
            intent = self._intent(others, [k for k, kept in zip(self._keys, keep) if kept])
            obj_xy, obj_h, owner, turn, _ = self._scene_conflicts(others, lanes, a_others, t_long, intent)
            rear = turn | self.p.ignore_rear
        else:
            obj_xy, obj_h = object_predict(others, t_long, a_others if self.p.target_model == "ca" else None)
            owner = np.arange(len(others))
            rear = np.full(len(owner), self.p.ignore_rear)
        return SimpleNamespace(
            ego=ego, in_turn=in_turn, keep=keep, recent=recent, others=others, a_others=a_others, t_long=t_long,
            lanes=lanes, intent=intent, obj_xy=obj_xy, obj_h=obj_h, owner=owner, rear=rear,
            idx=np.flatnonzero(keep)[owner], size=np.asarray(others[owner, 5:7], dtype=float).reshape(-1, 2),
            v=ego["speed"], a=ego["accel"], s0=ego["s"],
            front_to_line=self.stop_line_s - (ego["s"] + 0.5 * ego["size"][0]))

    def _scene_conflicts(self, others: np.ndarray, lanes: list, a_others: np.ndarray, t_long: np.ndarray,
                         intent: np.ndarray | None) -> tuple:
        """The conflict model's paths of the scene's kept road users (:meth:`ConflictModel.predict`: positions
        (K, H, 2) m, headings (K, H) rad, owner, is a map hypothesis, probability); the batch hands its shields
        these for all envs at once (:meth:`ConflictModel.predict_rows`)."""
        return self._conflicts.predict(others, lanes, a_others, t_long, intent)

    def _ttc_of(self, sc: SimpleNamespace, ds: np.ndarray, n: int, margin: float, xy_o=None, h_o=None,
                size_o=None, rear_o=None) -> tuple[float, int]:
        """TTC and hypothesis hit of the ego driving the distance profile ``ds`` (first ``n`` slices) against the
        scene's predictions (or the given ones), its footprint grown by ``margin``."""
        xy_o = sc.obj_xy if xy_o is None else xy_o
        h_o = sc.obj_h if h_o is None else h_o
        size_o = sc.size if size_o is None else size_o
        rear_o = sc.rear if rear_o is None else rear_o
        return driven_ttc(self.driven, sc.s0, ds[:n], sc.t_long[:n], sc.ego["size"], xy_o[:n], h_o[:n], size_o,
                          margin, rear_o)

    def _at_trigger_point(self, sc: SimpleNamespace) -> bool:
        """The stop-line trigger: the front bumper within the stopping distance (+ one decision period and
        stop_margin) of the line, not past it."""
        if not (sc.in_turn and 0.0 <= sc.front_to_line):
            return False
        at = getattr(sc, "at_trigger", None)  # asked up to three times a decision: the same answer
        if at is None:
            reach = sc.v * self.p.step + self.p.stop_margin
            # beyond an upper bound of the stopping distance the ticks cannot make it True (most decisions far up
            # the approach): the same answer without them
            if sc.front_to_line > self.actuator.stopping_bound(sc.v, sc.a, self.sim_dt) + reach:
                at = False
            else:
                d_stop, _ = self.actuator.stopping_distance(sc.v, sc.a, self.sim_dt)
                at = sc.front_to_line <= d_stop + sc.v * self.p.step + self.p.stop_margin
            sc.at_trigger = at
        return at

    def _release_test(self, sc: SimpleNamespace, ttc: float, setoff) -> tuple | None:
        """Latched: the ego setting off again (or carrying on, if still rolling) must be predicted conflict-free,
        with the larger release margin (hysteresis), for release_hold s. Returns the braking decision while it
        is not, None once released."""
        ego, others, t_long = sc.ego, sc.others, sc.t_long
        ttc_go, tgo = float("inf"), -1
        profiles = [sc.ds_cruise] if ego["set_speed"] is not None else [sc.ds_cruise, self._go_profile(ego, t_long)]
        predictions = [(sc.obj_xy, sc.obj_h)]
        speeding_up = self._along_accel(others, sc.a_others, sign=1.0)
        if self.p.release_accel_time > 0 and self.p.target_model == "conflict" and speeding_up.any():
            accel_xy, accel_h, _, _ = self._accel_predict(others, sc.lanes, speeding_up, t_long, sc.intent,
                                                          self.p.release_accel_time)
            predictions.append((accel_xy, accel_h))
        for p_xy, p_h in predictions:
            xy_r, h_r = self._release_objects(ego, others, sc.owner, p_xy, p_h)
            for ds_p in profiles:  # commanded acceleration: safe whether the agent holds its speed or sets off
                n_p = int(round(self._horizon(sc.s0, ds_p, t_long) / self.p.step))
                ttc_p, tg_p = self._ttc_of(sc, ds_p, n_p, self.p.release_margin, xy_r, h_r)
                if ttc_p < ttc_go:
                    ttc_go, tgo = ttc_p, tg_p
        if setoff is not None:  # a car standing in the box that may set off (before the line only)
            for ds_p in profiles:
                n_p = int(round(self._horizon(sc.s0, ds_p, t_long) / self.p.step))
                n_p = min(n_p, int(round(self.p.setoff_horizon / self.p.step)))
                ttc_p, _ = self._ttc_of(sc, ds_p, n_p, self.p.release_margin, *setoff[:2], *setoff[3:])
                ttc_go = min(ttc_go, ttc_p)
        self._clear_for = self._clear_for + self.p.step if not np.isfinite(ttc_go) else 0.0
        if not np.isfinite(ttc_go) and self._clear_for + 1e-9 >= self.p.release_hold:
            self._release()
            return None
        t_out = int(sc.idx[tgo]) if tgo >= 0 else sc.target_out
        return BRAKE, min(ttc, ttc_go), sc.horizon, t_out, False

    def _setoff_stop(self, sc: SimpleNamespace, setoff, t: float) -> tuple | None:
        """A standing car that may set off: a reason to stop at the line, never an emergency."""
        n_set = min(sc.n, int(round(self.p.setoff_horizon / self.p.step)))
        ttc_set, k = self._ttc_of(sc, sc.ds_cruise, n_set, self.p.margin, *setoff[:2], *setoff[3:])
        if not np.isfinite(ttc_set) or self._second_opinion_withholds():
            return None
        self._latch(t)
        return BRAKE, ttc_set, sc.horizon, int(np.flatnonzero(sc.keep)[setoff[2][k]]), False

    def _warn_or_brake(self, sc: SimpleNamespace, ttc: float, target: int, t: float) -> tuple:
        """A conflict is predicted: brake at the stop-line trigger point or in an emergency (TTC <= ttc_brake on
        the unmargined footprints, or a braking road user keeping its deceleration), unless braking would park
        the ego in the path of the object braked for; else warn (in the turn window, or TTC <= warn_ttc)."""
        stop_line_trigger = self._at_trigger_point(sc)
        emergency = False
        if ttc <= self.p.ttc_brake:
            ttc_raw, _ = self._ttc_of(sc, sc.ds_cruise, sc.n, 0.0)
            emergency = ttc_raw <= self.p.ttc_brake
            if not emergency and self.p.emergency_accel_time > 0 and self.p.target_model == "conflict":
                emergency = self._braking_ttc(sc.ego, sc.ds_cruise, sc.n, sc.others, sc.lanes, sc.a_others,
                                              sc.t_long, sc.intent) <= self.p.ttc_brake
        if not (stop_line_trigger or emergency) or (not emergency and self._second_opinion_withholds()):
            return (WARN if sc.in_turn or ttc <= self.p.warn_ttc else MONITOR), ttc, sc.horizon, sc.target_out, False
        # Feasibility against the object braked for (any of its path hypotheses) only: another road user that
        # would reach the standing ego seconds later is a later conflict (it can brake, the ego can set off),
        # not a reason to drive into this one (seed 1019: a rear-end at TTC 1.3 s went unbraked because a car
        # merging into the exit lane was predicted through the stopped ego 5.9 s later).
        mine = sc.owner == sc.owner[target]
        if self.p.feasibility and self._parked_in_path(sc.v, sc.a, sc.s0, sc.ego, sc.obj_xy[:, mine],
                                                       sc.obj_h[:, mine], sc.size[mine], sc.t_long,
                                                       np.broadcast_to(sc.rear, sc.owner.shape)[mine]):
            return WARN, ttc, sc.horizon, sc.target_out, True
        self._latch(t)
        return BRAKE, ttc, sc.horizon, sc.target_out, False

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
        off from 0.5 m/s at ``setoff_accel`` (for :data:`SETOFF_ACCEL_TIME` s); None when there is none."""
        box = np.array([lane is not None and str(lane[0]).startswith("ir") for lane in lanes], dtype=bool)
        speed = np.hypot(others[:, 2], others[:, 3]) if len(others) else np.zeros(0)
        slow = box & (speed < self.p.setoff_speed) & recent
        if not slow.any():
            return None
        idx = np.flatnonzero(slow)
        mod = others[idx].copy()
        direction = np.stack([np.cos(mod[:, 4]), np.sin(mod[:, 4])], 1)
        mod[:, 2:4] = 0.5 * direction
        sub_lanes = [lanes[i] for i in idx]
        sub_intent = None if intent is None else intent[idx]
        # Marked as following their lanes: the conflict model's own speed test (>= 0.5 m/s) would meet this
        # 0.5 m/s start across a rounding (its hypot is one ulp under 0.5 for ~1.4 % of headings, and a car's
        # heading one ulp apart between two stacks then picked its lanes or a straight line).
        xy, h, owner, turn = self._accel_predict(mod, sub_lanes, self.p.setoff_accel * direction, t_long,
                                                 sub_intent, SETOFF_ACCEL_TIME, follow=True)
        return xy, h, idx[owner], np.asarray(others[idx[owner], 5:7], dtype=float).reshape(-1, 2), \
            turn | self.p.ignore_rear

    def _accel_predict(self, others, lanes, accels, t_long, intent, accel_time, follow: bool = False):
        """The conflict model's path hypotheses (same ones, same order) with each road user keeping the
        acceleration ``accels`` (M, 2, world frame; along its path) for ``accel_time`` s, never reversing;
        ``follow``: every road user on a lane takes its lane hypotheses whatever its speed
        (:meth:`ConflictModel.predict`'s ``follow``)."""
        model = self._conflicts
        saved = model.accel_time
        model.accel_time = accel_time
        try:
            obj_xy, obj_h, owner, turn, _ = model.predict(others, lanes, accels, t_long, intent,
                                                          np.ones(len(others), bool) if follow else None)
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
                                                         self.p.emergency_accel_time)
        size_b = np.asarray(others[owner, 5:7], dtype=float).reshape(-1, 2)
        ttc, _ = driven_ttc(self.driven, ego["s"], ds[:n], t_long[:n], ego["size"], obj_xy[:n], obj_h[:n], size_b,
                            0.0, turn | self.p.ignore_rear)
        return ttc

    def _release_objects(self, ego: dict, others: np.ndarray, owner: np.ndarray, obj_xy: np.ndarray,
                         obj_h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The predicted objects the release test checks: all path hypotheses, except (``release_standing``) with
        the ego standing in the box, where every road user slower than ``release_standing`` is predicted standing
        at its current place and heading. Why: braked to a standstill in the box, the ego would otherwise wait for
        a car that is barely moving there itself (one yielding, creeping, or sliding to a stop after a collision
        with another car) whose path hypotheses at that speed cross the ego's, until the time-out or until a third
        car runs into the standing ego; a car that does set off again is still met by the emergency brake."""
        if self.p.release_standing <= 0 or ego["speed"] > STOP_SPEED or len(owner) == 0:
            return obj_xy, obj_h
        front_to_line = self.stop_line_s - (ego["s"] + 0.5 * ego["size"][0])
        if front_to_line >= 0.0 or ego["s"] >= self.clear_s:
            return obj_xy, obj_h
        slow = np.hypot(others[owner, 2], others[owner, 3]) < self.p.release_standing
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
        action = self._proposed if self.p.check_action else None
        u = self.env.unwrapped
        if ego["set_speed"] is not None:
            name = u.action_type.actions.get(int(action)) if action is not None and np.ndim(action) == 0 else None
            if name in ("FASTER", "SLOWER"):  # MDPVehicle.act for this action, repeated
                return setpoint_steps(ego["speed"], u.vehicle.target_speeds, 1 if name == "FASTER" else -1, t,
                                      dt=self.sim_dt)
            return go_profile(ego["speed"], ego["set_speed"], t, GO_TAU, self._rise_for(t))
        accel = ego["accel"] if action is None else u.action_type.acceleration(action)
        v_cap = max(ego["speed"], self.p.go_speed, ego["speed_limit"] or self.p.go_speed)
        a = accel if ego["speed"] > STOP_SPEED else max(accel, 0.0)
        return cruise_profile(ego["speed"], a, t, v_max=v_cap)

    def _go_profile(self, ego: dict, t: np.ndarray) -> np.ndarray:
        """Distance (m) at times ``t`` if the brake is released now: the first-order speed response to the
        vehicle's cruise set-point, or to ``go_speed`` (at least the current speed) when it has none — an agent
        commanding acceleration is assumed to set off again."""
        v_set = ego["set_speed"] if ego["set_speed"] is not None else max(self.p.go_speed, ego["speed"])
        return go_profile(ego["speed"], v_set, t, GO_TAU, self._rise_for(t))

    def _rise_for(self, t: np.ndarray) -> np.ndarray | None:
        """go_profile's decay over ``t`` where ``t`` is the shield's :func:`long_times` (kept), else None."""
        return _go_rise(self.p) if t is long_times(self.p) else None

    def _parked_in_path(self, v, a, s0, ego, obj_xy, obj_h, size, t_long, rear) -> bool:
        """Brake-feasibility check (digest 003 §9.7): would braking now leave the ego standing where a target
        will hit it? A collision that happens while the ego is still moving is not a reason to hold off (braking
        still mitigates it); one after standstill is."""
        ticks = int(round(self.p.step / self.sim_dt))
        xs, vs = self.actuator.profile(v, a, t_long[-1] + 1e-9, self.sim_dt)
        ds = xs[ticks - 1::ticks][: len(t_long)]
        stopped = vs[ticks - 1::ticks][: len(t_long)] <= 0.0
        ttc, _ = driven_ttc(self.driven, s0, ds, t_long[: len(ds)], ego["size"], obj_xy[: len(ds)],
                            obj_h[: len(ds)], size, self.p.margin, rear)
        if not np.isfinite(ttc):
            return False
        k = int(round(ttc / self.p.step)) - 1
        return bool(stopped[k])
