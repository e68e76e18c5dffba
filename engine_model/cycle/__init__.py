"""Numba kernels of the crank-angle-resolved cycle model.

Rule of this package: pure ``@njit(cache=True)`` functions over float64 scalars
and arrays, SI units, no I/O, no pandas, no logging.  The Python face that
builds the arrays from an :class:`~engine_model.spec.EngineSpec` lives in
:mod:`engine_model.prepare` and :mod:`engine_model.simulate`.
"""
