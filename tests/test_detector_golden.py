"""The per-env detector's own numbers pinned (av_gym/sensors/detector.py ``Detector``): a few seeded left-turn drives,
their frames as the detector gave them before its frame arithmetic was shared with the batch's detector (a clean
archive of ce06def). Both stacks now run ``frame_draws`` / ``assemble_frames``, so the comparisons of one stack with
the other cannot see a change to those; this can (a reordered draw, another noise scale, another sort)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import av_gym  # noqa: F401
from av_gym.sensors.detector import Detector

TURN = "av_gym/UnprotectedLeftTurn-v0"
STEPS = (3, 6, 9)
"""The steps (of IDLE from reset) whose frames are pinned."""

# per drive, per step of STEPS: the rows present, each row's truth id (-1: clutter) and [x, y, vx, vy] (m, m/s,
# float32 as the observation holds them)
GOLDEN = {
    "default": [
        (4, [-1, 4, 3, 5], [[7.533581, 1.792062, 0.0, 0.0], [7.362405, -2.451527, -8.027882, -3.681569],
                            [-17.274786, 1.1939421, 8.332402, 0.020573452],
                            [42.397316, -1.7409502, -7.423787, -0.119887225]]),
        (4, [3, 4, 2, 5], [[-16.21156, 2.2190025, 7.8706546, 0.86429816],
                           [6.920874, -4.6798716, -7.7365785, -4.4088173],
                           [-39.11477, 1.8341374, 6.9547157, 0.1142619],
                           [40.94457, -1.6429007, -6.8864784, 0.121239364]]),
        (3, [3, 4, 2], [[-12.258115, 0.95751375, 8.060595, 0.34913856], [4.301093, -6.7470345, -5.3002644, -6.149367],
                        [-35.926193, 1.5979156, 5.596824, -0.45561755]]),
    ],
    "bursty misses, clutter 3, 120 deg": [
        (4, [-1, -1, -1, 3], [[-17.523632, 26.451607, 0.0, 0.0], [-12.740522, 23.151611, 0.0, 0.0],
                              [23.926292, 13.373739, 0.0, 0.0], [-7.133601, -3.8605711, -7.076546, 5.477284]]),
        (5, [-1, -1, -1, -1, 3], [[7.180008, 43.061836, 0.0, 0.0], [-6.839677, 31.803885, 0.0, 0.0],
                                  [38.235252, 23.26032, 0.0, 0.0], [36.359264, 10.54674, 0.0, 0.0],
                                  [-10.500711, -3.2343953, -8.9635105, 2.8598716]]),
        (4, [-1, -1, 3, -1], [[14.470344, 26.00245, 0.0, 0.0], [-12.215074, 1.6524283, 0.0, 0.0],
                              [-12.779873, -2.9675183, -9.333631, 1.1510702], [26.205875, -7.289737, 0.0, 0.0]]),
    ],
    "ego frame, max_objects 4, clutter 1": [
        (4, [-1, 4, 3, 5], [[18.068352, -30.568586, 0.0, 0.0], [37.11434, -16.053104, -0.08367931, 8.941677],
                            [40.254356, 31.346664, -0.14065424, -6.803692],
                            [36.233448, -45.894344, 0.36543247, 7.9976873]]),
        (3, [4, 3, 5], [[33.38125, -13.812751, -0.3935313, 8.377824], [38.093113, 29.519089, 0.16266204, -6.662778],
                        [34.134243, -43.419765, 0.60965675, 6.1432457]]),
        (3, [4, 3, 5], [[30.165316, -10.464414, 1.1572886, 8.406831], [35.10281, 27.309162, -0.030142574, -6.08333],
                        [30.6124, -40.72946, 0.1481691, 8.355703]]),
    ],
}
DRIVES = {
    "default": ({}, 0),
    "bursty misses, clutter 3, 120 deg": (dict(miss_rate=0.3, burst_length=3.0, clutter_rate=3.0, fov_deg=120.0), 1),
    "ego frame, max_objects 4, clutter 1": (dict(frame="ego", max_objects=4, clutter_rate=1.0), 2),
}


@pytest.mark.parametrize("name", list(DRIVES))
def test_the_detectors_frames_of_seeded_drives_are_pinned(name):
    overrides, seed = DRIVES[name]
    env = Detector(gym.make(TURN), **overrides)
    env.reset(seed=seed)
    frames = []
    for step in range(1, max(STEPS) + 1):
        obs, *_ = env.step(1)
        if step in STEPS:
            frames.append((obs["detector"].copy(), env.truth_ids.copy()))
    for (det, ids), (n, want_ids, want) in zip(frames, GOLDEN[name]):
        assert det[:, 0].tolist() == [1.0] * n + [0.0] * (len(det) - n)
        assert ids.tolist() == want_ids + [-1] * (len(ids) - n)
        # float32 in the observation: the literals are their shortest round-trip strings
        assert np.allclose(det[:n, 1:5], np.array(want, dtype=np.float32), rtol=0.0, atol=1e-9)
