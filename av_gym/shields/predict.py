"""Motion prediction and collision tests for the predictive AEB shield (:mod:`av_gym.shields.aeb`).

Pure functions on numpy arrays, SI units (m, s, rad), highway-env's world frame (x right, y down on screen; a
left turn *decreases* the heading). Three families:

- **Paper** (digest 003 §4.2–4.6): constant-acceleration (CA) prediction of positions in fixed axes, eqs.
  (2)–(6), with the paper's literal ``A·t²`` term (``half_accel_term=False``) or the kinematic ``½·A·t²``;
  constant-yaw-rate ego heading, eq. (9); the vehicle-size collision limits of eqs. (7)–(8) and the
  speed-dependent horizon map.
- **Improved**: the ego advanced along its planned route (:class:`RouteTable`) with a longitudinal profile
  (cruise, brake, go), the others constant-velocity or constant-acceleration, and oriented-box (SAT) overlap of the
  footprints with a margin (:func:`footprint_ttc`).
- **Standard AEB**: ``TTC = Δx/Δv`` for targets ahead of the ego in its own corridor only (:func:`standard_ttc`).
"""

from __future__ import annotations

import numpy as np

from av_gym.geometry import box_corners, boxes_overlap, may_overlap

KMH = 1 / 3.6
PAPER_SPEEDS_KMH = (10.0, 15.0, 20.0)
PAPER_HORIZONS_S = (4.0, 3.0, 2.0)


# ----------------------------------------------------------------------------------------------- paper (003 §4)
def paper_horizon(speed: float) -> float:
    """Prediction horizon N·T (s) for ego ``speed`` (m/s): the paper's linear map 10/15/20 km/h → 4/3/2 s
    (``H = 6 − 0.2·v[km/h]``), clamped to 4 s below 10 km/h and 2 s above 20 km/h (digest 003 §4.4)."""
    return float(np.interp(float(speed) / KMH, PAPER_SPEEDS_KMH, PAPER_HORIZONS_S))


def paper_limits(phi, length_tgt, width_tgt, length_ego, width_ego):
    """Collision limits of eqs. (7)–(8): centre distances (m) below which the boxes touch, along the approach
    axis x and across it y, for ego yaw ``phi`` (rad, relative to the approach, + = turning left). Literal: at
    φ = 0 Δy omits the ego half-width; at φ = π/2 Δx omits it and Δy uses the ego half-*width* (003 §4.5)."""
    phi = np.asarray(phi, dtype=float)
    dx = 0.5 * length_tgt + 0.5 * length_ego * np.cos(phi)
    dy = 0.5 * width_tgt + 0.5 * width_ego * np.sin(phi)
    return dx, dy


def aabb_limits(phi, length_tgt, width_tgt, length_ego, width_ego):
    """Corrected limits: the exact axis-aligned half-extents of the ego box rotated by ``phi`` plus the target's
    (which keeps its length along x). Reduce to ``(L_t + L_e)/2`` and ``(W_t + W_e)/2`` at φ = 0."""
    phi = np.asarray(phi, dtype=float)
    c, s = np.abs(np.cos(phi)), np.abs(np.sin(phi))
    dx = 0.5 * length_tgt + 0.5 * length_ego * c + 0.5 * width_ego * s
    dy = 0.5 * width_tgt + 0.5 * length_ego * s + 0.5 * width_ego * c
    return dx, dy


def ca_predict(x0: np.ndarray, v0: np.ndarray, a0: np.ndarray, t: np.ndarray,
               half_accel_term: bool = False) -> np.ndarray:
    """Constant-acceleration positions at times ``t`` (K,): eqs. (2)–(5), ``X̂(t) = X0 + (V0 + A0·t)·t`` —
    literally substituted, so without the ½ (``half_accel_term=False``, paper replication) — or the kinematic
    ``X0 + V0·t + ½·A0·t²``. ``x0, v0, a0`` broadcast as (..., 2) → (K, ..., 2)."""
    t = np.asarray(t, dtype=float)
    x0, v0, a0 = (np.asarray(a, dtype=float) for a in (x0, v0, a0))
    tt = t.reshape((-1,) + (1,) * x0.ndim)
    k = 0.5 if half_accel_term else 1.0
    return x0 + v0 * tt + k * a0 * tt**2


