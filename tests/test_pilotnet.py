"""PilotNet and its behaviour-cloning pipeline: network, preprocessing, labels, balancing, augmentation, the
expert, the on-disk demos, checkpoints (weights_only), and a tiny ``python -m train agent=pilotnet`` + eval."""

from __future__ import annotations

import csv
import math
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

from agents.bc import PilotNetParams
from agents.pilotnet import (FORMAT, N_PARAMETERS, PilotNet, PilotNetPolicy, count_parameters, crop_resize,
                             load_checkpoint, preprocess, rgb_to_yuv)
from av_gym.errors import ConfigError
from av_gym.sensors.camera import WINDSHIELD_HALF_WIDTH, CameraSpec
from train.bc import (PurePursuitExpert, augment, balance, geometric_side_label, load_demos, save_demos,
                      split_by_chunks)
from conftest import conf


# ------------------------------------------------------------------------------------------------ network
def test_parameter_count_is_the_papers():
    assert count_parameters(PilotNet()) == N_PARAMETERS == 252_219


def test_forward_shapes_follow_table_1():
    net = PilotNet().eval()
    x = torch.zeros(4, 3, 66, 200)
    shapes = []
    for layer in net.features:
        x = layer(x)
        if isinstance(layer, torch.nn.Conv2d):
            shapes.append(tuple(x.shape[1:]))
    assert shapes == [(24, 31, 98), (36, 14, 47), (48, 5, 22), (64, 3, 20), (64, 1, 18)]
    assert net(torch.zeros(4, 3, 66, 200)).shape == (4,)
    assert sum(isinstance(m, torch.nn.Dropout) and m.p == 0.5 for m in net.modules()) == 4
    assert sum(isinstance(m, torch.nn.ELU) for m in net.modules()) == 8


# ------------------------------------------------------------------------------------------------ preprocessing
def test_yuv_matches_opencv_and_input_is_normalised():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (66, 200, 3), dtype=np.uint8)
    ours = rgb_to_yuv(torch.from_numpy(img).permute(2, 0, 1)[None].float())[0].permute(1, 2, 0).numpy()
    assert np.abs(ours - cv2.cvtColor(img, cv2.COLOR_RGB2YUV).astype(float)).max() <= 1.0
    x = preprocess(img, crop_top=0)
    assert x.shape == (1, 3, 66, 200) and x.dtype == torch.float32
    assert -1.0 <= float(x.min()) and float(x.max()) <= 1.0
    black = preprocess(np.zeros((66, 200, 3), np.uint8), crop_top=0)[0]
    assert black[0].max() == pytest.approx(-1.0) and black[1].abs().max() < 0.01  # Y = 0, U = V = 128 -> ~0


def test_crop_removes_the_sky_rows_and_keeps_the_input_size():
    img = np.full((66, 200, 3), 100, np.uint8)
    img[:12] = (255, 0, 0)  # "sky"
    out = crop_resize(img, crop_top=12)
    assert out.shape == (66, 200, 3) and not (out[..., 0] > 150).any()
    assert crop_resize(np.stack([img, img]), 12).shape == (2, 66, 200, 3)


def _plain_args(**kw) -> PilotNetParams:
    base = dict(flip_p=0.0, shift_px=0.0, vshift_px=0.0, rotate_deg=0.0, brightness=0.0, contrast=0.0, gain=0.0,
                pixel_noise=0.0, night_p=0.0, fog_p=0.0, blur_p=0.0)
    base.update(kw)
    return PilotNetParams(**base)


# The conditions off, as the old Args() defaults had them (conf/agent/pilotnet.yaml, now the defaults, turns them on)
NO_CONDITIONS = dict(night_p=0.0, fog_p=0.0, blur_p=0.0)


def test_flip_mirrors_the_image_and_negates_the_label():
    rgb = torch.rand(6, 3, 66, 200, generator=torch.Generator().manual_seed(1)) * 255
    y, slope = torch.linspace(-0.9, 0.9, 6), torch.full((6,), -3.0)
    out, y_out = augment(rgb, y, slope, _plain_args(flip_p=1.0), 142.8, torch.Generator().manual_seed(0))
    assert torch.allclose(out, rgb.flip(-1), atol=1e-3)
    assert torch.allclose(y_out, -y)
    same, y_same = augment(rgb, y, slope, _plain_args(), 142.8, torch.Generator().manual_seed(0))
    assert torch.allclose(same, rgb, atol=1e-3) and torch.allclose(y_same, y)


