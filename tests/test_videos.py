"""``videos=true`` on the left turn (it silently wrote nothing): each agent's first episode, top-down,
as ``turn_<agent>.webm`` beside results.csv, as the lane keeper gets ``lap_<agent>.webm``. The videos are VP8 WebM,
which browsers play (``mp4v`` they did not), checked by decoding them."""

from __future__ import annotations

import cv2
import numpy as np

from conftest import conf


def _fourcc(video: cv2.VideoCapture) -> str:
    code = int(video.get(cv2.CAP_PROP_FOURCC)) & 0xFFFFFFFF
    return code.to_bytes(4, "little").decode("ascii", "replace")


def _decode(path) -> list[np.ndarray]:
    video = cv2.VideoCapture(str(path))
    frames = []
    ok, frame = video.read()
    while ok:
        frames.append(frame)
        ok, frame = video.read()
    return frames


def test_write_frames_writes_a_webm_that_decodes_frame_for_frame(tmp_path):
    from eval.plots import write_frames

    rng = np.random.default_rng(0)
    frames = [np.full((48, 64, 3), 10 * i, np.uint8) + rng.integers(0, 5, (48, 64, 3), np.uint8) for i in range(12)]
    path = write_frames(frames, tmp_path / "clip.mp4", 10.0)
    assert path == tmp_path / "clip.webm" and sorted(p.name for p in tmp_path.iterdir()) == ["clip.webm"]
    assert path.read_bytes()[:4] == b"\x1a\x45\xdf\xa3"  # EBML: a Matroska/WebM file
    video = cv2.VideoCapture(str(path))
    assert _fourcc(video) == "VP80" and video.get(cv2.CAP_PROP_FPS) == 10.0
    decoded = _decode(path)
    assert len(decoded) == 12 and decoded[0].shape == (48, 64, 3)
    # lossy, but each frame is the one written (RGB in, BGR out: grey frames are the same either way)
    assert all(abs(float(d.mean()) - float(f.mean())) < 3 for d, f in zip(decoded, frames))


def test_write_frames_falls_back_to_a_gif_without_a_vp8_encoder(tmp_path, monkeypatch):
    from PIL import Image

    from eval.plots import write_frames

    class NoEncoder:
        def __init__(self, *args) -> None:
            pass

        def isOpened(self) -> bool:
            return False

    monkeypatch.setattr(cv2, "VideoWriter", NoEncoder)
    frames = [np.full((48, 64, 3), 20 * i, np.uint8) for i in range(10)]
    path = write_frames(frames, tmp_path / "clip.webm", 10.0)
    assert path == tmp_path / "clip.gif" and sorted(p.name for p in tmp_path.iterdir()) == ["clip.gif"]
    with Image.open(path) as gif:
        assert gif.n_frames == 5 and gif.size == (64, 48)  # every other frame


def test_videos_on_the_left_turn_show_each_agents_first_episode(tmp_path):
    from av_gym.seeds import config_seeds
    from eval.agents import plan_agent
    from eval.plots import turn_videos

    env = {**conf("env", "left_turn"), "duration": 2.0}  # 20 decisions: a short clip
    plans = [plan_agent(name, "left_turn", conf("sensors", "truth"), {"kind": "none"}, "checkpoints")
             for name in ("always_proceed", "gap_acceptance")]
    first = config_seeds("validation", 1, None, "seed").start
    paths = turn_videos(env, plans, tmp_path, first, "checkpoints")
    assert [p.name for p in paths] == ["turn_always_proceed.webm", "turn_gap_acceptance.webm"]
    clips = []
    for path in paths:
        frames = _decode(path)
        video = cv2.VideoCapture(str(path))
        assert len(frames) == 21  # the reset and each of the 20 steps
        assert _fourcc(video) == "VP80"  # VP8: what browsers play in a WebM
        assert video.get(cv2.CAP_PROP_FPS) == 10.0  # real time at the policy's 10 Hz
        assert np.std(frames[0]) > 10  # a rendered road, not a blank frame
        clips.append(np.stack(frames).astype(float)[:, 24:])  # below the label and clock
    # the scene moves: always_proceed's last frame is not its first (the ego and traffic have driven on)
    assert np.abs(clips[0][-1] - clips[0][0]).mean() > 0.1