def paper_ttc(rel_xy: np.ndarray, v_ego: np.ndarray, a_ego: np.ndarray, v_tgt: np.ndarray, a_tgt: np.ndarray,
              size_tgt: np.ndarray, size_ego: tuple[float, float], phi0: float, phi_rate: float,
              horizon: float, step: float = 0.1, half_accel_term: bool = False,
              limits: str = "paper") -> tuple[float, int]:
    """Predicted TTC (s) of the paper (003 §4.5–4.6): the first slice ``k·T`` (k = 1…N, N = round(H/T)) at which
    ``|x̂_e − x̂_t| < Δx_lim`` **and** ``|ŷ_e − ŷ_t| < Δy_lim``, minimum over targets; ``inf`` if none.

    All vectors are in the approach-aligned frame (x along the approach, y across), ego at the origin:
    ``rel_xy`` (M, 2) target positions relative to the ego, ``v_*``/``a_*`` (2,) for the ego and (M, 2) for the
    targets, ``size_tgt`` (M, 2) ``[length, width]``, ``size_ego = (length, width)``; ``phi0``/``phi_rate`` the ego
    yaw (rad, + = left) and yaw rate for eq. (9). Returns ``(ttc, index of the target)`` (-1 if none)."""
    rel_xy = np.asarray(rel_xy, dtype=float).reshape(-1, 2)
    if len(rel_xy) == 0:
        return float("inf"), -1
    n = max(1, int(round(horizon / step)))
    t = step * np.arange(1, n + 1)
    xe = ca_predict(np.zeros(2), v_ego, a_ego, t, half_accel_term)[:, None, :]  # (K, 1, 2)
    xt = ca_predict(rel_xy, v_tgt, a_tgt, t, half_accel_term)  # (K, M, 2)
    phi = phi0 + phi_rate * t  # eq. (9)
    lim = paper_limits if limits == "paper" else aabb_limits
    size_tgt = np.asarray(size_tgt, dtype=float).reshape(-1, 2)
    dx_lim, dy_lim = lim(phi[:, None], size_tgt[None, :, 0], size_tgt[None, :, 1], size_ego[0], size_ego[1])
    d = np.abs(xe - xt)
    hit = (d[..., 0] < dx_lim) & (d[..., 1] < dy_lim)  # (K, M)
    if not hit.any():
        return float("inf"), -1
    k = int(np.argmax(hit.any(1)))
    return float(t[k]), int(np.argmax(hit[k]))


