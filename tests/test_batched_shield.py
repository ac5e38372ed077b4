"""The AEB shield on the batch (av_gym/batched/shield.py) against the per-env shield (ImprovedAEB around highway-env),
same seeds, same agents: per episode the steps it overrode (interventions), the time of its first brake, the stop
position (front bumper past the stop line at the first standstill under braking), and the outcome (collision,
success, length, time-out).

Tolerances, and why: the steps overridden, the outcomes and whether a brake time or stop position exists are
decisions and must be equal; the brake time is a tick count (equal); the stop position is a float of the ego's
pose, compared within 1 cm: the batch's engine steps within 1e-12 relative of highway-env (tests/test_batched_sim.py),
but a car creeping to a stop steers with gains divided by its speed, which amplifies those last bits into its pose
(measured on seed 2,000,072 of the test split, dagger_turn_perceived+aeb, unbraked: the same speeds every step, the
route position 7e-9 m apart at 0.12 m/s and 1.7e-5 m at 0.09 m/s; at most 1.5e-3 m over 1,000 test episodes). The
per-env shield's own code decides on the batch (each row's ImprovedAEB on a view of its arrays, every input equal
within 1e-9), so only a decision the per-env shield itself takes on a last bit can split: its set-off rule predicts a
car standing in the box setting off at exactly 0.5 m/s (``0.5 * [cos h, sin h]``), and the conflict model follows
the lanes only at ``speed >= 0.5``, so the last bit of that car's heading decides whether the car is predicted along
its lanes or straight on (traced: test seed 2,000,732, dagger_turn+aeb, braked one step later on the batch). Measured
over 1,000 test episodes each: dagger_turn_perceived+aeb 0 splits, dagger_turn+aeb 3; the 50-episode slow test
allows 1 and names it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from av_gym.errors import ConfigError
from av_gym.presets import compose_group
from tests.conftest import conf

STOP_TOL = 0.01  # m (module docstring)
VALIDATION = 1_000_000


def _plan(spec: str, shield: dict | None = None):
    """``spec``'s plan (``shield``: the command line's ``shield=`` section, applied to it), env and policy."""
    from eval.agents import make_eval_env, plan_agent, resolve_agent

    plan = plan_agent(spec, "left_turn", conf("sensors", "truth"), shield or {"name": "none", "kind": "none"},
                      "checkpoints")
    env = make_eval_env(conf("env", "left_turn"), plan.sensors, plan.shield)
    _, policy = resolve_agent(plan.spec, env, "left_turn", "checkpoints")
    return plan, env, policy


def per_env(spec: str, seeds: list[int], shield: dict | None = None) -> dict[int, tuple[dict, dict]]:
    """Per seed: EpisodeMetrics' row and what the shield did (its ``info["aeb_*"]`` at the end, the steps it
    overrode), on the per-env stack."""
    plan, env, policy = _plan(spec, shield)
    out = {}
    try:
        for seed in seeds:
            obs, _ = env.reset(seed=seed)
            policy.reset()
            overrides, k, done = [], 0, False
            while not done:
                obs, _, term, trunc, info = env.step(policy.act(obs))
                if info["shield_override"]:
                    overrides.append(k)
                k, done = k + 1, term or trunc
            out[seed] = (info["episode_metrics"], {"brake_time": info["aeb_brake_time"],
                                                   "stop_position": info["aeb_stop_position"], "overrides": overrides})
    finally:
        env.close()
    return out


def batched(spec: str, seeds: list[int], n_envs: int, shield: dict | None = None) -> dict[int, tuple[dict, dict]]:
    """The same on the batch (``n_envs`` at a time), by ``python -m eval vec_env=batched``'s loop."""
    from eval.batched import NO_OBS_SENSORS, check_batched_plan, plan_kind, play_batched

    plan, env, policy = _plan(spec, shield)
    env.close()
    check_batched_plan(plan, conf("env", "left_turn"))
    sensors = NO_OBS_SENSORS if plan_kind(plan) == "always_proceed" else plan.sensors
    aeb: dict = {}
    rows = play_batched(conf("env", "left_turn"), sensors, plan.shield, policy, seeds, n_envs, spec, progress=False,
                        aeb=aeb)
    return {r["seed"]: (r, aeb[r["seed"]]) for r in rows}


