"""``agent.device`` for every trained kind, tested without a GPU.

What broke on a GPU (``python -m train agent.device=cuda``: "index is on cpu, different from other tensors on
cuda:0" in the cloning step) was a tensor created without ``device=``, so on torch's default device while the policy
sat elsewhere. Here the default device is made torch's ``meta`` device (``with torch.device("meta")``) while the
networks stay on the CPU: every tensor the trainers create without naming a device lands on ``meta`` and the first
operation mixing it with the CPU network fails, as the same code did on ``cuda``. With every tensor placed
explicitly the run gives exactly what it gives outside the context."""

from __future__ import annotations

import hashlib
import subprocess
import sys

import numpy as np
import pytest
import torch

from conftest import conf


def _digest(module: torch.nn.Module) -> str:
    return hashlib.sha256(b"".join(p.detach().cpu().numpy().tobytes() for p in module.parameters())).hexdigest()


def _clone(default_device: str) -> tuple[dict, str]:
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.ppo import make_ppo
    from eval.agents import compose_group
    from train.ppo import _env_factory, make_teacher, pretrain_from_teacher

    sensors, env = compose_group("sensors", "turn_truth"), {**conf("env", "left_turn"), "duration": 5.0}
    make = lambda: _env_factory(env, sensors, {"kind": "none"}, 0.0, 5, "go_yield")  # noqa: E731
    model = make_ppo(DummyVecEnv([make]), {"policy": "MultiInputPolicy", "net_arch": [32], "n_steps": 64,
                                           "batch_size": 64}, seed=0, tensorboard_log=None)
    with torch.device(default_device):  # the student drives the second episode (DAgger): predict() is covered too
        stats = pretrain_from_teacher(model, make(), make_teacher("gap_acceptance", "go_yield"), range(2),
                                      gamma=0.95, epochs=1, batch_size=32, dagger_rounds=1, log=lambda _: None)
    return stats, _digest(model.policy)


@pytest.mark.slow  # 4 episodes and 2 fits, ~10 s; the fit itself is in the fast suite (test_dagger_rounds_fit_...)
def test_cloning_puts_every_tensor_on_the_policys_device():
    stats, digest = _clone("meta")
    assert (stats, digest) == _clone("cpu")
    assert stats["decisions"] > 4


def _tiny_demos(path) -> None:
    """Demonstrations in train/bc.py's on-disk format: 2 laps of 20 frames x 3 cameras of seeded noise images."""
    from train.bc import DEMO_VERSION, save_demos

    rng = np.random.default_rng(0)
    frames, n = 40, 120
    save_demos({"images": rng.integers(0, 256, (n, 90, 160, 3), dtype=np.uint8),
                "steering": rng.uniform(-1, 1, n).astype(np.float32),
                "dsteer_dyaw": rng.uniform(-1, 1, n).astype(np.float32),
                "camera": np.tile(np.arange(3, dtype=np.int8), frames),
                "frame": np.repeat(np.arange(frames, dtype=np.int32), 3),
                "lap": np.repeat((np.arange(frames) >= frames // 2).astype(np.int16), 3),
                "meta": {"version": DEMO_VERSION, "policy_frequency": 10.0, "focal_px": 140.0}}, path)


def _train_pilotnet(tmp_path, default_device: str) -> str:
    from agents.bc import PilotNetParams
    from eval.agents import compose_group
    from train.bc import train

    demos = tmp_path / "demos.npz"
    if not demos.is_file():
        _tiny_demos(demos)
    args = PilotNetParams(demos=str(demos), epochs=2, batch_size=16, val_fraction=0.25, val_chunk_s=1.0, seed=3,
                          torch_threads=1, crop_top=0)
    out = tmp_path / default_device
    with torch.device(default_device):
        path = train(args, conf("env", "lane_keeping"), compose_group("sensors", "cameras"), out / "run",
                     out / "ckpt", log=lambda _: None)
    state = torch.load(path, weights_only=True)["state_dict"]
    assert all(v.device.type == "cpu" for v in state.values())  # eval loads checkpoints on the CPU
    return hashlib.sha256(b"".join(v.numpy().tobytes() for v in state.values())).hexdigest()


@pytest.mark.slow  # two tiny trainings with every augmentation, ~10 s
def test_pilotnet_training_puts_every_tensor_on_the_networks_device(tmp_path):
    assert _train_pilotnet(tmp_path, "meta") == _train_pilotnet(tmp_path, "cpu")


def test_auto_is_the_cpu_without_a_gpu_and_a_bad_device_is_one_line():
    from av_gym.errors import ConfigError
    from train.device import device_problems, resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert device_problems("tpu") == ["agent.device must be one of ['cpu', 'cuda', 'auto'], got 'tpu'"]
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match=r"^agent.device=cuda but torch.cuda.is_available\(\) is False"):
            resolve_device("cuda")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU: cuda is a valid device here")
def test_cuda_without_a_gpu_is_refused_in_one_line_before_any_folder():
    """The command-line check ``python -m train`` runs before Hydra makes a folder (train/__main__.py): what it
    raises is printed as ``error: <line>`` with exit status 2 (tests/test_cli.py checks that path)."""
    from av_gym.errors import ConfigError
    from conf.check import check_command_line
    from train.__main__ import _validate

    (cfg,) = check_command_line("train", ["agent=ppo_turn", "agent.device=cuda"])
    with pytest.raises(ConfigError) as err:
        _validate(cfg)
    assert str(err.value).startswith("agent.device=cuda but torch.cuda.is_available() is False")
    assert "\n" not in str(err.value)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU: cuda is a valid device here")
def test_pilotnet_checks_its_device_like_ppo():
    from omegaconf import OmegaConf

    from agents.bc import PilotNetParams
    from eval.agents import compose_group
    from train.bc import validate

    cfg = OmegaConf.create({"env": {"name": "lane_keeping"}, "sensors": compose_group("sensors", "cameras"),
                            "agent": PilotNetParams(device="cuda").as_dict()})
    assert [p.split(" (")[0] for p in validate(cfg)] == ["agent.device=cuda but torch.cuda.is_available() is False"]
    cfg.agent.device = "auto"
    assert validate(cfg) == []


def test_dagger_rounds_fit_on_the_policys_device():
    """train/dagger.py refits its student with the cloning's fit (train/imitation.py fit_policy, where the GPU run
    crashed): the same placement, the same result."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.ppo import make_ppo
    from eval.agents import compose_group
    from train.dagger import Round, fit
    from train.ppo import _env_factory

    sensors = compose_group("sensors", "turn_truth")
    make = lambda: _env_factory(conf("env", "left_turn"), sensors, {"kind": "none"}, 0.0, 5, "go_yield")  # noqa: E731
    space = make().observation_space
    space.seed(3)
    rng = np.random.default_rng(1)
    data = Round(obs=[space.sample() for _ in range(40)], labels=[int(v) for v in rng.integers(0, 2, 40)],
                 returns=[float(v) for v in rng.normal(size=40)])
    results = []
    for default_device in ("meta", "cpu"):
        model = make_ppo(DummyVecEnv([make]), {"policy": "MultiInputPolicy", "net_arch": [16], "n_steps": 64,
                                               "batch_size": 64}, seed=0, tensorboard_log=None)
        with torch.device(default_device):
            accuracy = fit(model, data, 2, 16, 3e-3, 1)
        results.append((accuracy, _digest(model.policy)))
    assert results[0] == results[1]
