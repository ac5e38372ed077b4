"""The AEB shield's second opinion (``shield.second_opinion``, :attr:`av_gym.shields.aeb.AEBShield.opinion`):
before a brake at the stop line the shield asks whether going on is safe and withholds the brake when it is;
emergency brakes are never asked about. The harness installs the belief planner (eval.agents.make_eval_env)."""

from __future__ import annotations

import pytest

from agents.belief import PlannerOpinion
from av_gym.errors import ConfigError
from av_gym.shields.aeb import find_shield
from conftest import ccftap_cfg, conf, proceed_infos
from eval.agents import compose_group, make_eval_env


class Fixed:
    """An opinion with a fixed answer, counting what it is shown and asked."""

    def __init__(self, safe: bool) -> None:
        self.safe, self.observed, self.asked, self.resets = safe, 0, 0, 0

    def reset(self) -> None:
        self.resets += 1

    def observe(self, env, obs) -> None:
        self.observed += 1

    def go_is_safe(self, env) -> bool:
        self.asked += 1
        return self.safe


def shielded(opinion=None, sensors=None, shield="aeb"):
    """The paper's case (ego 15 km/h, oncoming 45 km/h, meeting in the middle), where the plain shield stops the
    ego behind the line and no shield collides (tests/test_aeb.py)."""
    from av_gym.make import make_env

    env = make_env(ccftap_cfg(15, 45, 0.0), compose_group("sensors", sensors) if sensors else None, conf("shield", shield))
    find_shield(env).opinion = opinion
    return env


def test_an_opinion_that_never_finds_going_on_safe_changes_nothing():
    plain = proceed_infos(shielded())
    asked = Fixed(safe=False)
    infos = proceed_infos(shielded(asked))
    assert [i["aeb_stage"] for i in infos] == [i["aeb_stage"] for i in plain]
    assert asked.resets == 1 and asked.observed == len(infos) + 1  # the reset's observation and every step's
    assert asked.asked >= 1 and infos[-1]["aeb_withheld"] == 0
    assert not infos[-1]["episode_metrics"]["collision"]


def test_a_withheld_stop_line_brake_leaves_only_the_emergency_brake():
    """With every stop-line brake withheld the ego enters the box; what brakes it there, if anything, is the
    emergency test, never a brake before the line."""
    plain = proceed_infos(shielded())
    first_plain = next(i for i in plain if i["aeb_stage"] == 2)
    assert first_plain["truth"]["stop_line_offset"] <= 0.0  # the plain shield brakes before the line
    yes = Fixed(safe=True)
    env = shielded(yes)
    infos = proceed_infos(env)
    assert yes.asked >= 1 and infos[-1]["aeb_withheld"] == yes.asked
    braked = [i for i in infos if i["aeb_stage"] == 2]
    assert all(i["truth"]["stop_line_offset"] > 0.0 for i in braked[:1])  # the first brake: inside the box
    assert braked == [] or braked[0]["aeb_ttc"] <= find_shield(env).ttc_brake + 1e-9  # an emergency brake


def test_the_planner_keeps_a_needed_brake():
    """The belief planner, asked at the stop line with the oncoming car 1.5 s from the meeting point, does not
    find going on safe: the ego stops behind the line as with the plain shield, with no collision."""
    env = make_eval_env(ccftap_cfg(15, 45, 0.0), compose_group("sensors", "turn_truth"), conf("shield", "aeb_belief"))
    opinion = find_shield(env).opinion
    assert isinstance(opinion, PlannerOpinion)
    infos = proceed_infos(env)
    m = infos[-1]["episode_metrics"]
    assert opinion.asked >= 1 and infos[-1]["aeb_withheld"] == 0
    assert not m["collision"] and m["intervention"] == 1.0 and -1.0 < infos[-1]["aeb_stop_position"] <= 0.0


def test_a_shield_asking_for_an_opinion_nobody_installed_says_so():
    with pytest.raises(ConfigError, match=r"shield.second_opinion='belief_lookahead' is the harness's planner and "
                                          r"none is installed"):
        shielded(None, "turn_truth", "aeb_belief").reset(seed=0)


def test_the_planner_needs_the_turn_features():
    env = make_eval_env(ccftap_cfg(15, 45, 0.0), None, conf("shield", "aeb_belief"))
    with pytest.raises(ConfigError, match=r"reads obs\['intent'\]; run the agent with sensors turn_truth"):
        env.reset(seed=0)


def test_a_bad_second_opinion_is_one_line_naming_the_field():
    # the names are the harness's (agents.registry.OPINIONS): it refuses one it cannot install
    with pytest.raises(ConfigError, match=r"second_opinion.*'none'.*'belief_lookahead'"):
        make_eval_env(ccftap_cfg(15, 45, 0.0), None, {**conf("shield", "aeb"), "second_opinion": "oracle"})
