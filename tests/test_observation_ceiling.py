"""train/observation_ceiling.py: the episodes of an aggregate, the held-out split and the two estimates of the
observation's own ceiling, on constructed cases whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.errors import ConfigError
from train.observation_ceiling import episode_ids, holdout_mask, neighbour_errors, twin_disagreement


def test_an_episode_starts_wherever_the_elapsed_time_does_not_grow():
    elapsed = [0.0, 0.025, 0.05, 0.0, 0.025, 0.0, 0.0, 1.0, 1.0]
    assert episode_ids(elapsed).tolist() == [0, 0, 0, 1, 1, 2, 3, 3, 4]


def test_the_held_out_share_is_of_whole_episodes_and_drawn_from_its_seed():
    episodes = np.repeat(np.arange(50), 7)
    mask = holdout_mask(episodes, 0.1, seed=3)
    held = np.unique(episodes[mask])
    assert len(held) == 5 and mask.sum() == 35  # whole episodes, none split
    assert np.array_equal(mask, holdout_mask(episodes, 0.1, seed=3))
    assert not np.array_equal(mask, holdout_mask(episodes, 0.1, seed=4))
    assert not holdout_mask(episodes, 0.0, seed=3).any()
    with pytest.raises(ConfigError, match="--holdout"):
        holdout_mask(episodes, 1.0, seed=3)


def test_twins_are_states_of_other_episodes_in_the_same_cell():
    """One cell: episode 0 holds two GO states, episode 1 one YIELD state; another cell holds two states of one
    episode with different labels (no twins: one moment's neighbour is not another observation of it)."""
    x = np.array([[0.0, 0.0], [0.001, 0.0], [0.0, 0.002], [5.0, 5.0], [5.0, 5.001]])
    labels = np.array([1, 1, 0, 1, 0])
    episodes = np.array([0, 0, 1, 2, 2])
    row = twin_disagreement(x, labels, episodes, resolution=0.01)
    # each GO state's one twin is the YIELD, the YIELD's two twins are GO: every twin disagrees
    assert row["D"] == 1.0 and row["states_with_twins"] == pytest.approx(3 / 5) and row["cells"] == 1
    assert row["minority_plugin"] == pytest.approx(1 / 3)
    agree = twin_disagreement(x, np.array([1, 1, 1, 1, 0]), episodes, resolution=0.01)
    assert agree["D"] == 0.0


def test_twin_disagreement_brackets_the_bayes_error_of_known_label_probabilities():
    """Cells of 6 states from 6 episodes, each labelled GO with the cell's own probability q: D estimates
    E[2q(1-q)] and [D/2, D] holds the Bayes error E[min(q, 1-q)]."""
    rng = np.random.default_rng(0)
    cells, per = 4000, 6
    q = rng.choice([0.0, 0.05, 0.3, 0.5, 0.9, 1.0], size=cells)
    x = np.repeat(np.arange(cells, dtype=float), per)[:, None] * np.array([[1.0, -1.0]])
    labels = (rng.random(cells * per) < np.repeat(q, per)).astype(int)
    episodes = np.arange(cells * per)
    row = twin_disagreement(x, labels, episodes, resolution=0.1)
    assert row["D"] == pytest.approx(np.mean(2 * q * (1 - q)), abs=0.01)
    bayes = np.mean(np.minimum(q, 1 - q))
    assert row["bayes_low"] <= bayes <= row["bayes_high"]
    assert row["minority_plugin"] < bayes  # the plug-in on small cells is biased low


def test_nearest_neighbours_recover_a_known_label_noise_and_skip_their_own_episode():
    """Two far clusters labelled by cluster, each label flipped with probability 0.1: the Bayes error is 0.1;
    1-NN errs on ~2·0.1·0.9 = 0.18 and the Cover-Hart bracket's low end from it is 0.1; 25 neighbours vote it to ~0.1."""
    rng = np.random.default_rng(1)
    n = 4000
    side = rng.integers(0, 2, n)
    x = rng.normal(size=(n, 3)) + 20.0 * side[:, None]
    labels = np.where(rng.random(n) < 0.1, 1 - side, side)
    out = neighbour_errors(x, labels, np.arange(n), [1, 25], queries=1500, seed=0)
    assert out["error"]["1"] == pytest.approx(0.18, abs=0.03)
    assert out["error"]["25"] == pytest.approx(0.10, abs=0.025)
    low, high = out["cover_hart"]  # equal noise everywhere: 1-NN's 2R(1-R) is the bound's own case, tight at R
    assert low == pytest.approx(0.1, abs=0.015) and high > 0.1
    # two states of one episode side by side with different labels, one state of another episode 1.0 from
    # each's side: each takes the other episode's label (right); its own episode's twin would be wrong for both
    x2 = np.array([[0.0], [0.01], [-1.0], [1.01]])
    own = neighbour_errors(x2, np.array([0, 1, 0, 1]), np.array([0, 0, 1, 2]), [1], queries=4, seed=0)
    assert own["error"]["1"] == 0.0