OUTCOME = ("collision", "success", "length", "truncated", "interventions", "override_fraction", "first_override_s")


def splits(ref: dict, got: dict) -> list[str]:
    """Each seed whose shield or outcome differs, with what differs."""
    out = []
    for seed, (m, a) in ref.items():
        mb, b = got[seed]
        diff = [f"{k} {m[k]} vs {mb[k]}" for k in OUTCOME if not (m[k] == mb[k] or (m[k] != m[k] and mb[k] != mb[k]))]
        if a["overrides"] != b["overrides"]:
            diff.append(f"overrides {a['overrides']} vs {b['overrides']}")
        for k, tol in (("brake_time", 1e-9), ("stop_position", STOP_TOL)):
            if math.isinf(a[k]) != math.isinf(b[k]) or (math.isfinite(a[k]) and abs(a[k] - b[k]) > tol):
                diff.append(f"{k} {a[k]} vs {b[k]}")
        if diff:
            out.append(f"seed {seed}: " + "; ".join(diff))
    return out


def _check(spec: str, seeds: list[int], n_envs: int, allowed: int = 0, shield: dict | None = None) -> dict:
    ref = per_env(spec, seeds, shield)
    got = batched(spec, seeds, n_envs, shield)
    assert sorted(got) == sorted(ref) == sorted(seeds)
    found = splits(ref, got)
    assert len(found) <= allowed, found
    return ref


@pytest.mark.parametrize("spec, seeds", [
    ("always_proceed+aeb", [VALIDATION + k for k in (0, 3, 4, 5)]),  # brakes, stops at the line, a time-out
    ("dagger_turn+aeb", [VALIDATION + k for k in range(2)]),  # 50 episodes of each: the slow test below
    ("dagger_turn_perceived+aeb", [VALIDATION + k for k in range(2)]),  # mode: ground truth; agent on tracks
])
def test_the_shield_on_the_batch_is_the_per_env_shield(spec, seeds):
    """Interventions, brake times, stop positions and outcomes per episode equal to the per-env stack's, with
    several episodes in one batch (the rows' shields are independent) and with the brake actually used."""
    ref = _check(spec, seeds, n_envs=len(seeds))
    if spec == "always_proceed+aeb":  # the comparison means something: the shield braked and stopped the car
        assert sum(bool(a["overrides"]) for _, a in ref.values()) >= 3
        assert any(math.isfinite(a["stop_position"]) for _, a in ref.values())


def test_the_perceived_shield_on_the_batch_is_the_per_env_one():
    """``shield.mode=perceived`` (its own detector on the ``aeb_detector`` stream and Kalman tracker): the same
    interventions, brake times, stop positions and outcomes as the per-env shield."""
    ref = _check("always_proceed", [VALIDATION + k for k in (0, 4, 5)], n_envs=3,
                 shield={**compose_group("shield", "aeb"), "mode": "perceived"})
    assert sum(bool(a["overrides"]) for _, a in ref.values()) >= 2


@pytest.mark.slow  # ~1-5 CPU-minutes per agent, most of it the per-env stack's 50 shielded episodes
@pytest.mark.parametrize("spec", ["always_proceed+aeb", "dagger_turn+aeb", "dagger_turn_perceived+aeb"])
def test_the_shield_on_the_batch_is_the_per_env_shield_on_50_episodes(spec):
    """50 validation episodes per agent (the 3,000 test episodes of docs/shield.md, "On the batch", are the long
    comparison): every episode's interventions, brake time, stop position and outcome equal but for at most one
    split on a last bit (module docstring), named by seed."""
    _check(spec, list(range(VALIDATION, VALIDATION + 50)), n_envs=25, allowed=1)


