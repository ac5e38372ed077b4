"""benchmarks/belief_tracks_waiting.py: the box gap that names the car touching the ego, how it met the ego, and
the YIELD its futures play (the same meta-actions as av_gym.wrappers.meta_actions gives the real ego)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

from av_gym.geometry import box_corners

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
waiting = importlib.import_module("belief_tracks_waiting")


def _box(x: float, y: float, h: float = 0.0) -> np.ndarray:
    return box_corners(np.array([x, y]), h, 5.0, 2.0)


def test_box_gap():
    ego = _box(0.0, 0.0)
    assert waiting.box_gap(ego, _box(0.0, 3.0)) == pytest.approx(1.0)  # side by side, 1 m between the edges
    assert waiting.box_gap(ego, _box(6.0, 0.0)) == pytest.approx(1.0)  # bumper to bumper, 1 m apart
    assert waiting.box_gap(ego, _box(4.0, 0.5)) == 0.0  # overlapping
    # a box turned 90° whose nearest edge is 0.5 m beyond the ego's front (x = 2.5 + 0.5 + its half-width 1)
    assert waiting.box_gap(ego, _box(4.0, 0.0, np.pi / 2)) == pytest.approx(0.5)
    # a corner (turned 45°) pointing at the ego's side: the corner-to-edge distance, not centre to centre
    turned = _box(0.0, 1.0 + 0.3 + np.hypot(2.5, 1.0) * np.sin(np.pi / 4 + np.arctan2(1.0, 2.5)), np.pi / 4)
    assert waiting.box_gap(ego, turned) == pytest.approx(0.3, abs=1e-9)


@pytest.mark.parametrize("args, expected", [
    ((5.0, 0.0, 0.0, -1.7, False), "in front: backing into the ego"),
    ((5.0, 0.1, 0.02, 0.1, False), "in front: the ego ran into it"),
    ((5.0, -0.3, 3.1, 0.1, True), "in front: a wreck"),
    ((5.0, 0.7, 3.1, 2.0, False), "in front: across or head-on"),
    ((3.5, -2.9, 2.2, 1.5, True), "from the side: a wreck"),
    ((-5.2, 0.5, 0.1, 6.8, False), "from behind"),
    ((2.0, -3.0, 3.1, 5.0, False), "opposite heading"),
    ((2.7, -2.1, 1.6, 7.8, False), "crossing or turning across"),
])
def test_relation(args, expected):
    assert waiting.relation(*args) == expected


@pytest.mark.slow  # 4.3 s alone at load 3.2, most of it the first import of the batched engine
def test_yield_meta_is_the_real_yield():
    """The futures' YIELD (read from the engine's truth) asks for the meta-actions the real ego gets for YIELD
    (av_gym.wrappers.meta_actions on the turn features), step by step while the rows approach and stop; ``back``
    moves the stop earlier."""
    from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
    from av_gym.presets import compose_group
    from av_gym.wrappers import YIELD

    seeds = list(range(1_000_000, 1_000_004))
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, compose_group("sensors", "turn_truth"), None, len(seeds),
                                pool=0)
    obs = venv.play(iter(seeds))
    seen = set()
    for _ in range(60):
        real = meta_actions(np.full(len(seeds), YIELD), obs["turn"])
        np.testing.assert_array_equal(waiting.yield_meta(venv.engine), real)
        seen |= set(real.tolist())
        obs, _, done, _ = venv.step(real)
        assert not done.any()
    assert seen == {0, 1}  # SLOWER on the way to the line, IDLE at its set-point
    offset = venv.engine.truth()["stop_line_offset"]
    assert ((offset > -2.0) & (offset < 0.0)).all(), offset  # stood before the line
    # 4 m farther back from the same start: a set-point drop (SLOWER) earlier than at the line
    venv = BatchedLeftTurnBatch({"name": "left_turn"}, compose_group("sensors", "turn_truth"), None, len(seeds),
                                pool=0)
    venv.play(iter(seeds))
    for _ in range(60):
        venv.step(waiting.yield_meta(venv.engine, 4.0))
    assert (venv.engine.truth()["stop_line_offset"] < offset - 3.0).all()
