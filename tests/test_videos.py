"""``videos=true`` on the left turn (it silently wrote nothing): each agent's first episode, top-down,
as ``turn_<agent>.mp4`` beside results.csv, as the lane keeper gets ``lap_<agent>.mp4``."""

from __future__ import annotations

import cv2
import numpy as np

from conftest import conf


def test_videos_on_the_left_turn_show_each_agents_first_episode(tmp_path):
    from av_gym.seeds import config_seeds
    from eval.agents import plan_agent
    from eval.plots import turn_videos

    env = {**conf("env", "left_turn"), "duration": 2.0}  # 20 decisions: a short clip
    plans = [plan_agent(name, "left_turn", conf("sensors", "truth"), {"kind": "none"}, "checkpoints")
             for name in ("always_proceed", "gap_acceptance")]
    first = config_seeds("validation", 1, None, "seed").start
    paths = turn_videos(env, plans, tmp_path, first, "checkpoints")
    assert [p.name for p in paths] == ["turn_always_proceed.mp4", "turn_gap_acceptance.mp4"]
    clips = []
    for path in paths:
        video = cv2.VideoCapture(str(path))
        frames = []
        ok, frame = video.read()
        while ok:
            frames.append(frame)
            ok, frame = video.read()
        assert len(frames) == 21  # the reset and each of the 20 steps
        assert video.get(cv2.CAP_PROP_FPS) == 10.0  # real time at the policy's 10 Hz
        assert np.std(frames[0]) > 10  # a rendered road, not a blank frame
        clips.append(np.stack(frames).astype(float)[:, 24:])  # below the label and clock
    # the scene moves: always_proceed's last frame is not its first (the ego and traffic have driven on)
    assert np.abs(clips[0][-1] - clips[0][0]).mean() > 0.1