# ----------------------------------------------------------------------------------------------- the actuator
def _venv(n: int = 2, shield: dict | None = None, **env):
    from av_gym.batched.vec_env import BatchedLeftTurnBatch
    from av_gym.presets import compose_group

    return BatchedLeftTurnBatch({"name": "left_turn", **env}, compose_group("sensors", "turn_truth"),
                                compose_group("shield", "aeb") if shield is None else shield, n, pool=0)


def test_the_brake_follows_the_actuator_tick_by_tick():
    """An engaged brake gives the ego, on each 20 Hz tick, the per-env actuator's deceleration: nothing for its
    0.15 s delay, then a 30 m/s³ ramp to 8 m/s² (BrakeActuator.command), whatever the agent asks for; the engine
    applies the plan tick by tick within one step."""
    from av_gym.shields.actuator import BrakeActuator

    venv = _venv(1)
    venv.play(iter([VALIDATION]))
    e, sh = venv.engine, venv.shield
    actuator = sh.shields[0].actuator
    assert sh.brake_plan(np.array([0])) is None  # nobody brakes: the engine's own step
    actuator.engage(e.ticks[0] / 20)
    accels = []
    for _ in range(6):
        plan = sh.brake_plan(np.array([0]))
        accels += plan[:, 0].tolist()
        ego = e.ego_slot([0])[0]
        v0 = e.traffic.v[0, ego]
        e.step(np.array([2]), None, plan)
        if not np.isnan(plan[0, 0]):  # both ticks braked: the speed fell by the plan's two decelerations
            assert e.traffic.v[0, ego] == pytest.approx(max(v0 + 0.05 * plan[:, 0].sum(), 0.0), abs=1e-9)
        assert e.traffic.acc[0, ego] == pytest.approx(plan[-1, 0]) or np.isnan(plan[-1, 0])
    ref = BrakeActuator()
    want = [ref.deceleration(k * 0.05, 0.05) for k in range(12)]
    assert [None if np.isnan(a) else -a for a in accels] == want


@pytest.mark.parametrize("env", [{}, {"action": "continuous"}])
def test_the_engine_takes_a_brake_plan_per_tick_on_both_paths(env):
    """``BatchedLeftTurn.step(..., ego_acceleration)`` (frames, B): NaN everywhere is the engine's own step bit
    for bit; a plan braking some envs on some ticks gives the same state on the compiled tick
    (kernels.advance) as on the numpy path (Traffic.act per tick), to tests/_numerics.py's tolerance, with
    meta-actions and continuous commands kept where the plan is NaN."""
    from _numerics import same

    from av_gym.sim import batched as sb

    venv = _venv(6, {"name": "none", "kind": "none"}, **env)
    venv.play(iter([VALIDATION + k for k in range(6)]))
    e, rows, rng = venv.engine, np.arange(6), np.random.default_rng(0)
    for step in range(60):
        a = rng.uniform(-1, 1, 6) if env else rng.integers(0, 3, 6)
        plan = np.where(rng.random((e.frames, 6)) < 0.4, -rng.uniform(0, 8, (e.frames, 6)), np.nan)
        own, nan, numpy_path = e.fork(rows), e.fork(rows), e.fork(rows)
        own.step(a)
        nan.step(a, None, np.full((e.frames, 6), np.nan))
        for name in ("x", "y", "v", "h", "acc", "target", "steer"):
            np.testing.assert_array_equal(getattr(own.traffic, name), getattr(nan.traffic, name), err_msg=name)
        e.step(a, None, plan)
        with sb.using_kernels(sb.KERNELS - {"tick"}):
            numpy_path.step(a, None, plan)
        for name in sb.Traffic.FIELDS:
            if name != "vid":
                assert same(getattr(e.traffic, name), getattr(numpy_path.traffic, name)), (step, name)
        assert same(e.ticks, numpy_path.ticks) and same(e.arrived_time, numpy_path.arrived_time)
    assert (e.traffic.v[rows, e.ego_slot(rows)] < 1.0).any()  # the brakes acted


