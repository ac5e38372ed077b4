"""The unprotected left turn (``av_gym.envs.left_turn``, both modes, both action types) for B environments at
once, on the batched traffic of :mod:`av_gym.sim.batched`.

:class:`BatchedLeftTurn` is the env layer: per-environment seeded generators drawing the traffic exactly as
``UnprotectedLeftTurnEnv.reset(seed=s)`` / ``step`` do, the reward terms, termination, ``info["truth"]``'s fields
and the ``obs["turn"]`` turn features (``TurnFeatures(source=truth)``) for the whole batch as arrays. The RL
interfaces (SB3 ``VecEnv``, Gymnasium ``VectorEnv``) are in :mod:`av_gym.batched.vec_env`.
"""

from __future__ import annotations

import copy
import itertools

import numpy as np
from gymnasium.utils import seeding
from highway_env import utils

from av_gym.envs.left_turn import CONFLICT_POINT, ONCOMING_NEAR_EDGE_X, ROUTE, UnprotectedLeftTurnEnv
from av_gym.estimation.turn_features import (IntentHistory, TurnEncoding, TurnFeaturesParams, TurnIntentParams,
                                            T_MAX, turn_features, turn_path)
from av_gym.sensors.base import episode_rng
from av_gym.sensors.turn_signal import (DriverDraws, TurnSignalsParams, node_index, read_signals, route_origin,
                                       turn_signal)
from av_gym.sim import batched, kernels
from av_gym.sim.batched import LENGTH, SPAWN_PRIOR, WIDTH, LaneTable, SpawnPrior, Traffic

SPAWN_CLEAR = 15.0  # m, IntersectionEnv._spawn_vehicle: no spawn this close to another vehicle
EGO_CLEAR = 20.0  # m, _make_vehicles: vehicles this close to the ego are removed ("prevent early collisions")
INITIAL_SPAWN_PROBABILITY = 0.6  # _spawn_vehicle's default, which _make_vehicles' initial spawns use
# the state arrays a spawn kernel writes (kernels._spawn_one's ``fl``, ``flags``, ``it``)
_SPAWN_FLOATS = ("x", "y", "h", "v", "target", "delta", "steer", "acc", "impact_x", "impact_y")
_SPAWN_FLAGS, _SPAWN_INTS = ("crashed", "yielding", "has_impact"), ("lane", "tlane", "rpos", "vid")
_CLEAR_FLAGS = ("alive", "ego", "plain", "mdp", *_SPAWN_FLAGS)  # kernels.clear_exits' ``bl`` (alive, ego first)

_TABLES = None
_NOT_READ = object()  # a row whose generator's state address was not read yet (BatchedLeftTurn._row_states)


def tables() -> tuple[LaneTable, object]:
    """The intersection's lanes (IntersectionEnv._make_road), built once."""
    global _TABLES
    if _TABLES is None:
        env = UnprotectedLeftTurnEnv(config={"fast": False})
        env._make_road()
        _TABLES = (LaneTable(env.road.network), env.road.network)
    return _TABLES


def full_config(config: dict | None) -> dict:
    cfg = UnprotectedLeftTurnEnv.default_config()
    for k, v in (config or {}).items():
        cfg[k] = {**cfg[k], **v} if isinstance(v, dict) and isinstance(cfg.get(k), dict) else v
    return cfg


