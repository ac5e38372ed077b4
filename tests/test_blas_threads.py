"""tests/conftest.py's one BLAS thread per test process reaches numpy's OpenBLAS in the process that runs this test
(pytest's own under ``-p no:xdist``, or an xdist worker): OpenBLAS reads OMP_NUM_THREADS once, when numpy loads, so
the variable must be set before anything imports numpy."""

from __future__ import annotations

import ctypes
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

# threadpoolctl would say this but is no dependency of the project; its method, by hand: the OpenBLAS numpy loaded,
# found among the process's mapped libraries, asked through its C API (the symbol's prefix differs by build)
GETTERS = ("scipy_openblas_get_num_threads64_", "openblas_get_num_threads64_", "openblas_get_num_threads")


def _numpy_openblas_threads() -> int | None:
    """The thread count of the OpenBLAS under numpy (None: not Linux, or numpy not on OpenBLAS)."""
    maps = Path("/proc/self/maps")
    if not maps.exists():
        return None
    here = Path(np.__file__).resolve().parent.parent  # numpy's bundled libraries live beside it (numpy.libs)
    libs = sorted({p for p in re.findall(r"(/\S*openblas\S*\.so\S*)", maps.read_text()) if p.startswith(str(here))})
    for lib in libs:
        handle = ctypes.CDLL(lib)
        for name in GETTERS:
            getter = getattr(handle, name, None)
            if getter is not None:
                getter.restype = ctypes.c_int
                return int(getter())
    return None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/maps")
def test_numpys_openblas_runs_the_threads_conftest_set():
    from conftest import OMP_SET_HERE

    if not OMP_SET_HERE:
        pytest.skip("OMP_NUM_THREADS came from the user, or numpy was loaded (by a plugin) before the conftest")
    if "OPENBLAS_NUM_THREADS" in os.environ or "GOTO_NUM_THREADS" in os.environ:
        pytest.skip("the user set OpenBLAS's own thread variable, which wins over OMP_NUM_THREADS")
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one core: OpenBLAS runs one thread whatever the variable says, nothing to tell apart")
    threads = _numpy_openblas_threads()
    if threads is None:
        pytest.skip("numpy is not on a loaded OpenBLAS here")
    assert threads == 1, threads
