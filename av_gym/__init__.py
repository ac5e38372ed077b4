"""av-gym: Gymnasium scenarios, sensor-noise wrappers and metrics for autonomous-driving research."""

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

ENV_IDS = {
    "lane_keeping": "av_gym/LaneKeepingLap-v0",
    "left_turn": "av_gym/UnprotectedLeftTurn-v0",
}

if ENV_IDS["lane_keeping"] not in registry:
    register(id=ENV_IDS["lane_keeping"], entry_point="av_gym.envs.lane_keeping:LaneKeepingLapEnv")
if ENV_IDS["left_turn"] not in registry:
    register(id=ENV_IDS["left_turn"], entry_point="av_gym.envs.left_turn:UnprotectedLeftTurnEnv")