class BatchedLeftTurn:
    """B left-turn episodes stepped together. ``reset(seeds)`` / ``reset_envs(rows, seeds)``; ``step(actions)``
    with the env's actions (discrete meta-actions (B,), or continuous (B,) / (B, 1) in [-1, 1]) returns reward,
    terminated, truncated; :meth:`observe` gives obs["turn"] (B, F) and the truth arrays (:meth:`truth`).

    ``mode: ccftap``: every episode is the Euro NCAP test case of the config (the ego and one plain ``Vehicle``
    target, no traffic); an episode's only draw is its episode seed, as on the per-env stack."""

    # the per-env (B,) arrays of the episode clocks and progress (besides the traffic and the generators): what a
    # fork copies row by row
    _ROW_ARRAYS = ("time", "ticks", "_route_k", "progress_s", "progress_total", "arrived_time", "episode_seed", "cmd")

    def __init__(self, n_envs: int, config: dict | None = None, features: TurnFeaturesParams | dict | None = None,
                 pool: int = 0, **feature_overrides) -> None:
        self.config = c = full_config(config)
        problems = UnprotectedLeftTurnEnv.Params.config_problems(c, where="env")  # the env's own checks, as its keys
        if problems:
            raise ValueError(problems[0])
        self.ccftap, self.continuous = c["mode"] == "ccftap", c["action"]["type"] == "continuous"
        # the MDPVehicle's set-points (UnprotectedLeftTurnEnv.define_spaces: ccftap has [0, test speed])
        self.speeds = np.array([0.0, float(c["ccftap_ego_speed"])] if self.ccftap else c["action"]["target_speeds"],
                               dtype=float)
        self.acceleration_range = [float(a) for a in c["action"]["acceleration_range"]]
        self.B = int(n_envs)
        self.cmd = np.zeros(self.B)  # RouteFollowingVehicle.commanded_acceleration (continuous actions), m/s²
        self._case = self._ccftap_case() if self.ccftap else None
        self.time_limit = self._case["time_limit"] if self.ccftap else float(c["duration"])
        self.T, network = tables()
        self.dt = 1.0 / c["simulation_frequency"]
        self.frames = int(c["simulation_frequency"] // c["policy_frequency"])
        self.traffic = Traffic(self.T, self.B)
        self.rngs = [seeding.np_random(None)[0] for _ in range(self.B)]
        T = self.T
        self.route = np.array([T.id[i] for i in ROUTE])
        self._spawn_table = self._spawn_lanes()
        self.route_starts = np.concatenate([[0.0], np.cumsum(T.length[self.route])[:-1]])
        turn = network.get_lane(ROUTE[1])
        self.conflict_s = self.route_starts[1] + turn.local_coordinates(CONFLICT_POINT)[0]
        # obs["turn"]: TurnFeatures(source=truth) with these parameters (its defaults and checks)
        self.features = TurnFeaturesParams.build(features, **feature_overrides)
        self.max_objects = int(self.features.max_objects)
        self.path, self.path_s = turn_path(turn, network.get_lane(ROUTE[2]))
        self.n_features = TurnEncoding.of(self.features).width
        B = self.B
        self.time, self.ticks = np.zeros(B), np.zeros(B, dtype=int)
        self._route_k, self.progress_s, self.progress_total = np.zeros(B, dtype=int), np.zeros(B), np.ones(B)
        self.prior: SpawnPrior = SPAWN_PRIOR  # the spawns' speed and IDM draws (the belief planner reads it too)
        self.arrived_time = np.full(B, np.nan)
        self.episode_seed = np.zeros(B, dtype=np.int64)
        self._new: list[tuple[int, int]] = []  # (env, slot) of vehicles added since the last settle
        self.pool_size = int(pool)
        self._pending: list = []  # generators whose next episode is not made yet
        self._ready, self._ready_rngs, self._ready_seeds = None, [], []
        self._state_rngs, self._states = None, None  # the generator addresses of _row_states

    # ------------------------------------------------------------------------------------------- traffic draws
    def _spawn(self, t: Traffic, b: int, rng, longitudinal: float = 0.0, position_deviation: float = 1.0,
               speed_deviation: float = 1.0, spawn_probability: float = INITIAL_SPAWN_PROBABILITY,
               go_straight: bool = False,
               u: float | None = None) -> None:
        """IntersectionEnv._spawn_vehicle: the same draws in the same order on env b's generator (``u``: its first
        draw, when the caller made it)."""
        if (rng.uniform() if u is None else u) > spawn_probability:
            return
        # choice(range(4), ...) as highway-env calls it: the same draws and values from the int population (the
        # range becomes arange(4), indexed by the same picks), without converting the range each time
        route = rng.choice(4, size=2, replace=False)
        route[1] = (route[0] + 2) % 4 if go_straight else route[1]
        T = self.T
        lane = T.id[(f"o{route[0]}", f"ir{route[0]}", 0)]
        s = longitudinal + 5.0 + rng.normal() * position_deviation
        speed = self.prior.draw_speed(rng, speed_deviation)
        pose = T.pose(lane, s)
        x, y = pose[0], pose[1]
        a = t.alive[b]
        if (np.hypot(t.x[b, a] - x, t.y[b, a] - y) < SPAWN_CLEAR).any():
            return
        dest = route[1]
        plan = [lane, T.id[(f"ir{route[0]}", f"il{dest}", 0)], T.id[(f"il{dest}", f"o{dest}", 0)]]
        delta = self.prior.draw_delta(rng)  # IDMVehicle.randomize_behavior
        # plan[0]: settled to the closest lane
        self._new.append((b, t.add(b, lane, s, speed, plan, delta=delta, pose=pose)))

    def _spawn_lanes(self) -> np.ndarray | None:
        """The spawn kernels' lane table (kernels._spawn_one's ``lanes``), or None if a spawn lane is not straight
        (the kernels place vehicles by the straight-lane arithmetic; numpy's calls then spawn)."""
        T, out = self.T, np.full((4, 6), -1, dtype=np.int64)
        for r in range(4):
            out[r, 0], out[r, 5] = T.id[(f"o{r}", f"ir{r}", 0)], T.id[(f"il{r}", f"o{r}", 0)]
            for d in range(4):
                out[r, 1 + d] = T.id.get((f"ir{r}", f"il{d}", 0), -1)
        return None if T.circular[out[:, 0]].any() else out

    def _spawn_kernel(self, t: Traffic, rngs: list, new_per_env: int, call) -> bool:
        """Run the spawn kernel ``call(fns, states, *lane and state arrays, first_id)`` on ``t`` for the generators
        ``rngs`` (one per row it draws for), each row adding at most ``new_per_env`` vehicles. False (nothing drawn)
        when the numpy calls must spawn instead: ``spawn`` not in KERNELS, or a generator that is not a PCG64 or
        shared. Slots: the arrays grow by 8 at a time as far as the spawns could need, then keep only the growth
        that Traffic.add's own (8 slots when a spawn finds its row full) would have made."""
        if "spawn" not in batched.KERNELS or self._spawn_table is None:
            return False
        states = kernels.generator_states(rngs)
        if states is None:
            return False
        before = t.N
        short = int(t.alive.sum(axis=1).max(initial=0)) + new_per_env - before
        if short > 0:
            t.grow(8 * -(-short // 8))
        self._spawn_call(t, states, call)
        if short > 0:
            used = int(t.alive.sum(axis=1).max(initial=0)) - before
            t.cut(before + 8 * -(-max(used, 0) // 8))
        return True

    def _spawn_tries(self, t: Traffic, rows: np.ndarray, p: float) -> bool:
        """The spawn tries of ``rows`` (probability ``p``) in kernels.spawn_tries, or False (nothing drawn) as
        :meth:`_spawn_kernel`. A spawn that finds its row full comes back drawn but not placed: Traffic.add places
        it (growing the slots by 8, as on numpy's path) and settles it, and the tries go on after its row."""
        if "spawn" not in batched.KERNELS or self._spawn_table is None:
            return False
        states = self._row_states(rows)
        if states is None:
            return False
        start, pending, stop = 0, np.zeros(9), [-1]

        def tries(*args) -> int:
            n, stop[0] = kernels.spawn_tries(args[0], args[1], rows, start, p, *args[2:], pending)
            return n

        while start <= len(rows):
            self._spawn_call(t, states, tries)
            if stop[0] < 0:
                return True
            k, s, x, y, h, speed, delta, lane1, lane2 = pending
            b, k = int(rows[stop[0]]), int(k)
            slot = t.add(b, k, s, speed, [k, int(lane1), int(lane2)], delta=delta, pose=(x, y, h))
            t.settle(np.array([b]), np.array([slot]))
            start = stop[0] + 1
        return True

    def _row_states(self, rows: np.ndarray) -> np.ndarray | None:
        """kernels.generator_states of the generators of ``rows``, reading only those of rows whose generator
        changed since it was last read (a state's address is fixed for its generator's life; reading B of them
        costs ~1.5 us each, most of a step's spawn tries at B = 1,024). ``_state_rngs`` holds the generators whose
        addresses ``_states`` caches, so none of them is freed while cached."""
        if self._state_rngs is None or len(self._state_rngs) != self.B:
            self._state_rngs, self._states = [_NOT_READ] * self.B, np.zeros(self.B, dtype=np.uint64)
        cached, rngs = self._state_rngs, self.rngs
        stale = [b for b in np.asarray(rows).tolist() if rngs[b] is not cached[b]]  # Python ints: list indexing
        if stale:
            read = kernels.generator_states([rngs[b] for b in stale])
            if read is None:
                return None
            self._states[stale] = read
            for b in stale:
                cached[b] = rngs[b]
        states = self._states[rows]
        ordered = np.sort(states)  # a generator shared by two rows: equal neighbours (a sort, not np.unique's hash)
        return None if (ordered[1:] == ordered[:-1]).any() else states

    def _spawn_call(self, t: Traffic, states: np.ndarray, call) -> None:
        """:meth:`_spawn_kernel`'s call, with the lane table, the prior and ``t``'s state arrays."""
        p = self.prior
        args = (kernels.pcg64_functions(), states, self.T.arr, self._spawn_table,
                np.array([p.speed, p.speed_sd, *p.delta], dtype=float), tuple(batched._contiguous(t, *_SPAWN_FLOATS)),
                *batched._contiguous(t, "alive", "ego", "plain", "mdp"), tuple(batched._contiguous(t, *_SPAWN_FLAGS)),
                tuple(batched._contiguous(t, *_SPAWN_INTS)), *batched._contiguous(t, "route"))
        batched.numbered(lambda first: call(*args, first))

    def _settle(self, t: Traffic) -> None:
        if self._new:
            b, slots = np.array(self._new).T
            t.settle(b, slots)
        self._new = []

    def _ccftap_case(self) -> dict:
        """The CCFtap case's initial ego and target and its time limit, from the per-env env's own set-up
        (UnprotectedLeftTurnEnv._make_ccftap, which draws nothing): one source for the test's geometry and timing,
        whose floats the batch then starts from."""
        env = UnprotectedLeftTurnEnv(config={k: v for k, v in self.config.items() if k != "observation"})
        env.reset(seed=0)
        ego, target = env.vehicle, env.ccftap_target
        state = lambda v: (float(v.position[0]), float(v.position[1]), float(v.heading), float(v.speed))  # noqa: E731
        case = {"ego": state(ego), "ego_target": float(getattr(ego, "target_speed", ego.speed)),
                "target": state(target), "time_limit": float(env._ccftap_time_limit)}
        env.close()
        return case

    def _make_ccftap(self, rngs: list) -> tuple[Traffic, list[int]]:
        """UnprotectedLeftTurnEnv._make_ccftap + ScenarioMixin._finish_reset for one episode per generator: the ego
        and the target in road order, then the episode seed (the episode's only draw)."""
        t, T, case = Traffic(self.T, len(rngs), N=4), self.T, self._case
        ego_lane = T.id[ROUTE[0]]
        for b in range(len(rngs)):
            for key, ego in (("ego", True), ("target", False)):
                x, y, h, v = case[key]
                slot = t.add(b, ego_lane, 0.0, v, [ego_lane, *self.route[1:]] if ego else [-1], ego=ego,
                             target=case["ego_target"] if ego else v, plain=not ego, mdp=ego and not self.continuous)
                t.x[b, slot], t.y[b, slot], t.h[b, slot] = x, y, h
                if not ego:
                    t.route[b, slot] = -1
                self._new.append((b, slot))
        self._settle(t)
        t.route[t.plain] = -1  # settle() wrote the closest lane as the route's first step: a plain Vehicle has none
        return t, [int(rng.integers(2**63 - 1)) for rng in rngs]

    def _make_vehicles(self, rngs: list) -> tuple[Traffic, list[int]]:
        """IntersectionEnv._make_vehicles(initial_vehicle_count) + ScenarioMixin._finish_reset for one new episode
        per generator in ``rngs``, as a sub-batch: initial traffic, 3 s of simulation (batched), the challenger,
        the ego, no vehicle within 20 m of the ego, then the episode seed. Returns the traffic and episode seeds.
        CCFtap: :meth:`_make_ccftap`."""
        if self.ccftap:
            return self._make_ccftap(rngs)
        n_vehicles = int(self.config["initial_vehicle_count"])
        starts = np.linspace(0, 80, n_vehicles)  # m, the initial vehicles' spawn offsets
        t = Traffic(self.T, len(rngs), N=max(16, n_vehicles + 4))
        first = starts[: max(n_vehicles - 1, 0)]
        initial = lambda fns, states, lt, lanes, prior, *rest: kernels.spawn_initial(  # noqa: E731
            fns, states, first, INITIAL_SPAWN_PROBABILITY, lt, lanes, prior, *rest)
        if not self._spawn_kernel(t, rngs, len(first), initial):
            for b, rng in enumerate(rngs):
                for k in range(n_vehicles - 1):
                    self._spawn(t, b, rng, starts[k])
        self._settle(t)
        warm_up = 3 * int(self.config["simulation_frequency"])
        if "tick" in batched.KERNELS:
            t.advance(self.dt, warm_up)
        else:
            for _ in range(warm_up):
                t.act()
                t.step(self.dt)
        T = self.T
        ego_lane = T.id[ROUTE[0]]
        ego_s, ego_id = np.zeros(len(rngs)), np.zeros(len(rngs), dtype=np.int64)
        challengers = lambda *args: kernels.spawn_challengers(*args, ego_s, ego_id)  # noqa: E731
        compiled = self._spawn_kernel(t, rngs, 2, challengers)
        for b, rng in enumerate(rngs):
            if not compiled:
                self._spawn(t, b, rng, 60, spawn_probability=1.0, go_straight=True, position_deviation=0.1,
                            speed_deviation=0.0)
                ego_s[b] = 60.0 + 5.0 * rng.normal(1.0)
            slot = t.add(b, ego_lane, float(ego_s[b]), T.speed_limit[ego_lane], [ego_lane, *self.route[1:]],
                         ego=True, target=self._ego_target(T.speed_limit[ego_lane]), mdp=not self.continuous,
                         vid=int(ego_id[b]) if compiled else None)
            t.h[b, slot] = T.heading_at(ego_lane, 60.0)
            self._new.append((b, slot))
        self._settle(t)
        seeds = []
        for b, rng in enumerate(rngs):
            slot = int(np.argmax(t.ego[b]))
            near = t.alive[b] & ~t.ego[b] & (np.hypot(t.x[b] - t.x[b, slot], t.y[b] - t.y[b, slot]) < EGO_CLEAR)
            t.alive[b] &= ~near
            seeds.append(int(rng.integers(2**63 - 1)))  # ScenarioMixin._finish_reset
        t.compact()
        t.trim()
        return t, seeds

    def _ego_target(self, speed: float) -> float:
        """The new ego's target speed: MDPVehicle.__init__'s speed_to_index / index_to_speed of its speed
        (discrete: 10 m/s → 9 m/s), or ControlledVehicle's (the speed itself) for the continuous action's
        RouteFollowingVehicle."""
        if self.continuous:
            return float(speed)
        ts = self.speeds
        x = (speed - ts[0]) / (ts[-1] - ts[0])
        return float(ts[int(np.clip(np.round(x * (ts.size - 1)), 0, ts.size - 1))])

    # ------------------------------------------------------------------------------------------- episodes
    def reset(self, seeds=None):
        return self.reset_envs(np.arange(self.B), seeds)

    def reset_envs(self, rows, seeds=None):
        """Reset the envs ``rows`` (seeded with ``seeds`` where given, else their generators go on)."""
        rows = np.asarray(rows, dtype=int)
        if seeds is not None:
            for row, seed in zip(rows, seeds):
                if seed is not None:
                    self.rngs[row] = seeding.np_random(int(seed))[0]
        traffic, episode_seeds = self._make_vehicles([self.rngs[r] for r in rows])
        self._start(rows, traffic, episode_seeds)
        if self.pool_size and len(rows) == self.B:  # spare streams, seeded from the batch's seeds
            given = [int(s) for s in seeds if s is not None] if seeds is not None else []
            self._fill_pool(np.random.SeedSequence(given or None))
        return self.observe(rows)

    def _start(self, rows, traffic: Traffic, episode_seeds) -> None:
        self.traffic.put(rows, traffic)
        self.episode_seed[rows] = episode_seeds
        self.time[rows], self.ticks[rows], self._route_k[rows] = 0.0, 0, 0
        self.arrived_time[rows] = np.nan
        self.cmd[rows] = 0.0
        s = self._route_s(rows)
        self.progress_s[rows] = s
        self.progress_total[rows] = np.maximum(1.0, self.route_starts[2] + 25.0 - s)

    # ------------------------------------------------------------------------------------------- auto-reset
    # A reset costs 3 s of warm-up simulation (60 ticks): alone, a numpy tick costs about as much for 1 env as
    # for 30. So episodes for auto-reset come from a pool of ready episodes, made ~pool at a time. Each
    # generator ("stream") plays exactly the episodes the per-env stack plays with it (reset(seed) then resets
    # without a seed); only which slot a stream's next episode runs in changes.
    def _fill_pool(self, seed_seq: np.random.SeedSequence | None = None) -> None:
        """Make ready episodes from the streams waiting for one (or ``pool`` new streams from ``seed_seq``)."""
        if seed_seq is not None:
            self._pending = [np.random.Generator(np.random.PCG64(s)) for s in seed_seq.spawn(self.pool_size)]
            self._ready = None
        if not self._pending:
            return
        traffic, seeds = self._make_vehicles(self._pending)
        if self._ready is None:
            self._ready, self._ready_rngs, self._ready_seeds = traffic, list(self._pending), seeds
        else:
            self._ready = Traffic.concat(self._ready, traffic)
            self._ready_rngs += self._pending
            self._ready_seeds += seeds
        self._pending = []

    def step_autoreset(self, actions: np.ndarray):
        """``step`` for every env; the envs whose episode ended start their next one (from the pool).
        Returns obs (B, F) (the new episode's first for the ended ones), reward, terminated, truncated, and
        for the ended envs: their rows, final obs and final truth."""
        reward, terminated, truncated = self.step(actions)
        done = np.nonzero(terminated | truncated)[0]
        final_obs = final_truth = None
        if len(done):
            final_obs, final_truth = self.observe(done), self.last_truth
            self.start_from_pool(done)
        return self.observe(), reward, terminated, truncated, (done, final_obs, final_truth)

    def start_from_pool(self, done) -> None:
        """The envs ``done`` (whose episodes ended) start the next episode of a ready stream; their own streams
        wait for their next episode, made with the next batch of them."""
        self._pending += [self.rngs[r] for r in done]
        n_ready = 0 if self._ready is None else self._ready.B
        if n_ready < len(done):
            self._fill_pool()
        k = len(done)
        self._start(done, self._ready.subset(np.arange(k)), self._ready_seeds[:k])
        for r, rng in zip(done, self._ready_rngs[:k]):
            self.rngs[r] = rng
        rest = np.arange(k, self._ready.B)
        self._ready = self._ready.subset(rest) if len(rest) else None
        self._ready_rngs, self._ready_seeds = self._ready_rngs[k:], self._ready_seeds[k:]

    # ------------------------------------------------------------------------------------------- seeded queue
    # Evaluation plays given seeds: episode k of the queue is the one ``reset(seed=seeds[k])`` gives (a fresh
    # generator seeded with it, as reset_envs), made ``chunk`` at a time in one batched warm-up.
    def queue(self, seeds, chunk: int) -> None:
        """Episodes for :meth:`start_queued`, one per seed of ``seeds`` (any iterable of ints, drawn lazily)."""
        self._q_iter, self._q_chunk = iter(seeds), max(1, int(chunk))
        self._q, self._q_rngs, self._q_eps, self._q_seeds = None, [], [], []

    def start_queued(self, rows) -> list:
        """Start the envs ``rows`` on the next queued episodes, in order. Returns each row's seed, None where the
        queue ran out (that env is left as it is)."""
        rows = [int(r) for r in rows]
        if len(self._q_seeds) < len(rows):
            want = max(self._q_chunk, len(rows) - len(self._q_seeds))
            new = [int(s) for s in itertools.islice(self._q_iter, want)]
            if new:
                rngs = [seeding.np_random(s)[0] for s in new]
                traffic, eps = self._make_vehicles(rngs)
                self._q = traffic if self._q is None else Traffic.concat(self._q, traffic)
                self._q_rngs, self._q_eps, self._q_seeds = self._q_rngs + rngs, self._q_eps + eps, self._q_seeds + new
        k = min(len(rows), len(self._q_seeds))
        seeds = self._q_seeds[:k] + [None] * (len(rows) - k)
        if k:
            self._start(np.array(rows[:k]), self._q.subset(np.arange(k)), self._q_eps[:k])
            for r, rng in zip(rows[:k], self._q_rngs[:k]):
                self.rngs[r] = rng
            rest = np.arange(k, self._q.B)
            self._q = self._q.subset(rest) if len(rest) else None
            self._q_rngs, self._q_eps, self._q_seeds = self._q_rngs[k:], self._q_eps[k:], self._q_seeds[k:]
        return seeds

    # ------------------------------------------------------------------------------------------- futures, views
    def fork(self, rows, k: int = 1, spawns: bool = True, rngs: list | None = None) -> "BatchedLeftTurn":
        """A new engine of len(rows)·k rows: each row of ``rows`` repeated ``k`` times (row-major: row 0's k copies
        first), its traffic, clocks and progress copied, without the episode pool or queue; stepping it leaves this
        engine as it is. ``rngs``: the new rows' generators (used as given, not copied); by default a deep copy of
        each row's own, so that the fork draws the spawns its episode will draw. ``spawns=False``: no vehicle
        enters the fork (only those on the map now drive on)."""
        rows = np.repeat(np.asarray(rows, dtype=int), int(k))
        if rngs is not None and len(rngs) != len(rows):
            raise ValueError(f"fork: rngs must give one generator per new row ({len(rows)}), got {len(rngs)}")
        f = copy.copy(self)  # shares the read-only tables, config, prior and path geometry
        if not spawns:
            f.config = {**self.config, "spawn_probability": 0.0}
        f.B, f.traffic = len(rows), self.traffic.subset(rows)
        f.rngs = [copy.deepcopy(self.rngs[r]) for r in rows] if rngs is None else list(rngs)
        for name in self._ROW_ARRAYS:
            setattr(f, name, getattr(self, name)[rows].copy())
        f._new, f._pending, f._ready, f._ready_rngs, f._ready_seeds = [], [], None, [], []
        f.pool_size, f._state_rngs, f._states = 0, None, None
        if self._state_rngs is not None and len(self._state_rngs) == self.B:  # _row_states' reads carried over
            f._state_rngs, f._states = [self._state_rngs[r] for r in rows], self._states[rows]
        return f

    def keep(self, rows) -> "BatchedLeftTurn":
        """This engine with only the rows ``rows`` (a future whose other rows ended): their generators move over
        as they are, not copied, so each stream goes on where it was."""
        rows = np.asarray(rows, dtype=int)
        return self.fork(rows, rngs=[self.rngs[r] for r in rows])

    def observed(self, traffic: Traffic, time: np.ndarray, ticks: np.ndarray, episode_seed: np.ndarray) \
            -> "BatchedLeftTurn":
        """A new engine (this one's config and tables) holding ``traffic`` as it was observed mid-episode: the
        episode clocks ``time`` (s) and ``ticks``, the episode seeds, the progress reward measured from the ego's
        place now, no arrival yet, no commanded acceleration, no generators (the caller gives a fork its own).
        The belief planner's view of a per-env env (agents/belief.py, EnvView)."""
        B = traffic.B
        e = self.fork(np.zeros(0, dtype=int), rngs=[])
        e.B, e.traffic, e.rngs = B, traffic, [None] * B
        e.time, e.ticks = np.array(time, dtype=float).reshape(B), np.array(ticks, dtype=int).reshape(B)
        e.episode_seed = np.array(episode_seed, dtype=np.int64).reshape(B)
        e._route_k, e.arrived_time, e.cmd = np.zeros(B, dtype=int), np.full(B, np.nan), np.zeros(B)
        rows = np.arange(B)
        e.progress_s = e._route_s(rows)
        e.progress_total = np.maximum(1.0, e.route_starts[2] + 25.0 - e.progress_s)
        return e

    def state_bytes(self) -> int:
        pool = 0 if self._ready is None else self._ready.state_bytes()
        return self.traffic.state_bytes() + pool + sum(a.nbytes for a in (
            self.time, self.ticks, self._route_k, self.progress_s, self.progress_total, self.arrived_time))

    def ego_slot(self, rows=None) -> np.ndarray:
        rows = np.arange(self.B) if rows is None else rows
        return np.argmax(self.traffic.ego[rows], axis=1)

    def _route_s(self, rows: np.ndarray) -> np.ndarray:
        """LanePath.locate from the hint ``_route_k`` + path_s, for the ego of each env in ``rows``."""
        t, T = self.traffic, self.T
        e = self.ego_slot(rows)
        x, y = t.x[rows, e], t.y[rows, e]
        k = self._route_k[rows].copy()
        s, lat = T.local(self.route[k], x, y)
        step = np.where(s > T.length[self.route[k]], 1, np.where(s < 0, -1, 0))
        for _ in range(len(self.route)):
            nxt = k + step
            go = (step != 0) & (nxt >= 0) & (nxt < len(self.route))
            if not go.any():
                break
            k = np.where(go, nxt, k)
            s2, lat2 = T.local(self.route[k], x, y)
            s, lat = np.where(go, s2, s), np.where(go, lat2, lat)
            done = ((step > 0) & (s <= T.length[self.route[k]])) | ((step < 0) & (s >= 0))
            step = np.where(go & ~done, step, 0)
        self._route_k[rows] = k
        self._lat = lat
        return self.route_starts[k] + s

    def has_arrived(self, rows, slots, exit_distance: float = batched.EXIT_DISTANCE) -> np.ndarray:
        """IntersectionEnv.has_arrived: on an "il"→"o" lane, ≥ 25 m along it."""
        t, T = self.traffic, self.T
        lane = t.lane[rows, slots]
        s, _ = T.local(lane, t.x[rows, slots], t.y[rows, slots])
        return T.exit[lane] & (s >= exit_distance)

    def _clear_and_spawn(self, rows: np.ndarray) -> None:
        """The left turn's step prologue: IntersectionEnv._clear_vehicles, then one spawn try at
        spawn_probability / policy_frequency."""
        t, T = self.traffic, self.T
        rows = np.asarray(rows, dtype=np.int64)
        if "clear" in batched.KERNELS:  # the same test and compaction in one call
            kernels.clear_exits(T.arr, T.rules, rows, 4 * LENGTH, tuple(batched._contiguous(t, *_SPAWN_FLOATS)),
                                tuple(batched._contiguous(t, *_CLEAR_FLAGS)),
                                tuple(batched._contiguous(t, *_SPAWN_INTS)), *batched._contiguous(t, "route"))
        else:
            gone = np.zeros_like(t.alive)
            gone[rows] = (t.alive & ~t.ego & T.exit[t.lane])[rows]  # on a leaving lane; then: near its end?
            b, i = np.nonzero(gone)
            s, _ = T.local(t.lane[b, i], t.x[b, i], t.y[b, i])
            gone[b, i] = s >= T.length[t.lane[b, i]] - 4 * LENGTH
            if gone.any():
                t.alive &= ~gone
                t.compact()
        p = self.config["spawn_probability"] / self.config["policy_frequency"]
        if not self._spawn_tries(t, rows, float(p)):
            # the spawn try's first draw, rng.uniform() (most tries stop there): random() draws the same double
            # from the stream and uniform(0, 1) returns 0 + 1 · it, the same float, for a quarter of the call's cost
            u = [self.rngs[b].random() for b in rows]
            for b, u_b in zip(rows, u):
                if u_b <= p:
                    self._spawn(t, int(b), self.rngs[b], spawn_probability=p, u=u_b)
        self._settle(t)

    def step(self, actions: np.ndarray, active: np.ndarray | None = None, ego_acceleration: np.ndarray | None = None):
        """One policy step of every env (``active``: the envs to step; the others are left as they are).
        ``actions``: discrete meta-actions (B,) {0: SLOWER, 1: IDLE, 2: FASTER}, or continuous (B,) / (B, 1) in
        [-1, 1] mapped onto ``acceleration_range`` (LongitudinalAction.act). ``ego_acceleration`` (frames, B), m/s²:
        the ego's acceleration per tick over its own control where not NaN (the AEB shield's brake)."""
        c, t = self.config, self.traffic
        active = np.ones(self.B, bool) if active is None else np.asarray(active, bool)
        rows = np.nonzero(active)[0]
        if not self.ccftap:
            self._clear_and_spawn(rows[self.ticks[rows] > 0])
        self.time[rows] += 1.0 / c["policy_frequency"]
        meta = None
        if self.continuous:  # LongitudinalAction.act: clip to [-1, 1], then utils.lmap onto the range
            a = np.clip(np.asarray(actions, dtype=float).reshape(self.B, -1)[:, 0], -1.0, 1.0)
            lo, hi = self.acceleration_range
            self.cmd[rows] = (lo + (a - -1) * (hi - lo) / (1 - -1))[rows]
        else:
            meta = np.where(active, np.asarray(actions).reshape(self.B), 1)
        cmd = self.cmd if self.continuous else None
        if ego_acceleration is not None:  # per tick: the brake where given, the ego's own command elsewhere
            own = np.broadcast_to(np.nan if cmd is None else cmd, (self.frames, self.B))
            cmd = np.where(np.isnan(ego_acceleration), own, ego_acceleration)
        if "tick" in batched.KERNELS:  # every tick of every active env in one compiled call
            t.advance(self.dt, self.frames, active, meta, self.speeds, cmd,
                      clocks=(self.ticks, self.time, self.arrived_time))
        else:
            self._ticks(rows, ~active, meta, cmd)
        t.trim()
        reward, terminated, truncated = np.zeros(self.B), np.zeros(self.B, bool), np.zeros(self.B, bool)
        reward[rows], crashed, arrived = self._reward(rows)
        # arrival ends the episode in both modes (UnprotectedLeftTurnEnv._is_terminated): paid once, and a CCFtap
        # ego that has not arrived runs on to the time limit, so one parked in the target's path is hit
        terminated[rows] = crashed | arrived
        truncated[rows] = self.time[rows] >= self.time_limit
        return reward, terminated, truncated

    def _ticks(self, rows: np.ndarray, idle: np.ndarray, meta: np.ndarray | None, cmd: np.ndarray | None) -> None:
        """A policy step's ticks on the numpy path (Traffic.act, Traffic.step), the ego's commanded acceleration
        ``cmd`` ((B,) or (frames, B), m/s², NaN: its speed control; None: none), arrivals stamped per tick; the
        envs ``idle`` are stepped too and then put back as they were (a done env waits for its reset)."""
        t = self.traffic
        frozen = {name: getattr(t, name)[idle].copy() for name in Traffic.FIELDS} if idle.any() else None
        steps_frozen = t.road_steps[idle].copy()
        for frame in range(self.frames):
            t.act(meta if frame == 0 else None, self.speeds,
                  None if cmd is None else np.broadcast_to(cmd, (self.frames, self.B))[frame])
            t.step(self.dt)
            self.ticks[rows] += 1
            e = self.ego_slot(rows)
            arrived = self.has_arrived(rows, e) & np.isnan(self.arrived_time[rows])
            self.arrived_time[rows[arrived]] = self.time[rows[arrived]]
        if frozen is not None:  # envs already done wait for their reset unchanged
            for name, value in frozen.items():
                getattr(t, name)[idle] = value
            t.road_steps[idle] = steps_frozen

    def _reward(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """UnprotectedLeftTurnEnv._reward for the envs ``rows``, and whether each ego crashed and has arrived."""
        c, t = self.config, self.traffic
        dt = 1.0 / c["policy_frequency"]
        lo, hi = c["reward_speed_range"]
        if "reward" in batched.KERNELS:  # the same terms in one call (kernels.rewards)
            prm = np.array([c["high_speed_reward"], lo, hi, dt, c["progress_reward"], c["comfort_reward"],
                            c["collision_reward"], c["arrived_reward"], batched.EXIT_DISTANCE], dtype=float)
            return kernels.rewards(self.T.arr, self.T.rules, self.route, self.route_starts,
                                   np.asarray(rows, dtype=np.int64), *batched._contiguous(t, "x", "y", "v", "acc",
                                                                                          "ego", "crashed", "lane"),
                                   self._route_k, self.progress_s, self.progress_total, prm)
        e = self.ego_slot(rows)
        v = t.v[rows, e]
        reward = c["high_speed_reward"] * np.clip((v - lo) / (hi - lo), 0, 1) * dt
        if c["progress_reward"]:
            s = self._route_s(rows)
            reward = reward + c["progress_reward"] * np.maximum(0.0, s - self.progress_s[rows]) \
                / self.progress_total[rows]
            self.progress_s[rows] = np.maximum(s, self.progress_s[rows])
        if c["comfort_reward"]:
            reward = reward - c["comfort_reward"] * (t.acc[rows, e] / 3.0) ** 2 * dt
        crashed = t.crashed[rows, e]
        arrived = self.has_arrived(rows, e)
        return reward + np.where(crashed, c["collision_reward"], np.where(arrived, c["arrived_reward"], 0.0)), \
            crashed, arrived

    # ------------------------------------------------------------------------------------------- truth, obs
    def truth(self, rows=None) -> dict:
        """``info["truth"]``'s scalar fields as arrays over ``rows`` (SI units; see UnprotectedLeftTurnEnv.truth).
        ``others`` is not built per env here: :meth:`others` gives (rows, N, 7) with a mask."""
        rows = np.arange(self.B) if rows is None else np.asarray(rows)
        t = self.traffic
        if "truth" in batched.KERNELS:  # the same fields in one call (kernels.truth)
            return self._truth_dict(kernels.truth(*self._truth_args(rows)))
        e = self.ego_slot(rows)
        route_s = self._route_s(rows)
        x, y, h, v = t.x[rows, e], t.y[rows, e], t.h[rows, e], t.v[rows, e]
        steer, acc = t.steer[rows, e], t.acc[rows, e]
        beta = np.arctan(0.5 * np.tan(steer))
        c, s = np.cos(h), np.sin(h)
        corner_x = x[:, None] + np.array([-1, -1, 1, 1]) * LENGTH / 2 * c[:, None] \
            - np.array([-1, 1, 1, -1]) * WIDTH / 2 * s[:, None]
        return {"time": self.time[rows].copy(), "x": x, "y": y, "heading": h, "speed": v,
                "yaw_rate": v * np.sin(beta) / (LENGTH / 2), "acceleration": acc, "steering": steer,
                "route_s": route_s, "cte": self._lat, "stop_line_offset": route_s + LENGTH / 2 - self.route_starts[1],
                "distance_to_conflict": self.conflict_s - route_s,
                "oncoming_gap": corner_x.min(axis=1) - ONCOMING_NEAR_EDGE_X,
                "collision": t.crashed[rows, e].copy(), "arrived": self.has_arrived(rows, e),
                "arrived_time": self.arrived_time[rows].copy(), "set_point": t.target[rows, e].copy()}

    def _truth_args(self, rows: np.ndarray, *extra: str) -> tuple:
        """kernels.truth's arguments for the envs ``rows`` (the state arrays made contiguous in place); ``extra``
        state arrays after ``target`` (kernels.observe's ``alive``)."""
        geo = np.array([LENGTH, WIDTH, self.conflict_s, ONCOMING_NEAR_EDGE_X, batched.EXIT_DISTANCE])
        state = batched._contiguous(self.traffic, "x", "y", "h", "v", "steer", "acc", "target", *extra, "ego",
                                    "crashed", "lane")
        # rows contiguous: a strided selection (rows[::2]) would compile a second specialization of the kernel
        return (self.T.arr, self.T.rules, self.route, self.route_starts, geo,
                np.ascontiguousarray(rows, dtype=np.int64),
                *state, self._route_k, self.time, self.arrived_time)

    def _truth_dict(self, columns: np.ndarray) -> dict:
        """kernels.truth's (n, 17) columns as :meth:`truth`'s dict (collision and arrived as bools)."""
        tr = {name: columns[:, k] for k, name in enumerate(kernels.TRUTH_FIELDS)}
        tr["collision"], tr["arrived"] = tr["collision"] != 0.0, tr["arrived"] != 0.0
        self._lat = tr["cte"]
        return tr

    def ttc(self, rows=None) -> np.ndarray:
        """``info["truth"]["ttc"]`` for the envs ``rows``: av_gym.geometry.constant_velocity_ttc (the first time on
        its 0.05 s grid up to ``ttc_horizon`` at which the ego's box and another's overlap when both keep their
        velocity and heading; +inf if none) for all of them at once.

        Two boxes moving at constant velocity and fixed heading overlap during one time interval [t_in, t_out]:
        on each of the four separating axes (the two boxes' edge normals) the projected centre distance is linear
        in t and must stay within the summed half-extents. That interval is solved for every (env, vehicle) pair,
        and only the grid times around t_in (t_in's grid step, one before, two after) get the per-env test itself
        (box_corners / boxes_overlap at ``t``, the same arithmetic), so rounding at the interval's ends decides as
        it does there; a pair whose interval is longer than those times and none overlapped (an end fixed by a
        near-zero relative speed, where t_in is poorly conditioned) gets all its grid times tested."""
        from av_gym.geometry import box_corners, boxes_overlap

        rows = np.arange(self.B) if rows is None else np.asarray(rows)
        t, n = self.traffic, len(rows)
        horizon, dt = float(self.config["ttc_horizon"]), 0.05
        grid = np.arange(0.0, horizon + 1e-9, dt)
        if "ttc" in batched.KERNELS:  # the same intervals and box tests, pair by pair (av_gym/sim/kernels.py)
            return kernels.ttc_rows(np.asarray(rows, dtype=np.int64), *batched._contiguous(t, "x", "y", "h", "v",
                                                                                          "alive", "ego"),
                                    grid, horizon, dt, LENGTH, WIDTH)
        K = len(grid)
        out = np.full(n, np.inf)
        e = self.ego_slot(rows)
        ex, ey, eh, ev = t.x[rows, e], t.y[rows, e], t.h[rows, e], t.v[rows, e]
        evx, evy = ev * np.cos(eh), ev * np.sin(eh)
        other = t.alive[rows] & ~t.ego[rows]
        oh = t.h[rows]
        ovx, ovy = t.v[rows] * np.cos(oh), t.v[rows] * np.sin(oh)
        px, py = t.x[rows] - ex[:, None], t.y[rows] - ey[:, None]
        wx, wy = ovx - evx[:, None], ovy - evy[:, None]
        t_in, t_out = np.full(px.shape, -np.inf), np.full(px.shape, np.inf)
        eh2 = np.broadcast_to(eh[:, None], px.shape)
        for theta in (eh2, eh2 + np.pi / 2, oh, oh + np.pi / 2):
            ux, uy = np.cos(theta), np.sin(theta)
            half = LENGTH / 2 * (np.abs(np.cos(eh2 - theta)) + np.abs(np.cos(oh - theta))) \
                + WIDTH / 2 * (np.abs(np.sin(eh2 - theta)) + np.abs(np.sin(oh - theta)))
            q, r = ux * px + uy * py, ux * wx + uy * wy
            moving = r != 0.0
            rr = np.where(moving, r, 1.0)
            ta, tb = (-half - q) / rr, (half - q) / rr
            lo = np.where(moving, np.minimum(ta, tb), np.where(np.abs(q) <= half, -np.inf, np.inf))
            hi = np.where(moving, np.maximum(ta, tb), np.where(np.abs(q) <= half, np.inf, -np.inf))
            t_in, t_out = np.maximum(t_in, lo), np.minimum(t_out, hi)
        cand = other & (t_in <= t_out + dt) & (t_out >= -dt) & (t_in <= horizon + dt)
        if not cand.any():
            return out
        m, j = np.nonzero(cand)
        first = np.clip(np.floor(np.maximum(t_in[m, j], 0.0) / dt).astype(int) - 1, 0, K - 1)
        last = np.clip(np.ceil(np.minimum(t_out[m, j], horizon) / dt).astype(int) + 1, 0, K - 1)

        def test(pair, k):
            mm, jj, tk = m[pair], j[pair], grid[k]
            r = rows[mm]
            ego_c = np.stack([ex[mm], ey[mm]], -1) + tk[:, None] * np.stack([evx[mm], evy[mm]], -1)
            oth_c = np.stack([t.x[r, jj], t.y[r, jj]], -1) + tk[:, None] * np.stack([ovx[mm, jj], ovy[mm, jj]], -1)
            hit = boxes_overlap(box_corners(ego_c, eh[mm], LENGTH, WIDTH),
                                box_corners(oth_c, oh[mm, jj], LENGTH, WIDTH))
            np.minimum.at(out, mm[hit], tk[hit])
            found = np.zeros(len(m), bool)
            found[pair[hit]] = True
            return found

        pair = np.repeat(np.arange(len(m)), 4)
        k = first[pair] + np.tile(np.arange(4), len(m))
        ok = k <= last[pair]
        found = test(pair[ok], k[ok])
        rest = np.nonzero(~found & (last > first + 3))[0]
        if len(rest):
            count = last[rest] - first[rest] - 3
            pair = np.repeat(rest, count)
            k = first[pair] + 4 + np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
            test(pair, k)
        return out

    def observe(self, rows=None) -> np.ndarray:
        """TurnFeatures.features (source=truth) for the envs ``rows``: (len(rows), width) float32, by the same
        function (:func:`av_gym.estimation.turn_features.turn_features`) for all of them at once."""
        rows = np.arange(self.B) if rows is None else np.asarray(rows)
        if {"truth", "turn_features"} <= batched.KERNELS:  # truth and features in one call (kernels.observe)
            enc = TurnEncoding.of(self.features)
            columns, out, order, present = kernels.observe(
                *self._truth_args(rows, "alive"), self.path, self.path_s, CONFLICT_POINT, enc.max_objects,
                float(self.features.max_range), enc.ego_scales, enc.object_scales, T_MAX)
            self.last_truth, self.described = self._truth_dict(columns), (order, present)
            return out
        t, tr = self.traffic, self.truth(rows)
        self.last_truth = tr
        v, h = t.v[rows], t.h[rows]
        others = np.stack([t.x[rows], t.y[rows], v * np.cos(h), v * np.sin(h)], axis=-1)
        out, order, present = turn_features(tr, others, t.alive[rows] & ~t.ego[rows], self.path, self.path_s,
                                            CONFLICT_POINT, self.features)
        self.described = (order, present)
        return out

    def others_described(self, rows) -> tuple[list, list]:
        """Per env of ``rows`` (after :meth:`observe` on them): the others ``(k, 4) [x, y, vx, vy]`` in road order
        (``info["truth"]["others"][:, :4]``) and the indices into it that ``obs["turn"]`` describes, nearest
        first (TurnFeatures.others / .described)."""
        t = self.traffic
        order, present = self.described
        others, described = [], []
        for n, r in enumerate(rows):
            keep = t.alive[r] & ~t.ego[r]
            v = t.v[r, keep]
            others.append(np.stack([t.x[r, keep], t.y[r, keep], v * np.cos(t.h[r, keep]), v * np.sin(t.h[r, keep])],
                                   axis=1))
            slot_to_other = np.cumsum(keep) - 1
            described.append(slot_to_other[order[n][present[n]]])
        return others, described


class BatchedIntent:
    """``obs["signals"]`` (TurnSignals) and ``obs["intent"]`` (TurnIntent) for a :class:`BatchedLeftTurn`, the
    same readings as the per-env sensors: each env's signal channel draws from its own
    ``sensor_rng(episode_seed, "signals")`` in the same order (per new vehicle: indicates?, wrong?; per reading:
    seen?), and the acceleration compares each described object with the nearest vehicle of the oldest kept past
    (``history`` s)."""

    def __init__(self, engine: BatchedLeftTurn, signals: dict | None, intent: dict) -> None:
        self.e = engine
        # the sensors' own Params (defaults and checks), as the per-env wrappers build them
        self.sig = None if signals is None else TurnSignalsParams.from_mapping(signals, "sensors.turn_signals")
        p = TurnIntentParams.from_mapping(intent or {}, "sensors.turn_intent")
        self.history, self.gate, self.signal_gate = float(p.history), float(p.gate), float(p.signal_gate)
        self.past = IntentHistory(engine.B, p, self.sig)
        self.rngs = [None] * engine.B
        self.draws = DriverDraws()  # the per-driver channel (TurnSignals.draws), by vehicle id
        T = engine.T
        # intended_signal's route origin and destination of every lane (the rule is in av_gym.sensors.turn_signal)
        self.origin = np.array([route_origin(f, t) for f, t, _ in T.index])
        self.dest = np.array([node_index(t, "o") for _, t, _ in T.index])

    def reset(self, rows) -> None:
        for r in rows:
            self.rngs[r] = episode_rng(self.e.episode_seed[r], "signals")
        self.past.clear(rows)

    def signals(self, rows) -> np.ndarray:
        """TurnSignals.measure for the envs ``rows``: (n, max_objects, 4) float32, by the same function
        (:func:`~av_gym.sensors.turn_signal.read_signals`) for all of them at once. The per-driver draws are kept
        by vehicle id (unique in the process, so one table by id is every env's per-episode channel)."""
        e, t = self.e, self.e.traffic
        last = t.route[rows][..., 2]  # -1: no route (a plain Vehicle): intended_signal is 0
        intended = turn_signal(self.origin[t.lane[rows]], np.where(last >= 0, self.dest[last], -1))
        eslot = e.ego_slot(rows)
        x, y = t.x[rows], t.y[rows]
        d = np.hypot(x - t.x[rows, eslot][:, None], y - t.y[rows, eslot][:, None])
        return read_signals(x, y, d, t.alive[rows] & ~t.ego[rows], intended, t.vid[rows], self.draws,
                            [self.rngs[r] for r in rows], self.sig)

    def intent(self, rows, signals) -> np.ndarray:
        """TurnIntent.observation for the envs ``rows`` (after the engine's :meth:`BatchedLeftTurn.observe` on
        them), for all of them at once: the same :class:`~av_gym.estimation.turn_features.IntentHistory`, whose
        snapshots here are the slot arrays (road order)."""
        e, t = self.e, self.e.traffic
        rows = np.asarray(rows)
        n, M = len(rows), e.max_objects
        now = e.ticks[rows] / e.config["simulation_frequency"]
        v = t.v[rows]
        snap = np.stack([t.x[rows], t.y[rows], v * np.cos(t.h[rows]), v * np.sin(t.h[rows])], axis=-1)  # (n, N, 4)
        order, present = e.described
        objects = np.zeros((n, M, 4))
        objects[:, : order.shape[1]] = np.take_along_axis(snap, order[..., None], axis=1)  # nearest first
        described = np.zeros((n, M), bool)
        described[:, : present.shape[1]] = present
        return self.past.observe(rows, now, objects, described, snap, t.alive[rows] & ~t.ego[rows], signals)
