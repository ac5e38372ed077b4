"""Confidence intervals, per-agent aggregation and markdown formatting."""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats as _st

__all__ = ["mean_ci", "wilson_ci", "is_binary", "aggregate", "markdown_table", "format_ci"]

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


def is_binary(x: Any) -> bool:
    """True iff ``x`` has at least one finite value and all finite values are 0 or 1."""
    try:
        a = np.asarray(x, dtype=float).ravel()
    except (TypeError, ValueError):
        return False
    a = a[np.isfinite(a)]
    return bool(a.size > 0 and np.all((a == 0.0) | (a == 1.0)))


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
    group) and, for each metric, ``metric``, ``metric_lo`` and ``metric_hi``.
    Binary metrics (0/1 over all rows) get Wilson bounds, others mean +/- the
    Student-t half-width. NaNs and missing values are ignored. Groups keep
    first-appearance order.
    """
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
    # Decide binary-ness over all rows so every group of one metric uses the
    # same kind of interval.
    binary = {m: is_binary(col) for m, col in columns.items()}

    groups: dict[Any, list[int]] = {}
    for i, row in enumerate(rows):
        if group_key not in row:
            raise ValueError(f"row {i} has no {group_key!r} key")
        groups.setdefault(row[group_key], []).append(i)

    out: list[dict] = []
    for name, idx in groups.items():
        entry: dict[str, Any] = {group_key: name, "n": len(idx)}
        for m in metrics:
            vals = columns[m][idx]
            vals = vals[~np.isnan(vals)]
            if binary[m]:
                p, lo, hi = wilson_ci(int(vals.sum()), int(vals.size), confidence)
            else:
                p, half = mean_ci(vals, confidence)
                lo, hi = p - half, p + half
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