def test_the_batch_gives_each_shield_the_per_env_objects_and_accelerations(monkeypatch):
    """Ground-truth mode: the road users' state rows, EMA accelerations, follower mask, indicator turn weights and
    recently-moved flags the batch computes for all rows at once (``_Kinematics``, remembered per vehicle id;
    ``_followers``; ``_Channel``, each row's generator drawn in the per-env order; ``_Moved``) are, at every
    decision, what the per-env shield's own ``_objects``, ``_accelerations``, ``_relevant``, ``_intent`` and
    ``_recently_moved`` compute on the row (its dicts keyed by the vehicle objects, its own generator; bit for bit,
    the turn weights within 1e-12 relative: a stacked product), across spawns, departures, the engine's compaction
    of its slots (vehicles change slot) and new episodes in a row. Fails with the memory kept per slot instead of
    per vehicle, an EMA not dropped for a vehicle that left, the first sightings' draws taken after the readings'
    or the channel's counts shared across rows' posteriors."""
    from av_gym.batched import shield as batched_shield
    from av_gym.shields.aeb_base import AEBShield
    from av_gym.shields.aeb_improved import ImprovedAEB

    monkeypatch.setattr(batched_shield, "SCREEN_CHECK", True)  # the screened rows' own decisions run (and read) too
    venv = _venv(3)
    row_shield = type(venv.shield.shields[0])
    own_objects, own_accels, own_relevant = row_shield._objects, row_shield._decision_accels, row_shield._relevant
    own_intent, own_recent = row_shield._intent, row_shield._recently_moved
    seen = {"decisions": 0, "moving": 0, "followers": 0, "read": 0, "recent": 0}

    def bits(a):
        return np.ascontiguousarray(a, dtype=float).view(np.int64)

    def objects(self, ego):
        got, lanes = own_objects(self, ego), self._lanes
        self.env.refresh()  # the whole row, as the per-env env holds it (the batch's view reads its ego alone)
        ref = AEBShield._objects(self, ego)
        assert np.array_equal(bits(got[0]), bits(ref[0])) and got[1] == [v.vid for v in ref[1]] and got[2] == ref[2]
        assert lanes == self._lanes
        return got

    def accelerations(self, ego, others, keys, t):  # the ego's first, then each road user's
        got = own_accels(self, ego, others, keys, t)
        ref = AEBShield._accelerations(self, ["__ego__", *keys], np.vstack([ego["velocity"][None], others[:, 2:4]]), t)
        assert np.array_equal(bits(got), bits(ref)), (t, got, ref)
        seen["decisions"] += 1
        seen["moving"] += int((np.abs(ref) > 1e-3).any())
        return got

    def relevant(self, ego, others):
        got, ref = own_relevant(self, ego, others), ImprovedAEB._relevant(self, ego, others)
        assert np.array_equal(got, ref)
        seen["followers"] += int((~ref).sum())
        return got

    def vehicles(self, keys):  # the row's vehicles of the batch's keys (their ids), as the per-env shield keys them
        return [self.env._by_vid[k] for k in keys]

    def intent(self, others, keys):
        got, ref = own_intent(self, others, keys), ImprovedAEB._intent(self, others, vehicles(self, keys))
        # the batch stacks the decisions' posteriors: bit for bit with OpenBLAS, not promised by every BLAS build
        assert got.shape == ref.shape and np.allclose(got, ref, rtol=1e-12, atol=1e-15, equal_nan=True), (got, ref)
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        seen["read"] += int(np.isfinite(ref).all(axis=1).sum())
        return got

    def recently_moved(self, others, t):
        got, keys = own_recent(self, others, t), self._keys
        self._keys = vehicles(self, keys)
        ref = ImprovedAEB._recently_moved(self, others, t)
        self._keys = keys
        assert np.array_equal(got, ref)
        seen["recent"] += int(ref.sum())
        return got

    monkeypatch.setattr(row_shield, "_intent", intent)
    monkeypatch.setattr(row_shield, "_recently_moved", recently_moved)
    monkeypatch.setattr(row_shield, "_relevant", relevant)
    monkeypatch.setattr(row_shield, "_objects", objects)
    monkeypatch.setattr(row_shield, "_decision_accels", accelerations)
    venv.play(iter([VALIDATION + k for k in range(5)]))
    e, moved, where = venv.engine, 0, {}
    rng = np.random.default_rng(0)
    for _ in range(400):
        if venv.idle.all():
            break
        venv.step(rng.integers(1, 3, 3))
        t = e.traffic
        for r, slot in zip(*np.nonzero(t.alive)):
            moved += where.get(t.vid[r, slot], slot) != slot
            where[t.vid[r, slot]] = slot
    assert venv.idle.all() and seen["decisions"] > 300 and seen["moving"] > 100 and seen["followers"] > 0
    assert seen["read"] > 300 and seen["recent"] > 100  # drivers read (weights, not NaN), cars that moved lately
    assert moved > 0  # the engine compacted slots under live vehicles: the memory followed the vehicles


