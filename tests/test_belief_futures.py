"""agents.belief.play_go_fast lets the GO futures that ended wait in the engine (step's ``active`` mask) and drops
them once half of the rows have ended: each future must end as it does when every ended row is dropped at once
(one copy of the engine per end, the planner's play before this bookkeeping)."""

from __future__ import annotations

import numpy as np

from agents.belief import play_go_fast
from av_gym.batched.left_turn import BatchedLeftTurn
from av_gym.make import highway_config
from av_gym.sim.batched import FASTER, IDLE, SLOWER


def _play_dropping_each_end(f) -> np.ndarray:
    """GO to the end on every row, the ended rows dropped (BatchedLeftTurn.keep) at every step some row ends."""
    safe, idx, top = np.ones(f.B, bool), np.arange(f.B), float(f.speeds[-1])
    while len(idx):
        sp = f.traffic.target[np.arange(f.B), f.ego_slot()]
        _, terminated, truncated = f.step(np.where(top > sp + 1e-3, FASTER, np.where(top < sp - 1e-3, SLOWER, IDLE)))
        ended = terminated | truncated
        if ended.any():
            e = np.nonzero(ended)[0]
            safe[idx[e]] = ~f.traffic.crashed[e, f.ego_slot(e)]
            keep = np.nonzero(~ended)[0]
            idx = idx[keep]
            if len(idx):
                f = f.keep(keep)
    return safe


def test_go_futures_end_as_when_each_ended_row_is_dropped_at_once():
    _, config = highway_config({"name": "left_turn"})
    bt = BatchedLeftTurn(12, config)
    bt.reset(list(range(4100, 4112)))
    for _ in range(5):
        bt.step(np.full(12, IDLE))
    futures = bt.fork(np.arange(12), 4)  # 48 rows, each with a copy of its row's generator: its own spawns
    fast = play_go_fast(futures.fork(np.arange(futures.B)))
    ref = _play_dropping_each_end(futures.fork(np.arange(futures.B)))
    assert np.array_equal(fast, ref) and fast.any() and not fast.all(), (fast, ref)
