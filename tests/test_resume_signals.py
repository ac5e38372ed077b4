"""What a signal leaves for a resume (train.ppo.learn with train.callbacks.AtomicCheckpointCallback), on a tiny PPO
(CartPole, 32 decisions per rollout): a signal during an update saves the next boundary, not a half-updated state
under the previous one's label; a second signal saves nothing part-way; checkpoint_every counts env steps; the
messages name the step saved in decisions and env steps; a signal mid-rollout saves the boundary's RNG states and
leaves a boundary already saved as it is; a resumed run's TensorBoard files (PPO's and DAgger's) hold each step once,
and a torn last record goes even when nothing follows the checkpoint."""

from __future__ import annotations

import os
import signal
import types
from pathlib import Path

import pytest
from stable_baselines3.common.callbacks import BaseCallback

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


class _Rollouts(BaseCallback):
    """Records the global RNG states at each rollout boundary (step -> train.checkpoint.rng_state()) and those at
    the moment it sends SIGTERM, during the rollout, once ``num_timesteps`` reaches ``signal_at`` (None: never)."""

    def __init__(self, signal_at: int | None = None):
        super().__init__()
        self.signal_at, self.at_boundary, self.at_signal = signal_at, {}, None

    def _on_rollout_start(self) -> None:
        from train.checkpoint import rng_state

        self.at_boundary[self.num_timesteps] = rng_state()

    def _on_step(self) -> bool:
        if self.signal_at is not None and self.at_signal is None and self.num_timesteps >= self.signal_at:
            from train.checkpoint import rng_state

            self.at_signal = rng_state()
            os.kill(os.getpid(), signal.SIGTERM)
        return True


