"""How another road user's possible paths relate to the ego's planned path on highway-env's four-way intersection,
read from the road network, never from the vehicle's motion.

Partner types (:func:`partner_type`), in this order of precedence:

- ``ahead`` / ``behind``: on a lane of the ego's route, in front of / behind the ego along it;
- ``merging``: its planned lanes join the ego's route further on (e.g. an oncoming car turning right into the
  ego's exit, or a car from the east going straight to the ego's exit);
- ``oncoming``: it comes from the approach opposite the ego's (straight across the ego's turn, or turning);
- ``crossing``: any other road user (from the left or the right approach, or leaving on another exit).

Node names are highway-env's intersection's: approach ``o{i}→ir{i}``, through the box ``ir{i}→il{j}``, exit
``il{j}→o{j}``.
"""

from __future__ import annotations

import weakref

import numpy as np

PARTNER_TYPES = ("oncoming", "crossing", "merging", "ahead", "behind", "unknown")


def approach_of(lane_index) -> int | None:
    """The approach (0-3) a vehicle on ``lane_index`` came from, or None on an exit lane / an unknown road."""
    if not lane_index:
        return None
    a, b = str(lane_index[0]), str(lane_index[1])
    if a.startswith("o") and b.startswith("ir"):
        tag = b[2:]
    elif a.startswith("ir") and b.startswith("il"):
        tag = a[2:]
    else:
        return None
    return int(tag) if tag.isdigit() else None


def planned_lanes(vehicle) -> list[tuple]:
    """The lanes ``vehicle`` is on and plans to drive (its current lane, then the rest of its route)."""
    lane = getattr(vehicle, "lane_index", None)
    if lane is None:
        return []
    route = list(getattr(vehicle, "route", None) or [])
    key = lambda li: (li[0], li[1])  # noqa: E731 -- lane ids in a route may carry another lane number
    keys = [key(li) for li in route]
    rest = route[keys.index(key(lane)) + 1:] if key(lane) in keys else []
    return [tuple(lane), *[tuple(li) for li in rest]]


def route_position(network, route: list[tuple], starts: np.ndarray, lane_index, position) -> float | None:
    """Distance (m) along the ego's ``route`` (lane ``k`` begins at ``starts[k]``) of a point on one of its lanes;
    None when ``lane_index`` is not on the route."""
    keys = [(li[0], li[1]) for li in route]
    if lane_index is None or (lane_index[0], lane_index[1]) not in keys:
        return None
    k = keys.index((lane_index[0], lane_index[1]))
    s, _ = network.get_lane(route[k]).local_coordinates(np.asarray(position, dtype=float))
    return float(starts[k] + s)


def partner_type(vehicle, network, ego_route: list[tuple], ego_starts: np.ndarray, ego_s: float) -> str:
    """The partner type (module docstring) of ``vehicle`` relative to an ego at ``ego_s`` m along ``ego_route``."""
    lane = getattr(vehicle, "lane_index", None)
    if lane is None:
        return "unknown"
    s = route_position(network, ego_route, ego_starts, lane, vehicle.position)
    if s is not None:
        return "ahead" if s > ego_s else "behind"
    keys = {(li[0], li[1]) for li in ego_route}
    if any((li[0], li[1]) in keys for li in planned_lanes(vehicle)[1:]):
        return "merging"
    ego_approach = approach_of(ego_route[0])
    origin = approach_of(lane)
    if ego_approach is not None and origin is not None and origin == (ego_approach + 2) % 4:
        return "oncoming"
    return "crossing"


# ----------------------------------------------------------------------------------------------- conflict model
def path_turn(seq: tuple) -> float:
    """The indicator a driver on lane sequence ``seq`` would show: +1 left, -1 right, 0 straight or unknown (the
    rule of :func:`av_gym.sensors.turn_signal.intended_signal`, applied to a hypothesis instead of a route)."""
    origin = approach_of(seq[0])
    end = str(seq[-1][1])
    if origin is None or not (end.startswith("o") and end[1:].isdigit()):
        dest = [str(li[1]) for li in seq if str(li[1]).startswith("il")]
        if origin is None or not dest or not dest[0][2:].isdigit():
            return 0.0
        end = "o" + dest[0][2:]
    turn = (int(end[1:]) - origin) % 4
    return 1.0 if turn == 1 else -1.0 if turn == 3 else 0.0


