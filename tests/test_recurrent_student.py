"""The recurrent student (agents/recurrent.py, train/dagger_recurrent.py): it learns what only memory can tell (a
label set by an input seen three decisions earlier) where the same code without its GRU cannot; on the batch each
row's hidden state starts anew with the row's episode; a saved student loads to the same choices; the aggregate's
episodes are read in decision order (and refused out of order) with the held-out episodes of dagger_forms."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from agents.recurrent import RecurrentForm, RecurrentPolicy, RecurrentStudent, load_student, save_student
from av_gym.errors import ConfigError
from av_gym.estimation.turn_features import EGO_FEATURES, OBJECT_FEATURES
from av_gym.wrappers import GO, YIELD
from tests.test_dagger import _one_torch_thread  # noqa: F401 (the fixture: one torch thread, as train)
from train.dagger_recurrent import Episodes, accuracy, episode_index, fit, split_episodes

N_OBJECTS, LAG, PERIOD = 2, 3, 0.025  # objects in the toy observation; the label's lag (decisions); time step
TURN_DIM = len(EGO_FEATURES) + len(OBJECT_FEATURES) * N_OBJECTS
CUE, TIME = EGO_FEATURES.index("speed"), EGO_FEATURES.index("time")


def _lag_task(n_episodes: int, seed: int, length: int = 10) -> Episodes:
    """Episodes of ``length`` decisions stored one after another; a cue of +-1 in the ego's speed column at every
    decision, the label GO where the cue ``LAG`` decisions earlier was +1 (YIELD for the first ``LAG``): no single
    observation tells the label; the history does."""
    rng = np.random.default_rng(seed)
    cue = rng.choice([-1.0, 1.0], size=(n_episodes, length))
    turn = np.zeros((n_episodes, length, TURN_DIM), np.float32)
    turn[..., CUE] = cue
    turn[..., TIME] = PERIOD * np.arange(length)
    labels = np.full((n_episodes, length), YIELD, dtype=np.int64)
    labels[:, LAG:] = np.where(cue[:, :-LAG] > 0, GO, YIELD)
    turn, labels = turn.reshape(-1, TURN_DIM), labels.reshape(-1)
    return Episodes({"turn": turn}, labels, episode_index(turn[:, TIME]))


def _fitted(hidden: int) -> RecurrentStudent:
    import torch as th

    th.manual_seed(0)
    student = RecurrentStudent(RecurrentForm(TURN_DIM, hidden=hidden, attention_dim=16, net_arch=(32,)))
    fit(student, _lag_task(200, seed=1), None, epochs=10, batch_episodes=16, lr=1e-2, lr_end=1e-3, seed=1)
    return student


@pytest.fixture(scope="module")
def memory_student() -> RecurrentStudent:
    return _fitted(hidden=16)


def test_the_gru_learns_a_label_seen_three_decisions_earlier_and_the_feed_forward_form_cannot(memory_student):
    held = _lag_task(200, seed=2)
    assert accuracy(memory_student, held) > 0.95
    # without memory: the first LAG decisions (always YIELD) and a coin toss on the others, 0.65 expected
    assert accuracy(_fitted(hidden=0), held) < 0.72


def _decider(policy, rows: int):
    from types import SimpleNamespace

    from eval.batched import _Decider

    return _Decider(policy, SimpleNamespace(B=rows, continuous=False))


def _obs(turn: np.ndarray) -> dict:
    return {"turn": np.asarray(turn, np.float32)}


def test_a_row_that_restarts_on_the_batch_drives_its_new_episode_as_a_fresh_policy(memory_student):
    """Row 0 drives episode A then B (restarted as the batched evaluation restarts a row), row 1 drives B from the
    start at once: both drive B as a per-env policy reset before it (every decision's choice and hidden state).
    Without the reset, row 0 carries A's last cues into B's first decisions."""
    a = _lag_task(1, seed=7).obs["turn"]
    b = _lag_task(1, seed=8).obs["turn"]
    a[:, CUE] = 1.0  # A ends on GO cues, B starts on YIELD cues: a remembered A answers GO where B says YIELD
    b[:, CUE] = -1.0
    repeat = memory_student.form.action_repeat
    per_env = RecurrentPolicy(memory_student)
    per_env.reset()
    batch = RecurrentPolicy(memory_student)
    decide = _decider(batch, rows=2)
    for step in range(len(a) * repeat):  # row 0 drives A while row 1 drives B
        decide.act(_obs(np.stack([a[step // repeat], b[step // repeat]])), np.array([True, True]))
    decide.reset(np.array([0]))
    for step in range(len(b) * repeat):
        t = step // repeat
        env_action = decide.act(_obs(np.stack([b[t], b[t]])), np.array([True, False]))[0]
        assert env_action == per_env.act({"turn": b[t]})
        assert batch.held[0] == per_env.held[0], f"decision {t}"
        np.testing.assert_allclose(batch.h[0].numpy(), per_env.h[0].numpy(), atol=1e-5)
    assert batch.held[0] == YIELD  # B's cues, not A's


def test_a_saved_student_loads_to_the_same_choices_and_form(memory_student, tmp_path):
    import torch as th

    path = save_student(memory_student, tmp_path / "student.pt", extra={"note": "test"})
    loaded = load_student(path)
    assert loaded.form == memory_student.form
    x, _, valid = _lag_task(50, seed=3).batch(np.arange(50))
    with th.no_grad():
        np.testing.assert_array_equal(loaded(x, valid).numpy(), memory_student(x, valid).numpy())
    assert load_student(path, go_threshold=0.9).form.go_threshold == 0.9
    (tmp_path / "not.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="not a recurrent student's checkpoint"):
        load_student(tmp_path / "not.pt")
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary file left


def test_the_aggregate_is_read_episode_by_episode_in_decision_order_or_refused():
    data = _lag_task(5, seed=4, length=4)
    elapsed = data.obs["turn"][:, TIME]
    np.testing.assert_array_equal(data.index[1], [4, 5, 6, 7])
    short = np.concatenate([elapsed[:6], elapsed[7:]])  # episode 1 loses its third decision
    with pytest.raises(ConfigError, match="in order"):
        episode_index(short)
    with pytest.raises(ConfigError, match="in order"):
        episode_index(elapsed[1:])  # the first episode starts after 0


def test_the_held_out_episodes_are_those_dagger_forms_keeps_out():
    from train.observation_ceiling import episode_ids, holdout_mask

    data = _lag_task(50, seed=5, length=6)
    data.index = episode_index(np.concatenate([data.obs["turn"][:, TIME]]))
    fitted, held = split_episodes(data, 0.2, seed=3)
    forms = holdout_mask(episode_ids(data.obs["turn"][:, TIME]), 0.2, 3)  # train/dagger_forms.py's _split
    assert sorted(held.index[held.valid]) == list(np.flatnonzero(forms))
    assert sorted(fitted.index[fitted.valid]) == list(np.flatnonzero(~forms))


def _median_p_go(student: RecurrentStudent, env, seed: int, decisions: int = 20) -> float:
    """The median P(GO) of ``student`` over the first ``decisions`` of episode ``seed`` of ``env`` (held at IDLE, up
    to its end)."""
    import torch as th

    obs, _ = env.reset(seed=seed)
    h, p = student.initial_state(1), []
    with th.no_grad():
        for _ in range(decisions):
            x = {k: th.as_tensor(np.asarray(obs[k], np.float32)[None]) for k in ("turn", "intent")}
            logits, h = student.step(x, h)
            p.append(float(th.softmax(logits, -1)[0, GO]))
            for _ in range(student.form.action_repeat):
                obs, _, terminated, truncated, _ = env.step(1)
                if terminated or truncated:
                    return float(np.median(p))
    return float(np.median(p))


@pytest.mark.slow
def test_the_recurrent_student_drives_the_same_episodes_on_the_batch_as_per_env():
    """Real left-turn episodes (turn_truth_memory), two rows for six seeds so that rows restart: every episode's
    outcome on the batch (one hidden state per row) as on the per-env stack (one policy, reset per episode)."""
    import torch as th

    from av_gym.presets import compose_group
    from eval.agents import make_eval_env
    from eval.batched import play_batched
    from eval.runner import run_episodes
    from tests.conftest import conf

    env_cfg, sensors = conf("env", "left_turn"), compose_group("sensors", "turn_truth_memory")
    shield = {"name": "none", "kind": "none"}
    env = make_eval_env(env_cfg, sensors, shield)
    th.manual_seed(3)
    obs = {k: np.asarray(v)[None] for k, v in env.observation_space.sample().items()}
    student = RecurrentStudent(RecurrentForm.of_observations(obs, attention_dim=16, hidden=16, net_arch=(16,)))
    # untrained, its P(GO) stays within ~1e-3 of one value: at that value's median GO and YIELD both occur
    student.form = replace(student.form, go_threshold=_median_p_go(student, env, seed=999_999))
    seeds = list(range(1_000_000, 1_000_006))
    try:
        per_env = run_episodes(env, RecurrentPolicy(student), seeds, "gru", progress=False)
    finally:
        env.close()
    batch = play_batched(env_cfg, sensors, shield, RecurrentPolicy(student), seeds, 2, "gru", progress=False)
    keys = ("collision", "success", "length", "truncated")
    assert [[r[k] for k in keys] for r in batch] == [[r[k] for k in keys] for r in per_env]
    assert len({(r["length"], r["success"]) for r in batch}) > 1  # the student's choices shaped the episodes
