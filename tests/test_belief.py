"""belief_lookahead decides on what the car can know: re-randomising the simulator's hidden draws (the other
drivers' routes, IDM exponents, set-points and regulation holds, and the rows' generators that hold the future
spawns) while every observable stays equal leaves its decisions bit for bit as they were, and changes the
privileged oracle's (so the test can fail); its draws come from its own seeded streams."""

from __future__ import annotations

import numpy as np
import pytest

from agents.batched_oracle import oracle_labels
from agents.belief import BeliefLookaheadParams, BeliefPlanner
from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
from av_gym.wrappers import GO, YIELD

SENSORS = {"name": "turn_truth", "turn_signals": {}, "turn_features": {"source": "truth"}, "turn_intent": {},
           "observe": ["turn", "intent"]}
B = 24


@pytest.fixture(scope="module")
def scene():
    """B episodes driven 8 decisions' worth of env steps under YIELD (at the line, traffic crossing), the planner
    reading every indicator on the way."""
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, SENSORS, None, B, pool=0)
    obs = venv.play(iter(range(400_000, 400_000 + B)))
    planner = BeliefPlanner(BeliefLookaheadParams(samples=8), n_rows=B)
    for _ in range(40):
        live = np.nonzero(~venv.idle)[0]
        planner.read(venv.engine, live, obs["intent"][live])
        obs, _, _, _ = venv.step(meta_actions(np.full(B, YIELD), obs["turn"]))
    rows = np.nonzero(~venv.idle)[0]
    planner.read(venv.engine, rows, obs["intent"][rows])
    return venv.engine, planner, rows


def rerandomise(engine, rows, seed: int) -> None:
    """New hidden draws for every traffic driver of ``rows``: a destination (its route re-planned from its origin
    and the step it is on kept), IDM delta, set-point, regulation hold; new generators for the rows (other future
    spawns). Positions, headings, speeds, lanes, accelerations, crashes and identities stay."""
    from agents.track_prior import lane_kinds

    t, T = engine.traffic, engine.T
    g = np.random.default_rng(seed)
    kind, origin, dest = lane_kinds(T)
    lane_of = {(k, int(o), int(d)): i for i, (k, o, d) in enumerate(zip(kind, origin, dest))}
    approach = {int(o): i for i, (k, o) in enumerate(zip(kind, origin)) if k == 0}
    cross = {(int(o), int(d)): i for i, (k, o, d) in enumerate(zip(kind, origin, dest)) if k == 1}
    exits = {int(d): i for i, (k, d) in enumerate(zip(kind, dest)) if k == 2}
    assert lane_of
    for r in rows:
        for j in np.nonzero(t.alive[r] & ~t.ego[r])[0]:
            o = int(origin[t.route[r, j, 0]]) if t.route[r, j, 0] >= 0 else int(g.integers(4))
            d = int((o + g.integers(1, 4)) % 4)
            t.route[r, j] = [approach[o], cross[(o, d)], exits[d]]
            t.tlane[r, j] = t.route[r, j, min(int(t.rpos[r, j]), 2)]
            t.delta[r, j] = g.uniform(3.5, 4.5)
            t.target[r, j] = g.uniform(5.0, 10.0)
            t.yielding[r, j] = g.random() < 0.5
        engine.rngs[r] = np.random.default_rng(g.integers(2**63))


def test_decisions_ignore_hidden_draws(scene):
    engine, planner, rows = scene
    p_before = planner.go_collision(engine, rows)
    oracle_before = oracle_labels(engine, rows)[0]
    hidden = {name: getattr(engine.traffic, name).copy() for name in ("route", "tlane", "delta", "target",
                                                                    "yielding")}
    rerandomise(engine, rows, seed=7)
    assert any((hidden[name] != getattr(engine.traffic, name)).any() for name in hidden)  # something did change
    p_after = planner.go_collision(engine, rows)
    oracle_after = oracle_labels(engine, rows)[0]
    np.testing.assert_array_equal(p_before, p_after)  # the planner: bit for bit
    assert (oracle_before != oracle_after).any(), "the oracle reads the hidden draws: its labels must move"
    assert 0.0 < p_before.mean() < 1.0  # not a degenerate planner that always yields or always goes


def test_seeded_draws(scene):
    engine, planner, rows = scene
    again = BeliefPlanner(planner.params, n_rows=B)
    again.counts = planner.counts
    np.testing.assert_array_equal(planner.go_collision(engine, rows), again.go_collision(engine, rows))
    other = BeliefPlanner(BeliefLookaheadParams(samples=8, seed=1), n_rows=B)
    other.counts = planner.counts
    assert (other.go_collision(engine, rows) != planner.go_collision(engine, rows)).any()