_DRIVEN: dict = {}  # lane sequence geometry -> DrivenPath, shared by every shield in the process
# network -> {lane sequence -> DrivenPath}: the look-up without the geometry key, per road network (a reset builds a
# new one); module-level and weak so that deep copies of the stack (the lookahead oracle) neither copy nor keep it
_BY_NETWORK: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()



def _turn_weights(hyps: list, intent_row: np.ndarray | None) -> list[float]:
    """Each lane continuation's probability: weighted by the turn its indicator reading gives (``intent_row``:
    right, straight, left, :data:`av_gym.estimation.driver_intent.TURNS`), normalised; uniform without a reading,
    and uniform where the reading weighs every continuation 0 (it rules out each turn the lane can take, so it
    cannot say which of them: 0/0 would give NaN probabilities)."""
    n_h = len(hyps)
    if intent_row is None:
        return [1.0 / n_h] * n_h
    p = np.array([intent_row[int(turn) + 1] for _, turn in hyps]) / n_h
    total = p.sum()
    return [1.0 / n_h] * n_h if total == 0 else (p / total).tolist()


CONFLICT_KERNEL = True
"""False: :meth:`ConflictModel.predict` chooses the hypotheses with its Python reference :meth:`ConflictModel._select`
(tests, A/B checks)."""


class _Lanes:
    """The lanes a conflict model met on one road network, as the rows :func:`av_gym.shields.kernels.
    conflict_hypotheses` reads: ``lanes`` (L, 8) each lane's geometry, ``hyp_off`` / ``hyp_n`` where its hypotheses
    are in ``hyp_turn`` (their turns), ``ids`` (their driven paths' ids in the kernels' store) and ``paths``
    (the DrivenPaths)."""

    def __init__(self) -> None:
        self.row: dict = {}
        self.lanes, self.hyp_off, self.hyp_n = np.zeros((0, 8)), np.zeros(0, np.int64), np.zeros(0, np.int64)
        self.hyp_turn, self.ids, self.paths = np.zeros(0), np.zeros(0, np.int64), []

    def rows(self, model: "ConflictModel", lane_indices: list) -> np.ndarray | None:
        """Each lane index's row (-1 for None), registering new lanes with ``model``'s hypotheses; None if one cannot
        be a kernel row."""
        get = self.row.get
        out = [-1 if li is None else get(li, -2) for li in lane_indices]
        if -2 in out:
            for m, li in enumerate(lane_indices):
                if out[m] == -2:
                    out[m] = self._register(model, li)
                    if out[m] < 0:
                        return None
        return np.array(out, dtype=np.int64)

    def _register(self, model: "ConflictModel", lane_index) -> int:
        """A new lane's row (its geometry, its hypotheses), -1 if it cannot be one."""
        geometry = _geometry(model.network.get_lane(lane_index))
        if geometry is None:
            return -1
        hyps, driven = model.hypotheses(lane_index), model._driven_all(lane_index)
        ids = [path._register() for path in driven]
        if min(ids) < 0:
            return -1
        k = len(self.lanes)
        self.lanes = np.vstack([self.lanes, [geometry]])
        self.hyp_off = np.append(self.hyp_off, len(self.paths))
        self.hyp_n = np.append(self.hyp_n, len(hyps))
        self.hyp_turn = np.append(self.hyp_turn, [turn for _, turn in hyps])
        self.ids = np.append(self.ids, ids)
        self.paths += list(driven)
        self.row[lane_index] = k
        return k


def _geometry(lane) -> list[float] | None:
    """A straight or circular lane's kernel row (:func:`av_gym.shields.kernels._stock_local`'s layout) from its own
    attributes; None for another lane type."""
    from highway_env.road.lane import CircularLane, StraightLane

    if type(lane) is StraightLane:
        return [0.0, *map(float, lane.start), *map(float, lane.direction), *map(float, lane.direction_lateral),
                float(lane.heading)]
    if type(lane) is CircularLane:
        return [1.0, *map(float, lane.center), float(lane.radius), float(lane.start_phase), float(lane.direction),
                0.0, 0.0]
    return None


def _lanes_of(model: "ConflictModel") -> _Lanes:
    """The lane registry of ``model``'s road network, kept beside that network's driven paths and shared as they
    are (no reference back to a model: the network is a weak key)."""
    by_seq = _BY_NETWORK.setdefault(model.network, {})
    reg = by_seq.get("kernel lanes")
    if reg is None:
        reg = by_seq["kernel lanes"] = _Lanes()
    return reg


