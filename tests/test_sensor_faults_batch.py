"""A non-finite sensor reading on the batch (av_gym/batched) is handled as the per-env sensor's guard handles it
(av_gym/sensors/base.py SensorWrapper._guarded): made finite, marked invalid (a detector row dropped before the
tracker reads it), counted, and the episode's count is the results' ``sensor_faults`` column, per env and batch
alike (closing note of 2026-11-30: the batch's compiled sensors had no guard, and no results column said a run had
non-finite readings). The same fault is injected on both stacks by patching their measurement functions."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.batched.left_turn import BatchedLeftTurn
from av_gym.batched.perception import BatchedDetector
from av_gym.batched.vec_env import BatchedLeftTurnBatch
from av_gym.estimation.turn_features import TurnFeatures
from av_gym.make import make_env
from av_gym.presets import compose_group
from av_gym.sensors.detector import Detector

ENV = {"name": "left_turn"}


def _actions(seed: int, n: int = 400) -> np.ndarray:
    return np.random.default_rng(seed).choice(3, size=n, p=[0.2, 0.5, 0.3])


def _poison_detections(det: np.ndarray) -> np.ndarray:
    """Every reading (…, M, 9): the first object's vx NaN and the second's x +inf, where present."""
    det = np.array(det, dtype=np.float32, copy=True)
    for rows in det.reshape(-1, *det.shape[-2:]):
        if rows[0, 0] > 0:
            rows[0, 3] = np.nan
        if rows[1, 0] > 0:
            rows[1, 1] = np.inf
    return det


def _poison_turn(turn: np.ndarray) -> np.ndarray:
    """Every feature vector (…, width): its first feature NaN."""
    turn = np.array(turn, dtype=np.float32, copy=True)
    turn[..., 0] = np.nan
    return turn


def _faults(info: dict) -> int:
    return sum(info.get("sensor_faults", {}).values())


def _per_env(seed: int, sensors: dict, keys: tuple[str, ...], n_steps: int = 400) -> tuple[list[dict], float]:
    """Every step's readings of ``keys`` on the per-env stack and its faults: the episode's sensor_faults
    (EpisodeMetrics) if it ended within ``n_steps``, else info["sensor_faults"] summed so far (reset included)."""
    env = make_env(ENV, sensors)
    obs, info = env.reset(seed=seed)
    steps, faults = [{k: obs[k].copy() for k in keys}], _faults(info)
    for a in _actions(seed)[:n_steps]:
        obs, _, term, trunc, info = env.step(int(a))
        steps.append({k: obs[k].copy() for k in keys})
        faults += _faults(info)
        if term or trunc:
            assert info["episode_metrics"]["sensor_faults"] == faults  # EpisodeMetrics sums what info said
            break
    env.close()
    return steps, faults


def _batch(seed: int, sensors: dict, keys: tuple[str, ...], n_steps: int = 400) -> tuple[list[dict], float]:
    """The same on the batch (one env): its episode's sensor_faults, or its count so far."""
    venv = BatchedLeftTurnBatch(ENV, {**sensors, "observe": list(keys)}, None, 1, pool=0)
    obs = venv.play(iter([seed]))
    steps = [{k: obs[k][0].copy() for k in keys}]
    for a in _actions(seed)[:n_steps]:
        obs, _, ended, infos = venv.step(np.array([a]))
        o = infos[0]["terminal_observation"] if ended[0] else {k: obs[k][0] for k in keys}
        steps.append({k: np.array(o[k]) for k in keys})
        if ended[0]:
            return steps, infos[0]["episode_metrics"]["sensor_faults"]
    return steps, float(venv._faults[0])  # the episode's count so far (what its metrics row would say)


def _sensors(preset: str) -> dict:
    return {k: v for k, v in compose_group("sensors", preset).items() if k != "observe"}


def test_a_nan_detection_is_dropped_before_the_tracker_on_the_batch_as_per_env(monkeypatch):
    real_env, real_batch = Detector.measure, BatchedDetector.measure
    monkeypatch.setattr(Detector, "measure", lambda self: _poison_detections(real_env(self)))
    monkeypatch.setattr(BatchedDetector, "measure", lambda self, *a: _poison_detections(real_batch(self, *a)))
    keys = ("detector", "tracks", "turn", "intent")
    sensors = _sensors("turn_perceived")
    ref, ref_faults = _per_env(3, sensors, keys, n_steps=80)
    got, got_faults = _batch(3, sensors, keys, n_steps=80)
    assert len(got) == len(ref)
    for n, (a, b) in enumerate(zip(ref, got)):
        assert all(np.all(np.isfinite(b[k])) for k in keys), f"step {n}: a non-finite reading reached the agent"
        assert np.array_equal(a["detector"], b["detector"]), f"step {n}: detections"
        for k in ("tracks", "turn", "intent"):  # tests/test_batched_perception.py's tolerance
            assert np.allclose(a[k], b[k], rtol=0, atol=1e-4), f"step {n}: obs[{k!r}]"
    dropped = sum(int(np.sum(s["detector"][:2, 0] == 0)) for s in got)
    assert dropped > 0 and ref_faults > 0  # the poisoned rows were there, and dropped (present = 0)
    assert got_faults == ref_faults


def test_a_nan_truth_feature_is_replaced_and_counted_on_the_batch_as_per_env(monkeypatch):
    real_env, real_batch = TurnFeatures.features, BatchedLeftTurn.observe
    monkeypatch.setattr(TurnFeatures, "features", lambda self, *a: _poison_turn(real_env(self, *a)))
    monkeypatch.setattr(BatchedLeftTurn, "observe", lambda self, *a: _poison_turn(real_batch(self, *a)))
    keys = ("turn", "intent")
    sensors = _sensors("turn_truth")
    ref, ref_faults = _per_env(5, sensors, keys)
    got, got_faults = _batch(5, sensors, keys)
    assert len(got) == len(ref)
    for n, (a, b) in enumerate(zip(ref, got)):
        assert np.all(np.isfinite(a["turn"])) and np.all(np.isfinite(b["turn"])), f"step {n}"
        assert np.allclose(a["turn"], b["turn"], rtol=0, atol=1e-4), f"step {n}: obs['turn']"
    assert got_faults == ref_faults == len(ref)  # one NaN per reading, the first at reset included


@pytest.mark.parametrize("preset", ["turn_truth", "turn_perceived"])
def test_an_episode_without_faults_counts_none(preset):
    _, ref_faults = _per_env(3, _sensors(preset), ("turn",))
    _, got_faults = _batch(3, _sensors(preset), ("turn",))
    assert ref_faults == got_faults == 0.0
