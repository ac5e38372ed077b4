"""The batched left turn checks what it is given as the per-env stack does: actions against the action space
(:func:`av_gym.actions.check_actions`, the batch's :func:`~av_gym.actions.check_action`), their shape, a step
before the first reset, and seeds; one line each. Its SB3 adapter is importable from ``av_gym_sb3``."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces

from av_gym.actions import InvalidAction, check_action, check_actions
from av_gym.batched.vec_env import BatchedLeftTurnBatch, batch_seeds
from av_gym.errors import ConfigError

N = 4
DISCRETE, BOX = spaces.Discrete(3), spaces.Box(-1.0, 1.0, (1,), np.float32)


def _one_line(err: pytest.ExceptionInfo) -> str:
    text = str(err.value)
    assert "\n" not in text and len(text) < 300
    return text


@pytest.mark.parametrize("space,actions,says", [
    (DISCRETE, np.full(N, 5),
     "action 5 of env 0 is not in the action space Discrete(3): expected an integer in [0, 2]"),
    (DISCRETE, np.array([0, 1, -1, 2]), "action -1 of env 2 is not in the action space Discrete(3)"),
    (DISCRETE, np.full(N, np.nan), "got float64"),
    (DISCRETE, np.full(N, 1e9), "got float64"),
    (DISCRETE, np.array([True, False, True, False]), "got bool"),
    (DISCRETE, np.zeros(N - 1, int), "actions of shape (3,) for 4 envs: expected shape (4,) or (4, 1)"),
    (DISCRETE, np.zeros((N, 2), int), "actions of shape (4, 2) for 4 envs"),
    (DISCRETE, "x", "actions of shape () for 4 envs"),
    (DISCRETE, None, "actions of shape () for 4 envs"),
    (BOX, np.array([[0.0], [np.nan], [0.0], [0.0]]), "action [nan] of env 1 is not in the action space Box"),
    (BOX, np.full((N, 1), 5.0), "out of bounds"),
    (BOX, np.full((N, 1), -np.inf), "not finite"),
    (BOX, np.zeros((N, 2)), "actions of shape (4, 2) for 4 envs: expected shape (4, 1) or (4,)"),
])
def test_check_actions_refuses_in_one_line(space, actions, says) -> None:
    with pytest.raises(InvalidAction) as err:
        check_actions(space, actions, N)
    assert says in _one_line(err)
    assert isinstance(err.value, ConfigError) and isinstance(err.value, gym.error.InvalidAction)


@pytest.mark.parametrize("space,actions", [
    (DISCRETE, np.array([0, 1, 2, 0])), (DISCRETE, np.array([[0], [1], [2], [0]], np.int32)),
    (DISCRETE, [0, 1, 2, 1]), (BOX, np.array([[-1.0], [0.0], [0.5], [1.0]], np.float32)),
    (BOX, np.array([-1.0, 0.0, 0.5, 1.0])),
])
def test_check_actions_takes_every_action_of_the_space(space, actions) -> None:
    check_actions(space, actions, N)
    for a in np.asarray(actions).reshape(N, *space.shape):  # the per-env check agrees env by env
        check_action(space, a.item() if space.shape == () else a)


@pytest.mark.parametrize("seed,says", [
    ("x", "seed must be a non-negative integer, a list of 4 of them (one per env) or None, got 'x'"),
    (-1, "got -1"), (1.5, "got 1.5"), (True, "got True"), ([1, 2], "seed lists 2 seeds for 4 envs"),
    ([0, 1, -2, 3], "seed[2] must be a non-negative integer or None, got -2"), ([0, None, "y", 3], "seed[2]"),
])
def test_batch_seeds_refuse_in_one_line(seed, says) -> None:
    with pytest.raises(ConfigError) as err:
        batch_seeds(seed, N)
    assert says in _one_line(err)


def test_batch_seeds() -> None:
    assert batch_seeds(7, N) == [7, 8, 9, 10] and batch_seeds(np.int64(7), 2) == [7, 8]
    assert batch_seeds(None, 2) == [None, None] and batch_seeds((3, None), 2) == [3, None]


@pytest.fixture(scope="module")
def batch() -> BatchedLeftTurnBatch:
    return BatchedLeftTurnBatch({"name": "left_turn", "duration": 1.0}, {"turn_features": {}}, None, N, pool=0)


def test_step_before_reset_is_reset_needed() -> None:
    fresh = BatchedLeftTurnBatch({"name": "left_turn"}, {"turn_features": {}}, None, N, pool=0)
    with pytest.raises(gym.error.ResetNeeded) as err:
        fresh.step(np.zeros(N, int))
    assert "before calling reset()" in _one_line(err)


@pytest.mark.parametrize("actions", [np.full(N, 5), np.full(N, -1), np.full(N, np.nan), np.full(N, 1e9),
                                     np.zeros(N - 1, int)])
def test_the_batch_refuses_actions_outside_its_space(batch, actions) -> None:
    """5, -1, NaN and 1e9 drove like a valid action; a wrong shape was numpy's reshape error."""
    batch.reset()
    with pytest.raises(InvalidAction):
        batch.step(actions)
    batch.step(np.array([0, 1, 2, 1]))  # a refused step changed nothing: the batch goes on


