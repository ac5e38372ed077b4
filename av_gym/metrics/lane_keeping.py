"""Lane-keeping metrics computed from one episode's per-step traces.

All distances are in metres and angles in radians unless a key says otherwise.
The ``*_units`` keys use paper 001's scale, where the lane is 100 units wide
(lines at +/-50, right of centre positive).
"""

from __future__ import annotations

import numpy as np

__all__ = ["LANE_UNITS", "lane_keeping_summary"]

# Paper 001 reports deviation on a scale where the whole lane spans 100 units.
LANE_UNITS = 100.0


def _as_1d_finite(name: str, x: np.ndarray) -> np.ndarray:
    """Return ``x`` as a 1-D float array, or raise ValueError naming ``name``."""
    arr = np.asarray(x, dtype=float)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} must contain at least one sample")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must contain only finite values")
    return arr


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0.0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return value


def count_sign_changes(x: np.ndarray, deadband: float = 0.0) -> int:
    """Number of sign changes between consecutive samples of ``x`` (shape (T,)).

    Samples with ``|x| <= deadband`` are dropped first, so small jitter around
    zero neither creates nor hides a reversal of the steering direction.
    """
    x = np.asarray(x, dtype=float)
    signs = np.sign(x[np.abs(x) > deadband])
    if signs.size < 2:
        return 0
    return int(np.count_nonzero(signs[1:] != signs[:-1]))


def count_departures(out: np.ndarray) -> int:
    """Number of False->True transitions in the boolean trace ``out`` (shape (T,)).

    A trace that is already True at step 0 counts as one departure, since the
    vehicle is out of its lane from the start.
    """
    out = np.asarray(out, dtype=bool)
    if out.size == 0:
        return 0
    return int(out[0]) + int(np.count_nonzero(out[1:] & ~out[:-1]))


def _same_length(**series: np.ndarray) -> list[np.ndarray]:
    """Each series as a finite 1-D float array (ValueError naming it otherwise), all of one length."""
    arrays = [_as_1d_finite(name, values) for name, values in series.items()]
    if len({a.size for a in arrays}) > 1:
        raise ValueError(
            f"{', '.join(list(series)[:-1])} and {list(series)[-1]} must have the same length, got "
            f"{', '.join(str(a.size) for a in arrays)}"
        )
    return arrays


def lane_keeping_summary(
    cte: np.ndarray,
    steering: np.ndarray,
    progress: np.ndarray,
    *,
    lane_width: float,
    vehicle_width: float,
    lap_length: float,
    lap_completed: bool,
    steer_deadband: float = 1e-3,
) -> dict[str, float]:
    """Summarise one lane-keeping episode.

    Args:
        cte: shape (T,), signed cross-track error in m (+ = right of lane centre).
        steering: shape (T,), applied steering angle in rad.
        progress: shape (T,), cumulative distance along the centreline in m.
        lane_width: lane width in m (> 0).
        vehicle_width: ego width in m (0 <= vehicle_width < lane_width).
        lap_length: length of one lap in m (> 0).
        lap_completed: whether the episode finished the lap.
        steer_deadband: |steering| at or below this (rad) is treated as zero
            when counting sign changes.

    Returns:
        A dict of floats (booleans as 0.0/1.0); see the module docs for keys.
    """
    cte_a, steer_a, prog_a = _same_length(cte=cte, steering=steering, progress=progress)
    lane_width = _positive("lane_width", lane_width)
    lap_length = _positive("lap_length", lap_length)
    vehicle_width = float(vehicle_width)
    if not np.isfinite(vehicle_width) or not 0.0 <= vehicle_width < lane_width:
        raise ValueError(
            f"vehicle_width must be finite and in [0, lane_width), got {vehicle_width!r}"
        )
    steer_deadband = float(steer_deadband)
    if not np.isfinite(steer_deadband) or steer_deadband < 0.0:
        raise ValueError(f"steer_deadband must be a finite number >= 0, got {steer_deadband!r}")

    abs_cte = np.abs(cte_a)
    # Paper units: the lane spans LANE_UNITS, so the lines sit at +/- LANE_UNITS/2.
    u = LANE_UNITS * cte_a / lane_width
    abs_u = np.abs(u)

    # A wheel touches the line once the centre is more than half the free
    # lateral space (lane minus car) away from the lane centre.
    out_threshold = 0.5 * lane_width - 0.5 * vehicle_width
    out = abs_cte > out_threshold

    distance = float(prog_a[-1] - prog_a[0])
    # Clip to [0, 1] so a backwards-running episode does not report a negative lap.
    lap_fraction = float(np.clip(distance / lap_length, 0.0, 1.0))

    n_changes = count_sign_changes(steer_a, steer_deadband)
    changes_per_100m = 100.0 * n_changes / distance if distance > 0.0 else 0.0

    return {
        "cte_mean_abs_m": float(abs_cte.mean()),
        "cte_rms_m": float(np.sqrt(np.mean(cte_a**2))),
        "cte_std_m": float(cte_a.std(ddof=0)),
        "cte_max_abs_m": float(abs_cte.max()),
        "cte_bias_m": float(cte_a.mean()),
        "cte_mean_abs_units": float(abs_u.mean()),
        "cte_std_units": float(u.std(ddof=0)),
        "cte_max_abs_units": float(abs_u.max()),
        # Paper 001 Table 3 removes the mean before taking the MAE.
        "cte_centred_mae_units": float(np.mean(np.abs(u - u.mean()))),
        "lap_completed": float(bool(lap_completed)),
        "lap_fraction": lap_fraction,
        "distance_m": distance,
        "lane_departures": float(count_departures(out)),
        "time_fraction_out_of_lane": float(out.mean()),
        "steering_sign_changes_per_100m": float(changes_per_100m),
    }
