"""The Python API validates like the command line and the registered ids build the
harness's stacks in one call."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.error import ResetNeeded

import av_gym  # noqa: F401 - registers the ids
from av_gym.actions import InvalidAction
from av_gym.errors import ConfigError
from av_gym.make import make_env, make_training_env
from tests.conftest import conf

TURN, LANE = "av_gym/UnprotectedLeftTurn-v0", "av_gym/LaneKeepingLap-v0"


# ----------------------------------------------------------------------------------------------- rows 1 and 14
@pytest.mark.parametrize("env_id,config,shield,action,says", [
    (TURN, {"action": {"type": "continuous"}}, "aeb", [np.nan], "not finite"),  # segfaulted in the shield
    (TURN, {"action": {"type": "continuous"}}, "aeb", [np.inf], "not finite"),
    (TURN, {"action": {"type": "continuous"}}, None, [np.nan], "not finite"),
    (TURN, {"action": {"type": "continuous"}}, "aeb", [0.1, 0.2], "expected shape (1,), got (2,)"),
    (TURN, {"action": {"type": "continuous"}}, None, [3.0], "out of bounds"),
    (TURN, None, None, 3, "expected an integer in [0, 2]"),
    (TURN, None, "aeb", -1, "expected an integer in [0, 2]"),
    (TURN, None, None, 10**9, "expected an integer in [0, 2]"),
    (TURN, None, None, None, "got NoneType"),
    (TURN, None, "aeb", np.nan, "got float"),
    (LANE, None, None, [0.1, 0.2], "expected shape (1,), got (2,)"),
    (LANE, None, None, 0.1, "expected shape (1,), got ()"),
    (LANE, None, None, [], "expected shape (1,), got (0,)"),
])
def test_bad_action_is_one_line_before_the_simulation(env_id, config, shield, action, says) -> None:
    env = gym.make(env_id, config=config, shield=shield) if shield else gym.make(env_id, config=config)
    env.reset(seed=0)
    time = env.unwrapped.time
    with pytest.raises(InvalidAction) as err:
        env.step(action)
    message = str(err.value)
    assert "\n" not in message and says in message and "action space" in message
    assert isinstance(err.value, ValueError)
    assert env.unwrapped.time == time  # nothing simulated
    env.step(env.action_space.sample())  # and the env goes on


def test_go_yield_actions_are_checked_too() -> None:
    env = gym.make(TURN, checkpoint="checkpoints/reference/ppo_turn")  # go/yield on top of the turn's actions
    env.reset(seed=0)
    for bad in (np.nan, 2, None):
        with pytest.raises(InvalidAction, match=r"Discrete\(2\)"):
            env.step(bad)


def test_good_actions_of_every_usual_type_are_taken() -> None:
    env = gym.make(TURN)
    env.reset(seed=0)
    for action in (1, np.int64(2), np.array(0)):
        env.step(action)
    lane = gym.make(LANE)
    lane.reset(seed=0)
    for action in ([0.1], np.array([-1.0]), np.array([0.5], dtype=np.float32), (0.0,)):
        lane.step(action)


# ----------------------------------------------------------------------------------------------- row 15
@pytest.mark.parametrize("kwargs,says", [
    ({"config": {"spawn_prob": 0.3}}, "config.spawn_prob is not a setting of left_turn (did you mean "
                                      "'spawn_probability'?)"),
    ({"config": {"duration": -5}}, "config.duration must be a number in (0, 600], got -5"),
    ({"config": {"duration": "long"}}, "config.duration must be a number in (0, 600], got 'long'"),
    ({"config": {"policy_frequency": 0}}, "config.policy_frequency must be an integer in [10, 1000], got 0"),
    ({"config": {"simulation_frequency": 0}}, "config.simulation_frequency must be an integer in [1, 1000], got 0"),
    ({"config": {"action": {"type": "bogus"}}}, "config.action.type must be one of ['discrete', 'continuous']"),
    ({"config": {"fast": 1}}, "config.fast must be true or false, got 1"),
    ({"render_mode": "hologram"}, "render_mode must be one of ['human', 'rgb_array'] or None, got 'hologram'"),
    ({"env": {"duration": 0}}, "env.duration must be a number in (0, 600], got 0"),
    ({"config": {"duration": 1e9}}, "config.duration must be a number in (0, 600], got 1000000000.0"),
    ({"sensors": "nope"}, "sensors 'nope' is not in conf/sensors/"),
    ({"shield": {"name": "aeb", "ttc_brak": 1.0}}, "shield.ttc_brak is not a parameter"),
])
def test_bad_config_is_one_line(kwargs, says) -> None:
    with pytest.raises(ConfigError) as err:
        gym.make(TURN, **kwargs)
    assert says in str(err.value) and "\n" not in str(err.value)


def test_partial_action_config_keeps_the_defaults() -> None:
    env = gym.make(TURN, config={"action": {"type": "continuous"}})  # was a KeyError (acceleration_range)
    env.reset(seed=0)
    assert env.action_space.shape == (1,)
    assert env.unwrapped.config["action"]["acceleration_range"] == [-8.0, 3.0]
    env.step([0.0])


# ----------------------------------------------------------------------------------------------- row 16
@pytest.mark.parametrize("env_id", [TURN, LANE])
def test_step_after_the_end_needs_reset(env_id) -> None:
    env = gym.make(env_id, config={"duration": 1.0} if env_id == TURN else {"time_limit": 1.0})
    env.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        done = terminated or truncated
    with pytest.raises(ResetNeeded, match=r"call reset\(\)"):
        env.step(env.action_space.sample())
    env.reset(seed=1)
    env.step(env.action_space.sample())


# ----------------------------------------------------------------------------------------------------- stacks
def _run(env, seed: int, steps: int, actions) -> list:
    out = [env.reset(seed=seed)[0]]
    for a in actions[:steps]:
        out.append(env.step(a)[0])
    return out


def _equal(a, b) -> None:
    for x, y in zip(a, b):
        assert x.keys() == y.keys()
        for k in x:
            np.testing.assert_array_equal(x[k], y[k])


def test_gym_make_builds_the_harness_stack() -> None:
    """gym.make(id, sensors=, shield=, env=) is make_env with the composed presets: the same observations."""
    from conf.presets import compose_group

    sensors = compose_group("sensors", "turn_perceived")
    sensors["detector"]["miss_rate"] = 0.3
    env_cfg = {**conf("env", "left_turn"), "spawn_probability": 0.9}
    ours = gym.make(TURN, sensors={"name": "turn_perceived", "detector": {"miss_rate": 0.3}}, shield="aeb",
                    env={"spawn_probability": 0.9})
    theirs = make_env(env_cfg, sensors, compose_group("shield", "aeb"))
    assert ours.observation_space == theirs.observation_space
    actions = [2] * 15
    _equal(_run(ours, 7, 15, actions), _run(theirs, 7, 15, actions))


def test_checkpoint_env_is_the_one_it_was_trained_on() -> None:
    import yaml

    folder = "checkpoints/reference/ppo_turn"
    cfg = yaml.safe_load(open(f"{folder}/config.yaml"))
    ours = gym.make(TURN, checkpoint=folder)
    theirs = make_training_env(cfg["env"], cfg["sensors"], cfg["shield"], 0.0, cfg["agent"]["action_repeat"],
                               cfg["agent"]["actions"])
    assert ours.action_space == gym.spaces.Discrete(2)  # go / yield
    _equal(_run(ours, 3, 8, [1] * 8), _run(theirs, 3, 8, [1] * 8))
    with pytest.raises(ConfigError, match="trained on env=left_turn"):
        gym.make(LANE, checkpoint=folder)