def test_shift_is_read_as_a_yaw_and_corrects_the_label():
    """A bar at column 100; after a shift the bar moved by tx px; the label moved by slope·(−atan(tx/f))."""
    img = torch.zeros(1, 3, 66, 200)
    img[..., 99:101] = 255.0
    rgb, y, slope, f = img.repeat(8, 1, 1, 1), torch.zeros(8), torch.full((8,), -3.0), 142.8
    out, y_out = augment(rgb, y, slope, _plain_args(shift_px=15.0), f, torch.Generator().manual_seed(1))
    tx = out[:, 0, 33].argmax(-1).float() + 0.5 - 100.0  # new bar column minus the old one
    assert tx.abs().max() > 3  # it did shift
    expected = (slope * -torch.atan(tx / f)).clamp(-1, 1)
    assert torch.allclose(y_out, expected, atol=0.03)
    assert (torch.sign(y_out[tx.abs() > 1]) == torch.sign(tx[tx.abs() > 1])).all()  # road moved right: steer right


def test_night_and_fog_follow_the_camera_model_and_keep_the_label():
    """Augmented night/fog on clean frames look like the camera's own night/fog renders of the same pose:
    darker / hazier by about as much, labels untouched."""
    import gymnasium as gym

    import av_gym  # noqa: F401
    from train.bc import WeatherMaps
    from av_gym.sensors.camera import Weather, render_view

    env = gym.make("av_gym/LaneKeepingLap-v0", config={"start_s": 60.0, "initial_lateral_std": 0.0,
                                                       "initial_heading_std": 0.0})
    env.reset(seed=0)
    clean, night, fog = (crop_resize(render_view(env, weather=w), 12) for w in
                         (Weather(), Weather(night=True), Weather(fog_visibility=80.0)))
    maps = WeatherMaps.for_camera(conf("sensor", "cameras"), 12)
    x = torch.from_numpy(np.stack([clean] * 64)).permute(0, 3, 1, 2).float()
    y = torch.linspace(-0.5, 0.5, 64)
    for args, target in ((_plain_args(night_p=1.0), night), (_plain_args(fog_p=1.0, fog_min_m=80.0, fog_max_m=80.0),
                                                              fog)):
        out, y_out = augment(x, y, torch.zeros(64), args, 142.8, torch.Generator().manual_seed(0), maps)
        assert torch.equal(y_out, y)
        mean_out = out.mean(0).permute(1, 2, 0).numpy()
        # mean brightness within 15 % of the camera's render of the condition, and far from the clean frame
        assert abs(mean_out.mean() - target.mean()) < 0.15 * target.mean(), (mean_out.mean(), target.mean())
        assert abs(mean_out.mean() - clean.mean()) > 3 * abs(mean_out.mean() - target.mean())
    # with the conditions off, the generator is used exactly as before (a plain run trains the same model)
    a, _ = augment(x[:8], y[:8], torch.zeros(8), PilotNetParams(**NO_CONDITIONS), 142.8,
                   torch.Generator().manual_seed(3), maps)
    b, _ = augment(x[:8], y[:8], torch.zeros(8), PilotNetParams(**NO_CONDITIONS), 142.8,
                   torch.Generator().manual_seed(3), None)
    assert torch.equal(a, b)


def test_balancing_caps_every_bin():
    rng = np.random.default_rng(0)
    steering = np.concatenate([np.zeros(5000), rng.uniform(-1, 1, 1000), np.full(300, 0.45)])
    keep, cap = balance(steering, bins=25, cap=100, rng=rng)
    counts = np.bincount(np.clip(((steering[keep] + 1) / 2 * 25).astype(int), 0, 24), minlength=25)
    assert cap == 100 and counts.max() <= 100
    full = np.bincount(np.clip(((steering + 1) / 2 * 25).astype(int), 0, 24), minlength=25)
    assert (counts[full <= 100] == full[full <= 100]).all()  # bins under the cap keep everything
    _, auto_cap = balance(steering, bins=25, cap_factor=2.0)
    assert auto_cap == int(2.0 * np.median(full[full > 0]))


