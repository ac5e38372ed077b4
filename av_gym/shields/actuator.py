"""The brake actuator the AEB shield drives the ego with (:class:`BrakeActuator`: delay, jerk-limited build-up,
full deceleration) and the wrapper around the ego's ``act`` that applies it every simulation tick."""

from __future__ import annotations


import numpy as np

from av_gym.params import Params
from av_gym.shields.aeb_params import BrakeParams


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
        highway-env's ``Vehicle.step`` (position with the speed before the update); the ticks in one compiled call
        (:func:`av_gym.shields.kernels.brake_profile`, :meth:`deceleration`'s arithmetic: the shield asks for ~40
        ticks several times per decision)."""
        from av_gym.shields.kernels import brake_profile

        n = int(np.ceil(duration / dt - 1e-9))
        return brake_profile(max(float(v0), 0.0), float(a_before), n, float(dt), float(self.decel),
                             float(self.delay), float(self.jerk))

    def stopping_distance(self, v0: float, a_before: float, dt: float) -> tuple[float, float]:
        """Distance (m) and time (s) to standstill when braking is commanded now."""
        if v0 <= 0:
            return 0.0, 0.0
        a_before = max(a_before, 0.0)
        # The horizon must reach the stop, no more. jerk 0 is a step (no ramp). A tiny jerk made the full ramp
        # decel / jerk huge (jerk 1e-6: ~1.6e8 ticks), though the car stops long before it: the ramp is capped at
        # sqrt(2 v_peak / jerk) + 3 dt, which covers the stop. Why (real arithmetic): the speed after the delay
        # is at most v_peak = v0 + a_before (delay + dt) (the delay's ticks end before delay + dt). Tick k after
        # the delay brakes at least min(decel, jerk s) for every s in [k dt, (k + 1) dt) (its deceleration is
        # the ramp's at the tick's end, the delay's rounding at most 1e-9 s against it). When the cap is the
        # smaller, jerk s < decel up to s = sqrt(2 v_peak / jerk), so the speed lost by then is at least
        # jerk s² / 2 = v_peak: standstill within delay + sqrt(2 v_peak / jerk) + 3 dt (one tick of delay
        # rounding, one for the partial tick, one against the 1e-9), inside the capped horizon (whose
        # v / decel + 1 s slack is kept). Otherwise the cap is not taken and the horizon is the one before. Either
        # way the ticks up to the stop are the same (brake_profile's ticks do not depend on their count), so
        # every answer is unchanged (tests/test_aeb.py checks a grid against the uncapped horizon).
        if self.jerk > 0:
            v_peak = v0 + a_before * (self.delay + dt)
            ramp = min(1.0 / self.jerk * self.decel, float(np.sqrt(2.0 * v_peak / self.jerk)) + 3.0 * dt)
        else:
            ramp = 0.0
        t_max = self.delay + ramp + (v0 + a_before * self.delay) / self.decel + 1.0
        xs, vs = self.profile(v0, a_before, t_max, dt)
        i = int(np.argmax(vs <= 0.0)) if (vs <= 0.0).any() else len(vs) - 1
        return float(xs[i]), float((i + 1) * dt)

    def stopping_bound(self, v0: float, a_before: float, dt: float) -> float:
        """An upper bound (m) of :meth:`stopping_distance`'s distance, from the same parameters without its ticks:
        the speed never exceeds ``v_peak`` (``a_before`` >= 0 kept for at most ``delay + dt``), the delay and the
        jerk's ramp take at most ``delay + decel / jerk + 2 dt`` at ``v_peak`` or less, and full deceleration from
        ``v_peak`` at most ``v_peak² / (2 decel) + 2 v_peak dt`` (a tick moves with the speed before its update);
        grown by 1 % and 1 µm so that no rounding of either side can reach it. Lets a caller skip the ticks where
        the distance cannot matter (the shield's stop-line trigger far from the line)."""
        v_peak = max(float(v0), 0.0) + max(float(a_before), 0.0) * (self.delay + dt)
        return self._bound_at_peak(v_peak, dt)

    def stopping_bounds(self, v0: np.ndarray, a_before: np.ndarray, dt: float) -> np.ndarray:
        """:meth:`stopping_bound` of many states at once (``v0`` m/s, ``a_before`` m/s², same shape): the same
        operations element by element, the same floats (the batch's shield asks it for all rows at once)."""
        v0 = np.maximum(np.asarray(v0, dtype=float), 0.0)
        v_peak = v0 + np.maximum(np.asarray(a_before, dtype=float), 0.0) * (self.delay + dt)
        return self._bound_at_peak(v_peak, dt)

    def _bound_at_peak(self, v_peak, dt: float):
        """:meth:`stopping_bound`'s bound (m) from its peak speed ``v_peak`` (m/s; a float or an array, element by
        element): one expression for the per-row and the all-rows bound, so that they stay the same floats."""
        ramp = self.decel / self.jerk if self.jerk > 0 else 0.0
        bound = v_peak * (self.delay + ramp + 4.0 * dt) + v_peak * v_peak / (2.0 * self.decel)
        return 1.01 * bound + 1e-6


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
