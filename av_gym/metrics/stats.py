"""Confidence intervals, per-agent aggregation and markdown formatting."""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats as _st

__all__ = ["mean_ci", "wilson_ci", "bootstrap_ci", "interval", "aggregate", "markdown_table", "format_ci"]

BOOTSTRAP_RESAMPLES = 2000  # resampled means per interval: bounds stable to ~1 % of their width
BOOTSTRAP_SEED = 0  # every interval is reproducible: the same episodes give the same bounds

_NAN = float("nan")
_DASH = "\u2013"  # en dash, shown for NaN cells
_SKIP_KEYS = ("seed", "episode")  # identifiers, not metrics


def _check_confidence(confidence: float) -> float:
    confidence = float(confidence)
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    return confidence


def mean_ci(x: ArrayLike, confidence: float = 0.95) -> tuple[float, float]:
    """Sample mean and Student-t half-width of its confidence interval.

    ``x`` is flattened and NaNs are ignored. Returns ``(nan, nan)`` for no
    data and ``(mean, nan)`` for one sample (no spread estimate).
    """
    confidence = _check_confidence(confidence)
    a = np.asarray(x, dtype=float).ravel()
    a = a[~np.isnan(a)]
    n = a.size
    if n == 0:
        return _NAN, _NAN
    mean = float(a.mean())
    if n < 2:
        return mean, _NAN
    sem = float(a.std(ddof=1)) / math.sqrt(n)
    t = float(_st.t.ppf(0.5 + confidence / 2.0, df=n - 1))
    return mean, t * sem


def wilson_ci(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float, float]:
    """Success rate and Wilson score interval ``(p, lo, hi)`` for a binomial.

    Wilson rather than the normal approximation because it stays inside
    [0, 1] and is sensible at 0 or n successes with few episodes.
    Returns NaNs when ``n == 0``.
    """
    confidence = _check_confidence(confidence)
    if n < 0 or successes < 0 or successes > n:
        raise ValueError(f"successes must be in [0, n] with n >= 0, got successes={successes}, n={n}")
    if n == 0:
        return _NAN, _NAN, _NAN
    p = successes / n
    z = float(_st.norm.ppf(0.5 + confidence / 2.0))
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2.0 * n)) / denom
    half = z * math.sqrt(p * (1.0 - p) / n + z2 / (4.0 * n * n)) / denom
    # At 0 or n successes the bound is exactly 0 or 1; set it so rounding
    # cannot push it outside [0, 1].
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return float(p), float(lo), float(hi)


def bootstrap_ci(x: ArrayLike, confidence: float = 0.95, seed: int = BOOTSTRAP_SEED,
                 resamples: int = BOOTSTRAP_RESAMPLES) -> tuple[float, float, float]:
    """Mean and a bootstrap interval ``(mean, lo, hi)`` of a quantity that cannot be negative (or is otherwise
    bounded by its episodes' values): scipy's BCa bootstrap of the mean over resampled episodes, from a generator
    seeded with ``seed`` (``resamples`` resampled means). Its bounds are means of resampled episodes, so they lie in [min, max] of the data: never
    negative for a non-negative quantity, exactly [0, 0] when every episode is 0. NaNs are ignored; no data gives
    NaNs, one value (or all equal) gives ``(v, v, v)``."""
    confidence = _check_confidence(confidence)
    a = np.asarray(x, dtype=float).ravel()
    a = a[~np.isnan(a)]
    if a.size == 0:
        return _NAN, _NAN, _NAN
    mean = float(a.mean())
    lo_data, hi_data = float(a.min()), float(a.max())
    if lo_data == hi_data:  # no spread: nothing to resample (BCa's acceleration would divide by zero)
        return mean, lo_data, hi_data
    res = _st.bootstrap((a,), np.mean, confidence_level=confidence, n_resamples=resamples,
                        method="BCa", random_state=np.random.default_rng(seed))
    lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
    if not (math.isfinite(lo) and math.isfinite(hi)):  # BCa undefined (e.g. one odd value): plain percentiles
        res = _st.bootstrap((a,), np.mean, confidence_level=confidence, n_resamples=resamples,
                            method="percentile", random_state=np.random.default_rng(seed))
        lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
    # A resampled mean cannot leave [min, max]; the clip only removes rounding in scipy's interpolation.
    return mean, min(max(lo, lo_data), mean), max(min(hi, hi_data), mean)


