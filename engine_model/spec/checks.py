"""Validation helpers of the spec dataclasses: messages that name the field, the value and the allowed range."""

from __future__ import annotations

import math

__all__ = ["check", "check_segments"]


def check(owner: str, name: str, value, lo=None, hi=None, lo_open=False, hi_open=False):
    """Raise ValueError unless ``lo (<|<=) value (<|<=) hi`` and value is finite."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.{name}: expected a number, got {value!r}") from None
    ok = math.isfinite(v)
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if not ok:
        lo_s = "-inf" if lo is None else f"{lo:g}"
        hi_s = "inf" if hi is None else f"{hi:g}"
        lb = "(" if lo_open or lo is None else "["
        rb = ")" if hi_open or hi is None else "]"
        raise ValueError(f"{owner}.{name} = {value!r} is outside the allowed range {lb}{lo_s}, {hi_s}{rb}")


def check_segments(owner: str, n):
    """Runner segment count: an integer in [1, 8]."""
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 8:
        raise ValueError(f"{owner}.runner_segments = {n!r} must be an integer in [1, 8]")
