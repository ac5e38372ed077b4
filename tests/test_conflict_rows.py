"""The batched shield's rows kernel that writes straight into the flat buffers (av_gym/shields/conflict_rows.py)
against the per-decision rows kernel it replaces (kernels.conflict_predict_rows: conflict_predict per decision, then
two copies): the same bytes in every buffer, for decisions of every size, with and without road users, served or not
(a speed bin not simulated yet, a block too small). That each decision is its own ConflictModel.predict is
tests/test_shield_kernels.py's (predict_rows runs this kernel)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_shield_kernels import _decisions, fresh_paths  # noqa: F401 -- fresh_paths: a fixture

K = 80


def _args(model, decisions, t: np.ndarray, shrink: int | None = None) -> tuple:
    """The rows kernels' arguments up to ``h_off``, as ConflictModel.predict_rows_flat builds them (block ``shrink``
    one hypothesis smaller than its room, if given)."""
    from av_gym.shields import conflicts

    others, lanes, accels, intent, row_off = decisions
    reg, args = model._kernel_inputs(others, lanes, accels, intent)
    h_off = conflicts._row_blocks(reg, args[3], row_off)
    if shrink is not None:
        size = np.diff(h_off)
        size[shrink] -= 1
        h_off = np.concatenate([[0], np.cumsum(size)]).astype(np.int64)
    return (row_off, *args, reg.ids, t, float(model.accel_time), *conflicts._store_arrays(), h_off)


def _run(kernel, args: tuple, fill: float) -> list[np.ndarray]:
    """``kernel`` on ``args`` into flat buffers first filled with ``fill`` (so that an entry written by one kernel and
    not the other shows), returned: xy, hh, owner, is_map, prob, n_h."""
    row_off, h_off = args[0], args[-1]
    n_all, R = int(h_off[-1]), len(row_off) - 1
    out = [np.full(2 * K * n_all, fill), np.full(K * n_all, fill), np.full(n_all, 7, np.int64),
           np.zeros(n_all, np.bool_), np.full(n_all, fill), np.full(R, 9, np.int64)]
    kernel(*args, *out)
    return out


# ~19 s in the fast suite (both kernels compiled, speed bins simulated): slow; tests/test_shield_kernels.py's rows
# test (each decision its own ConflictModel.predict, through this kernel) keeps the claim in the fast suite
@pytest.mark.slow
def test_the_direct_rows_kernel_writes_the_per_decision_kernels_bytes(fresh_paths):  # noqa: F811
    """Random decisions (sizes 0-9, standing, moving, off the map, with and without indicator readings; one whose
    road user reads speed bins not simulated yet; one whose block is a hypothesis too small): every flat buffer
    byte for byte the per-decision kernel's, including which decisions are served. Fails if a decision's block is
    written at another offset, transposed, from another decision's road users, or a decision not served is written."""
    from av_gym.shields.conflict_rows import conflict_predict_rows as direct
    from av_gym.shields.conflicts import ConflictModel
    from av_gym.shields.kernels import conflict_predict_rows as per_decision

    t = 0.1 * np.arange(1, K + 1)
    rng = np.random.default_rng(41)
    served, unserved, cv, on_map = 0, 0, 0, 0
    for trial in range(8):
        model = ConflictModel(fresh_paths, min_p=(0.1, 0.3)[trial % 2])
        sizes = tuple(int(s) for s in rng.integers(0, 10, 6))
        decisions = _decisions(fresh_paths, rng, sizes, own=int(np.argmax(sizes)))
        shrink = int(rng.integers(0, len(sizes))) if trial % 3 == 2 else None
        others, lanes, accels, intent, row_off = decisions
        if trial % 2:  # the speed bins they read simulated first (the reference's own calls): served
            for a, b in zip(row_off[:-1].tolist(), row_off[1:].tolist()):
                model.predict(others[a:b], lanes[a:b], accels[a:b], t, intent[a:b])
        for fill in (np.nan, -3.5):
            args = _args(model, decisions, t, shrink)
            want, got = _run(per_decision, args, fill), _run(direct, args, fill)
            for name, a, b in zip(("xy", "hh", "owner", "is_map", "prob", "n_h"), want, got):
                assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), (trial, fill, name)
        h_off, n_h = args[-1], want[5]
        served, unserved = served + int((n_h >= 0).sum()), unserved + int((n_h < 0).sum())
        for o, H in zip(h_off[:-1].tolist(), n_h.tolist()):
            on_map, cv = on_map + int(want[3][o: o + max(H, 0)].sum()), cv + int((~want[3][o: o + max(H, 0)]).sum())
    assert served > 20 and unserved >= 2 and on_map > 30 and cv > 5  # every branch met
