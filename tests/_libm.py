"""Whether numpy's float64 ufuncs give the C library's results on this machine: numba's ``math`` calls the C
library (Python's math.hypot does not, hence ctypes), so where they agree the kernels' tests compare floats bit for
bit; an AVX-512 numpy build uses its own SIMD maths and may differ in the last bit. Shared by the kernel tests of
the batched simulator, the sensors and the shield."""

from __future__ import annotations

import ctypes
import ctypes.util

import numpy as np


def numpy_is_libm(*names: str) -> bool:
    """numpy's float64 ``names`` (of cos, sin, tan, asin, atan2, hypot, pow) equal libm's on 2,000 sample values."""
    libm = ctypes.CDLL(ctypes.util.find_library("m"))
    rng = np.random.default_rng(0)
    a, b = rng.uniform(-10, 10, (2, 2000))
    x = rng.uniform(-1, 1, 2000)
    cases = {"cos": (np.cos, (a,)), "sin": (np.sin, (a,)), "tan": (np.tan, (a / 7,)), "asin": (np.arcsin, (x,)),
             "atan2": (np.arctan2, (a, b)), "hypot": (np.hypot, (a, b)), "pow": (np.power, (np.abs(a), b / 3))}
    for name in names:
        ufunc, args = cases[name]
        c = getattr(libm, name)
        c.restype, c.argtypes = ctypes.c_double, [ctypes.c_double] * len(args)
        if not np.array_equal(ufunc(*args), [c(*v) for v in zip(*args)]):
            return False
    return True
