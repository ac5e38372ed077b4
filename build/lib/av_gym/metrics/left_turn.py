"""Unprotected-left-turn metrics computed from one episode's per-step traces.

Times are in s, speeds in m/s and distances in m.
"""

from __future__ import annotations

import numpy as np

__all__ = ["STOP_SPEED", "left_turn_summary"]

STOP_SPEED = 0.1  # m/s, below this the ego counts as stopped


def _as_1d(name: str, x: np.ndarray, *, dtype: type = float, allow_pos_inf: bool = False) -> np.ndarray:
    """Return ``x`` as a non-empty 1-D array, or raise ValueError naming ``name``."""
    arr = np.asarray(x)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} must contain at least one sample")
    try:
        arr = arr.astype(float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric") from None
    if allow_pos_inf:
        # TTC is +inf when no collision is predicted; NaN and -inf are still bugs.
        bad = np.isnan(arr) | (arr == -np.inf)
    else:
        bad = ~np.isfinite(arr)
    if np.any(bad):
        what = "finite or +inf" if allow_pos_inf else "finite"
        raise ValueError(f"{name} must contain only {what} values")
    if dtype is bool:
        if np.any((arr != 0.0) & (arr != 1.0)):
            raise ValueError(f"{name} must be boolean (0/1)")
        return arr.astype(bool)
    return arr


def left_turn_summary(
    time: np.ndarray,
    speed: np.ndarray,
    collision: np.ndarray,
    arrived: np.ndarray,
    ttc: np.ndarray,
    stop_line_offset: np.ndarray,
    oncoming_gap: np.ndarray,
    *,
    ttc_cap: float = 10.0,
) -> dict[str, float]:
    """Summarise one left-turn episode.

    Args (all shape (T,), one entry per policy step):
        time: s since episode start.
        speed: ego speed in m/s.
        collision: bool, ego crashed at or before this step.
        arrived: bool, ego reached the exit.
        ttc: time to collision in s; +inf when none is predicted.
        stop_line_offset: m, front bumper distance past the stop line
            (negative = before it).
        oncoming_gap: m, smallest x of the ego footprint minus the oncoming
            lane's near edge (negative = intruding into the oncoming lane).
        ttc_cap: s, upper bound applied to ``min_ttc_s`` so it is never inf.

    Returns:
        A dict of floats (booleans as 0.0/1.0, undefined values as NaN).
    """
    t = _as_1d("time", time)
    v = _as_1d("speed", speed)
    crashed = _as_1d("collision", collision, dtype=bool)
    done = _as_1d("arrived", arrived, dtype=bool)
    ttc_a = _as_1d("ttc", ttc, allow_pos_inf=True)
    offset = _as_1d("stop_line_offset", stop_line_offset)
    gap = _as_1d("oncoming_gap", oncoming_gap)
    sizes = {a.size for a in (t, v, crashed, done, ttc_a, offset, gap)}
    if len(sizes) != 1:
        raise ValueError(
            "time, speed, collision, arrived, ttc, stop_line_offset and oncoming_gap "
            "must have the same length"
        )
    ttc_cap = float(ttc_cap)
    if not np.isfinite(ttc_cap) or ttc_cap <= 0.0:
        raise ValueError(f"ttc_cap must be a finite number > 0, got {ttc_cap!r}")

    any_arrived = bool(done.any())
    any_collision = bool(crashed.any())
    # Everything "before exit" is the prefix up to (not including) the first
    # arrived step; without an arrival the whole episode counts.
    first_arrival = int(np.argmax(done)) if any_arrived else t.size
    before = slice(0, first_arrival)

    stopped_mask = v[before] < STOP_SPEED
    stopped = bool(stopped_mask.any())
    first_stop = int(np.argmax(stopped_mask)) if stopped else -1

    gap_before = gap[before]

    return {
        "collision": float(any_collision),
        "success": float(any_arrived and not any_collision),
        "time_to_exit_s": float(t[first_arrival]) if any_arrived else float("nan"),
        "min_ttc_s": float(min(ttc_a.min(), ttc_cap)),
        "stopped": float(stopped),
        "stop_line_offset_at_stop_m": float(offset[first_stop]) if stopped else float("nan"),
        "oncoming_gap_at_stop_m": float(gap[first_stop]) if stopped else float("nan"),
        # NaN when the ego is already arrived at step 0 (no steps before exit).
        "min_oncoming_gap_before_exit_m": float(gap_before.min()) if gap_before.size else float("nan"),
        "mean_speed_mps": float(v.mean()),
        "duration_s": float(t[-1]),
    }
