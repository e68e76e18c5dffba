"""Run small dense linear algebra on one BLAS thread.

OpenBLAS threads even 50 x 50 triangular solves; on a machine whose cores are
busy (the Dask workers of a sweep, other jobs) every threaded call then waits
for a free core, and a Gaussian-process fit that should take 0.1 s took 10 s
(measured here: a 51 x 51 Cholesky solve with 51 right-hand sides 24 ms on the
threaded library vs 0.04 ms on one thread).  :func:`single_thread_blas`
switches the OpenBLAS copies loaded in this process (numpy's and scipy's) to
one thread for the duration of a ``with`` block and restores them after.  Where
the libraries cannot be found (not Linux, another BLAS) it does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes

_NAMES = (("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
          ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
          ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
          ("openblas_get_num_threads", "openblas_set_num_threads"))
_CACHE: list | None = None


def _controls() -> list:
    global _CACHE
    if _CACHE is not None:
        return _CACHE
    found, paths = [], set()
    try:
        with open("/proc/self/maps") as fh:
            for line in fh:
                p = line.split()[-1]
                if "openblas" in p.lower() and ".so" in p:
                    paths.add(p)
    except OSError:
        paths = set()
    for p in sorted(paths):
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        for get, set_ in _NAMES:
            if hasattr(lib, get) and hasattr(lib, set_):
                g, s = getattr(lib, get), getattr(lib, set_)
                g.restype = ctypes.c_int
                s.argtypes = [ctypes.c_int]
                found.append((g, s))
                break
    _CACHE = found
    return found


@contextlib.contextmanager
def single_thread_blas():
    """Context: OpenBLAS on one thread inside, previous thread counts restored after."""
    import numpy  # noqa: F401  make sure the libraries are loaded before looking for them
    import scipy.linalg  # noqa: F401

    ctl = _controls()
    before = [g() for g, _ in ctl]
    try:
        for _, s in ctl:
            s(1)
        yield
    finally:
        for (_, s), n in zip(ctl, before):
            s(n)