def test_the_batch_predicts_each_shields_conflicts_as_the_shield_does(monkeypatch):
    """Ground-truth mode: the conflict model's paths of every decision's kept road users, which the batch computes
    for all its rows in one compiled call (``ConflictModel.predict_rows``), are at every decision bit for bit the
    row's shield's own ``ConflictModel.predict`` (positions, headings, owners, map flags, probabilities), across
    turn weights read and unread, constant-velocity and lane hypotheses and new episodes in a row;
    a decision whose speed bins are not simulated yet falls back to the shield's own call. Fails if a row reads
    another row's road users, lanes, accelerations or weights, or the flat buffers are cut at the wrong place."""
    from av_gym.batched import shield as batched_shield
    from av_gym.shields.aeb_improved import ImprovedAEB

    monkeypatch.setattr(batched_shield, "SCREEN_CHECK", True)  # the screened rows' own decisions run (and read) too
    venv = _venv(2)
    row_shield = type(venv.shield.shields[0])
    own = row_shield._scene_conflicts
    seen = {"served": 0, "own": 0, "map": 0, "cv": 0, "weighted": 0}

    def scene_conflicts(self, others, lanes, a_others, t_long, intent):
        served = self.env.predicted is not None
        got, ref = own(self, others, lanes, a_others, t_long, intent), \
            ImprovedAEB._scene_conflicts(self, others, lanes, a_others, t_long, intent)
        assert len(got) == len(ref) == 5
        for a, b in zip(got, ref):
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
        seen["served" if served else "own"] += 1
        seen["map"] += int(ref[3].sum())
        seen["cv"] += int((~ref[3]).sum())
        seen["weighted"] += int(intent is not None and np.isfinite(intent).all(axis=1).any())
        return got

    monkeypatch.setattr(row_shield, "_scene_conflicts", scene_conflicts)
    venv.play(iter([VALIDATION + k for k in range(2, 5)]))
    rng = np.random.default_rng(0)
    for _ in range(400):
        if venv.idle.all():
            break
        venv.step(rng.integers(1, 3, 2))
    assert venv.idle.all() and seen["served"] > 200, seen  # "own": new speed bins (most in a fresh process)
    assert seen["map"] > 1000 and seen["cv"] > 50 and seen["weighted"] > 100, seen


