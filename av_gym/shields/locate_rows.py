"""``LanePath.locate`` of many points at once, for the AEB shield on the batch (it locates every row's ego each
step). Here, not on ``LanePath``, because the compiled walk and the lanes' kernel rows are the shields' (envs sit on
the same floor as shields and import none of them: tests/test_imports.py)."""

from __future__ import annotations

import numpy as np

from av_gym.shields.conflicts import _geometry
from av_gym.shields.kernels import DOT_FUSED
from av_gym.shields.kernels import locate_rows as _locate_rows_kernel


def locate_rows(path, x: np.ndarray, y: np.ndarray,
                hint: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``path.locate`` (an :class:`av_gym.envs.lane_path.LanePath`, not imported: envs and shields share a floor)
    of R points at once: ``x``, ``y`` (R,) m from the hint lanes ``hint`` (R,); each
    point's lane (R,) int, s on it (R,) m and lateral offset (R,) m, the method's walk and floats for each point
    (one compiled call, :func:`av_gym.shields.kernels.locate_rows`; why: ~10 us a point through ``locate``'s numpy
    calls on 2-vectors). Paths of lanes other than straight and circular, or a numpy whose 2-vector dot the kernel
    cannot reproduce: :meth:`LanePath.locate` point by point."""
    x, y = np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(y, dtype=float)
    hint = np.ascontiguousarray(hint, dtype=np.int64)
    table = _kernel_table(path)
    if table is None or DOT_FUSED is None:
        got = [path.locate(np.array([a, b]), k) for a, b, k in zip(x.tolist(), y.tolist(), hint.tolist())]
        k, s, lat = zip(*got) if got else ((), (), ())
        return np.array(k, dtype=np.int64), np.array(s, dtype=float), np.array(lat, dtype=float)
    lanes, lengths = table
    # numpy's own arctan2 of each point from each lane's centre (the stock local_coordinates' call; an
    # AVX-512 numpy's is not the C library's), unread for straight lanes
    phi = np.arctan2(y[:, None] - lanes[None, :, 2], x[:, None] - lanes[None, :, 1])
    out_k, out_s, out_lat = np.empty(len(x), np.int64), np.empty(len(x)), np.empty(len(x))
    _locate_rows_kernel(lanes, lengths, bool(path.closed), hint, x, y, phi, DOT_FUSED, out_k, out_s, out_lat)
    return out_k, out_s, out_lat


def _kernel_table(path) -> tuple[np.ndarray, np.ndarray] | None:
    """The lanes' kernel rows (L, 8) and lengths (L,) m of ``path``, kept on it; None where a lane is neither
    straight nor circular."""
    if "_locate_table" not in path.__dict__:
        rows = [_geometry(lane) for lane in path.lanes]
        path._locate_table = None if any(r is None for r in rows) else (
            np.array(rows, dtype=float), np.array([lane.length for lane in path.lanes], dtype=float))
    return path._locate_table
