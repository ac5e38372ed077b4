"""Seed splits (av_gym/seeds.py): disjoint ranges, and every tool draws from the split its use allows."""

from __future__ import annotations

import pytest

from av_gym.errors import ConfigError
from av_gym.seeds import SPLITS, config_seeds, seeds, split_of, train_seed


def test_splits_are_disjoint_and_contiguous():
    ranges = list(SPLITS.values())
    for i, a in enumerate(ranges):
        for b in ranges[i + 1:]:
            assert not set(range(max(a.start, b.start), min(a.stop, b.stop)))  # no common seed
    assert [split_of(r.start) for r in ranges] == list(SPLITS)
    assert [split_of(r.stop - 1) for r in ranges] == list(SPLITS)


def test_a_seed_range_leaving_its_split_is_refused():
    test = SPLITS["test"]
    assert seeds("test", 3) == range(test.start, test.start + 3)
    with pytest.raises(ValueError, match="leaves split 'test'"):
        seeds("test", 10, first=SPLITS["validation"].stop - 5)  # starts in validation
    with pytest.raises(ValueError, match="leaves split 'validation'"):
        seeds("validation", 10, first=SPLITS["validation"].stop - 5)  # runs into test
    with pytest.raises(ConfigError, match="train.eval_seed="):
        config_seeds("validation", 1, test.start, "train.eval_seed")
    with pytest.raises(ValueError, match="split must be one of"):
        seeds("holdout", 1)


@pytest.mark.parametrize("base,offset", [(0, 0), (3, 122_880), (999_999, 1), (10**9, 5 * 10**6)])
def test_training_streams_stay_in_the_train_split(base, offset):
    """PPO seeds its env streams with seed + steps done (a resume): any seed, any run length stays in train."""
    assert split_of(train_seed(base, offset)) == "train"


def _train_options(**train):
    from conf.commands import TrainOptions

    return TrainOptions(**{"eval_seed": None, "eval_episodes": 100, "eval_n": 30, **train})


def test_training_evaluations_draw_from_validation():
    """The periodic evaluation (best.zip) and the brief one after training: validation, never test."""
    from train.__main__ import validation_seeds

    assert split_of(validation_seeds(_train_options(), 100).start) == "validation"
    assert split_of(validation_seeds(_train_options(), 100)[-1]) == "validation"
    with pytest.raises(ConfigError, match="train.eval_seed"):
        validation_seeds(_train_options(eval_seed=SPLITS["test"].start), 30)


def test_eval_defaults_to_validation_and_reports_the_split():
    from eval.__main__ import episode_seeds

    from conf.commands import EvalCommand

    assert episode_seeds(EvalCommand(split="validation", seed=None, episodes=20)) == seeds("validation", 20)
    with pytest.raises(ConfigError, match="leaves split 'validation'"):
        episode_seeds(EvalCommand(split="validation", seed=1000, episodes=20))  # the old default


def test_demonstrations_and_pid_search_draw_from_train(monkeypatch):
    from types import SimpleNamespace

    from train import pid_search, ppo

    drawn = []

    class Drawn(Exception):
        pass

    def pretrain(model, env, teacher, seeds, *args):  # what cloning would drive the teacher on
        drawn.extend(seeds)
        raise Drawn

    monkeypatch.setattr(ppo, "pretrain_from_teacher", pretrain)
    params = SimpleNamespace(init="gap_acceptance", actions="go_yield", action_repeat=5, vec_env="subproc",
                             init_episodes=40, gamma=0.99, init_epochs=1, batch_size=8, init_action_noise=0.0,
                             init_dagger_rounds=0, init_lr=None, learning_rate=1e-3)
    stack = SimpleNamespace(params=params, one=lambda **_: SimpleNamespace(close=lambda: None))  # the demo env
    with pytest.raises(Drawn):
        ppo.clone_teacher(None, stack, "left_turn")
    assert len(drawn) == 40 and {split_of(s) for s in drawn} == {"train"}
    with pytest.raises(ValueError, match="train split"):
        pid_search.search(pid_search.GRIDS["quick"], [SPLITS["test"].start])
    assert pid_search.TRAIN_SEEDS == SPLITS["train"]