# ----------------------------------------------------------------------------------------------- improved
class RouteTable:
    """The ego's planned route as a dense lookup table: pose (x, y, heading) at any arc length ``s`` (m), by
    linear interpolation every ``ds`` m; beyond either end the route is extended straight along its end heading.

    Built from a :class:`av_gym.envs.lane_path.LanePath` (or any list of highway-env lanes)."""

    def __init__(self, lanes, ds: float = 0.2) -> None:
        self.lanes = list(lanes)
        lengths = np.array([lane.length for lane in lanes], dtype=float)
        self.starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        self.length = float(lengths.sum())
        s = np.arange(0.0, self.length + ds, ds)
        s[-1] = min(s[-1], self.length)
        k = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(lanes) - 1)
        pts, hdg = [], []
        for si, ki in zip(s, k):
            local = min(si - self.starts[ki], lanes[ki].length)
            pts.append(lanes[ki].position(local, 0.0))
            hdg.append(lanes[ki].heading_at(local))
        self.s, self.xy, self.heading = s, np.array(pts, dtype=float), np.unwrap(np.array(hdg, dtype=float))

    def poses(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (..., 2) and headings (...) at arc lengths ``s`` (...)."""
        s = np.asarray(s, dtype=float)
        sc = np.clip(s, 0.0, self.length)
        x = np.interp(sc, self.s, self.xy[:, 0])
        y = np.interp(sc, self.s, self.xy[:, 1])
        h = np.interp(sc, self.s, self.heading)
        extra = s - sc  # straight extension before the start / after the end
        x, y = x + extra * np.cos(h), y + extra * np.sin(h)
        return np.stack([x, y], -1), h


class DrivenPath:
    """Where the ego actually drives along its route, not just the lane centreline: highway-env's route-following
    controller (``ControlledVehicle.steering_control``: lateral P-control through a heading reference, pursuit
    look-ahead, bicycle kinematics with slip) cuts the turn by up to ~0.6 m at 20 km/h and lags in heading.

    The controller is replicated and run once per speed bin (``speeds``, m/s) at constant speed from
    ``lead`` m before ``s_from`` to ``s_to`` + ``lead`` m along the route (cached per route), tabulating position
    and heading against the distance driven. :meth:`poses` then places the ego at any distance ahead along that
    path, blending the two speed bins around each predicted speed. Before the table the centreline is exact
    (straight approach, no offset)."""

    KP_LATERAL, KP_HEADING, TAU_PURSUIT = 1 / 0.6, 1 / 0.2, 0.1  # highway-env ControlledVehicle
    MAX_STEERING, LENGTH, LANE_SWITCH = np.pi / 3, 5.0, 2.5
    kernel = True  # False: every look-up through the numpy reference :meth:`poses_numpy` (tests, A/B checks)

    def __init__(self, route: RouteTable, s_from: float, s_to: float, lead: float = 15.0, dt: float = 0.05,
                 speeds: np.ndarray | None = None) -> None:
        self.route, self.dt = route, dt
        self.s_start, self.s_end = max(0.0, s_from - lead), min(route.length, s_to + lead)
        self.speeds = DRIVEN_SPEEDS if speeds is None else np.asarray(speeds, dtype=float)
        self._tables: dict[int, tuple[np.ndarray, ...]] = {}
        self.store_id = -1  # its row in the kernel's store (av_gym.shields.kernels.Store), once registered

    def _simulate(self, v: float) -> tuple[np.ndarray, ...]:
        """The controller driven at constant speed ``v`` (m/s) every ``dt`` s from ``s_start`` until the route
        position passes ``s_end``: per step the distance driven, x, y, heading and route position (m, rad).

        highway-env's formulas in its order of operations, one float at a time (each step's numbers as the stock
        controller's, bit for bit; a bin's ~100-2,400 steps are most of a new path's cost): the lanes' own
        ``local_coordinates`` and ``heading_at`` (numpy's 2-vector dot inside), the angle functions through
        :mod:`av_gym.sim.fmath` (Python's math where it equals numpy here, else numpy's ufunc), the position
        as two floats (the array update's element-wise products and sums)."""
        from av_gym.sim import fmath

        lanes, starts = self.route.lanes, self.route.starts
        k = int(np.clip(np.searchsorted(starts, self.s_start, side="right") - 1, 0, len(lanes) - 1))
        pos = np.array(lanes[k].position(self.s_start - starts[k], 0.0), dtype=float)
        x, y = float(pos[0]), float(pos[1])
        h = float(lanes[k].heading_at(self.s_start - starts[k]))
        d, rows = self.s_start, []
        vz = v if abs(v) > 1e-2 else 1e-2
        asin, atan, tan, cos, sin, clip = fmath.asin, fmath.atan, fmath.tan, fmath.cos, fmath.sin, fmath.clip
        lateral_gain, slip_gain, step = -self.KP_LATERAL, self.LENGTH / 2 / vz, v * self.dt
        pursuit, last, max_steer, quarter = v * self.TAU_PURSUIT, len(lanes) - 1, self.MAX_STEERING, np.pi / 4
        lane, switch_at = lanes[k], lanes[k].length - self.LANE_SWITCH
        while True:
            s_l, lat = lane.local_coordinates(pos)
            if s_l > switch_at and k < last:  # follow_road (after_end)
                k += 1
                lane, switch_at = lanes[k], lanes[k].length - self.LANE_SWITCH
                s_l, lat = lane.local_coordinates(pos)
            s_route = starts[k] + s_l
            rows.append((d, x, y, h, s_route))
            if s_route >= self.s_end:
                break
            ref = lane.heading_at(s_l + pursuit) + clip(asin(clip(lateral_gain * lat / vz, -1.0, 1.0)), -quarter,
                                                        quarter)
            rate = self.KP_HEADING * ((ref - h + np.pi) % (2 * np.pi) - np.pi)
            steer = clip(atan(2 * tan(asin(clip(slip_gain * rate, -1.0, 1.0)))), -max_steer, max_steer)
            beta = atan(0.5 * tan(steer))
            x, y = x + step * cos(h + beta), y + step * sin(h + beta)
            pos = np.array((x, y))
            h += v * sin(beta) / (self.LENGTH / 2) * self.dt
            d += step
        ds, xs, ys, hs, ss = np.array(rows, dtype=float).T
        return ds.copy(), xs.copy(), ys.copy(), np.unwrap(hs), ss.copy()

    def _table(self, i: int) -> tuple[np.ndarray, ...]:
        if i not in self._tables:
            self._tables[i] = self._simulate(float(self.speeds[i]))
            if self.store_id >= 0:
                _store().add_bin(self.store_id, i, self._tables[i])
        return self._tables[i]

    def _register(self) -> int:
        """This path's id in the kernel's store (registered on first use, with the bins simulated so far); -1 for
        speed bins other than the default ones (the numpy reference serves those)."""
        if self.store_id < 0 and self.speeds is DRIVEN_SPEEDS:
            store, r = _store(), self.route
            self.store_id = store.register((r.s, r.xy[:, 0], r.xy[:, 1], r.heading), self.s_start, r.length)
            for i, tab in self._tables.items():
                store.add_bin(self.store_id, i, tab)
        return self.store_id

    def _poses_bin(self, i: int, s0: float, ds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d_tab, x, y, h, s_tab = self._table(i)
        # distance driven at route position s0: the table's inside it, shifted one for one after it (np.interp
        # alone clamps there, which froze every prediction started past the table's end at that end)
        d0 = s0 if s0 <= self.s_start else float(np.interp(s0, s_tab, d_tab)) + max(s0 - s_tab[-1], 0.0)
        d = d0 + ds
        xy_c, h_c = self.route.poses(np.where(d < self.s_start, d, d - d_tab[-1] + s_tab[-1]))
        inside = (d >= self.s_start) & (d <= d_tab[-1])
        xy = xy_c.copy()
        hh = h_c.copy()
        if inside.any():
            xy[inside, 0] = np.interp(d[inside], d_tab, x)
            xy[inside, 1] = np.interp(d[inside], d_tab, y)
            hh[inside] = np.interp(d[inside], d_tab, h)
        return xy, hh

    def poses(self, s0: float, ds: np.ndarray, speeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (K, 2) and headings (K,) after driving ``ds`` (K,) m from route position ``s0`` at the
        speeds ``speeds`` (K,) m/s (:func:`driven_poses`, the compiled look-up; :meth:`poses_numpy` is the
        reference it reproduces bit for bit)."""
        if not DrivenPath.kernel:
            return self.poses_numpy(s0, ds, speeds)
        ds = np.asarray(ds, dtype=float)
        xy, h = driven_poses([self], np.array([float(s0)]), ds[None], np.asarray(speeds, dtype=float)[None])
        return xy[0], h[0]

    def poses_numpy(self, s0: float, ds: np.ndarray, speeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The numpy reference of :meth:`poses` (the code before the kernel)."""
        ds, speeds = np.asarray(ds, dtype=float), np.asarray(speeds, dtype=float)
        if s0 + (ds[-1] if len(ds) else 0.0) < self.s_start:
            return self.route.poses(s0 + ds)
        n = len(self.speeds)
        f = np.clip(np.interp(speeds, self.speeds, np.arange(n)), 0, n - 1)
        lo = np.floor(f).astype(int)
        hi = np.minimum(lo + 1, n - 1)
        w = f - lo
        xy, hh = np.zeros((len(ds), 2)), np.zeros(len(ds))
        for i in np.unique(np.concatenate([lo, hi])):
            wi = np.where(lo == i, 1.0 - w, 0.0) + np.where(hi == i, w, 0.0)
            xy_i, h_i = self._poses_bin(int(i), s0, ds)
            xy += wi[:, None] * xy_i
            hh += wi * h_i
        return xy, hh


DRIVEN_SPEEDS = np.arange(0.5, 12.01, 0.5)
"""DrivenPath's default speed bins (m/s); shared, so that a batch of paths on it blends in one vectorised step."""


_STORE = None


def _store():
    """The kernel's store of driven-path tables (av_gym.shields.kernels.Store), made on first use (numba is
    imported then, not with this module)."""
    global _STORE
    if _STORE is None:
        from av_gym.shields.kernels import Store

        _STORE = Store(DRIVEN_SPEEDS)
    return _STORE


def simulating_bins(call, need: np.ndarray, path_of):
    """The return of ``call()``, a kernel on the :func:`_store` that sets ``need[h, i]`` for each speed bin ``i``
    its look-up ``h`` reads and the store lacks, and returns their count (first, where it returns a tuple): called
    again until none is missing, the flagged bins simulated in between, lazily as the reference
    (``path_of(h, out)``: look-up ``h``'s DrivenPath, ``out`` the last return)."""
    while True:
        out = call()
        if not (out[0] if isinstance(out, tuple) else out):
            return out
        for h, i in zip(*np.nonzero(need)):
            path_of(h, out)._table(int(i))
        need[:] = False


def driven_poses(paths: list, s0: np.ndarray, ds: np.ndarray, speeds: np.ndarray, ids: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`DrivenPath.poses` of H look-ups at once: ``paths`` (H DrivenPaths, repeats allowed), route positions
    ``s0`` (H,), distances ``ds`` and speeds ``speeds`` (H, K); positions (H, K, 2) and headings (H, K), each row
    the reference's (:meth:`DrivenPath.poses_numpy`) bit for bit, in one compiled call
    (:func:`av_gym.shields.kernels.driven_poses`) instead of ~20 numpy calls per look-up. ``ids``: the paths' ids in
    the kernels' store, where the caller has them (all registered)."""
    from av_gym.shields.kernels import driven_poses as kernel

    ds = np.ascontiguousarray(ds, dtype=float)
    H, K = ds.shape
    if ids is None:
        ids = np.array([p.store_id if p.store_id >= 0 else p._register() for p in paths], dtype=np.int64)
    if H and ids.min() < 0:  # speed bins of its own: the reference, one look-up at a time
        out = [p.poses_numpy(float(a), d, v) for p, a, d, v in zip(paths, s0, ds, speeds)]
        return np.stack([o[0] for o in out]), np.stack([o[1] for o in out])
    s0 = np.ascontiguousarray(s0, dtype=float)
    speeds = np.ascontiguousarray(speeds, dtype=float)
    xy, hh = np.empty((H, K, 2)), np.empty((H, K))
    st = _store()
    need = np.zeros((H, len(DRIVEN_SPEEDS)), dtype=np.bool_)
    simulating_bins(lambda: kernel(st.data, st.route, st.limits, st.bins, st.grid_table, ids, s0, ds, speeds, xy, hh,
                                   need), need, lambda m, _: paths[m])
    return xy, hh


def profile_speeds(ds: np.ndarray, t: np.ndarray, v0: float) -> np.ndarray:
    """Speeds (m/s) along a distance profile ``ds`` sampled at times ``t`` (finite differences)."""
    d = np.concatenate([[0.0], np.asarray(ds, dtype=float)])
    tt = np.concatenate([[0.0], np.asarray(t, dtype=float)])
    v = np.diff(d) / np.maximum(np.diff(tt), 1e-9)
    return np.maximum(v, 0.0) if len(v) else np.array([v0])


def cruise_profile(v0: float, a0: float, t: np.ndarray, accel_time: float = 1.0,
                   v_max: float = 40.0) -> np.ndarray:
    """Distance (m) travelled at times ``t`` if the ego keeps its current acceleration ``a0`` for ``accel_time`` s,
    then its speed; speed kept in [0, ``v_max``] (never reverses)."""
    t = np.asarray(t, dtype=float)
    dt = np.diff(np.concatenate([[0.0], t]))
    a = np.where(t <= accel_time + 1e-9, a0, 0.0)
    v, s, out = float(v0), 0.0, np.empty_like(t)
    for i, (h, ai) in enumerate(zip(dt, a)):
        v_new = float(np.clip(v + ai * h, 0.0, max(v_max, v)))
        s += 0.5 * (v + v_new) * h
        v = v_new
        out[i] = s
    return out


def go_profile(v0: float, v_set: float, t: np.ndarray, tau: float = 0.6, rise: np.ndarray | None = None
               ) -> np.ndarray:
    """Distance (m) at times ``t`` for a first-order speed response from ``v0`` to ``v_set`` with time constant
    ``tau`` (highway-env's cruise controller, ``TAU_ACC`` = 0.6 s): the ego setting off again after a stop.
    ``rise``: ``1 - exp(-t / tau)`` (K,) where the caller keeps it for its ``t`` (the same floats: it is the
    same expression, only not evaluated again per call)."""
    t = np.asarray(t, dtype=float)
    if rise is None:
        rise = 1.0 - np.exp(-t / tau)
    return v_set * t + (v0 - v_set) * tau * rise


def setpoint_profile(v0: float, set_at, t: np.ndarray, dt: float = 0.05, tau: float = 0.6) -> np.ndarray:
    """Distance (m) at times ``t`` (multiples of ``dt``) when the cruise set-point is chosen anew at the start of
    every interval of ``t`` from the speed then, ``set_at(v)`` (m/s): a discrete agent that repeats FASTER or
    SLOWER at every policy step (``MDPVehicle.act`` moves one set-point from the one nearest the current speed),
    so setting off climbs the set-points as the speed does. Integrated tick by tick as highway-env does (speed
    controller ``(v_set - v) / tau`` with ``TAU_ACC`` = 0.6 s, position with the speed before the update): the
    moment a set-point switches depends on it (the continuous response reaches 2.25 m/s one policy step later)."""
    v, s, prev = float(v0), 0.0, 0.0
    out = np.empty(len(t))
    for i, ti in enumerate(np.asarray(t, dtype=float)):
        v_set = float(set_at(v))
        for _ in range(int(round((ti - prev) / dt))):
            s += v * dt
            v += (v_set - v) / tau * dt
        prev = ti
        out[i] = s
    return out


def setpoint_steps(v0: float, target_speeds: np.ndarray, step: int, t: np.ndarray, dt: float = 0.05,
                   tau: float = 0.6) -> np.ndarray:
    """:func:`setpoint_profile` for a discrete agent repeating FASTER (``step`` +1) or SLOWER (-1) on highway-env's
    ``MDPVehicle`` with the set-points ``target_speeds`` (m/s, evenly spaced, ascending): ``set_at(v)`` is
    ``index_to_speed(clip(speed_to_index(v) + step))``. One compiled call (:func:`av_gym.shields.kernels.
    setpoint_ticks`, the same floats as the reference with that ``set_at``) instead of a Python loop over the ticks."""
    from av_gym.shields.kernels import setpoint_ticks

    return setpoint_ticks(float(v0), np.ascontiguousarray(target_speeds, dtype=float), int(step),
                          np.ascontiguousarray(t, dtype=float), float(dt), float(tau))


def object_predict(others: np.ndarray, t: np.ndarray, accel: np.ndarray | None = None,
                   accel_time: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Positions (K, M, 2) and headings (K, M) of ``others`` (M, 7) ``[x, y, vx, vy, heading, length, width]`` at
    times ``t`` (K,): constant velocity, or with ``accel`` (M, 2) constant acceleration for ``accel_time`` s
    (then constant velocity), never reversing (a braking object stops and stays)."""
    t = np.asarray(t, dtype=float)
    p0, v0 = others[:, 0:2], others[:, 2:4]
    tt = t[:, None, None]
    if accel is None or not np.any(accel):
        pos = p0[None] + v0[None] * tt
    else:
        a = np.asarray(accel, dtype=float)
        speed = np.linalg.norm(v0, axis=1)
        along = np.einsum("mi,mi->m", a, v0) / np.maximum(speed, 1e-6)
        # time at which a decelerating object stops (no reversing), and the acceleration phase length
        t_stop = np.where(along < -1e-6, speed / np.maximum(-along, 1e-6), np.inf)
        ta = np.minimum(np.minimum(t_stop, accel_time)[None, :, None], tt)  # (K, M, 1)
        pos = p0[None] + v0[None] * ta + 0.5 * a[None] * ta**2
        v_end = v0[None] + a[None] * ta
        v_end = np.where((t_stop[None, :, None] <= accel_time) & (tt >= t_stop[None, :, None]), 0.0, v_end)
        pos = pos + v_end * (tt - ta)
    heading = np.broadcast_to(others[None, :, 4], pos.shape[:2])
    return pos, heading


FOOTPRINT_KERNEL = True
"""False: :func:`footprint_ttc` through its numpy reference :func:`footprint_ttc_numpy` (tests, A/B checks)."""


def footprint_ttc(ego_xy: np.ndarray, ego_heading: np.ndarray, ego_size: tuple[float, float],
                  others_xy: np.ndarray, others_heading: np.ndarray, others_size: np.ndarray,
                  t: np.ndarray, margin: float = 0.0, ignore_rear: bool | np.ndarray = False) -> tuple[float, int]:
    """First time in ``t`` (K,) at which the ego box (``ego_xy`` (K, 2), heading (K,), ``(length, width)``
    grown by ``margin`` m on every side) overlaps any other box (``others_xy`` (K, M, 2), heading (K, M), size
    (M, 2)) — separating-axis test; ``(inf, -1)`` if none, else ``(time, index of the other)``.

    ``ignore_rear`` (bool, or one per other): skip overlaps in which the other is behind the ego and heading the
    same way (within 45°) at that moment — it would be running into the ego from behind, which is the follower's
    to avoid (an IDM car brakes for the car ahead), not a reason for the ego to brake.

    One compiled call (:func:`av_gym.shields.kernels.footprint_hit`: the pairs in slice order, stopping at the
    first hit) instead of the reference's arrays over every pair (:func:`footprint_ttc_numpy`, the same answer)."""
    if not FOOTPRINT_KERNEL:
        return footprint_ttc_numpy(ego_xy, ego_heading, ego_size, others_xy, others_heading, others_size, t, margin,
                                   ignore_rear)
    if others_xy.shape[1] == 0 or len(t) == 0:
        return float("inf"), -1
    from av_gym.shields.kernels import footprint_hit

    k, m = footprint_hit(np.ascontiguousarray(ego_xy, dtype=float), np.ascontiguousarray(ego_heading, dtype=float),
                         *_footprint_args(ego_size, others_xy, others_heading, others_size, margin, ignore_rear))
    return (float("inf"), -1) if k < 0 else (float(t[k]), int(m))


_HALF_DIAGONAL: dict[tuple[float, float], np.float64] = {}  # (length, width) m -> half the box's diagonal, m


def _footprint_args(ego_size: tuple[float, float], others_xy: np.ndarray, others_heading: np.ndarray,
                    others_size: np.ndarray, margin: float, ignore_rear: bool | np.ndarray) -> tuple:
    """:func:`av_gym.shields.kernels.footprint_hit`'s arguments after the ego's poses: the ego box's length and width
    (m, grown by ``margin`` on every side), the others' positions, headings and sizes as contiguous float arrays,
    each pair's reach (M,, m: numpy's hypot of the half-diagonals) and the rear rule per other (M,)."""
    length, width = ego_size[0] + 2 * margin, ego_size[1] + 2 * margin
    others_size = np.asarray(others_size, dtype=float)
    half = _HALF_DIAGONAL.get((length, width))
    if half is None:  # numpy's scalar hypot, kept per box: the same float64 every call, without ~1 us a call
        half = _HALF_DIAGONAL[(length, width)] = 0.5 * np.hypot(length, width)
    reach = half + 0.5 * np.hypot(others_size[:, 0], others_size[:, 1])
    rear = np.asarray(ignore_rear, dtype=bool)
    # one per other (the scene's flags, usually) or one for all, without np.broadcast_to's ~3 us a call
    rear = np.ascontiguousarray(rear) if rear.shape == reach.shape else np.full(reach.shape, rear)
    return (float(length), float(width), np.ascontiguousarray(others_xy, dtype=float),
            np.ascontiguousarray(others_heading, dtype=float), np.ascontiguousarray(others_size), reach, rear)


def driven_ttc(path: DrivenPath, s0: float, ds: np.ndarray, t: np.ndarray, ego_size: tuple[float, float],
               others_xy: np.ndarray, others_heading: np.ndarray, others_size: np.ndarray, margin: float = 0.0,
               ignore_rear: bool | np.ndarray = False) -> tuple[float, int]:
    """:func:`footprint_ttc` of the ego driving the distance profile ``ds`` (K,, m) at the times ``t`` (K,, s) along
    its driven path ``path`` from route position ``s0`` (m), i.e. ``footprint_ttc(*path.poses(s0, ds,
    profile_speeds(ds, t, v)), ...)``: ``(time s, other)``, or ``(inf, -1)`` (also for no slice or no other, where
    the poses cannot matter). One compiled call (:func:`av_gym.shields.kernels.driven_ttc`) instead of three
    wrappers and ~15 numpy calls; the composition of the references where a kernel is switched off
    (``DrivenPath.kernel``, :data:`FOOTPRINT_KERNEL`) or the path has speed bins of its own."""
    ds, t = np.ascontiguousarray(ds, dtype=float), np.ascontiguousarray(t, dtype=float)
    if not len(ds) or not others_xy.shape[1]:
        return float("inf"), -1
    if DrivenPath.kernel and FOOTPRINT_KERNEL and path._register() >= 0:
        from av_gym.shields.kernels import driven_ttc as kernel

        args = _footprint_args(ego_size, others_xy, others_heading, others_size, margin, ignore_rear)
        st, need = _store(), np.zeros((1, len(DRIVEN_SPEEDS)), dtype=np.bool_)

        def call():
            return kernel(st.data, st.route, st.limits, st.bins, st.grid_table, path.store_id, float(s0), ds, t,
                          *args, need)

        missing, k, m = call()  # simulating_bins' first call, without its closures where no bin is missing
        if missing:  # a speed bin not simulated yet: simulated lazily, as the reference does, then called again
            for i in np.flatnonzero(need[0]).tolist():
                path._table(i)
            need[:] = False
            _, k, m = simulating_bins(call, need, lambda h, _: path)
        return (float("inf"), -1) if k < 0 else (float(t[k]), int(m))
    xy, h = path.poses(s0, ds, profile_speeds(ds, t, 0.0))  # v0 is read only for an empty ds
    return footprint_ttc(xy, h, ego_size, others_xy, others_heading, others_size, t, margin, ignore_rear)


def footprint_ttc_numpy(ego_xy: np.ndarray, ego_heading: np.ndarray, ego_size: tuple[float, float],
                        others_xy: np.ndarray, others_heading: np.ndarray, others_size: np.ndarray,
                        t: np.ndarray, margin: float = 0.0, ignore_rear: bool | np.ndarray = False
                        ) -> tuple[float, int]:
    """The numpy reference of :func:`footprint_ttc` (every (slice, other) pair as arrays)."""
    if others_xy.shape[1] == 0 or len(t) == 0:
        return float("inf"), -1
    ego_xy, ego_heading = np.asarray(ego_xy, dtype=float), np.asarray(ego_heading, dtype=float)
    length, width = ego_size[0] + 2 * margin, ego_size[1] + 2 * margin
    # Two boxes can only overlap if their centres are within the sum of their half-diagonals (as
    # av_gym.geometry.constant_velocity_ttc): the separating-axis test runs on those (slice, hypothesis) pairs
    # only, usually a few of the 80 x ~40 (testing every pair is half of the shield's cost per decision, docs/shield.md)
    d = others_xy - ego_xy[:, None, :]
    reach = 0.5 * np.hypot(length, width) + 0.5 * np.hypot(others_size[:, 0], others_size[:, 1])  # (M,)
    near = may_overlap(d, reach)  # (K, M)
    hit = np.zeros(near.shape, dtype=bool)
    if near.any():
        k, m = np.nonzero(near)
        ego_box = box_corners(ego_xy[k], ego_heading[k], length, width)  # (P, 4, 2)
        oth_box = box_corners(others_xy[k, m], others_heading[k, m], others_size[m, 0], others_size[m, 1])
        hit[k, m] = boxes_overlap(ego_box, oth_box)
    if np.any(ignore_rear) and hit.any():
        eh = np.asarray(ego_heading, dtype=float)[:, None]
        rel = others_xy - np.asarray(ego_xy, dtype=float)[:, None, :]
        ahead = rel[..., 0] * np.cos(eh) + rel[..., 1] * np.sin(eh)
        same = np.abs((others_heading - eh + np.pi) % (2 * np.pi) - np.pi) < np.radians(45)
        hit &= ~(same & (ahead < 0) & np.broadcast_to(ignore_rear, hit.shape))
    rows = hit.any(1)
    if not rows.any():
        return float("inf"), -1
    k = int(np.argmax(rows))
    return float(t[k]), int(np.argmax(hit[k]))


class LaneHypotheses:
    """Map-based prediction of another vehicle (``target_model: map``): from the lane it is on (map-matched by
    position and heading), one hypothesis per way the road network lets it continue (straight, left, right at
    the intersection), each driven at its current speed along the lane centrelines; plus the plain
    constant-velocity hypothesis for motion off the map. The shield uses the map, never the vehicle's intention:
    a conflict on any hypothesis counts. Route tables are cached per lane sequence."""

    def __init__(self, network, depth: int = 3, min_length: float = 60.0) -> None:
        self.network, self.depth, self.min_length = network, depth, min_length
        self._tables: dict[tuple, RouteTable] = {}

    def sequences(self, lane_index: tuple) -> list[tuple]:
        graph = self.network.graph
        out = []

        def walk(seq: list, length: float) -> None:
            _, b, i = seq[-1]
            nexts = list(graph.get(b, {}).items())
            if len(seq) >= self.depth or length >= self.min_length or not nexts:
                out.append(tuple(seq))
                return
            for c, lanes in nexts:
                nxt = (b, c, i if i < len(lanes) else 0)
                walk(seq + [nxt], length + self.network.get_lane(nxt).length)

        walk([tuple(lane_index)], 0.0)
        return out

    def table(self, seq: tuple) -> RouteTable:
        lanes = [self.network.get_lane(i) for i in seq]
        key = (seq, tuple(round(lane.length, 4) for lane in lanes), tuple(np.round(lanes[0].position(0, 0), 4)))
        if key not in self._tables:  # geometry in the key: the cache survives a road rebuilt at reset
            self._tables[key] = RouteTable(lanes, ds=0.25)
        return self._tables[key]

    def predict(self, others: np.ndarray, lane_indices: list, t: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Positions (K, M', 2), headings (K, M'), owner index (M',) and whether each is a map hypothesis (M',;
        False for the constant-velocity ones) over all hypotheses of ``others`` (M, 7) on lanes
        ``lane_indices`` (None = off the map: constant velocity only)."""
        t = np.asarray(t, dtype=float)
        cv_xy, cv_h = object_predict(others, t)
        xs, hs, owner = [cv_xy], [cv_h], [np.arange(len(others))]
        for m, lane_index in enumerate(lane_indices):
            if lane_index is None:
                continue
            speed = float(np.hypot(others[m, 2], others[m, 3]))
            if speed < 0.5:
                continue  # a standing vehicle: the constant-velocity hypothesis covers it
            lane = self.network.get_lane(lane_index)
            s0 = float(lane.local_coordinates(others[m, 0:2])[0])
            for seq in self.sequences(lane_index):
                if len(seq) == 1:
                    continue  # the straight continuation of a single lane is the CV hypothesis
                xy, h = self.table(seq).poses(s0 + speed * t)
                xs.append(xy[:, None, :])
                hs.append(h[:, None])
                owner.append(np.array([m]))
        owner = np.concatenate(owner)
        return np.concatenate(xs, 1), np.concatenate(hs, 1), owner, np.arange(len(owner)) >= len(others)


# ----------------------------------------------------------------------------------------------- standard AEB
def standard_ttc(ego_xy: np.ndarray, ego_heading: float, ego_speed: float, ego_size: tuple[float, float],
                 others: np.ndarray, lateral_margin: float = 0.0) -> tuple[float, int]:
    """Classic AEB TTC, eq. (1) ``TTC = Δx/Δv``, over the targets *ahead* of the ego in its own corridor: in the
    ego frame, ``x_rel > 0`` and the target's lateral extent overlapping the ego's width (+ ``lateral_margin``).
    Δx is the bumper-to-bumper gap, Δv the closing speed along the ego's heading; ``inf`` when none closes."""
    if len(others) == 0:
        return float("inf"), -1
    c, s = np.cos(ego_heading), np.sin(ego_heading)
    rel = others[:, 0:2] - np.asarray(ego_xy, dtype=float)
    x_rel = rel[:, 0] * c + rel[:, 1] * s
    y_rel = -rel[:, 0] * s + rel[:, 1] * c
    dpsi = others[:, 4] - ego_heading
    half_x = 0.5 * others[:, 5] * np.abs(np.cos(dpsi)) + 0.5 * others[:, 6] * np.abs(np.sin(dpsi))
    half_y = 0.5 * others[:, 5] * np.abs(np.sin(dpsi)) + 0.5 * others[:, 6] * np.abs(np.cos(dpsi))
    ahead = (x_rel > 0) & (np.abs(y_rel) < half_y + 0.5 * ego_size[1] + lateral_margin)
    gap = x_rel - half_x - 0.5 * ego_size[0]
    closing = ego_speed - (others[:, 2] * c + others[:, 3] * s)
    ttc = np.where(ahead & (closing > 1e-6), np.maximum(gap, 0.0) / np.maximum(closing, 1e-6), np.inf)
    i = int(np.argmin(ttc))
    return (float(ttc[i]), i) if np.isfinite(ttc[i]) else (float("inf"), -1)