@pytest.mark.parametrize("seed", ["x", -1, [1, 2]])
def test_the_batch_refuses_bad_seeds(batch, seed) -> None:
    """``reset(seed="x")`` was int()'s ValueError, -1 Gymnasium's seeding error from inside the engine, and a
    short list was taken (the envs past its end went on unseeded)."""
    with pytest.raises(ConfigError):
        batch.seed(seed)


@pytest.mark.parametrize("seeds,says", [(["x"], "seeds[0] must be a non-negative integer, got 'x'"),
                                        ([3, -1], "seeds[1] must be a non-negative integer, got -1")])
def test_the_batch_plays_only_seeds(batch, seeds, says) -> None:
    """The evaluation's seeded queue: int("x") was a bare ValueError, -1 Gymnasium's seeding error."""
    with pytest.raises(ConfigError) as err:
        batch.play(seeds)
    assert says in _one_line(err)


def test_vector_env_checks_too() -> None:
    venv = gym.make_vec("av_gym/UnprotectedLeftTurn-v0", num_envs=N, sensors="turn_truth", env={"duration": 1.0})
    with pytest.raises(gym.error.ResetNeeded):
        venv.step(np.zeros(N, int))
    with pytest.raises(ConfigError, match="seed must be a non-negative integer"):
        venv.reset(seed="x")
    obs, _ = venv.reset(seed=[0, 1, 2, 3])
    with pytest.raises(InvalidAction, match="not in the action space Discrete"):
        venv.step(np.full(N, 3))
    assert venv.observation_space.contains(venv.step(venv.action_space.sample())[0])


def test_continuous_batch_refuses_out_of_bounds() -> None:
    cont = BatchedLeftTurnBatch({"name": "left_turn", "action": "continuous", "duration": 1.0},
                                {"turn_features": {}}, None, N, pool=0)
    cont.seed(0)
    cont.reset()
    with pytest.raises(InvalidAction, match="out of bounds"):
        cont.step(np.full((N, 1), 1.5))
    cont.step(np.zeros((N, 1), np.float32))


def test_sb3_adapter_importable_from_the_library() -> None:
    """``from av_gym_sb3 import BatchedLeftTurnVecEnv``, the harness's old path the same class, and it checks."""
    from stable_baselines3.common.vec_env import VecEnv

    import agents.batched_vec_env
    from av_gym_sb3 import BatchedLeftTurnVecEnv

    assert agents.batched_vec_env.BatchedLeftTurnVecEnv is BatchedLeftTurnVecEnv
    venv = BatchedLeftTurnVecEnv({"name": "left_turn", "duration": 1.0}, {"turn_features": {}}, None, N, pool=0)
    assert isinstance(venv, VecEnv)
    with pytest.raises(gym.error.ResetNeeded):
        venv.step(np.zeros(N, int))
    venv.seed(0)
    venv.reset()
    with pytest.raises(InvalidAction):
        venv.step(np.full(N, 7))