def test_a_row_whose_prediction_is_for_other_road_users_than_its_shield_keeps_is_refused(monkeypatch):
    """The batch's prediction of a decision is for the road users it kept; a shield keeping another number of them
    (the batch and the shield out of step) stops with a RuntimeError naming the row instead of reading another set's
    paths."""
    from av_gym.batched.shield import BatchedShield

    venv = _venv(1)
    kinematics = BatchedShield._kinematics

    def out_of_step(self, rows):
        kinematics(self, rows)
        for r in rows.tolist():
            self.views[r].predicted_n += 1

    monkeypatch.setattr(BatchedShield, "_kinematics", out_of_step)
    venv.play(iter([VALIDATION]))
    refused = r"^row [0]: the batch's prediction holds \d+ road users, the shield keeps \d+"
    with pytest.raises(RuntimeError, match=refused):
        for _ in range(100):
            venv.step(np.array([1]))


def test_the_channels_posteriors_for_all_envs_are_each_envs_own_call():
    """The indicator channel's turn weights of every env's drivers read so far, computed for all envs at once
    (``_Channel._posteriors``: the envs with as many drivers in one stacked product (S, m, 3)), are each env's own
    ``DriverIntent.weights`` call on its drivers (the per-env shield's grouping), on random counts of 0-8 drivers
    per env. Fails with an env's drivers one off or another env's rows."""
    channel = _venv(1).shield.channel
    rng = np.random.default_rng(0)
    per_env = rng.integers(0, 9, 300)
    counts = rng.integers(0, 40, (int(per_env.sum()), 3))
    got = channel._posteriors(counts, per_env)
    start = np.cumsum(per_env) - per_env
    for a, m in zip(start.tolist(), per_env.tolist()):
        if m:
            want = channel.beliefs.weights(counts[a:a + m])
            # bit for bit with numpy's OpenBLAS here; a BLAS build may round a stacked product's last bit apart
            assert np.allclose(got[a:a + m], want, rtol=1e-12, atol=1e-15), (a, m)


# ----------------------------------------------------------------------------------------------- refusals
@pytest.mark.parametrize("shield, needle", [
    ("aeb_paper", "shield.variant=paper is not available with agent.vec_env=batched"),
    ("aeb_standard", "shield.variant=standard is not available with agent.vec_env=batched"),
    ("aeb_belief", "shield.second_opinion=belief_lookahead is not available with agent.vec_env=batched"),
])
def test_what_the_batch_does_not_run_of_the_shield_is_one_line(shield, needle):
    from av_gym.presets import compose_group

    with pytest.raises(ConfigError, match=needle) as exc:
        _venv(1, compose_group("shield", shield))
    assert "\n" not in str(exc.value)


def test_a_simulation_frequency_the_actuator_does_not_run_is_one_line():
    with pytest.raises(ConfigError, match="env.simulation_frequency=15 with shield=aeb is not available"):
        _venv(1, simulation_frequency=15)


def test_training_on_the_batch_still_refuses_a_shield():
    """check_batchable without ``with_shield`` (the DAgger replica: a shield would change the episodes its labels
    are for; PPO's training batch runs the shield, tests/test_ppo_batched_shield.py) refuses it in one line."""
    from av_gym.batched.vec_env import check_batchable
    from av_gym.presets import compose_group

    with pytest.raises(ConfigError, match="shield=aeb is not available with agent.vec_env=batched here"):
        check_batchable({"name": "left_turn"}, compose_group("sensors", "turn_truth"), compose_group("shield", "aeb"))


def test_ppo_on_the_batch_refuses_an_intervention_cost_before_any_folder(tmp_path):
    """``agent.intervention_cost`` is paid on the shield's override time: with ``shield=none`` there is none, and
    `python -m train` refuses it in one line on the command line, before a run folder exists."""
    from tests.conftest import cli

    res = cli("train", "agent=ppo_turn_shielded", "agent.vec_env=batched", "shield=none", "run_name=costed",
              cwd=tmp_path)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert "agent.intervention_cost=1 is paid on the shield's overrides: it needs shield=aeb" in lines[0]
    assert list(tmp_path.iterdir()) == [], "no runs/ or checkpoints/ folder for a refused command"


