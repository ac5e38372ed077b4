"""``EpisodeMetrics`` wrapper: turns each step's ``info["truth"]`` into one summary row per episode.

Outermost wrapper by design (see ``av_gym.make``), so the metrics always come from ground truth, whatever the
sensors and shield did to observations and actions."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from av_gym.metrics.lane_keeping import lane_keeping_summary
from av_gym.metrics.left_turn import left_turn_summary

TRACES = {
    "lane_keeping": ("cte", "steering", "progress"),
    "left_turn": ("time", "speed", "collision", "arrived", "ttc", "stop_line_offset", "oncoming_gap"),
}


class EpisodeMetrics(gym.Wrapper):
    """Adds ``info["episode_metrics"]`` (a flat dict of floats, see :mod:`av_gym.metrics`) on the step that ends an
    episode, plus ``return`` and ``length`` (policy steps), ``override_fraction`` (share of steps whose action a
    safety shield overrode, ``info["shield_override"]``), ``intervention`` (1 if it overrode at least once),
    ``interventions`` (how many times an override started: a brake held for 2 s counts once),
    ``first_override_s`` (time of the first override, NaN if none) and ``sensor_faults`` (the non-finite entries the
    sensors' guard replaced this episode, ``info["sensor_faults"]`` summed over sensors and steps, the first
    reading at reset included: 0 when every reading was finite)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.scenario = env.unwrapped.scenario
        if self.scenario not in TRACES:
            raise ValueError(f"no metrics defined for scenario {self.scenario!r}; known: {sorted(TRACES)}")
        self._traces: dict[str, list] = {}

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._traces = {k: [] for k in TRACES[self.scenario]}
        self._return, self._length, self._overrides, self._onsets, self._overriding = 0.0, 0, 0, 0, False
        self._first_override = float("nan")
        self._faults = _faults(info)
        self._last_truth = info["truth"]
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        truth = info["truth"]
        for key, trace in self._traces.items():
            trace.append(truth[key])
        self._return += float(reward)
        self._length += 1
        self._faults += _faults(info)
        overridden = bool(info.get("shield_override", False))
        self._overrides += int(overridden)
        self._onsets += int(overridden and not self._overriding)
        self._overriding = overridden
        if overridden and self._first_override != self._first_override:
            self._first_override = float(truth.get("time", self._length))
        self._last_truth = truth
        if terminated or truncated:
            info["episode_metrics"] = self.summary(truncated=truncated)
        return obs, reward, terminated, truncated, info

    def summary(self, truncated: bool = False) -> dict[str, float]:
        """Metrics of the episode so far (the wrapper calls it when the episode ends)."""
        tr = {k: np.asarray(v) for k, v in self._traces.items()}
        last = self._last_truth
        if self.scenario == "lane_keeping":
            row = lane_keeping_summary(tr["cte"], tr["steering"], tr["progress"], lane_width=last["lane_width"],
                                       vehicle_width=last["vehicle_width"], lap_length=last["lap_length"],
                                       lap_completed=last["lap_completed"])
        else:
            row = left_turn_summary(tr["time"], tr["speed"], tr["collision"], tr["arrived"], tr["ttc"],
                                    tr["stop_line_offset"], tr["oncoming_gap"])
        row.update({"return": self._return, "length": float(self._length), "truncated": float(truncated),
                    "override_fraction": self._overrides / max(1, self._length),
                    "intervention": float(self._overrides > 0), "interventions": float(self._onsets),
                    "first_override_s": self._first_override, "sensor_faults": float(self._faults)})
        return row


def _faults(info: dict) -> int:
    """The non-finite entries the sensors replaced in this step's readings (``info["sensor_faults"]``: per sensor
    key, av_gym/sensors/base.py)."""
    return int(sum((info.get("sensor_faults") or {}).values()))
