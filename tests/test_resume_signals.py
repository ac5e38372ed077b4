"""What a signal leaves for a resume (train.ppo.learn with train.callbacks.AtomicCheckpointCallback), on a tiny PPO
(CartPole, 32 decisions per rollout): a signal during an update saves the next boundary, not a half-updated state
under the previous one's label; a second signal saves nothing part-way; checkpoint_every counts env steps; the
messages name the step saved in decisions and env steps; a resumed run's TensorBoard files hold each step once."""

from __future__ import annotations

import os
import signal
import types
from pathlib import Path

import pytest

ROLLOUT = 32  # decisions per rollout (n_steps x n_envs)


def _model(seed: int = 0):
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env("CartPole-v1", n_envs=1, seed=seed)
    model = PPO("MlpPolicy", venv, n_steps=ROLLOUT, batch_size=16, n_epochs=3, seed=seed, device="cpu",
                policy_kwargs={"net_arch": [8]})
    return model, venv


def _state(model) -> dict:
    """Policy parameters and Adam's state, copied (tensors)."""
    import copy

    return copy.deepcopy({"policy": model.policy.state_dict(), "adam": model.policy.optimizer.state_dict()})


def _equal(a: dict, b: dict) -> bool:
    import torch

    pa, pb = a["policy"], b["policy"]
    if pa.keys() != pb.keys() or not all(torch.equal(pa[k], pb[k]) for k in pa):
        return False
    sa, sb = a["adam"]["state"], b["adam"]["state"]
    return sa.keys() == sb.keys() and all(torch.equal(sa[i][k], sb[i][k]) for i in sa for k in ("exp_avg",
                                                                                                 "exp_avg_sq"))


def _run(tmp_path: Path, total: int, every: int, repeat: int = 1, signal_at_step: tuple[int, ...] = ()):
    """train.ppo.learn on the tiny model to ``total`` decisions; SIGTERM sent from inside the optimizer's
    ``step`` calls numbered ``signal_at_step`` (1-based; 6 per update: 32 / 16 x 3 epochs), i.e. mid-update.
    Returns (model, checkpoint callback, KeyboardInterrupt raised?)."""
    from train.callbacks import AtomicCheckpointCallback, FiniteGuard
    from train.ppo import _tensorboard_logger, learn

    model, venv = _model()
    model.set_logger(_tensorboard_logger(tmp_path / "tb", None))
    optimizer, calls = model.policy.optimizer, [0]
    step = optimizer.step

    def signalling_step(*args, **kwargs):
        out = step(*args, **kwargs)
        calls[0] += 1
        if calls[0] in signal_at_step:
            os.kill(os.getpid(), signal.SIGTERM)
        return out

    optimizer.step = signalling_step
    checkpoint = AtomicCheckpointCallback(tmp_path / "ckpt", every, repeat)
    (tmp_path / "ckpt").mkdir(exist_ok=True)
    params = types.SimpleNamespace(total_timesteps=total, n_steps=ROLLOUT, n_envs=1, action_repeat=repeat)
    try:
        learn(model, venv, params, [FiniteGuard(3e-4), checkpoint], FiniteGuard(3e-4), checkpoint, False, "t")
    except KeyboardInterrupt:
        return model, checkpoint, True
    return model, checkpoint, False


def _reference_states(total: int) -> dict[int, dict]:
    """An uninterrupted run's state at each rollout boundary (step -> state)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Record(BaseCallback):
        def __init__(self):
            super().__init__()
            self.states = {}

        def _on_rollout_start(self) -> None:
            self.states[self.num_timesteps] = _state(self.model)

        def _on_training_end(self) -> None:
            self.states[self.num_timesteps] = _state(self.model)

        def _on_step(self) -> bool:
            return True

    model, _ = _model()
    record = Record()
    model.learn(total, callback=record)
    return record.states


def _saved(path: Path) -> tuple[int, dict]:
    from stable_baselines3 import PPO

    model = PPO.load(str(path), device="cpu")
    return int(model.num_timesteps), _state(model)


def test_a_signal_during_an_update_saves_the_next_boundary_and_says_so(tmp_path, capsys):
    # the 8th optimizer step is inside the second update (after the rollout 32 -> 64): before the fix, latest.zip
    # said 32 and held parameters part-way through that update
    model, checkpoint, interrupted = _run(tmp_path, 4 * ROLLOUT, every=10**6, repeat=5, signal_at_step=(8,))
    assert interrupted
    steps, state = _saved(tmp_path / "ckpt" / "latest.zip")
    assert _equal(state, _reference_states(4 * ROLLOUT)[steps]), "the saved state is the uninterrupted run's there"
    assert steps == 2 * ROLLOUT == checkpoint.saved_at == model.num_timesteps
    out = capsys.readouterr().out
    assert "during a PPO update: stopping when it ends" in out
    assert "holds 64 decisions (320 env steps)" in out and "interrupted at 64 decisions (320 env steps)" in out


def test_a_second_signal_during_the_update_saves_nothing_part_way(tmp_path, capsys):
    model, checkpoint, interrupted = _run(tmp_path, 4 * ROLLOUT, every=10**6, signal_at_step=(8, 9))
    assert interrupted and checkpoint.saved_at is None
    assert not (tmp_path / "ckpt" / "latest.zip").exists(), "a half-updated state must not be saved"
    assert "before any checkpoint: nothing was kept" in capsys.readouterr().out


def test_checkpoint_every_counts_env_steps(tmp_path):
    # 5 env steps per decision: 160 env steps = 32 decisions = every rollout (counted in decisions: none in 96)
    _, checkpoint, interrupted = _run(tmp_path, 3 * ROLLOUT, every=160, repeat=5)
    assert not interrupted and checkpoint.saved_at == 2 * ROLLOUT
    assert _saved(tmp_path / "ckpt" / "latest.zip")[0] == 2 * ROLLOUT


def test_a_resumed_runs_event_files_hold_each_step_once(tmp_path):
    """What a kill -9 leaves (events after the checkpoint, a torn last record), then the resumed run's logger:
    raw readers (not only TensorBoard, which honours purge_step) see every step once, the resumed run's values."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
    from torch.utils.tensorboard import SummaryWriter

    from train.ppo import _tensorboard_logger

    folder = tmp_path / "tb"
    killed = SummaryWriter(str(folder))
    for step in (512, 1024, 1536, 2048):  # checkpoint at 1024: 1536 and 2048 are redone after the resume
        killed.add_scalar("train/loss", 1.0, step)
    killed.close()
    first = next(folder.glob("events.*"))
    with open(first, "ab") as f:
        f.write(b"\x20\x00\x00\x00\x00\x00\x00\x00torn")  # a record cut short by the kill
    logger = _tensorboard_logger(folder, 1025)
    for step in (1536, 2048, 2560):
        logger.record("train/loss", 2.0)
        logger.dump(step)
    logger.close()
    from tensorboard.util.tensor_util import make_ndarray

    points = [(e.step, v.simple_value if v.HasField("simple_value") else float(make_ndarray(v.tensor)))
              for path in sorted(folder.glob("events.*")) for e in EventFileLoader(str(path)).Load()
              for v in e.summary.value if v.tag == "train/loss"]
    steps = sorted(s for s, _ in points)
    assert steps == [512, 1024, 1536, 2048, 2560], points
    assert dict(points)[1536] == pytest.approx(2.0) and dict(points)[1024] == pytest.approx(1.0)
