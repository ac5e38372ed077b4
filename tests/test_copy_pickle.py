"""Every shipped sensor stack deep-copies and pickles, and a copy goes on exactly as the original
(async vector envs pickle, the lookahead teacher deep-copies envs)."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest

from av_gym.make import make_env
from eval.agents import compose_group
from tests.conftest import conf

# every preset in conf/sensors/, on the scenario it is made for (the turn_* presets are left-turn only, the lane_*
# ones lane-keeping only); "localized" on both, since its kiss-icp odometry is the part that did not pickle
PRESETS = [("lane_keeping", p) for p in ("truth", "gnss_raw", "gnss_imu", "lidar", "camera_centre", "cameras",
                                         "detector", "full", "localized", "lane_localized")] + \
          [("left_turn", p) for p in ("truth", "turn_truth", "turn_perceived", "localized")]


def _action(env, k: int):
    space = env.action_space
    return k % space.n if hasattr(space, "n") else np.full(space.shape, 0.1 * ((k % 3) - 1), space.dtype)


def _same(a, b) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _same(a[k], b[k])
    else:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("scenario,preset", PRESETS, ids=[f"{s}-{p}" for s, p in PRESETS])
def test_stack_copies_and_pickles(scenario: str, preset: str) -> None:
    env = make_env(conf("env", scenario), compose_group("sensors", preset), None)
    env.reset(seed=3)
    for k in range(12):  # far enough for the odometry to hold a local map and its adaptive threshold to move
        env.step(_action(env, k))
    copies = [copy.deepcopy(env), pickle.loads(pickle.dumps(env))]
    for k in range(12, 17):
        step = env.step(_action(env, k))
        for twin in copies:
            twin_step = twin.step(_action(env, k))
            _same(step[0], twin_step[0])  # the same observation, sensor noise and estimates included
            assert step[1:4] == twin_step[1:4]