def test_validation_split_keeps_chunks_of_driving_whole():
    frame = np.repeat(np.arange(1000), 3)
    lap = (frame // 500).astype(np.int16)
    val = split_by_chunks(frame, lap, 50, 0.2, np.random.default_rng(0))
    assert 0.1 < val.mean() < 0.3
    for chunk in np.unique(frame // 50):
        assert len(set(val[frame // 50 == chunk])) == 1


# ------------------------------------------------------------------------------------------------ expert and labels
@pytest.fixture(scope="module")
def lap_env():
    from av_gym.make import make_env

    env = make_env(conf("env", "lane_keeping"))
    env.reset(seed=0)
    return env


def test_side_camera_labels_steer_back_towards_the_centre(lap_env):
    """The LEFT camera sees the car as if it were left of centre, so its label steers RIGHT (+ = right)."""
    u_env = lap_env.unwrapped
    expert = PurePursuitExpert(u_env.track, PilotNetParams().lookahead, u_env.config["max_steering"])
    lane = u_env.track.lanes[0]  # the 120 m start straight
    x, y = lane.position(30.0, 0.0)
    offsets = {"left": -WINDSHIELD_HALF_WIDTH, "centre": 0.0, "right": WINDSHIELD_HALF_WIDTH}
    u, du, _ = expert.labels(x, y, lane.heading_at(30.0), 0, offsets)
    assert u["centre"] == pytest.approx(0.0, abs=1e-6)
    assert u["left"] > 0.1 and u["right"] < -0.1 and u["left"] == pytest.approx(-u["right"], rel=1e-6)
    assert du["centre"] < 0  # heading further right -> steer left
    c = geometric_side_label(0.0, -0.6, 10.0, math.radians(25))
    assert c == pytest.approx(math.atan(0.06) / math.radians(25)) and c > 0
    assert geometric_side_label(0.0, 0.6, 10.0, math.radians(25)) == pytest.approx(-c)


@pytest.mark.parametrize("track", ["A", "B"])
def test_expert_drives_a_lap_better_than_the_paper_pid(make, lane_cfg, track):
    from agents.pid import PRESETS, PIDSteering

    env = make(dict(lane_cfg, track=track))
    scores = []
    for name in ("expert", "pid"):
        obs, info = env.reset(seed=0)
        u_env, hint, done = env.unwrapped, 0, False
        expert = PurePursuitExpert(u_env.track, PilotNetParams().lookahead, u_env.config["max_steering"])
        pid = PIDSteering(**PRESETS["paper"])
        while not done:
            t = info["truth"]
            if name == "expert":
                a, hint = expert.command(t["x"], t["y"], t["heading"], hint)
                a = np.array([a], np.float32)
            else:
                a = pid.act(obs)
            obs, _, term, trunc, info = env.step(a)
            done = term or trunc
        assert info["episode_metrics"]["lap_completed"] == 1.0
        scores.append(info["episode_metrics"]["cte_mean_abs_units"])
    assert scores[0] < scores[1]


def test_demos_round_trip_without_pickles(tmp_path):
    demos = {"images": np.zeros((6, 66, 200, 3), np.uint8), "steering": np.linspace(-1, 1, 6).astype(np.float32),
             "camera": np.array([0, 1, 2] * 2, np.int8), "meta": {"version": 1, "track": "A", "focal_px": 142.8}}
    path = save_demos(demos, tmp_path / "d" / "demos.npz")
    back = load_demos(path)
    assert back["meta"]["track"] == "A" and np.array_equal(back["steering"], demos["steering"])
    assert back["images"].dtype == np.uint8 and back["images"].shape == (6, 66, 200, 3)


def test_params_reject_unknown_and_bad_fields(tmp_path):
    from agents.registry import agent_problems
    from av_gym.params import ParamError

    with pytest.raises(ParamError, match="agent.epoch is not a field of a pilotnet agent"):
        PilotNetParams.from_mapping({"epoch": 3}, where="agent", what="a field of a pilotnet agent")
    problems = agent_problems({"kind": "pilotnet", "epochs": 0, "side_labels": "magic"}, "agent")
    assert any(p.startswith("agent.epochs must be an integer >= 1") for p in problems)
    assert any("agent.side_labels must be one of" in p for p in problems)
    problems = agent_problems({"kind": "pilotnet", "demos": str(tmp_path / "none.npz")}, "agent")
    assert any(p.startswith("agent.demos: no such file") for p in problems)


# ------------------------------------------------------------------------------------------------ checkpoints
def test_checkpoint_loads_with_weights_only_and_rejects_code(tmp_path):
    from agents.bc import PilotNetAgent

    _load_pilotnet = PilotNetAgent.load

    net = PilotNet()
    good = tmp_path / "model.pt"
    torch.save({"format": FORMAT, "state_dict": net.state_dict(), "preprocess": {"crop_top": 12}}, good)
    ckpt = load_checkpoint(good)
    assert set(ckpt["state_dict"]) == set(net.state_dict())
    bad = tmp_path / "evil.pt"
    torch.save({"format": FORMAT, "payload": PilotNetParams()}, bad)  # an arbitrary Python object: needs unpickling
    with pytest.raises(Exception):
        torch.load(bad, weights_only=True)

    class CameraEnv:
        observation_space = __import__("gymnasium").spaces.Dict({"cameras": __import__("gymnasium").spaces.Dict(
            {"centre": __import__("gymnasium").spaces.Box(0, 255, (66, 200, 3), np.uint8)})})

    policy = _load_pilotnet(good, CameraEnv())
    assert isinstance(policy, PilotNetPolicy)
    u = policy.act({"cameras": {"centre": np.zeros((66, 200, 3), np.uint8)}})
    assert u.shape == (1,) and -1.0 <= u[0] <= 1.0
    with pytest.raises(ConfigError):
        _load_pilotnet(bad, CameraEnv())


# ------------------------------------------------------------------------------------------------ end to end
def _run(module, *overrides, cwd):
    return subprocess.run([sys.executable, "-m", module, *overrides], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.slow  # demonstrations, training, evaluation with plots and a video
def test_tiny_train_then_eval_loads_the_checkpoint(tmp_path):
    res = _run("train", "agent=pilotnet", "env=lane_keeping", "agent.demo_laps=1", "agent.demo_max_steps=30",
               "agent.epochs=1", "train.eval_episodes=0", "train.progress_bar=false", "run_name=tiny", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    ckpt = tmp_path / "checkpoints" / "tiny"
    assert (ckpt / "model.pt").is_file() and (ckpt / "config.yaml").is_file()
    import yaml

    saved = yaml.safe_load((ckpt / "config.yaml").read_text())
    assert saved["agent"]["kind"] == "pilotnet" and "cameras" in saved["sensors"]
    assert (tmp_path / "runs" / "tiny" / "demos.npz").is_file()
    assert list((tmp_path / "runs" / "tiny" / "tb").glob("events.out.tfevents.*"))
    assert torch.load(ckpt / "model.pt", weights_only=True)["format"] == FORMAT
    assert not list(ckpt.glob(".*tmp*"))

    # pilotnet:latest is that run (plain pilotnet is the shipped reference, checkpoints/reference/pilotnet/)
    res = _run("eval", "env=lane_keeping", "agents=[pid_paper,pilotnet:latest]", "episodes=1", "env.time_limit=3",
               "out_dir=out", "progress_bar=false", "plots=true", "videos=true", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "pilotnet:latest: checkpoints/tiny/model.pt" in res.stdout, res.stdout[-2000:]
    rows = list(csv.DictReader(open(tmp_path / "out" / "results.csv")))
    assert [r["agent"] for r in rows] == ["pid_paper", "pilotnet:latest"]
    for name in ("cte_pid_paper.png", "cte_pilotnet_latest.png", "cte_all.png"):
        assert (tmp_path / "out" / name).stat().st_size > 1000
    assert list((tmp_path / "out").glob("lap_pilotnet_latest.*"))


def test_bad_pilotnet_input_is_one_line_naming_the_field(tmp_path):
    from conftest import cli  # the command-line check in this process; a real process only if it passes

    res = cli("train", "agent=pilotnet", "env=lane_keeping", f"agent.demos={tmp_path}/missing.npz",
              "train.progress_bar=false", cwd=tmp_path)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 2 and len(lines) == 1 and "agent.demos: no such file" in lines[0], res.stderr[-2000:]
    assert not (tmp_path / "checkpoints").exists()
