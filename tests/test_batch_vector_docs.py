"""What docs/performance.md ("Using the batch from your own code") says of ``gymnasium.make_vec``'s batch against
``vectorization_mode="sync"`` (prober R7, finding 5: no page said it): the batch autoresets in the same step, sync
in the next; the first episodes are the seeds' own, later ones are the pool's, not sync's; its info has no per-step
keys (no ``truth``)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import av_gym  # noqa: F401  (registers the ids)

ID = "av_gym/UnprotectedLeftTurn-v0"


def _first_observations(venv, same_step: bool, steps: int) -> list[dict]:
    """Env 0's first observation of each episode after the first, stepping IDLE: the step its episode ends
    (same step) or the step after it (next step)."""
    firsts, ended = [], False
    for _ in range(steps):
        obs, _, terminated, truncated, info = venv.step(np.array([1, 1]))
        assert "truth" not in info or not same_step, sorted(info)
        if (same_step and (terminated | truncated)[0]) or (not same_step and ended):
            firsts.append({k: v[0].copy() for k, v in obs.items()})
        ended = bool((terminated | truncated)[0])
    return firsts


@pytest.mark.slow  # 2-3 s at load 3-4: two vector envs built and 42 steps of the per-env stacks
def test_the_batch_autoresets_in_the_same_step_and_plays_pool_episodes_after_the_first():
    kw = {"num_envs": 2, "sensors": "turn_truth", "env": {"duration": 2}}  # 2 s episodes: 20 steps each
    batch, sync = gym.make_vec(ID, **kw), gym.make_vec(ID, vectorization_mode="sync", **kw)
    assert batch.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert sync.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    obs_b, info_b = batch.reset(seed=[7, 8])
    obs_s, info_s = sync.reset(seed=[7, 8])
    assert info_b == {} and "truth" in info_s  # the ground truth is the per-env stack's
    for key in obs_b:  # the first episodes: each seed's own, as on the per-env stack
        np.testing.assert_allclose(obs_b[key], obs_s[key], rtol=0, atol=1e-6)
    later_b, later_s = _first_observations(batch, True, 42), _first_observations(sync, False, 42)
    assert len(later_b) >= 2 and len(later_s) >= 2
    for b, s in zip(later_b, later_s):  # from the second on: a pool stream's episode, not env 0's generator's
        assert not np.allclose(b["turn"], s["turn"])
    sync.close()