def test_belief_follows_indicators(scene):
    """A driver read indicating left (and never right) is believed to turn left more than one read right."""
    _, planner, _ = scene
    p = planner.turn_probabilities([0], np.array([[-1, -2]]))
    planner.counts[0][-1], planner.counts[0][-2] = np.array([0, 1, 4]), np.array([4, 1, 0])
    q = planner.turn_probabilities([0], np.array([[-1, -2]]))
    del planner.counts[0][-1], planner.counts[0][-2]
    assert np.allclose(p[0].sum(axis=-1), 1.0)
    assert q[0, 0, 2] > 0.6 and q[0, 1, 0] > 0.6


def test_per_env_view_decides_as_the_batch():
    """The per-env agent's one-row view of its env (EnvView) gives the batch's probabilities for the same
    episodes and the same readings, decision by decision."""
    from agents.belief import BeliefLookahead
    from av_gym.make import make_env
    from av_gym.wrappers import meta_action

    seeds = [400_100, 400_101, 400_102]
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, SENSORS, None, len(seeds), pool=0)
    bobs = venv.play(iter(seeds))
    batch = BeliefPlanner(BeliefLookaheadParams(samples=4), n_rows=len(seeds))
    envs = [make_env({"name": "left_turn"}, SENSORS, None) for _ in seeds]
    obs = [e.reset(seed=s)[0] for e, s in zip(envs, seeds)]
    agents = [BeliefLookahead(e, BeliefLookaheadParams(samples=4)) for e in envs]
    rows = np.arange(len(seeds))
    compared = 0
    for k in range(11):
        batch.read(venv.engine, rows, bobs["intent"])
        views = [a.view.engine(e, o) for a, e, o in zip(agents, envs, obs)]
        for a, v, o in zip(agents, views, obs):
            a.planner.read(v, [0], o["intent"][None])
        if k % 5 == 0:
            per_env = [a.planner.go_collision(v, [0])[0] for a, v in zip(agents, views)]
            np.testing.assert_array_equal(batch.go_collision(venv.engine, rows), per_env)
            compared += len(seeds)
        bobs, _, done, _ = venv.step(meta_actions(np.full(len(seeds), YIELD), bobs["turn"]))
        obs = [e.step(meta_action(YIELD, o["turn"]))[0] for e, o in zip(envs, obs)]
        assert not done.any()
    for e in envs:
        e.close()
    assert compared == 9


def test_dagger_teacher_on_the_batch():
    """As DAgger's teacher on the batch (train/dagger.py BatchedLabels) it labels with the same planner, its
    belief from the readings at the decisions it is asked about."""
    from agents.belief import belief_lookahead_teacher
    from train.dagger import BatchedLabels

    params = BeliefLookaheadParams(samples=4)
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, SENSORS, None, 4, pool=0)
    obs = venv.play(iter(range(400_200, 400_204)))
    labeller = BatchedLabels(venv, belief_lookahead_teacher(params, "go_yield"), True, 0.0)
    planner = BeliefPlanner(params, n_rows=4)
    rows = np.arange(4)
    for _ in range(3):
        planner.read(venv.engine, rows, obs["intent"])
        np.testing.assert_array_equal(labeller(rows, obs), planner.labels(venv.engine, rows))
        for _ in range(5):
            obs, _, _, _ = venv.step(meta_actions(np.full(4, YIELD), obs["turn"]))


@pytest.mark.parametrize("commit", ["stop", "go", "never"])
def test_commit_says_which_choices_are_asked_again(scene, commit):
    """At a decision, ``never`` asks the planner for every row (as a DAgger teacher labels), ``go`` only the rows
    not holding GO, ``stop`` also keeps GO where the ego is past the line or too fast to stop before it."""
    engine, _, rows = scene
    planner = BeliefPlanner(BeliefLookaheadParams(samples=4, commit=commit), n_rows=B)
    asked = []
    planner.go_collision = lambda engine, r, K=None, stream=(): asked.append(np.asarray(r).copy()) or np.ones(len(r))
    choice = np.where(np.arange(len(rows)) % 2 == 0, GO, YIELD)
    after = planner.decide(engine, rows, choice, np.zeros(len(rows), int))
    held = rows[choice == GO]
    kept = planner.committed(engine, rows, choice)
    expected = {"never": rows, "go": rows[choice != GO], "stop": rows[~kept]}[commit]
    assert np.array_equal(asked[0] if asked else np.zeros(0, int), expected)
    assert (after[np.isin(rows, expected)] == YIELD).all() and len(held)
    assert planner.decide(engine, rows, choice, np.ones(len(rows), int)).tolist() == choice.tolist()  # not due