def interval(x: ArrayLike, kind: str, confidence: float = 0.95) -> tuple[float, float, float]:
    """``(mean, lo, hi)`` of per-episode values of a metric of ``kind`` (av_gym/metrics/kinds.py): Wilson for a
    rate (0/1 per episode; ValueError otherwise), a seeded bootstrap for counts, durations and other non-negative
    quantities, Student t for signed ones."""
    a = np.asarray(x, dtype=float).ravel()
    a = a[~np.isnan(a)]
    if kind == "rate":
        if not np.all((a == 0.0) | (a == 1.0)):
            raise ValueError(f"a rate's episodes must each be 0 or 1, got values {sorted(set(a.tolist()))[:5]}")
        return wilson_ci(int(a.sum()), int(a.size), confidence)
    if kind in ("count", "duration", "nonnegative"):
        if np.any(a < 0):
            raise ValueError(f"a {kind} cannot be negative, got {float(a.min())}")
        return bootstrap_ci(a, confidence)
    if kind == "signed":
        mean, half = mean_ci(a, confidence)
        return mean, mean - half, mean + half
    raise ValueError(f"kind must be one of ['rate', 'count', 'duration', 'nonnegative', 'signed'], got {kind!r}")


def _is_number(v: Any) -> bool:
    # bool is a Number too, which is what we want: success flags are metrics.
    if isinstance(v, np.bool_):
        return True
    return isinstance(v, numbers.Number) and not isinstance(v, (complex, np.complexfloating))


def aggregate(
    rows: list[dict],
    group_key: str = "agent",
    metrics: list[str] | None = None,
    confidence: float = 0.95,
) -> list[dict]:
    """Per-group mean and confidence bounds of per-episode metrics.

    Each output dict has ``group_key`` (the group name), ``n`` (episodes in the
    group) and, for each metric, ``metric``, ``metric_lo`` and ``metric_hi``, the
    interval its declared kind calls for (:func:`interval`, av_gym/metrics/kinds.py:
    Wilson for rates, bootstrap for non-negative quantities, t for signed ones).
    NaNs and missing values are ignored. Groups keep first-appearance order.
    """
    from av_gym.metrics.kinds import kind_of

    if metrics is None:
        metrics = []
        for row in rows:
            for k, v in row.items():
                if k != group_key and k not in _SKIP_KEYS and _is_number(v) and k not in metrics:
                    metrics.append(k)

    def value(row: dict, key: str) -> float:
        v = row.get(key, _NAN)
        if v is None:
            return _NAN
        try:
            return float(v)
        except (TypeError, ValueError):
            raise ValueError(f"metric {key!r} has non-numeric value {v!r}") from None

    columns = {m: np.array([value(r, m) for r in rows], dtype=float) for m in metrics}

    groups: dict[Any, list[int]] = {}
    for i, row in enumerate(rows):
        if group_key not in row:
            raise ValueError(f"row {i} has no {group_key!r} key")
        groups.setdefault(row[group_key], []).append(i)

    out: list[dict] = []
    for name, idx in groups.items():
        entry: dict[str, Any] = {group_key: name, "n": len(idx)}
        for m in metrics:
            p, lo, hi = interval(columns[m][idx], kind_of(m), confidence)
            entry[m] = p
            entry[m + "_lo"] = lo
            entry[m + "_hi"] = hi
        out.append(entry)
    return out


def _fmt_cell(v: Any, floatfmt: str) -> str:
    if v is None:
        return ""
    if isinstance(v, (float, np.floating)):
        return _DASH if math.isnan(v) else format(float(v), floatfmt)
    # Pipes would split the cell in markdown.
    return str(v).replace("|", "\\|")


def markdown_table(rows: list[dict], columns: list[str], floatfmt: str = ".3g") -> str:
    """GitHub-markdown table of ``rows`` restricted to ``columns``.

    Floats use ``floatfmt``; NaN shows as an en dash; missing keys are blank.
    """
    lines = [
        "| " + " | ".join(columns) + " |",
        "|" + "|".join(" --- " for _ in columns) + "|",
    ]
    for row in rows:
        lines.append("| " + " | ".join(_fmt_cell(row.get(c), floatfmt) for c in columns) + " |")
    return "\n".join(lines)


def format_ci(mean: float, lo: float, hi: float, binary: bool, *, floatfmt: str = ".3g") -> str:
    """``"mean [lo, hi]"``; binary metrics as a rate with two decimals.

    NaN mean gives an en dash; NaN bounds (e.g. one sample) give the mean alone.
    """
    fmt = ".2f" if binary else floatfmt
    if mean is None or math.isnan(mean):
        return _DASH
    if lo is None or hi is None or math.isnan(lo) or math.isnan(hi):
        return format(float(mean), fmt)
    return f"{float(mean):{fmt}} [{float(lo):{fmt}}, {float(hi):{fmt}}]"