def test_make_vec_and_the_sb3_vec_env_run_the_shield():
    """``gymnasium.make_vec(..., shield="aeb")`` and the SB3 VecEnv run the batch's shield: an always-proceed
    episode that the per-env shield brakes in is braked in (its first brake at the per-env shield's time)."""
    import gymnasium as gym

    from av_gym_sb3 import BatchedLeftTurnVecEnv
    from av_gym.presets import compose_group

    ref = per_env("always_proceed+aeb", [VALIDATION])[VALIDATION][1]
    venv = gym.make_vec("av_gym/UnprotectedLeftTurn-v0", 1, sensors="turn_truth", shield="aeb")
    assert venv.venv.shield is not None
    venv.reset(seed=VALIDATION)
    for _ in range(300):
        _, _, term, trunc, info = venv.step(np.array([2]))
        if term[0] or trunc[0]:
            break
    sb3 = BatchedLeftTurnVecEnv({"name": "left_turn"}, compose_group("sensors", "turn_truth"),
                                compose_group("shield", "aeb"), 1)
    assert sb3.shield is not None and math.isfinite(ref["brake_time"])
    assert info["episode_metrics"]["first_override_s"][0] == pytest.approx(ref["brake_time"] + 0.1)


@pytest.mark.slow  # ~14 s on idle cores: a whole eval process (imports, the batch, the shield's kernels loaded)
def test_eval_on_the_batch_records_the_shield_it_ran(tmp_path):
    """``python -m eval vec_env=batched agents=[always_proceed+aeb]`` runs (it was refused) and its results say
    the shield ran: the label, and interventions in its rows."""
    import csv

    from tests.conftest import cli

    res = cli("eval", "vec_env=batched", "agents=[always_proceed+aeb]", "episodes=4", f"seed={VALIDATION}",
              "split=validation", "progress_bar=false", "n_envs=4", f"out_dir={tmp_path / 'out'}", "videos=false",
              cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    rows = list(csv.DictReader(open(tmp_path / "out" / "results.csv")))
    assert {r["agent"] for r in rows} == {"always_proceed+aeb"}
    assert sum(float(r["interventions"]) for r in rows) > 0


def test_the_screened_decisions_are_each_rows_own(monkeypatch):
    """BatchedShield._screen decides the rows whose own decision is MONITOR with no conflict or a warning for all
    rows at once (the route position, profile, horizon and first TTC in arrays and compiled calls): with
    SCREEN_CHECK each screened row's own ``_decide`` runs from the same state and must give the same decision
    (stage, TTC, horizon, target, turn-window flag) and move its route lane and time as the screen does, over
    episodes with FASTER / SLOWER / IDLE proposed (check_action's set-point profiles), before, in and after the turn
    window. Fails if the screen's stage, TTC, target, horizon, route lane or time differ from the row's, or it
    screens a row whose own decision is another (a brake, an emergency test)."""
    from av_gym.batched import shield as batched_shield

    monkeypatch.setattr(batched_shield, "SCREEN_CHECK", True)
    seen = {"screened": 0, "active": 0, "setpoint": 0, "warn": 0}
    check = batched_shield._check_screened

    def counted(shield, want, route_k, now):
        check(shield, want, route_k, now)
        seen["screened"] += 1
        seen["active"] += int(want[4])
        seen["warn"] += int(np.isfinite(want[1]))
        seen["setpoint"] += int(shield._proposed in (0, 2))  # SLOWER, FASTER: under check_action, setpoint_steps

    monkeypatch.setattr(batched_shield, "_check_screened", counted)
    venv = _venv(3)
    venv.play(iter([VALIDATION + k for k in range(3)]))
    rng = np.random.default_rng(5)
    for _ in range(400):
        if venv.idle.all():
            break
        venv.step(rng.integers(0, 3, 3))
    assert venv.idle.all() and seen["screened"] > 100 and seen["active"] > 30 and seen["setpoint"] > 30, seen
    assert seen["warn"] > 20, seen  # a conflict later than ttc_brake, away from the trigger point: a warning
