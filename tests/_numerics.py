"""How the equivalence tests compare a compiled kernel (or the batched engine) with the numpy code it replaces,
on any machine the declared dependencies install on.

Decisions (bools, ints, indices) must be identical. Floats must agree to ``REL`` relative (with the same
non-finite pattern): numba calls the C library's ``cos``/``pow``/..., numpy may use its own SIMD maths (AVX-512
builds do), and LLVM and the C compiler may order or fuse (FMA) a sum differently, so the last bit or two of a
transcendental or a reordered sum differs between machines (measured on an AVX-512 machine: 21-28 of 896 IDM
accelerations differ by at most 1.2e-13 relative). 1e-12 is ~4,500 ULP: far above that noise, and ten orders of
magnitude below what a real change gives (a dropped term, a changed constant, ``<`` for ``<=`` at an exact tie:
see each test's docstring for the mutation that fails it)."""

from __future__ import annotations

import numpy as np

REL = 1e-12


def same(a, b, rel: float = REL) -> bool:
    """Same shape; same dtype kind; non-floats identical; floats within ``rel`` of each other relative to the larger
    magnitude (absolute ``rel`` below 1), with NaN and +-inf in the same places."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype.kind != b.dtype.kind:
        return False
    if a.dtype.kind not in "fc":
        return bool(np.array_equal(a, b))
    finite = np.isfinite(a)
    if not (np.array_equal(finite, np.isfinite(b)) and np.array_equal(np.isnan(a), np.isnan(b))
            and np.array_equal(a[np.isinf(a)], b[np.isinf(b)])):
        return False
    x, y = a[finite], b[finite]
    return bool(np.all(np.abs(x - y) <= rel * np.maximum(1.0, np.maximum(np.abs(x), np.abs(y)))))


def assert_same(a, b, what: str = "", rel: float = REL) -> None:
    """``same`` with a message giving the largest difference."""
    if not same(a, b, rel):
        a, b = np.asarray(a), np.asarray(b)
        detail = f"shapes {a.shape} vs {b.shape}, dtypes {a.dtype} vs {b.dtype}"
        if a.shape == b.shape and a.dtype.kind in "fc" and b.dtype.kind in "fc":
            with np.errstate(invalid="ignore"):
                d = np.abs(a - b)
            detail = f"max |diff| {np.nanmax(d) if d.size else 0:.3g}"
        raise AssertionError(f"{what} differ beyond {rel:g} relative: {detail}")
