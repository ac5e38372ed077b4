"""The batched left turn (:mod:`av_gym.batched.left_turn`) with the training wrappers done on the batch
(:class:`BatchedLeftTurnBatch`, SB3's ``VecEnv`` interface without importing SB3) and as a Gymnasium ``VectorEnv``
(:class:`BatchedLeftTurnVectorEnv`, what ``gymnasium.make_vec`` gives). The SB3 ``VecEnv`` that ``python -m train
agent=ppo_turn agent.vec_env=batched`` trains on is :class:`av_gym_sb3.BatchedLeftTurnVecEnv`
(``from av_gym_sb3 import BatchedLeftTurnVecEnv``): the library does not import SB3 or torch.

What the batch gives: ``env=left_turn`` in both modes (traffic, CCFtap) with discrete or continuous actions, and the
sensors of the ``turn_truth`` presets (``turn_features`` with ``source: truth``, ``turn_signals``, ``turn_intent``,
``observe``) and of the ``turn_perceived`` presets (``detector`` → ``tracker`` → ``turn_features`` with ``source:
tracks``, :mod:`av_gym.batched.perception`); the AEB shield ``shield=aeb`` (the improved variant, either mode,
:mod:`av_gym.batched.shield`: each finished episode's ``info["aeb"]`` says its brake time, stop position and the
steps it overrode); agent options ``actions`` (an action set of
:data:`av_gym.wrappers.ACTION_SETS`, mapped by its own function), ``action_repeat``, ``timeout_is_terminal`` and,
with the shield, ``intervention_cost`` (paid per env step of override, as :class:`av_gym.wrappers.InterventionCost`).
Anything else (another sensor, another shield) is refused with one line naming it; it runs on the per-env stack.

Auto-reset: an env whose episode ended starts its next one at once (SB3's convention: the step returns the new
episode's first observation, the last one is ``info["terminal_observation"]``), taken from a pool of ready
episodes (see :meth:`BatchedLeftTurn.step_autoreset`).
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.actions import check_actions
from av_gym.batched.left_turn import BatchedIntent, BatchedLeftTurn
from av_gym.batched.perception import BatchedPerception, check_perceived, perceived
from av_gym.batched.shield import BatchedShield, check_batched_shield, shield_kind
from av_gym.errors import ConfigError
from av_gym.estimation.object_tracking import BOUND as TRACK_BOUND
from av_gym.estimation.turn_features import TurnFeaturesParams
from av_gym.sensors.base import guarded_rows
from av_gym.wrappers import action_set, meta_actions  # noqa: F401 - meta_actions: imported from here too

SENSORS = ("name", "turn_features", "turn_signals", "turn_intent", "observe", "keep_state")
PERCEIVED = ("detector", "tracker")  # with turn_features.source=tracks (av_gym.batched.perception)


def check_batchable(env_cfg: dict, sensors_cfg: dict | None, shield_cfg: dict | None, *,
                    with_shield: bool = False) -> None:
    """One-line ConfigError for what the batch cannot run. ``with_shield``: the caller runs the batch's AEB shield
    (:class:`BatchedLeftTurnBatch`: ``python -m eval``, ``gymnasium.make_vec``, the SB3 VecEnv PPO trains on), which
    then takes ``shield=aeb`` as :func:`av_gym.batched.shield.check_batched_shield` allows it; other callers (the
    DAgger replica, whose episodes a shield would change) refuse any shield."""
    if env_cfg.get("name") != "left_turn":
        raise ConfigError(f"agent.vec_env=batched runs env=left_turn only, got env={env_cfg.get('name')}")
    s = dict(sensors_cfg or {})
    allowed = SENSORS + (PERCEIVED if perceived(s) else ())
    for key in s:
        if key not in allowed:
            raise ConfigError(f"sensors.{key} is not available with agent.vec_env=batched (the batch gives "
                              f"turn_features, turn_signals, turn_intent, and detector, tracker under "
                              f"turn_features.source=tracks); use agent.vec_env=subproc")
    if "turn_features" not in s:
        raise ConfigError(f"agent.vec_env=batched needs sensors with turn_features (sensors=turn_truth or "
                          f"turn_perceived), got sensors={s.get('name', 'truth')}")
    if perceived(s):
        check_perceived(s)
    if with_shield:
        check_batched_shield(shield_cfg, env_cfg)
        return
    kind = shield_kind(shield_cfg)
    if kind != "none":  # the preset given by name (aeb_paper, not its kind aeb, which reads as the allowed one)
        raise ConfigError(f"shield={(shield_cfg or {}).get('name', kind)} is not available with agent.vec_env=batched "
                          f"here (this batch runs without a shield: shield=none; python -m eval vec_env=batched and "
                          f"PPO's training batch run shield=aeb); use agent.vec_env=subproc")


def intervention_cost_problem(cost: float, shielded: bool, field: str = "intervention_cost") -> str | None:
    """One line on an intervention cost (reward/s) the batch cannot pay, naming ``field``: a negative one, or one
    without a shield whose overrides it is paid on; None if it can."""
    if not cost >= 0:
        return f"{field} must be >= 0 (reward per second of shield override), got {cost}"
    if cost > 0 and not shielded:
        return (f"{field}={cost:g} is paid on the shield's overrides: it needs shield=aeb, got shield=none (or set "
                f"{field}=0)")
    return None


def _cost_per_step(intervention_cost: float, shielded: bool, policy_frequency: float) -> float:
    """:class:`av_gym.wrappers.InterventionCost`'s reward per env step of override (``intervention_cost`` in
    reward/s over the env's ``policy_frequency`` in Hz); a ConfigError with :func:`intervention_cost_problem`'s
    line."""
    cost = float(intervention_cost)
    problem = intervention_cost_problem(cost, shielded)
    if problem:
        raise ConfigError(problem)
    return cost / float(policy_frequency)


def batch_seeds(seed, n: int) -> list:
    """The seeds of ``n`` envs for ``seed``: an int (env i gets ``seed + i``), a sequence of ``n`` seeds (None
    where an env's generator goes on), or None. Each a non-negative integer, as Gymnasium's ``reset(seed=)`` wants
    it; anything else is one ConfigError line naming the field (``seed``) and what it may be."""
    if seed is None:
        return [None] * n
    if _is_seed(seed):
        return [int(seed) + i for i in range(n)]
    if isinstance(seed, (str, bytes, dict)) or not hasattr(seed, "__len__"):
        raise ConfigError(f"seed must be a non-negative integer, a list of {n} of them (one per env) or None, "
                          f"got {seed!r:.80}")
    seeds = list(seed)
    if len(seeds) != n:
        raise ConfigError(f"seed lists {len(seeds)} seeds for {n} envs; give one per env (or an int: env i gets "
                          f"seed + i)")
    bad = [i for i, s in enumerate(seeds) if s is not None and not _is_seed(s)]
    if bad:
        raise ConfigError(f"seed[{bad[0]}] must be a non-negative integer or None, got {seeds[bad[0]]!r:.80}")
    return [None if s is None else int(s) for s in seeds]


def _checked_seeds(seeds) -> Iterator[int]:
    """``seeds`` (any iterable, drawn lazily), each checked as :func:`batch_seeds` checks one."""
    for k, seed in enumerate(seeds):
        if not _is_seed(seed):
            raise ConfigError(f"seeds[{k}] must be a non-negative integer, got {seed!r:.80}")
        yield int(seed)


def _is_seed(value) -> bool:
    """An int or numpy integer (not a bool, which Python counts as an int), >= 0."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)) and value >= 0


class BatchedLeftTurnBatch:
    """:class:`BatchedLeftTurn` with the training wrappers of the per-env stack (the action set's mapping,
    ActionRepeat, TimeLimitIsTerminal, FlatDictObservation) done on the batch, behind SB3's ``VecEnv`` methods
    (``reset``, ``step_async``/``step_wait``, ``seed``, ``get_attr`` ...), so that SB3's adapter is only the base class
    (:class:`av_gym_sb3.batched.BatchedLeftTurnVecEnv`)."""

    def __init__(self, env_cfg: dict, sensors_cfg: dict, shield_cfg: dict | None, n_envs: int, *,
                 action_repeat: int = 1, actions: str = "env", timeout_is_terminal: bool = False,
                 pool: int | None = None, intervention_cost: float = 0.0) -> None:
        """``intervention_cost`` (reward/s, >= 0, needs the shield): the training reward term of
        :class:`av_gym.wrappers.InterventionCost`, paid on every env step the shield overrides."""
        from av_gym.make import highway_config

        check_batchable(env_cfg, sensors_cfg, shield_cfg, with_shield=True)
        shield = check_batched_shield(shield_cfg, env_cfg)
        _, config = highway_config(env_cfg)
        self._cost_per_step = _cost_per_step(intervention_cost, shield is not None, config["policy_frequency"])
        s = dict(sensors_cfg)
        features = TurnFeaturesParams.from_mapping(s.get("turn_features") or {}, "sensors.turn_features")
        self.engine = BatchedLeftTurn(n_envs, config, features, pool=max(8, n_envs // 4) if pool is None else pool)
        self.perception = BatchedPerception(self.engine, s) if perceived(s) else None
        self.shield = BatchedShield(self.engine, shield) if shield is not None else None
        self.keys = list(s.get("observe") or ["turn", *(["signals"] if "turn_signals" in s else []),
                                              *(["intent"] if "turn_intent" in s else [])])
        need_intent = "intent" in self.keys or "signals" in self.keys
        self.intent = BatchedIntent(self.engine, s.get("turn_signals") if "turn_signals" in s else None,
                                    s.get("turn_intent") or {}) if need_intent else None
        M = self.engine.max_objects
        all_spaces = {"turn": spaces.Box(-1.0, 1.0, (self.engine.n_features,), np.float32),
                      "intent": spaces.Box(-1.0, 1.0, (M, self.intent.past.width if self.intent else 2), np.float32)}
        if self.perception is not None:  # the per-env stack's obs["detector"] and obs["tracks"]
            all_spaces["detector"] = self.perception.detector.sensor_space()
            all_spaces["tracks"] = spaces.Box(-TRACK_BOUND, TRACK_BOUND, self.perception.last_tracks.shape[1:],
                                              np.float32)
        if self.intent is not None and self.intent.sig is not None:
            all_spaces["signals"] = spaces.Box(-1e4, 1e4, (int(self.intent.sig.max_objects), 4), np.float32)
        missing = [k for k in self.keys if k not in all_spaces]
        if missing:
            raise ConfigError(f"sensors.observe lists {missing[0]!r}, which agent.vec_env=batched does not provide; "
                              f"allowed: {sorted(all_spaces)}")
        self._spaces = all_spaces  # every reading the batch makes, observed or not: each guarded (_guarded)
        obs_space = spaces.Dict({k: all_spaces[k] for k in self.keys})
        self.repeat, self.actions, self.timeout_is_terminal = int(action_repeat), actions, bool(timeout_is_terminal)
        self.action_set = action_set(actions)
        # the env's own actions: LongitudinalAction.space, or the three meta-actions
        env_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32) if self.engine.continuous else \
            spaces.Discrete(3)
        problem = self.action_set.problem(env_space, self.keys, "env.action=continuous" if self.engine.continuous
                                          else None)
        if problem:
            raise ConfigError(problem)
        action_space = self.action_set.space(env_space)
        self.num_envs, self.observation_space, self.action_space = int(n_envs), obs_space, action_space
        self._seeds: list | None = None
        self._actions = None
        self._obs: dict | None = None
        self._ep_return = np.zeros(n_envs)
        self._env_return = np.zeros(n_envs)  # EpisodeMetrics' return: summed per env step, in the same order
        self._ep_len = np.zeros(n_envs, dtype=int)
        self._ep_start = np.full(n_envs, time.time())
        self._traces: list[list] = [[] for _ in range(n_envs)]
        # EpisodeMetrics' shield columns: steps overridden, override onsets, time (s) of the first (NaN: none)
        self._overrides, self._onsets = np.zeros(n_envs, dtype=int), np.zeros(n_envs, dtype=int)
        self._first_override = np.full(n_envs, np.nan)
        self._overriding = np.zeros(n_envs, bool)
        self._faults = np.zeros(n_envs, dtype=int)  # EpisodeMetrics' sensor_faults: non-finite entries replaced
        self._idle = np.zeros(n_envs, bool)  # no episode to play (play(): its seeds ran out)
        self._queued = False
        self.row_seed: list = [None] * n_envs  # play(): the seed of the episode each env is playing

    # ---------------------------------------------------------------------------------------------- observe
    def _observe(self, rows: np.ndarray, new_episode: np.ndarray | None = None, trace: bool = True) -> dict:
        """Every env of ``rows``'s readings after an env step (``new_episode``: the first readings of new episodes),
        each guarded as the per-env sensor guards it (:func:`av_gym.sensors.base.guarded_rows`: a NaN/inf made
        finite and marked invalid, counted in the episode's ``sensor_faults``); the observed keys' readings."""
        e, seen = self.engine, self.perception
        if new_episode is not None and new_episode.any():
            self._faults[rows[new_episode]] = 0
        if seen is not None and new_episode is not None and new_episode.any():
            seen.reset(rows[new_episode])
        if self.shield is not None and new_episode is not None and new_episode.any():
            new = rows[new_episode]
            self.shield.reset(new)
            self._overrides[new], self._onsets[new], self._first_override[new], self._overriding[new] = 0, 0, np.nan, 0
        turn = e.observe(rows) if seen is None else seen.observe(rows)
        faults = np.zeros(len(rows), dtype=int) if seen is None else seen.faults.copy()  # the detector's, guarded
        out = {"turn": self._guard("turn", turn, faults)}
        if seen is not None:
            out["detector"], out["tracks"] = seen.last_detections[rows], self._guard("tracks", seen.last_tracks[rows],
                                                                                     faults)
        if self.intent is not None:
            if new_episode is not None and new_episode.any():
                self.intent.reset(rows[new_episode])
            signals = self.intent.signals(rows) if self.intent.sig is not None else None
            if signals is not None:  # guarded before the intent reads them, as TurnSignals sits below TurnIntent
                signals = out["signals"] = self._guard("signals", signals, faults)
            intent = self.intent.intent(rows, signals) if seen is None else seen.intent(self.intent, rows, signals)
            out["intent"] = self._guard("intent", intent, faults)
        self._faults[rows] += faults
        tr = e.last_truth
        ttc = e.ttc(rows) if trace else None
        for n, r in enumerate(rows if trace else ()):  # EpisodeMetrics records the truth of every step
            self._traces[r].append((tr["time"][n], tr["speed"][n], tr["collision"][n], tr["arrived"][n],
                                    tr["stop_line_offset"][n], tr["oncoming_gap"][n], ttc[n]))
        return {k: out[k] for k in self.keys}

    def _guard(self, key: str, values: np.ndarray, faults: np.ndarray) -> np.ndarray:
        """``values`` (n, ...) of reading ``key`` guarded (:func:`guarded_rows`), their non-finite entries added to
        ``faults`` (n,)."""
        values, counts = guarded_rows(values, self._spaces[key])
        faults += counts
        return values

    def _store(self, rows, obs: dict) -> None:
        for k in self.keys:
            self._obs[k][rows] = obs[k]

    # ---------------------------------------------------------------------------------------------- VecEnv API
    def reset(self):
        e = self.engine
        seeds = self._seeds if self._seeds is not None else [None] * self.num_envs
        self._seeds = None
        self._queued, self._idle[:] = False, False
        e.reset(seeds)
        rows = np.arange(self.num_envs)
        self._traces = [[] for _ in rows]
        obs = self._observe(rows, np.ones(self.num_envs, bool), trace=False)
        self._obs = {k: v.copy() for k, v in obs.items()}
        self._ep_return[:], self._env_return[:], self._ep_len[:] = 0.0, 0.0, 0
        self._ep_start[:] = time.time()
        return {k: v.copy() for k, v in self._obs.items()}

    def play(self, seeds, chunk: int | None = None) -> dict:
        """Evaluation: from now on the envs play the episodes of ``seeds`` (any iterable of ints), each the episode
        ``reset(seed=s)`` of the per-env stack gives, in order as envs become free (made ``chunk`` at a time,
        default ``num_envs``); an env left without one goes idle (``idle``) and is no longer stepped. The seed each
        env plays is ``row_seed``; a finished episode's is ``info["seed"]``. Returns the first observations."""
        e = self.engine
        e.queue(_checked_seeds(seeds), self.num_envs if chunk is None else chunk)
        self._queued = True
        rows = np.arange(self.num_envs)
        self.row_seed = e.start_queued(rows)
        self._idle = np.array([s is None for s in self.row_seed])
        self._traces = [[] for _ in rows]
        live = rows[~self._idle]
        obs = self._observe(live, np.ones(len(live), bool), trace=False)
        self._obs = {k: np.zeros((self.num_envs, *self.observation_space[k].shape), np.float32) for k in self.keys}
        self._store(live, obs)
        self._ep_return[:], self._env_return[:], self._ep_len[:] = 0.0, 0.0, 0
        self._ep_start[:] = time.time()
        return {k: v.copy() for k, v in self._obs.items()}

    @property
    def idle(self) -> np.ndarray:
        return self._idle.copy()

    def _restart(self, rows: np.ndarray) -> np.ndarray:
        """Start the next episodes of the envs ``rows`` (whose episodes ended); the rows that got one."""
        if not self._queued:
            self.engine.start_from_pool(rows)
            return rows
        seeds = self.engine.start_queued(rows)
        for r, s in zip(rows, seeds):
            self.row_seed[r] = s
        started = np.array([s is not None for s in seeds], bool)
        self._idle[rows[~started]] = True
        return rows[started]

    def step(self, actions: np.ndarray):
        self.step_async(actions)
        return self.step_wait()

    def step_async(self, actions: np.ndarray) -> None:
        """Take one action per env (shape ``(num_envs, *action_space.shape)``), checked against ``action_space``
        as the per-env stack checks its one (:func:`av_gym.actions.check_actions`: out of the space, NaN or a wrong
        shape is an :class:`~av_gym.actions.InvalidAction` line); before the first ``reset``/``play`` there is no
        episode to act in (Gymnasium's ``ResetNeeded``, as the per-env stack)."""
        if self._obs is None:
            raise gym.error.ResetNeeded("Cannot call step() before calling reset() (or play()) on the batch")
        check_actions(self.action_space, actions, self.num_envs)
        self._actions = np.asarray(actions).reshape(self.num_envs, -1)[:, 0]

    def step_wait(self):
        e, B = self.engine, self.num_envs
        active = ~self._idle
        total = np.zeros(B)
        term_all, trunc_all = np.zeros(B, bool), np.zeros(B, bool)
        for _ in range(self.repeat if active.any() else 0):
            meta = self.action_set.act(self._actions, self._obs)
            rows = np.nonzero(active)[0]
            reward, term, trunc = self._env_step(meta, active, rows)
            cost = self._intervention_cost(rows)  # right after the step: the shield's override of this step
            self._store(rows, self._observe(rows))
            total += np.where(active, reward - cost, 0.0)  # as InterventionCost inside ActionRepeat's sum
            self._env_return += np.where(active, reward, 0.0)
            term_all |= term & active
            trunc_all |= trunc & active
            active &= ~(term | trunc)
            if not active.any():
                break
        self._ep_return += total
        self._ep_len += 1
        done = term_all | trunc_all
        infos = [{} for _ in range(B)]
        rows = np.nonzero(done)[0]
        if len(rows):
            for r in rows:
                infos[r]["terminal_observation"] = {k: self._obs[k][r].copy() for k in self.keys}
                infos[r]["TimeLimit.truncated"] = bool(trunc_all[r] and not term_all[r] and
                                                       not self.timeout_is_terminal)
                infos[r]["episode"] = {"r": float(self._ep_return[r]), "l": int(self._ep_len[r]),
                                       "t": round(time.time() - self._ep_start[r], 6)}
                # EpisodeMetrics' `truncated` is the env's flag as it is, also when the episode ends both ways (the
                # ego arrives on the time limit's step); SB3's TimeLimit.truncated above is not
                infos[r]["episode_metrics"] = self._metrics(r, bool(trunc_all[r]))
                if self.shield is not None:  # what the shield did: the per-env shield's aeb_* info at the end
                    infos[r]["aeb"] = self.shield.episode(r)
                if self._queued:
                    infos[r]["seed"] = self.row_seed[r]
            self._traces_reset(rows)
            rows = self._restart(rows)
            if len(rows):
                self._store(rows, self._observe(rows, np.ones(len(rows), bool), trace=False))
            self._ep_return[rows], self._env_return[rows], self._ep_len[rows] = 0.0, 0.0, 0
            self._ep_start[rows] = time.time()
        if self.timeout_is_terminal:
            term_all, trunc_all = term_all | trunc_all, np.zeros(B, bool)
        return {k: v.copy() for k, v in self._obs.items()}, total.astype(np.float32), done, infos

    def _env_step(self, meta: np.ndarray, active: np.ndarray, rows: np.ndarray) -> tuple:
        """One env step of the envs ``active`` (``rows``) under the env actions ``meta``, behind the shield if
        there is one (its decision, the throttle cut, its brake on every tick, its override counted as
        EpisodeMetrics counts it: per env step, onsets, the time after the first)."""
        e, sh = self.engine, self.shield
        if sh is None:
            return e.step(meta, active)
        applied = sh.decide(rows, meta)
        out = e.step(applied, active, sh.brake_plan(rows))
        sh.after(rows)
        over = rows[sh.override[rows]]
        self._overrides[over] += 1
        self._onsets[over[~self._overriding[over]]] += 1
        self._overriding[rows] = sh.override[rows]
        first = over[np.isnan(self._first_override[over])]
        self._first_override[first] = e.time[first]
        return out

    def _intervention_cost(self, rows: np.ndarray) -> np.ndarray:
        """Per env, the intervention cost of the env step just taken: ``intervention_cost / policy_frequency`` in
        the rows ``rows`` the shield overrode, 0 elsewhere (EpisodeMetrics' return, ``_env_return``, excludes it as
        the per-env stack's does: InterventionCost wraps outside EpisodeMetrics)."""
        cost = np.zeros(self.num_envs)
        if self._cost_per_step > 0:
            cost[rows[self.shield.override[rows]]] = self._cost_per_step
        return cost

    def _traces_reset(self, rows) -> None:
        for r in rows:
            self._traces[r] = []

    def _metrics(self, r: int, truncated: bool) -> dict:
        """EpisodeMetrics' row from the ego's per-step truth: the left-turn summary (min TTC from
        :meth:`BatchedLeftTurn.ttc`), return, length, truncated, and the shield's columns (none without a shield:
        no override, ``first_override_s`` NaN)."""
        from av_gym.metrics.left_turn import left_turn_summary

        tr = np.array(self._traces[r], dtype=float)
        row = left_turn_summary(tr[:, 0], tr[:, 1], tr[:, 2].astype(bool), tr[:, 3].astype(bool),
                                tr[:, 6], tr[:, 4], tr[:, 5])
        row.update({"return": float(self._env_return[r]), "length": float(len(tr)),
                    "truncated": float(truncated), "override_fraction": self._overrides[r] / max(1, len(tr)),
                    "intervention": float(self._overrides[r] > 0), "interventions": float(self._onsets[r]),
                    "first_override_s": float(self._first_override[r]), "sensor_faults": float(self._faults[r])})
        return row

    def close(self) -> None:
        pass

    def seed(self, seed: int | list | None = None):
        """Seeds for the next reset: env i gets ``seed + i`` (as SB3's make_vec_env seeds per-env stacks), or
        ``seed[i]`` from a list of ``num_envs`` seeds (None: that env's generator goes on). A seed is a
        non-negative integer (as Gymnasium's ``reset(seed=)``); anything else is a ConfigError line."""
        self._seeds = batch_seeds(seed, self.num_envs)
        return self._seeds

    def get_attr(self, attr_name, indices=None):
        return [getattr(self, attr_name, None) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name, value, indices=None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        raise AttributeError(f"the batched left turn has no per-env {method_name!r}")

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False for _ in self._get_indices(indices)]

    def _get_indices(self, indices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [int(indices)] if isinstance(indices, (int, np.integer)) else list(indices)


class BatchedLeftTurnVectorEnv(gym.vector.VectorEnv):
    """Gymnasium ``VectorEnv`` over the same batch: meta-actions (or GO/YIELD), ``obs`` as a dict of batched
    arrays, autoreset in the same step (``info["final_obs"]`` / ``info["_final_obs"]``). On the step an env's episode
    ends, ``info`` has its end-of-episode keys as ``gymnasium.make_vec(..., vectorization_mode="sync")`` batches them
    on that step, with a ``_key`` mask of the envs that ended: ``episode_metrics`` (a dict of float arrays, one per
    metric) and, with the shield, ``aeb_brake_time`` / ``aeb_stop_position`` (float; inf where it did not brake /
    stop, ``av_gym.shields.aeb.NOT_YET``). Unlike sync / async (``AutoresetMode.NEXT_STEP``, every per-env key each
    step): no per-step keys (no ``truth``, no ``aeb_*`` while driving; ``reset`` gives ``{}``), and from its second
    episode on an env plays the pool's next ready episode, not its own generator's (docs/performance.md)."""

    def __init__(self, env_cfg: dict, sensors_cfg: dict, n_envs: int, shield_cfg: dict | None = None,
                 **kwargs) -> None:
        self.venv = BatchedLeftTurnBatch(env_cfg, sensors_cfg, shield_cfg, n_envs, **kwargs)
        self.num_envs = n_envs
        self.single_observation_space = self.venv.observation_space
        self.single_action_space = self.venv.action_space
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, n_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, n_envs)
        self.metadata = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP}

    def reset(self, *, seed=None, options=None):
        """Gymnasium's vector reset: ``seed`` an int (env i gets ``seed + i``), a list of ``num_envs`` seeds, or
        None (see :meth:`BatchedLeftTurnBatch.seed`)."""
        if seed is not None:
            self.venv.seed(seed)
        return self.venv.reset(), {}

    def step(self, actions):
        obs, reward, done, infos = self.venv.step(np.asarray(actions))
        truncated = np.array([i.get("TimeLimit.truncated", False) for i in infos])
        terminated = done & ~truncated
        final = np.array([i.get("terminal_observation") for i in infos], dtype=object)
        info = {"final_obs": final, "_final_obs": done.copy()}
        for r in np.flatnonzero(done).tolist():  # Gymnasium's own batching, as the per-env stacks' vector envs
            self._add_info(info, _episode_end(infos[r]), r)
        return obs, reward, terminated, truncated, info


def _episode_end(row_info: dict) -> dict:
    """A finished row's info under the per-env stack's keys (EpisodeMetrics' ``episode_metrics``; the shield's
    ``aeb_brake_time`` / ``aeb_stop_position`` from :meth:`BatchedShield.episode`)."""
    out = {"episode_metrics": row_info["episode_metrics"]}
    if "aeb" in row_info:
        out["aeb_brake_time"] = float(row_info["aeb"]["brake_time"])
        out["aeb_stop_position"] = float(row_info["aeb"]["stop_position"])
    return out
