"""Bounded linear least squares of the diagnosis and its K-fold held-out scores over operating points."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

__all__ = ["FitProblem", "solve_bounded", "columns_of", "fit_all", "heldout", "heldout_columns",
           "operating_point_groups", "make_folds"]


@dataclass
class FitProblem:
    """Whitened least-squares problem: r ~ A delta, rows = (point, output) observations."""

    r: np.ndarray          # (nobs,)
    a: np.ndarray          # (nobs, p) columns scaled to FD-step units
    point: np.ndarray      # (nobs,) point index of each observation
    output: np.ndarray     # (nobs,) output index
    base_cols: list[int]
    cand_cols: dict[str, list[int]]
    lo: np.ndarray         # (p,) bounds in step units (base: -inf)
    hi: np.ndarray

    @property
    def n_obs(self) -> int:
        """Number of measured observations (rows with ``point < 0`` are prior pseudo-observations)."""
        return int(np.count_nonzero(self.point >= 0))

    def fold_of_obs(self, folds: np.ndarray) -> np.ndarray:
        """Fold of each row; prior pseudo-observations get -2 (always fitted, never held out)."""
        return np.where(self.point >= 0, folds[np.maximum(self.point, 0)], -2)


def solve_bounded(a: np.ndarray, r: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Bounded linear least squares ||a x - r||, small ridge for rank-deficient columns."""
    if a.shape[1] == 0:
        return np.zeros(0)
    ata = a.T @ a
    lam = 1e-9 * (np.trace(ata) / a.shape[1] + 1e-30)
    try:
        x = np.linalg.solve(ata + lam * np.eye(a.shape[1]), a.T @ r)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(a, r, rcond=None)[0]
    if np.all(x >= lo - 1e-12) and np.all(x <= hi + 1e-12):
        return x
    from scipy.optimize import lsq_linear

    return lsq_linear(a, r, bounds=(lo, hi), method="bvls", lsmr_tol="auto").x


def columns_of(prob: FitProblem, cand: str | None) -> list[int]:
    return prob.base_cols + (prob.cand_cols[cand] if cand else [])


def fit_all(prob: FitProblem, cand: str | None, r: np.ndarray | None = None):
    cols = columns_of(prob, cand)
    r = prob.r if r is None else r
    a = prob.a[:, cols]
    x = solve_bounded(a, r, prob.lo[cols], prob.hi[cols])
    res = r - a @ x
    return x, float(res @ res), res


def heldout(prob: FitProblem, cand: str | None, folds: np.ndarray, r: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Held-out chi2 (sum over folds of test-point residuals) and per-observation held-out residuals.

    Prior pseudo-observations (``point < 0``) are in every training set and never held out (their held-out
    residual is 0).
    """
    return heldout_columns(prob, columns_of(prob, cand), folds, r)


def heldout_columns(prob: FitProblem, cols: list[int], folds: np.ndarray,
                  r: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """:func:`heldout` for any set of columns ``cols`` (e.g. the base plus two candidates)."""
    r = prob.r if r is None else r
    a = prob.a[:, cols]
    lo, hi = prob.lo[cols], prob.hi[cols]
    pred_res = np.zeros_like(r)
    fold_of_obs = prob.fold_of_obs(folds)
    for f in np.unique(fold_of_obs[fold_of_obs >= 0]):
        test = fold_of_obs == f
        train = ~test
        x = solve_bounded(a[train], r[train], lo, hi)
        pred_res[test] = r[test] - a[test] @ x
    return float(pred_res @ pred_res), pred_res


def operating_point_groups(points: pd.DataFrame) -> np.ndarray:
    """Operating-point index of each plan row: rows with the same speed, throttle and lambda (a spark sweep).

    Speeds are compared to 1 rpm, throttle to 0.1 %, lambda to 0.001.
    """
    key = pd.DataFrame({"n": np.round(points["speed_rpm"].to_numpy(float)),
                        "t": np.round(points["throttle_pct"].to_numpy(float), 1),
                        "l": np.round(points["lambda"].to_numpy(float), 3) if "lambda" in points.columns else 0.0})
    return key.groupby(["n", "t", "l"], sort=False).ngroup().to_numpy()


def make_folds(n_points: int, valid_points: np.ndarray, k: int, seed: int,
                groups: np.ndarray | None = None) -> np.ndarray:
    """Fold of each point; all points of one operating point (a spark sweep) share a fold, so a held-out
    point is never predicted from its own sweep's other sparks."""
    folds = np.full(n_points, -1)
    groups = np.arange(n_points) if groups is None else np.asarray(groups)
    ug = np.unique(groups[valid_points])
    k = max(2, min(k, ug.size))
    perm = np.random.default_rng(seed).permutation(ug.size)
    fold_of_group = dict(zip(ug[perm], np.arange(ug.size) % k))
    for i in np.flatnonzero(valid_points):
        folds[i] = fold_of_group[groups[i]]
    return folds

