"""Counterfactual intervention labels (eval/interventions.py) and the road-network partner types
(av_gym/shields/conflicts.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from agents import AlwaysProceed
from av_gym.envs.left_turn import ROUTE
from av_gym.shields.conflicts import approach_of, partner_type
from conftest import ccftap_cfg, conf
from eval.interventions import labelled_episode, main


def _aeb():
    return conf("shield", "aeb")


def _labelled(make, ego_kmh, target_kmh, dt):
    env = make(ccftap_cfg(ego_kmh, target_kmh, dt), None, _aeb())
    return labelled_episode(env, AlwaysProceed(env.unwrapped.cruise_action()), seed=0)


def test_brake_against_a_turn_across_path_collision_is_needed(make):
    # 15/45 km/h, dt = 0: without a shield the two meet in the middle (docs/shield.md: a collision)
    metrics, rows = _labelled(make, 15, 45, 0.0)
    assert metrics["collision"] == 0.0
    assert len(rows) == 1
    row = rows[0]
    assert row["needed"] and row["cf_collision"]
    assert row["target"] == "oncoming" and row["cf_partner"] == "oncoming"
    assert 0.0 < row["cf_collision_after_s"] < 8.0


def test_brake_that_the_driver_did_not_need_is_unneeded(make):
    # 10/30 km/h, dt = +2 s: the shield brakes, but the case clears by 0.2 m without it (docs/shield.md)
    metrics, rows = _labelled(make, 10, 30, 2.0)
    assert rows, "the shield brakes in this case"
    assert not any(r["needed"] for r in rows)
    assert all(not r["cf_collision"] and np.isnan(r["cf_collision_after_s"]) for r in rows)


def test_labelling_leaves_the_real_episode_unchanged(make, turn_cfg):
    # the counterfactual copies draw from their own generators: the labelled episode is the plain one
    env = make(turn_cfg, None, _aeb())
    policy = AlwaysProceed(env.unwrapped.cruise_action())
    labelled, rows = labelled_episode(env, policy, seed=1003)
    obs, _ = env.reset(seed=1003)
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(policy.act(obs))
        done = term or trunc
    assert (labelled.pop("collision_partner") != "") == bool(labelled["collision"])
    assert labelled.pop("withheld") == 0  # no second opinion on the plain shield
    np.testing.assert_equal(info["episode_metrics"], labelled)  # NaN == NaN here
    assert len(rows) == labelled["interventions"]


def test_no_shield_is_refused(make, turn_cfg):
    env = make(turn_cfg, None, None)
    with pytest.raises(ValueError, match="AEB shield"):
        labelled_episode(env, AlwaysProceed(env.unwrapped.cruise_action()), seed=0)


def _vehicle(lane, route=None, position=(0.0, 0.0)):
    return SimpleNamespace(lane_index=lane, route=route, position=np.array(position, dtype=float))


def test_partner_type_from_the_road_network(make, turn_cfg):
    env = make(turn_cfg, None, None)
    env.reset(seed=0)
    u = env.unwrapped
    net, starts = u.road.network, u.route.starts
    ego_s = float(starts[1]) - 5.0  # 5 m before the stop line
    pt = lambda v: partner_type(v, net, ROUTE, starts, ego_s)  # noqa: E731
    approach = net.get_lane(ROUTE[0])
    assert approach_of(ROUTE[0]) == 0 and approach_of(("il1", "o1", 0)) is None
    # on the ego's own approach, in front of it / behind it
    assert pt(_vehicle(ROUTE[0], position=approach.position(approach.length - 1.0, 0))) == "ahead"
    assert pt(_vehicle(ROUTE[0], position=approach.position(1.0, 0))) == "behind"
    # oncoming (from approach 2) going straight; turning right into the ego's exit is merging
    assert pt(_vehicle(("o2", "ir2", 0), [("o2", "ir2", 0), ("ir2", "il0", 0), ("il0", "o0", 0)])) == "oncoming"
    assert pt(_vehicle(("o2", "ir2", 0), [("o2", "ir2", 0), ("ir2", "il1", 0), ("il1", "o1", 0)])) == "merging"
    # from the east going straight ends on the ego's exit: merging; from the west going straight: crossing
    assert pt(_vehicle(("o3", "ir3", 0), [("o3", "ir3", 0), ("ir3", "il1", 0), ("il1", "o1", 0)])) == "merging"
    assert pt(_vehicle(("ir1", "il3", 0), [("o1", "ir1", 0), ("ir1", "il3", 0), ("il3", "o3", 0)])) == "crossing"
    # no route (a CCFtap target): its lane alone
    assert pt(_vehicle(("o2", "ir2", 0))) == "oncoming"


def test_cli_writes_the_tables(tmp_path):
    assert main(["--agents", "always_proceed+aeb", "--episodes", "2", "--seed", "1000000", "--out",
                 str(tmp_path)]) == 0
    text = (tmp_path / "interventions.md").read_text()
    assert "needed" in text and "unneeded_share" in text
    assert (tmp_path / "episodes.csv").read_text().count("\n") == 3