def _run(tmp_path: Path, total: int, every: int, repeat: int = 1, signal_at_step: tuple[int, ...] = (),
         rollouts: BaseCallback | None = None):
    """train.ppo.learn on the tiny model to ``total`` decisions; SIGTERM sent from inside the optimizer's
    ``step`` calls numbered ``signal_at_step`` (1-based; 6 per update: 32 / 16 x 3 epochs), i.e. mid-update;
    ``rollouts`` (after the checkpoint callback) records RNG states and may signal mid-rollout.
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
        learn(model, venv, params, [FiniteGuard(3e-4), checkpoint, *([rollouts] if rollouts else [])],
              FiniteGuard(3e-4), checkpoint, False, "t")
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


def _same_rng(a: dict, b: dict) -> bool:
    import numpy as np
    import torch

    return (a["python"] == b["python"] and all(np.array_equal(x, y) for x, y in zip(a["numpy"], b["numpy"]))
            and torch.equal(a["torch"], b["torch"]))


def test_a_signal_mid_rollout_saves_the_boundarys_rng_states(tmp_path):
    """A signal half-way through the third rollout (no checkpoint yet: every=10**6) saves the boundary at 64 with
    the RNG states taken there, not the later ones the half rollout advanced (the policy's action draws), so a
    resume from it draws as one from a checkpoint written at the boundary. Fails if save() takes rng_state() now."""
    from train.checkpoint import load_rng_state

    rollouts = _Rollouts(signal_at=2 * ROLLOUT + ROLLOUT // 2)
    _, checkpoint, interrupted = _run(tmp_path, 4 * ROLLOUT, every=10**6, rollouts=rollouts)
    assert interrupted and checkpoint.saved_at == 2 * ROLLOUT
    saved = load_rng_state(tmp_path / "ckpt" / "latest.zip")
    assert not _same_rng(rollouts.at_signal, rollouts.at_boundary[2 * ROLLOUT]), "the half rollout drew"
    assert _same_rng(saved, rollouts.at_boundary[2 * ROLLOUT]), "the boundary's states, not the signal's"
    assert "logger" in saved


def test_a_boundary_already_saved_is_not_written_again(tmp_path):
    """every=32 decisions saves each boundary as its rollout starts; a signal in that rollout finds it saved and
    leaves latest.zip as it is (the same file: not replaced). Fails without save()'s ``saved_at == _boundary``."""
    latest = tmp_path / "ckpt" / "latest.zip"
    seen = {}

    class Watch(_Rollouts):
        def _on_step(self) -> bool:
            if self.num_timesteps >= self.signal_at and not seen:
                seen["stat"] = latest.stat()
            return super()._on_step()

    _, checkpoint, interrupted = _run(tmp_path, 4 * ROLLOUT, every=ROLLOUT, rollouts=Watch(2 * ROLLOUT + 8))
    assert interrupted and checkpoint.saved_at == 2 * ROLLOUT == _saved(latest)[0]
    after = latest.stat()
    assert (after.st_ino, after.st_mtime_ns) == (seen["stat"].st_ino, seen["stat"].st_mtime_ns), "rewritten"


def _records(path: Path) -> list[bytes]:
    from tensorboard.backend.event_processing.event_file_loader import RawEventFileLoader

    return list(RawEventFileLoader(str(path)).Load())


def test_a_torn_tail_is_dropped_even_with_nothing_past_the_purge_step(tmp_path):
    """kill -9 mid-write of a point at or before the checkpoint: no whole event to cut, but the torn record is
    still removed (a strict TFRecord reader, e.g. tf.data, fails on it), the rest kept byte for byte. Fails
    without ``_whole`` in train.tb_events.truncate_events."""
    from torch.utils.tensorboard import SummaryWriter

    from train.tb_events import truncate_events

    folder = tmp_path / "tb"
    killed = SummaryWriter(str(folder))
    for step in (512, 1024):
        killed.add_scalar("train/loss", 1.0, step)
    killed.close()
    path = next(folder.glob("events.*"))
    whole = path.read_bytes()
    with open(path, "ab") as f:
        f.write(b"\x20\x00\x00\x00\x00\x00\x00\x00torn")
    assert truncate_events(folder, 1025) == 0  # no whole event removed
    assert path.read_bytes() == whole
    assert truncate_events(folder, 1025) == 0 and path.read_bytes() == whole  # a whole file is left alone


def test_a_resumed_dagger_runs_event_files_hold_each_step_once(tmp_path):
    """DAgger's round log (steps: label counts) resumed after the round at 200 labels, where the cut-short run had
    logged its round at 300 and torn a record: raw readers see 100, 200, 300 (the resumed run's), 400, once each.
    Fails when train.tb_events.resumed_writer only passes purge_step (TensorBoard's readers alone honour it)."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
    from tensorboard.util.tensor_util import make_ndarray

    from train.tb_events import resumed_writer as tensorboard_writer  # DAgger's round log opens it

    folder = tmp_path / "tb" / "dagger"
    killed = tensorboard_writer(folder, None)
    for step in (100, 200, 300):
        killed.add_scalar("dagger/agreement", 0.5, step)
    killed.close()
    with open(next(folder.glob("events.*")), "ab") as f:
        f.write(b"\x20\x00\x00\x00\x00\x00\x00\x00torn")
    resumed = tensorboard_writer(folder, 201)
    for step in (300, 400):
        resumed.add_scalar("dagger/agreement", 0.9, step)
    resumed.close()
    points = [(e.step, v.simple_value if v.HasField("simple_value") else float(make_ndarray(v.tensor)))
              for path in sorted(folder.glob("events.*")) for e in EventFileLoader(str(path)).Load()
              for v in e.summary.value if v.tag == "dagger/agreement"]
    assert sorted(s for s, _ in points) == [100, 200, 300, 400], points
    assert dict(points)[300] == pytest.approx(0.9) and dict(points)[200] == pytest.approx(0.5)


def _play(policy, seeds) -> list[dict]:
    """PeriodicEval's ``play`` on the tiny CartPole policy: per seed, its deterministic action on a seeded
    observation (1: a 'success', 0: a 'collision'), so each row depends on the parameters evaluated."""
    import numpy as np

    rows = []
    for seed in seeds:
        obs = np.random.default_rng(seed).normal(size=4).astype(np.float32)
        action = int(policy.model.predict(obs, deterministic=True)[0])
        rows.append({"agent": "eval", "success": float(action == 1), "collision": float(action == 0)})
    return rows


def _evaluation(folder: Path):
    """The periodic evaluation at every rollout (PeriodicEval, 16 seeds, no video) writing into ``folder``."""
    from train.callbacks import PeriodicEval

    (folder / "ckpt").mkdir(parents=True, exist_ok=True)
    return PeriodicEval(lambda mode: None, "left_turn", range(16), ROLLOUT, folder / "ckpt", folder, play=_play)


def _evaluations(folder: Path) -> tuple[list[tuple], dict]:
    """eval.csv's rows and best.json, without wall-clock time (the only thing allowed to differ)."""
    import csv
    import json

    with open(folder / "eval.csv") as f:
        rows = [tuple((k, v) for k, v in r.items() if k != "wall_clock_s") for r in csv.DictReader(f)]
    best = json.loads((folder / "ckpt" / "best.json").read_text())
    return rows, {k: v for k, v in best.items() if k != "wall_clock_s"}


def _resume(folder: Path, total: int) -> None:
    """train.ppo.learn from ``folder/ckpt/latest.zip`` to ``total`` decisions, as train_ppo resumes."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    from train.callbacks import AtomicCheckpointCallback, FiniteGuard
    from train.ppo import _tensorboard_logger, learn

    venv = make_vec_env("CartPole-v1", n_envs=1, seed=1)
    model = PPO.load(str(folder / "ckpt" / "latest.zip"), env=venv, device="cpu")
    model.set_logger(_tensorboard_logger(folder / "tb", model.num_timesteps + 1))
    checkpoint = AtomicCheckpointCallback(folder / "ckpt", 10**6)
    params = types.SimpleNamespace(total_timesteps=total, n_steps=ROLLOUT, n_envs=1, action_repeat=1)
    guard = FiniteGuard(3e-4)
    learn(model, venv, params, [guard, checkpoint, _evaluation(folder)], guard, checkpoint, False, "t")
    guard.check("the last PPO update")  # as train_ppo does next (it failed: the callbacks never started)


@pytest.mark.slow  # three tiny PPO runs: ~2.7 s at load 1.3
def test_a_run_stopped_in_its_last_update_gets_its_final_evaluation_on_resume(tmp_path):
    """SIGTERM inside the last PPO update (optimizer step 20 of 24) stops at the final boundary, saved, before the
    periodic evaluation's end-of-training one; the resume, with no step left to train, makes that evaluation:
    eval.csv and best.json as the uninterrupted run's. A second resume adds nothing. Fails without learn()'s
    callbacks at rounded == 0 or without PeriodicEval's schedule from eval.csv's last row (resumed: csv ends at 96)."""
    total = 4 * ROLLOUT
    _run(tmp_path / "whole", total, every=10**6, rollouts=_evaluation(tmp_path / "whole"))
    reference = _evaluations(tmp_path / "whole")
    assert [dict(r)["steps"] for r in reference[0]] == ["0", "32", "64", "96", "128"]

    cut = tmp_path / "cut"
    _, checkpoint, interrupted = _run(cut, total, every=10**6, signal_at_step=(20,), rollouts=_evaluation(cut))
    assert interrupted and checkpoint.saved_at == total
    assert [dict(r)["steps"] for r in _evaluations(cut)[0]] == ["0", "32", "64", "96"], "stopped before it"
    _resume(cut, total)
    assert _evaluations(cut) == reference
    _resume(cut, total)  # learning and its final evaluation both done: nothing twice
    assert _evaluations(cut) == reference
