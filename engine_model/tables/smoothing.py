"""Smoothing of a raw ECU table within per-cell bounds (a bounded least-squares fit with a curvature penalty),
and the weighted least-squares fit of a sequence under a monotone constraint (:func:`isotonic_nonincreasing`)."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["second_differences", "smooth_table", "bounded_quadratic", "isotonic_nonincreasing"]


def second_differences(table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Second differences per breakpoint along throttle (axis 0) and speed (axis 1)."""
    t = np.asarray(table, float)
    return t[2:, :] - 2 * t[1:-1, :] + t[:-2, :], t[:, 2:] - 2 * t[:, 1:-1] + t[:, :-2]


def _d2_operator(shape, keep: np.ndarray) -> np.ndarray:
    """Rows of the second-difference operator over stencils whose three cells are all ``keep``."""
    nt, ns = shape
    idx = np.arange(nt * ns).reshape(shape)
    rows = []
    for a, b, c in ((idx[:-2, :], idx[1:-1, :], idx[2:, :]), (idx[:, :-2], idx[:, 1:-1], idx[:, 2:])):
        for p, q, r in zip(a.ravel(), b.ravel(), c.ravel()):
            if keep[p] and keep[q] and keep[r]:
                row = np.zeros(nt * ns)
                row[p], row[q], row[r] = 1.0, -2.0, 1.0
                rows.append(row)
    return np.array(rows).reshape(-1, nt * ns)


def bounded_quadratic(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """argmin 0.5 x'Ax - b'x subject to lo <= x <= hi, A symmetric positive definite (primal active set)."""
    n = b.size
    at_lo, at_hi = lo >= hi, np.zeros(n, bool)   # fixed cells (lo == hi) sit at lo
    x = np.clip(np.zeros(n), lo, hi)
    for _ in range(4 * n + 10):
        free = ~(at_lo | at_hi)
        x = np.where(at_lo, lo, np.where(at_hi, hi, x))
        if free.any():
            rhs = b[free] - a[np.ix_(free, ~free)] @ x[~free]
            x[free] = np.linalg.solve(a[np.ix_(free, free)], rhs)
        low, high = free & (x < lo - 1e-12), free & (x > hi + 1e-12)
        if low.any() or high.any():
            at_lo |= low
            at_hi |= high
            continue
        g = a @ x - b                       # KKT: at a lower bound g >= 0, at an upper bound g <= 0
        rel = (at_lo & (lo < hi) & (g < -1e-10)) | (at_hi & (g > 1e-10))
        if not rel.any():
            break
        k = int(np.argmax(np.abs(np.where(rel, g, 0.0))))
        at_lo[k] = at_hi[k] = False
    return np.clip(x, lo, hi)


def smooth_table(raw: np.ndarray, weight: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 max_second_diff: float | None, stencil: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Least change that fills holes and bounds second differences, within per-cell bounds.

    Minimises ``sum w (x - raw)^2 + lam * sum (D2 x)^2`` subject to
    ``lower <= x <= upper`` (active-set solve, :func:`bounded_quadratic`), with the smallest
    ``lam`` (bisection in log10 over 1e-6..1e6) for which ``max |D2 x| <=
    max_second_diff`` over stencils of weighted cells.  Cells with weight 0
    (holes) take the minimum-curvature fill.

    Parameters
    ----------
    raw, weight, lower, upper : ndarray, shape (n_throttle, n_speed)
        Raw values (NaN allowed where weight is 0), weights (>= 0; the cost
        of moving a cell, e.g. its torque curvature), bounds.
    max_second_diff : float or None
        Bound [table unit]; None: fill only.
    stencil : ndarray of bool, optional
        Cells that take part in the smoothness penalty (default all).

    Returns
    -------
    ndarray
        Smoothed table.
    dict
        ``lam``, ``max_second_diff`` (achieved over weighted stencils),
        ``bound_met``, ``max_shift``, ``rms_shift`` (over weighted cells).
    """
    shape = raw.shape
    w = np.asarray(weight, float).ravel()
    r = np.where(w > 0, np.asarray(raw, float).ravel(), 0.0)
    lo, hi = np.asarray(lower, float).ravel(), np.asarray(upper, float).ravel()
    r = np.where(w > 0, np.clip(r, lo, hi), r)
    keep = np.ones(w.size, bool) if stencil is None else np.asarray(stencil, bool).ravel()
    d2 = _d2_operator(shape, keep)
    d2w = _d2_operator(shape, keep & (w > 0))
    dtd = d2.T @ d2 if d2.size else np.zeros((w.size, w.size))

    def solve(lam):
        return bounded_quadratic(np.diag(w) + lam * dtd + 1e-10 * np.eye(w.size), w * r, lo, hi)

    def worst(x):
        return float(np.max(np.abs(d2w @ x))) if d2w.size else 0.0

    lam_lo = 1e-6
    x = solve(lam_lo)
    lam = lam_lo
    if max_second_diff is not None and worst(x) > max_second_diff:
        x_hi = solve(1e6)
        if worst(x_hi) > max_second_diff:
            x, lam = x_hi, 1e6
        else:
            a, b = math.log10(lam_lo), 6.0
            x = x_hi
            for _ in range(14):   # 12 decades / 2^14: lam to within 0.2 %
                mid = 0.5 * (a + b)
                xm = solve(10 ** mid)
                if worst(xm) <= max_second_diff:
                    b, x = mid, xm
                else:
                    a = mid
            lam = 10 ** b
    if lam == lam_lo:   # no smoothing was needed: data cells keep their exact values, holes take the fill
        x = np.where(w > 0, r, x)
    shift = (x - r)[w > 0]
    info = {"lam": lam, "max_second_diff": worst(x),
            "bound_met": max_second_diff is None or worst(x) <= max_second_diff + 1e-9,
            "max_shift": float(np.max(np.abs(shift))) if shift.size else 0.0,
            "rms_shift": float(np.sqrt(np.mean(shift ** 2))) if shift.size else 0.0}
    return x.reshape(shape), info


def isotonic_nonincreasing(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """argmin sum w (x - y)^2 subject to x[0] >= x[1] >= ... (weighted least squares, non-increasing).

    Pool-adjacent-violators (Barlow et al., Statistical Inference under Order Restrictions, 1972, ch. 1): a
    run of neighbours that breaks the order is replaced by its weighted mean until none does; exact in at most
    n - 1 merges.  ``w`` > 0; a very large weight holds its value (a measured point among estimates).
    """
    y, w = np.asarray(y, float), np.asarray(w, float)
    if y.shape != w.shape or y.ndim != 1:
        raise ValueError(f"y and w must be 1-D of one length, got {y.shape} and {w.shape}")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(w)) and np.all(w > 0)):
        raise ValueError("y must be finite and w finite and > 0")
    mean, weight, size = [], [], []
    for v, u in zip(y, w):
        mean.append(float(v))
        weight.append(float(u))
        size.append(1)
        while len(mean) > 1 and mean[-2] < mean[-1]:
            u2 = weight[-2] + weight[-1]
            mean[-2] = (weight[-2] * mean[-2] + weight[-1] * mean[-1]) / u2
            weight[-2], size[-2] = u2, size[-2] + size[-1]
            del mean[-1], weight[-1], size[-1]
    return np.repeat(mean, size)