def _store_arrays() -> tuple[np.ndarray, ...]:
    """The kernels' store of driven-path tables as the conflict kernels take it (data, route, limits, bins,
    grid_table: :class:`av_gym.shields.kernels.Store`), read at each call (simulating a speed bin can grow ``data``
    into a new array)."""
    from av_gym.shields.predict import _store

    st = _store()
    return st.data, st.route, st.limits, st.bins, st.grid_table


def _row_blocks(reg: _Lanes, lane_row: np.ndarray, row_off: np.ndarray) -> np.ndarray:
    """Where each decision's block of :meth:`ConflictModel.predict_rows`' flat buffers starts, in hypotheses
    ((R + 1,): the last, their total), decision r's road users rows ``row_off[r]`` .. ``row_off[r + 1]`` on lane
    rows ``lane_row`` of ``reg``: room for each road user's lane hypotheses, or its one constant-velocity
    hypothesis (the kernel leaves a decision that outgrows its block to the caller)."""
    room = np.where(lane_row >= 0, reg.hyp_n[lane_row], 1) if len(reg.hyp_n) else np.ones(len(lane_row))
    return np.concatenate([[0], np.cumsum(np.maximum(room, 1))])[row_off].astype(np.int64)


class ConflictModel:
    """Every road user's possible paths across the ego's: one hypothesis per way the road network lets
    it continue from the lane it is on (:class:`av_gym.shields.predict.LaneHypotheses`: straight, left, right at
    the intersection, any lane the graph continues to), each with a probability, uniform over the continuations
    and, where the driver's indicator has been read, weighted by what its readings say about each turn
    (:class:`av_gym.estimation.driver_intent.DriverIntent`); hypotheses below ``min_p`` are dropped. Along each path
    the vehicle keeps its along-path acceleration for ``accel_time`` s (a braking car stops, it does not reverse),
    then its speed (``accel_time`` 0, the default: constant speed; measured, docs/shield.md: 1.5 s parked the ego in
    the box more often), on the path highway-env's route-following controller actually drives (:meth:`driven`). An
    object off the map (farther than ``on_lane`` m from its lane, or heading more than 30° off it) or standing
    still (under 0.5 m/s, unless :meth:`predict`'s ``follow`` marks it) gets the constant-velocity hypothesis
    instead.

    Compared with constant velocity (the improved shield's old default) it sees the car that turns across or into
    the ego's path; compared with the ``map`` model it drops the straight-line hypothesis of a car that follows a
    curved lane (a phantom conflict for every car already turning in the box), uses the car's braking (one that
    slows to yield is not predicted through the ego), and lets a turn signal rule out going straight."""

    def __init__(self, network, min_p: float = 0.1, accel_time: float = 0.0, on_lane: float = 2.0,
                 depth: int = 3, min_length: float = 60.0) -> None:
        from av_gym.shields.predict import LaneHypotheses

        self.lanes = LaneHypotheses(network, depth, min_length)
        self.min_p, self.accel_time, self.on_lane = min_p, accel_time, on_lane
        self._seqs: dict[tuple, list[tuple[tuple, float]]] = {}

    def driven(self, seq: tuple):
        """Where a car following lane sequence ``seq`` actually drives: highway-env's traffic uses the same
        route-following controller as the ego, which cuts a turn by up to ~1 m, so the ego's
        :class:`~av_gym.shields.predict.DrivenPath` replays it along the hypothesis (cached by geometry: a
        centreline prediction missed cars from the east turning left by ~1 m, seeds 1025 and 1088)."""
        from av_gym.shields.predict import DrivenPath

        by_seq = _BY_NETWORK.setdefault(self.network, {})
        if seq in by_seq:  # the geometry key below costs ~60 µs per call, ~40 calls per decision
            return by_seq[seq]
        table = self.lanes.table(seq)
        key = (seq, round(table.length, 4), *np.round(table.xy[0], 4))
        if key not in _DRIVEN:
            turns = [k for k, li in enumerate(seq) if str(li[0]).startswith("ir")]
            k = turns[0] if turns else 0
            s_to = table.starts[k + 1] if k + 1 < len(table.starts) else table.length
            _DRIVEN[key] = DrivenPath(table, float(table.starts[k]), float(s_to))
        by_seq[seq] = _DRIVEN[key]
        return _DRIVEN[key]

    @property
    def network(self):
        return self.lanes.network

    @network.setter
    def network(self, net) -> None:
        self.lanes.network = net

    def hypotheses(self, lane_index: tuple) -> list[tuple[tuple, float]]:
        """``(lane sequence, turn)`` for every continuation of ``lane_index`` (cached)."""
        key = tuple(lane_index)
        if key not in self._seqs:
            self._seqs[key] = [(seq, path_turn(seq)) for seq in self.lanes.sequences(key)]
        return self._seqs[key]

    def along(self, v: float, a: float, t: np.ndarray) -> np.ndarray:
        """Distance (m) along a path at times ``t`` from speed ``v`` with acceleration ``a`` for ``accel_time`` s,
        never reversing."""
        ta = np.minimum(t, self.accel_time)
        if a < 0:
            ta = np.minimum(ta, v / -a)
        s = v * ta + 0.5 * a * ta**2
        return s + (v + a * ta) * (t - ta)

    def along_many(self, v: np.ndarray, a: np.ndarray, t: np.ndarray) -> np.ndarray:
        """:meth:`along` for speeds ``v`` and accelerations ``a`` (M,) at once: (M, K), row m equal to
        ``along(v[m], a[m], t)`` bit for bit (the same operations, element by element)."""
        v, a = np.asarray(v, dtype=float)[:, None], np.asarray(a, dtype=float)[:, None]
        ta = np.minimum(t, self.accel_time)[None, :].repeat(len(v), 0)
        neg = a[:, 0] < 0
        if neg.any():
            ta[neg] = np.minimum(ta[neg], v[neg] / -a[neg])
        s = v * ta + 0.5 * a * ta**2
        return s + (v + a * ta) * (t - ta)

    def _driven_all(self, lane_index: tuple, by_seq: dict | None = None) -> list:
        """:meth:`driven` of every hypothesis of ``lane_index``, in :meth:`hypotheses`' order (cached per road
        network, beside the paths themselves; ``by_seq``: that network's cache, if the caller has it)."""
        if by_seq is None:
            by_seq = _BY_NETWORK.setdefault(self.network, {})
        key = ("hypotheses", tuple(lane_index))
        if key not in by_seq:
            by_seq[key] = [self.driven(seq) for seq, _ in self.hypotheses(lane_index)]
        return by_seq[key]

    def _select(self, others: np.ndarray, lane_indices: list, accels: np.ndarray, intent: np.ndarray | None,
                follow: np.ndarray | None = None):
        """The hypotheses of :meth:`predict`, one object at a time (the Python reference of :meth:`_select_compiled`):
        per map hypothesis its driven path, store id (None: looked up later), start (m along the lane), the object's
        place among those on the map and its row, probability; per object on the map its speed (m/s) and
        acceleration along its path (m/s²); the rows of the constant-velocity objects."""
        owner, prob, cv = [], [], []
        max_dh = np.radians(30)
        speeds_all = np.hypot(others[:, 2], others[:, 3]) if len(others) else np.zeros(0)
        on_map, v_on, a_on = [], [], []  # objects with map hypotheses: row, speed, along-path acceleration
        paths, starts, rows = [], [], []  # per map hypothesis: its driven path, start, object's row in on_map
        net = self.network
        by_seq = _BY_NETWORK.setdefault(net, {}) if len(lane_indices) else None
        read = None if intent is None else np.isfinite(intent).all(axis=1)  # objects whose indicator was read
        for m, lane_index in enumerate(lane_indices):
            speed = float(speeds_all[m])
            lane = net.get_lane(lane_index) if lane_index is not None else None
            if lane is not None and (speed >= 0.5 or (follow is not None and follow[m])):
                s0, lat = lane.local_coordinates(others[m, 0:2])
                s0, lat = float(s0), float(lat)
                dh = abs((float(lane.heading_at(s0)) - others[m, 4] + np.pi) % (2 * np.pi) - np.pi)
                if abs(lat) <= self.on_lane and dh <= max_dh:
                    a_along = float(accels[m] @ others[m, 2:4]) / speed
                    p = _turn_weights(self.hypotheses(lane_index),
                                      intent[m] if read is not None and read[m] else None)
                    row = len(on_map)
                    on_map.append(m), v_on.append(speed), a_on.append(a_along)
                    driven = self._driven_all(lane_index, by_seq)
                    if min(p) < self.min_p:
                        driven, p = zip(*[(path, pk) for path, pk in zip(driven, p) if not pk < self.min_p])
                    n_k = len(p)
                    paths += driven
                    prob += p
                    starts += [s0] * n_k
                    rows += [row] * n_k
                    owner += [m] * n_k
                    continue
            cv.append(m)
        return paths, None, starts, rows, v_on, a_on, owner, prob, cv

    def _kernel_inputs(self, others: np.ndarray, lane_indices: list, accels: np.ndarray,
                       intent: np.ndarray | None, follow: np.ndarray | None = None) -> tuple | None:
        """The arguments :func:`av_gym.shields.kernels.conflict_hypotheses` and ``conflict_predict`` share, from
        ``others`` onwards to ``fused``, on this road network's lane registry (:class:`_Lanes`), and the registry;
        None for a lane other than straight or circular, or a numpy whose 2-vector dot the kernel cannot reproduce
        (the reference serves those)."""
        from av_gym.shields.kernels import DOT_FUSED

        if DOT_FUSED is None:  # a BLAS whose 2-vector dot is neither sum: the reference
            return None
        reg = _lanes_of(self)
        lane_row = reg.rows(self, lane_indices)
        if lane_row is None:
            return None
        M = len(others)
        if intent is None:  # no reading of anyone: uniform weights
            intent = np.full((M, 3), np.nan)
        others = np.ascontiguousarray(others, dtype=float)
        # numpy's own hypot and arctan2 (the reference's; an AVX-512 numpy's are not the C library's), elementwise
        speeds = np.hypot(others[:, 2], others[:, 3])
        centre = reg.lanes[lane_row, 1:3] if len(reg.lanes) else np.zeros((M, 2))  # row -1: any, unread
        phis = np.arctan2(others[:, 1] - centre[:, 1], others[:, 0] - centre[:, 0])
        return reg, (others, speeds, phis, lane_row, reg.lanes, reg.hyp_off, reg.hyp_n, reg.hyp_turn,
                     np.ascontiguousarray(intent, dtype=float), np.ascontiguousarray(accels, dtype=float),
                     float(self.min_p), float(self.on_lane), float(np.radians(30)), DOT_FUSED,
                     np.zeros(M, np.bool_) if follow is None else np.ascontiguousarray(follow, dtype=np.bool_))

    def _select_compiled(self, others: np.ndarray, lane_indices: list, accels: np.ndarray,
                         intent: np.ndarray | None, follow: np.ndarray | None = None):
        """:meth:`_select` in one compiled call (:func:`av_gym.shields.kernels.conflict_hypotheses`: the same floats,
        with numpy's hypot, arctan2 and 2-vector dot as this machine's numpy computes them); None where
        :meth:`_kernel_inputs` is."""
        from av_gym.shields.kernels import conflict_hypotheses

        inputs = self._kernel_inputs(others, lane_indices, accels, intent, follow)
        if inputs is None:
            return None
        reg, args = inputs
        M, lane_row = len(others), args[3]
        n_max = int(reg.hyp_n[lane_row[lane_row >= 0]].sum()) if M else 0
        hyp, starts, rows, owner = np.empty(n_max, np.int64), np.empty(n_max), np.empty(n_max, np.int64), \
            np.empty(n_max, np.int64)
        prob, v_on, a_on, cv = np.empty(n_max), np.empty(M), np.empty(M), np.empty(M, np.int64)
        n, n_on, n_cv = conflict_hypotheses(*args, hyp, starts, rows, owner, prob, v_on, a_on, cv)
        hyp = hyp[:n]
        paths = [reg.paths[h] for h in hyp.tolist()]
        return paths, reg.ids[hyp], starts[:n], rows[:n], v_on[:n_on], a_on[:n_on], owner[:n], prob[:n], cv[:n_cv]

    def _predict_compiled(self, others: np.ndarray, lane_indices: list, accels: np.ndarray, t: np.ndarray,
                          intent: np.ndarray | None, follow: np.ndarray | None = None) -> tuple | None:
        """:meth:`predict` in one compiled call (:func:`av_gym.shields.kernels.conflict_predict`: the choice of
        hypotheses, their along-path profiles, the driven-path look-ups and the constant-velocity objects, each the
        kernel :meth:`predict` composes otherwise), calling again after simulating the speed bins it reads for the
        first time; None where :meth:`_kernel_inputs` is."""
        from av_gym.shields.kernels import conflict_predict
        from av_gym.shields.predict import DRIVEN_SPEEDS, simulating_bins

        inputs = self._kernel_inputs(others, lane_indices, accels, intent, follow)
        if inputs is None:
            return None
        reg, args = inputs
        lane_row = args[3]
        need = np.zeros((int(reg.hyp_n[lane_row[lane_row >= 0]].sum()), len(DRIVEN_SPEEDS)), dtype=np.bool_)
        out = simulating_bins(lambda: conflict_predict(*args, reg.ids, t, float(self.accel_time), *_store_arrays(),
                                                       need),
                              need, lambda h, out: reg.paths[out[1][h]])  # out[1]: the hypothesis indices
        return tuple(out[2:])

    def predict_rows(self, others: np.ndarray, row_off: np.ndarray, lane_indices: list, accels: np.ndarray,
                     t: np.ndarray, intent: np.ndarray | None = None) -> list:
        """:meth:`predict` (no ``follow``) of many decisions in one compiled call
        (:func:`av_gym.shields.kernels.conflict_predict_rows`): decision r's road users are rows ``row_off[r]`` ..
        ``row_off[r + 1]`` of ``others`` (M, 7), ``lane_indices`` (M), ``accels`` (M, 2) m/s² and ``intent``
        (M, 3; None: no readings), ``t`` (K,) s shared. Per decision :meth:`predict`'s tuple (the same floats as
        its own call), or None where the kernel does not serve it (a speed bin not simulated yet, a lane it cannot
        read, a kernel switched off): the caller's :meth:`predict` then does, simulating what is missing as the
        reference does."""
        return self.split_rows(self.predict_rows_flat(others, row_off, lane_indices, accels, t, intent), len(t),
                               len(row_off) - 1)

    @staticmethod
    def split_rows(flat: tuple | None, K: int, R: int) -> list:
        """:meth:`predict_rows_flat`'s buffers as :meth:`predict_rows`' per-decision tuples (views, no copies), for
        ``K`` times and ``R`` decisions."""
        if flat is None:
            return [None] * R
        h_off, n_h, xy, hh, owner, is_map, prob = flat
        out = []
        for o, H in zip(h_off.tolist(), n_h.tolist()):  # each decision's blocks of the flat buffers
            out.append(None if H < 0 else (xy[2 * K * o: 2 * K * (o + H)].reshape(K, H, 2),
                                           hh[K * o: K * (o + H)].reshape(K, H), owner[o: o + H], is_map[o: o + H],
                                           prob[o: o + H]))
        return out

    def predict_rows_flat(self, others: np.ndarray, row_off: np.ndarray, lane_indices: list, accels: np.ndarray,
                          t: np.ndarray, intent: np.ndarray | None = None) -> tuple | None:
        """:meth:`predict_rows`' flat buffers: ``(h_off (R + 1,), n_h (R,), xy, hh, owner, is_map, prob)``, decision
        r's H = ``n_h[r]`` hypotheses (-1: not served) from hypothesis ``h_off[r]`` on (``xy`` a (K, H, 2) block from
        ``2 K h_off[r]``, ``hh`` (K, H) from ``K h_off[r]``; :func:`av_gym.shields.conflict_rows.
        conflict_predict_rows`, :func:`~av_gym.shields.kernels.conflict_predict_rows` without its per-decision
        copies); None where the kernels are switched off or cannot read the lanes."""
        from av_gym.shields.conflict_rows import conflict_predict_rows
        from av_gym.shields.predict import DrivenPath

        row_off = np.asarray(row_off, dtype=np.int64)
        R = len(row_off) - 1
        inputs = self._kernel_inputs(others, lane_indices, accels, intent) \
            if CONFLICT_KERNEL and DrivenPath.kernel else None
        if inputs is None:
            return None
        reg, args = inputs
        t = np.ascontiguousarray(t, dtype=float)
        h_off = _row_blocks(reg, args[3], row_off)
        K, n_all = len(t), int(h_off[-1])
        xy, hh, prob = np.empty(2 * K * n_all), np.empty(K * n_all), np.empty(n_all)
        owner, is_map, n_h = np.empty(n_all, np.int64), np.empty(n_all, np.bool_), np.empty(R, np.int64)
        conflict_predict_rows(row_off, *args, reg.ids, t, float(self.accel_time), *_store_arrays(), h_off, xy, hh,
                              owner, is_map, prob, n_h)
        return h_off, n_h, xy, hh, owner, is_map, prob

    def predict(self, others: np.ndarray, lane_indices: list, accels: np.ndarray, t: np.ndarray,
                intent: np.ndarray | None = None, follow: np.ndarray | None = None):
        """Positions (K, M', 2), headings (K, M'), owner (M',), whether each is a map hypothesis (M',) and its
        probability (M',) over the hypotheses of ``others`` (M, 7) on ``lane_indices`` (None = off the map),
        ``accels`` (M, 2) m/s² world frame; ``intent`` (M, 3) the weight of each turn (right, straight, left:
        :data:`av_gym.estimation.driver_intent.TURNS`) from the object's indicator readings, a NaN row where there are
        none; ``follow`` (M,) bool: objects that take their lane hypotheses at any speed above 0 (the AEB shield's
        set-off rule marks the standing cars it predicts setting off along their lanes from 0.5 m/s: a speed
        test would meet that 0.5 across a rounding, ``hypot(0.5 cos h, 0.5 sin h)`` is one ulp under 0.5 for
        ~1.4 % of headings), None: none.

        All of it in one compiled call (:meth:`_predict_compiled`), which composes the kernels of the steps: which
        hypotheses each object gets (:func:`av_gym.shields.kernels.conflict_hypotheses`; ``CONFLICT_KERNEL =
        False``: :meth:`_select`, the Python reference), the distance and speed profiles of all objects
        (``along_profiles``; the reference: :meth:`along_many`), every map hypothesis on its driven path
        (:func:`av_gym.shields.predict.driven_poses`; ``DrivenPath.kernel = False``: one numpy look-up at a time, the
        reference), the constant-velocity objects (``object_predict``)."""
        from av_gym.shields.predict import DrivenPath, driven_poses, object_predict, profile_speeds

        t = np.ascontiguousarray(t, dtype=float)
        if CONFLICT_KERNEL and DrivenPath.kernel:  # all of it in one compiled call
            out = self._predict_compiled(others, lane_indices, accels, t, intent, follow)
            if out is not None:
                return out
        chosen = self._select_compiled(others, lane_indices, accels, intent, follow) if CONFLICT_KERNEL else None
        paths, ids, starts, rows, v_on, a_on, owner, prob, cv = chosen or self._select(others, lane_indices, accels,
                                                                                      intent, follow)
        xs, hs, is_map = [], [], [True] * len(paths)
        if len(paths):
            if CONFLICT_KERNEL:  # distances and path speeds (objects, K) in one compiled call
                from av_gym.shields.kernels import along_profiles

                dist, v_path = along_profiles(np.asarray(v_on, dtype=float), np.asarray(a_on, dtype=float), t,
                                              float(self.accel_time))
            else:
                dist = self.along_many(np.array(v_on), np.array(a_on), t)  # (objects, K)
                zero = np.zeros((len(dist), 1))
                # profile_speeds, row by row the same
                v_path = np.maximum(np.diff(np.concatenate([zero, dist], 1), axis=1)
                                    / np.maximum(np.diff(np.concatenate([[0.0], t])), 1e-9), 0.0)
            rows = np.asarray(rows)
            if DrivenPath.kernel:  # every hypothesis on its driven path in one compiled call
                xy, h = driven_poses(paths, np.asarray(starts, dtype=float), dist[rows], v_path[rows], ids)
                xs.append(xy.transpose(1, 0, 2))
                hs.append(h.T)
            else:  # the numpy reference, one look-up at a time, with the per-object profiles of before
                for path, s0, r in zip(paths, starts, rows):
                    ds = self.along(v_on[r], a_on[r], t)
                    xy, h = path.poses_numpy(s0, ds, profile_speeds(ds, t, v_on[r]))
                    xs.append(xy[:, None, :])
                    hs.append(h[:, None])
        if len(cv):
            cv_xy, cv_h = object_predict(others[cv], t)
            xs.append(cv_xy)
            hs.append(cv_h)
            owner = [*owner, *cv]
            is_map += [False] * len(cv)
            prob = [*prob, *[1.0] * len(cv)]
        if not xs:
            return np.zeros((len(t), 0, 2)), np.zeros((len(t), 0)), np.zeros(0, int), np.zeros(0, bool), \
                np.zeros(0)
        return (np.concatenate(xs, 1), np.concatenate(hs, 1), np.asarray(owner, dtype=int),
                np.asarray(is_map, dtype=bool), np.asarray(prob, dtype=float))
