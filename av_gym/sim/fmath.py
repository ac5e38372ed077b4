"""Scalar math for the fast paths: Python's ``math`` where it is bit-identical to numpy, else numpy itself.

highway-env calls numpy ufuncs on single floats (``np.cos(heading)``), which costs ~1 µs of dispatch per call;
``math.cos`` costs ~50 ns. Both call the platform libm on x86-64 without AVX-512, but numpy may use its own SIMD
kernels elsewhere (e.g. SVML on AVX-512), which can differ in the last bit. So each function is checked once at
import against numpy on a fixed set of arguments spanning the ranges the simulator uses; a function that differs
anywhere falls back to the numpy ufunc, so the fast paths are bit-identical to the stock code on any machine.
"""

from __future__ import annotations

import math

import numpy as np

_rng = np.random.default_rng(12345)
_ANGLES = np.concatenate([_rng.uniform(-10.0, 10.0, 800), _rng.uniform(-1e3, 1e3, 100), [0.0, -0.0, 1e-12]])
_UNIT = np.concatenate([_rng.uniform(-1.0, 1.0, 600), [-1.0, 1.0, 0.0]])
_X, _Y = _rng.uniform(-300.0, 300.0, 600), _rng.uniform(-300.0, 300.0, 600)


def _pick(fast, slow, *args):
    """``fast`` if it equals ``slow`` bit for bit on every sample (``args`` arrays), else ``slow``."""
    # The stock code calls numpy on single floats, so compare with numpy called on single floats (array loops
    # may take other SIMD paths).
    ref = np.array([slow(*(float(a[i]) for a in args)) for i in range(len(args[0]))], dtype=float)
    got = np.array([fast(*(float(a[i]) for a in args)) for i in range(len(args[0]))], dtype=float)
    return fast if np.array_equal(ref.view(np.int64), got.view(np.int64)) else slow


cos = _pick(math.cos, np.cos, _ANGLES)
sin = _pick(math.sin, np.sin, _ANGLES)
tan = _pick(math.tan, np.tan, _ANGLES / 8)
atan = _pick(math.atan, np.arctan, _ANGLES)
asin = _pick(math.asin, np.arcsin, _UNIT)
atan2 = _pick(math.atan2, np.arctan2, _X, _Y)
def _pow(x, y):
    return x ** y


power = _pick(_pow, np.power, np.abs(_X) / 100.0, 3.5 + np.abs(_Y) / 300.0)  # IDM's exponent (DELTA) range
power = _pick(power, np.power, np.abs(_X) / 100.0, np.full(len(_X), 4.0))
square = _pick(lambda x: x * x, lambda x: np.power(x, 2), _X / 3.0)
sqrt = math.sqrt  # IEEE 754 requires a correctly rounded square root: always identical
pi = math.pi  # == np.pi


def wrap_to_pi(x: float) -> float:
    """``highway_env.utils.wrap_to_pi`` on a float (same operations, same result)."""
    return ((x + pi) % (2 * pi)) - pi


def not_zero(x: float, eps: float = 1e-2) -> float:
    """``highway_env.utils.not_zero``."""
    if abs(x) > eps:
        return x
    elif x >= 0:
        return eps
    return -eps


def clip(x: float, lo: float, hi: float) -> float:
    """``np.clip`` on a float (NaN propagates, like numpy's)."""
    if x != x:
        return x
    return lo if x < lo else hi if x > hi else x


ALL_EXACT = all(f.__module__ == "math" for f in (cos, sin, tan, atan, asin, atan2) if hasattr(f, "__module__"))


def _dot_is_plain() -> bool:
    """Whether ``np.dot`` and ``np.linalg.norm`` of 2-vectors (BLAS) equal ``a0*b0 + a1*b1`` and its square root
    bit for bit here (no fused multiply-add in the BLAS kernel); the fast lane geometry relies on it."""
    a, b = _X.reshape(-1, 2) / 7.0, _Y.reshape(-1, 2) / 3.0
    for u, v in zip(a, b):
        if np.dot(u, v) != u[0] * v[0] + u[1] * v[1]:
            return False
        if np.linalg.norm(u) != sqrt(u[0] * u[0] + u[1] * u[1]):
            return False
    return True


DOT_EXACT = _dot_is_plain()


def _dot_is_fused() -> bool | None:
    """Whether numpy's 2-vector dot is ``fma(a1, b1, a0*b0)`` (an FMA BLAS) rather than the plain sum, on samples
    where the two differ (checked exactly with fractions); None if it is neither (the AEB shield's conflict model then
    keeps its Python reference: av_gym.shields.kernels._dot2 reproduces the other two)."""
    from fractions import Fraction

    rng = np.random.default_rng(12345)
    fused = plain = True
    for a in rng.uniform(-300.0, 300.0, (400, 4)):
        d = float(np.dot(a[:2], a[2:]))
        fused &= d == float(Fraction(a[1]) * Fraction(a[3]) + Fraction(float(a[0] * a[2])))
        plain &= d == a[0] * a[2] + a[1] * a[3]
    if not (fused or plain):  # pragma: no cover - another BLAS
        return None
    return fused and not plain


DOT_FUSED = _dot_is_fused()
