"""Pure test-plan (DOE) designs: grids, space-filling samples, D-optimal plans, bench order, Wiebe grids.

Every plan is a :class:`pandas.DataFrame` with a unique string ``point_id``,
the operating-point columns ``speed_rpm, throttle_pct, spark_deg_btdc,
lambda`` and the design's own columns (``design``, and, where they apply,
``run_order``, ``sweep_id``, ``step``, ``stop_reason``, ``feasible``,
``infeasible_reason``, ``base_point_id``).  Generators record how they were
called in ``plan.attrs`` (``generator``, ``seed``, ``bounds``), which
:func:`save_plan` writes next to the table.

Generators here are pure (no model run): :func:`full_factorial` (ECU-style
grid), :func:`latin_hypercube`, :func:`sobol`, :func:`d_optimal` (Fedorov
exchange); plan tools :func:`bench_order`, :func:`wiebe_grid`,
:func:`d_efficiency`.  Plans that need the model (spark sweeps, feasibility)
are in :mod:`engine_model.doe.screening`; plan files in
:mod:`engine_model.doe.plans`.

References
----------
.. [P] Mrda, Miljic, Kitanovic, Popovic, Tomic, "Model based approach in
   Yamaha R6 Formula Student engine control parameters optimisation",
   MVM2012-024 (Figure 1, Table 2, eqs 2-5, bench procedure).
.. [H] J.B. Heywood, Internal Combustion Engine Fundamentals, McGraw-Hill
   1988, sec. 9.3 (burn angles vs speed, load and residual gas).
.. [F] V.V. Fedorov, Theory of Optimal Experiments, Academic Press 1972;
   A.C. Atkinson, A.N. Donev, R.D. Tobias, Optimum Experimental Designs,
   with SAS, Oxford 2007, ch. 12 (exchange algorithms, D-efficiency).
"""

from __future__ import annotations

import functools
import itertools
import math
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from engine_model.contracts import PLAN_COLUMNS
from engine_model.priors import lambda_target, spark_estimate
from engine_model.spec import default_spec

__all__ = ["DEFAULT_BOUNDS", "FACTORS", "PHYSICAL_RANGES", "full_factorial", "latin_hypercube", "sobol",
           "model_matrix", "d_efficiency", "d_optimal", "maximin_augment", "bench_order", "wiebe_grid", "check_range",
           "finish_plan"]

#: Factors a space-filling or optimal design may vary, in canonical order.
FACTORS = ("speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda")

#: Default design space: the rpm range of the paper's Figure 1 and the throttle
#: range above the throttle plate's leakage regime.
DEFAULT_BOUNDS = {"speed_rpm": (3000.0, 13000.0), "throttle_pct": (5.0, 100.0)}



PHYSICAL_RANGES = {"throttle_pct": (0.0, 100.0), "spark_deg_btdc": (-30.0, 90.0), "lambda": (0.5, 2.0)}
_MODELS = ("linear", "interaction", "quadratic")


# --------------------------------------------------------------------------- priors











# --------------------------------------------------------------------------- helpers

@functools.lru_cache(maxsize=1)
def _max_speed_rpm() -> float:
    return default_spec().geometry.max_speed_rpm


def check_range(key: str, lo: float, hi: float, who: str) -> None:
    """ValueError unless low..high of factor ``key`` is finite and physically allowed."""
    plo, phi = (0.0, _max_speed_rpm()) if key == "speed_rpm" else PHYSICAL_RANGES[key]
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{who}: {key} range ({lo:g}, {hi:g}) must be finite")
    if lo < plo or hi > phi or (key == "speed_rpm" and lo <= 0):
        raise ValueError(f"{who}: {key} range ({lo:g}, {hi:g}) leaves the allowed range "
                         f"{'(' if key == 'speed_rpm' else '['}{plo:g}, {phi:g}]")


def _check_bounds(bounds: Mapping | None, who: str) -> dict:
    """Merge with DEFAULT_BOUNDS, validate, return {factor: (lo, hi)} in canonical order."""
    merged = dict(DEFAULT_BOUNDS)
    merged.update(bounds or {})
    for key in merged:
        if key not in FACTORS:
            raise ValueError(f"{who}: unknown bounds key {key!r}; allowed: {list(FACTORS)}")
    out = {}
    for key in FACTORS:
        if key not in merged:
            continue
        try:
            lo, hi = (float(v) for v in merged[key])
        except (TypeError, ValueError):
            raise ValueError(f"{who}: bounds[{key!r}] = {merged[key]!r} must be a (low, high) pair") from None
        check_range(key, lo, hi, who)
        if not lo < hi:
            raise ValueError(f"{who}: bounds[{key!r}] = ({lo:g}, {hi:g}) needs low < high")
        out[key] = (lo, hi)
    return out


def finish_plan(df: pd.DataFrame, prefix: str, design: str, attrs: dict) -> pd.DataFrame:
    """Fill spark/lambda estimates, add point_id and design, order the columns, set attrs."""
    n, t = df["speed_rpm"].to_numpy(float), df["throttle_pct"].to_numpy(float)
    if "spark_deg_btdc" not in df.columns:
        df["spark_deg_btdc"] = np.atleast_1d(spark_estimate(n, t))
    if "lambda" not in df.columns:
        df["lambda"] = np.atleast_1d(lambda_target(t))
    width = max(4, len(str(len(df))))
    df.insert(0, "point_id", [f"{prefix}-{i + 1:0{width}d}" for i in range(len(df))])
    df["design"] = design
    rest = ["design"] + [c for c in df.columns if c not in PLAN_COLUMNS + ("design",)]
    df = df[list(PLAN_COLUMNS) + rest].reset_index(drop=True)
    df.attrs = dict(attrs)
    return df


def _scale(unit: np.ndarray, bounds: dict) -> pd.DataFrame:
    lo = np.array([b[0] for b in bounds.values()])
    hi = np.array([b[1] for b in bounds.values()])
    return pd.DataFrame(lo + unit * (hi - lo), columns=list(bounds))


def _check_n(n, who: str) -> int:
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"{who}: n = {n!r} must be a positive integer")
    return int(n)


# --------------------------------------------------------------------------- generators

def full_factorial(speed_rpm: Sequence[float] = tuple(range(3000, 13001, 1000)),
                   throttle_pct: Sequence[float] = (5, 10, 15, 20, 30, 40, 60, 80, 100),
                   spark_deg_btdc=None, lam=None) -> pd.DataFrame:
    """ECU-style full-factorial grid (throttle % x rpm [x spark] [x lambda]).

    Parameters
    ----------
    speed_rpm : sequence of float
        Speed sites [rpm].  The default 3000-13000 rpm in 1000 rpm steps spans
        the paper's Figure 1 (its exact ECU sites are not given).
    throttle_pct : sequence of float
        Throttle sites [%].
    spark_deg_btdc : None, float or sequence of float
        None: :func:`spark_estimate` per site; a scalar: that advance [deg
        BTDC] everywhere; a sequence: an extra grid axis.
    lam : None, float or sequence of float
        None: :func:`lambda_target` per site (0.9 at WOT, 1.0 at part load);
        a scalar or a sequence (extra axis) as for spark.

    Returns
    -------
    DataFrame
        ``point_id`` 'ff-0001'..., the plan columns and ``design`` =
        'full_factorial', rows in bench order (throttle, then speed, spark,
        lambda ascending).
    """
    axes = {"throttle_pct": np.sort(np.atleast_1d(np.asarray(throttle_pct, float))),
            "speed_rpm": np.sort(np.atleast_1d(np.asarray(speed_rpm, float)))}
    for col, val in (("spark_deg_btdc", spark_deg_btdc), ("lambda", lam)):
        if val is not None:
            axes[col] = np.sort(np.atleast_1d(np.asarray(val, float)))
    for col, vals in axes.items():
        if vals.size == 0 or len(np.unique(vals)) != vals.size:
            raise ValueError(f"full_factorial: {col} sites must be non-empty and distinct; got {vals}")
        check_range(col, float(vals.min()), float(vals.max()), "full_factorial")
    df = pd.DataFrame(list(itertools.product(*axes.values())), columns=list(axes))
    attrs = {"generator": "full_factorial", "seed": None,
             "levels": {k: v.tolist() for k, v in axes.items()}}
    return finish_plan(df, "ff", "full_factorial", attrs)


def latin_hypercube(n: int = 32, bounds: Mapping | None = None, seed: int = 0) -> pd.DataFrame:
    """Latin-hypercube sample of the design space (``scipy.stats.qmc.LatinHypercube``).

    Parameters
    ----------
    n : int
        Number of points.
    bounds : dict {column: (low, high)}, optional
        Any of ``speed_rpm`` [rpm], ``throttle_pct`` [%], ``spark_deg_btdc``
        [deg BTDC], ``lambda`` [-]; merged over :data:`DEFAULT_BOUNDS`.
        Columns not bounded are filled by :func:`spark_estimate` /
        :func:`lambda_target`.
    seed : int
        Seed; the same seed gives the same plan.

    Returns
    -------
    DataFrame
        ``point_id`` 'lhs-0001'..., plan columns, ``design`` = 'latin_hypercube'.
    """
    from scipy.stats import qmc  # late import: scipy.stats costs ~0.9 s at package import

    n = _check_n(n, "latin_hypercube")
    b = _check_bounds(bounds, "latin_hypercube")
    unit = qmc.LatinHypercube(d=len(b), seed=np.random.default_rng(seed)).random(n)
    return finish_plan(_scale(unit, b), "lhs", "latin_hypercube",
                   {"generator": "latin_hypercube", "seed": seed, "bounds": b})


def sobol(n: int = 32, bounds: Mapping | None = None, seed: int = 0) -> pd.DataFrame:
    """Scrambled Sobol' sample of the design space (``scipy.stats.qmc.Sobol``).

    Parameters
    ----------
    n : int
        Number of points.  Sobol' balance properties hold for powers of 2;
        for other ``n`` the first ``n`` points of a ``2**ceil(log2 n)``
        sequence are returned (still low-discrepancy, slightly less uniform).
    bounds : dict, optional
        As in :func:`latin_hypercube`.
    seed : int
        Scrambling seed.

    Returns
    -------
    DataFrame
        ``point_id`` 'sobol-0001'..., plan columns, ``design`` = 'sobol'.
    """
    from scipy.stats import qmc

    n = _check_n(n, "sobol")
    b = _check_bounds(bounds, "sobol")
    gen = qmc.Sobol(d=len(b), scramble=True, seed=np.random.default_rng(seed))
    unit = gen.random_base2(m=max(0, math.ceil(math.log2(n))))[:n]
    return finish_plan(_scale(unit, b), "sobol", "sobol", {"generator": "sobol", "seed": seed, "bounds": b})


def _coded(plan: pd.DataFrame, bounds: dict) -> np.ndarray:
    cols = []
    for key, (lo, hi) in bounds.items():
        if key not in plan.columns:
            raise ValueError(f"d_efficiency: plan has no column {key!r} (factor of the bounds)")
        cols.append(2.0 * (plan[key].to_numpy(float) - lo) / (hi - lo) - 1.0)
    return np.column_stack(cols)


def model_matrix(coded: np.ndarray, model: str = "quadratic") -> np.ndarray:
    """Polynomial model matrix of coded factors.

    Parameters
    ----------
    coded : ndarray, shape (n, k)
        Factors coded to -1..1.
    model : {'linear', 'interaction', 'quadratic'}
        Intercept + main effects; + two-factor interactions; + pure squares.

    Returns
    -------
    ndarray, shape (n, p)
        p = 1 + k, 1 + k + k(k-1)/2 or 1 + 2k + k(k-1)/2.
    """
    if model not in _MODELS:
        raise ValueError(f"model = {model!r}; choose one of {list(_MODELS)}")
    x = np.atleast_2d(np.asarray(coded, float))
    k = x.shape[1]
    cols = [np.ones(len(x))] + [x[:, i] for i in range(k)]
    if model in ("interaction", "quadratic"):
        cols += [x[:, i] * x[:, j] for i, j in itertools.combinations(range(k), 2)]
    if model == "quadratic":
        cols += [x[:, i] ** 2 for i in range(k)]
    return np.column_stack(cols)


def d_efficiency(plan: pd.DataFrame, model: str = "quadratic", bounds: Mapping | None = None) -> float:
    """D-efficiency of a plan for a polynomial response-surface model [%].

    Parameters
    ----------
    plan : DataFrame
        Needs a column per bounded factor.
    model : {'linear', 'interaction', 'quadratic'}
    bounds : dict {column: (low, high)}, optional
        Coding of the factors (x_coded = 2 (x - low)/(high - low) - 1); default
        ``plan.attrs['bounds']``.  Only the columns in ``bounds`` are factors.

    Returns
    -------
    float
        ``D_eff = 100 * det(X'X)^(1/p) / n`` with X the (n x p) model matrix in
        coded units.  100 % for an orthogonal two-level design and a linear
        model (X'X = n I); 0 if X'X is singular.  Comparable between plans of
        the same size, model and bounds (Atkinson, Donev & Tobias 2007, [F]).
    """
    if bounds is None:
        bounds = plan.attrs.get("bounds")
        if bounds is None:
            raise ValueError("d_efficiency: pass bounds (the plan has no attrs['bounds'])")
    bounds = {k: tuple(map(float, v)) for k, v in bounds.items()}
    x = model_matrix(_coded(plan, bounds), model)
    sign, logdet = np.linalg.slogdet(x.T @ x)
    if sign <= 0:
        return 0.0
    return float(100.0 * math.exp(logdet / x.shape[1]) / x.shape[0])


def _fedorov(f: np.ndarray, n: int, rng: np.random.Generator, max_iter: int) -> tuple[np.ndarray, float]:
    """One Fedorov exchange run over candidate rows ``f`` (N x p); distinct rows; returns (idx, logdet)."""
    big_n, p = f.shape
    idx = rng.choice(big_n, size=n, replace=False)
    ridge = 1e-8 * n * np.eye(p)  # keeps a singular random start invertible; gone after a few swaps
    for _ in range(max_iter):
        xd = f[idx]
        minv = np.linalg.inv(xd.T @ xd + ridge)
        dd = np.einsum("ij,jk,ik->i", xd, minv, xd)
        dc = np.einsum("ij,jk,ik->i", f, minv, f)
        dx = xd @ minv @ f.T
        # det(M') / det(M) = 1 + delta(i, j) when design row i is swapped for candidate j
        delta = dc[None, :] - dd[:, None] - (dd[:, None] * dc[None, :] - dx**2)
        delta[:, idx] = -np.inf
        i, j = np.unravel_index(np.argmax(delta), delta.shape)
        if delta[i, j] <= 1e-9:
            break
        idx[i] = j
    sign, logdet = np.linalg.slogdet(f[idx].T @ f[idx])
    return idx, (logdet if sign > 0 else -np.inf)


def d_optimal(n: int = 20, model: str = "quadratic", candidates: pd.DataFrame | None = None,
              bounds: Mapping | None = None, seed: int = 0, levels: int = 7, n_starts: int = 5,
              max_iter: int = 500) -> pd.DataFrame:
    """D-optimal plan for a polynomial response surface (Fedorov exchange).

    Parameters
    ----------
    n : int
        Number of distinct points; at least the number of model terms p.
    model : {'linear', 'interaction', 'quadratic'}
        Response-surface model in coded factors (see :func:`model_matrix`).
    candidates : DataFrame, optional
        Candidate points (columns = the bounded factors).  Default: a
        full-factorial grid of ``levels`` equally spaced levels per bounded
        factor.
    bounds : dict {column: (low, high)}, optional
        Factors and their coding ranges, merged over :data:`DEFAULT_BOUNDS`.
        Unbounded plan columns are filled by the estimates.
    seed : int
        Seed of the random starting designs.
    levels : int
        Levels per factor of the default candidate grid (>= 3 for quadratic).
    n_starts : int
        Random starts; the best determinant is kept.
    max_iter : int
        Exchange cap per start.

    Returns
    -------
    DataFrame
        ``point_id`` 'dopt-0001'..., plan columns, ``design`` = 'd_optimal';
        ``attrs['d_efficiency']`` [%] (see :func:`d_efficiency`).

    Notes
    -----
    Each iteration swaps the design row i and candidate j that maximise the
    determinant ratio ``1 + delta(i, j)``, ``delta = d(j) - d(i) -
    [d(i) d(j) - d(i, j)^2]`` with ``d(i, j) = x_i' (X'X)^-1 x_j`` (Fedorov
    1972); it stops when no swap raises det(X'X).  Candidates already in the
    design are excluded, so points are not replicated (a bench hour is better
    spent on a new point).
    """
    n = _check_n(n, "d_optimal")
    b = _check_bounds(bounds, "d_optimal")
    if candidates is None:
        if levels < (3 if model == "quadratic" else 2):
            raise ValueError(f"d_optimal: levels = {levels} too few for the {model!r} model")
        grids = [np.linspace(lo, hi, levels) for lo, hi in b.values()]
        cand = pd.DataFrame(list(itertools.product(*grids)), columns=list(b))
    else:
        missing = [k for k in b if k not in candidates.columns]
        if missing:
            raise ValueError(f"d_optimal: candidates lack the bounded factor column(s) {missing}")
        cand = candidates[list(b)].astype(float).drop_duplicates().reset_index(drop=True)
        coded = _coded(cand, b)
        if np.any(np.abs(coded) > 1 + 1e-9):
            raise ValueError("d_optimal: some candidates lie outside the bounds")
    f = model_matrix(_coded(cand, b), model)
    p = f.shape[1]
    if not p <= n <= len(cand):
        raise ValueError(f"d_optimal: need p = {p} (terms of the {model!r} model) <= n = {n} <= "
                         f"{len(cand)} distinct candidates")
    rng = np.random.default_rng(seed)
    best_idx, best = None, -np.inf
    for _ in range(n_starts):
        idx, logdet = _fedorov(f, n, rng, max_iter)
        if logdet > best:
            best_idx, best = idx, logdet
    if best_idx is None:
        raise ValueError("d_optimal: no non-singular design found in the candidate set")
    df = cand.iloc[np.sort(best_idx)].reset_index(drop=True)
    plan = finish_plan(df, "dopt", "d_optimal",
                   {"generator": "d_optimal", "seed": seed, "bounds": b, "model": model})
    plan.attrs["d_efficiency"] = d_efficiency(plan, model, b)
    return plan


def maximin_augment(design: pd.DataFrame, candidates: pd.DataFrame, k: int, bounds: Mapping) -> pd.DataFrame:
    """Add ``k`` candidates to ``design``, each the one farthest from every point already chosen.

    Greedy maximin-distance augmentation (Johnson, Moore and Ylvisaker 1990, J. Stat. Plan. Inference 26:
    maximin designs spread points so that no region is far from data): in coded factors (each bound mapped to
    [-1, 1]) the candidate whose nearest design point is farthest joins the design, then the next.  A
    D-optimal design for a quadratic surface puts its points on three levels per factor (edges and centre);
    a Gaussian-process map model is uncertain in the gaps between them, which these points fill.

    Parameters
    ----------
    design : DataFrame
        Points already chosen (columns = the factors of ``bounds``).
    candidates : DataFrame
        Points that may be added (same columns); candidates equal to a design point are skipped.
    k : int
        Points to add (>= 0).
    bounds : dict {column: (low, high)}
        Factors and their coding ranges.

    Returns
    -------
    DataFrame
        The added points (``k`` rows, the factor columns, in the order chosen).
    """
    b = {key: (float(lo), float(hi)) for key, (lo, hi) in dict(bounds).items()}
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
        raise ValueError(f"maximin_augment: k = {k!r} must be an integer >= 0")
    for name, df in (("design", design), ("candidates", candidates)):
        missing = [key for key in b if key not in df.columns]
        if missing:
            raise ValueError(f"maximin_augment: {name} lacks the factor column(s) {missing}")
    cand = candidates[list(b)].astype(float).drop_duplicates().reset_index(drop=True)
    xc, xd = _coded(cand, b), _coded(design[list(b)].astype(float), b)
    d = np.min(np.linalg.norm(xc[:, None, :] - xd[None, :, :], axis=2), axis=1) if len(xd) else \
        np.full(len(cand), np.inf)
    free = d > 1e-9
    if int(free.sum()) < k:
        raise ValueError(f"maximin_augment: only {int(free.sum())} candidates differ from the design; "
                         f"{k} asked")
    chosen = []
    for _ in range(k):
        j = int(np.argmax(np.where(free, d, -np.inf)))
        chosen.append(j)
        free[j] = False
        d = np.minimum(d, np.linalg.norm(xc - xc[j], axis=1))
    return cand.iloc[chosen].reset_index(drop=True)


# --------------------------------------------------------------------------- model-driven plans







# --------------------------------------------------------------------------- plan tools

def bench_order(plan: pd.DataFrame) -> pd.DataFrame:
    """Sort a plan into the paper's bench order and number it.

    Throttle ascending, then speed ascending, then spark and lambda ascending
    (stable: ties keep their order) [P]; sets ``run_order`` = 1..n.

    Parameters
    ----------
    plan : DataFrame

    Returns
    -------
    DataFrame
        Sorted copy with a fresh index and ``run_order`` (int).
    """
    keys = [c for c in ("throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda") if c in plan.columns]
    out = plan.sort_values(keys, kind="mergesort").reset_index(drop=True)
    out["run_order"] = np.arange(1, len(out) + 1)
    out.attrs = dict(plan.attrs)
    return out


def wiebe_grid(plan: pd.DataFrame, bdur_10_90_deg=np.arange(20, 51, 2), wiebe_m=np.arange(2, 9, 1)) -> pd.DataFrame:
    """Cross every plan point with a full-factorial (BDUR10-90, m) grid.

    Parameters
    ----------
    plan : DataFrame
        Operating points.
    bdur_10_90_deg : array_like
        BDUR10-90 values [deg]; default 20, 22, ..., 50 (the paper's range).
    wiebe_m : array_like
        Wiebe m values [-]; default 2, 3, ..., 8.

    Returns
    -------
    DataFrame
        ``len(plan) * len(bdur) * len(m)`` rows; ``point_id`` '<orig>-b24-m6.4',
        ``base_point_id`` the original id; all rows of one operating point are
        consecutive (BDUR outer, m inner), so :func:`engine_model.simulate`
        warm-starts each from the previous one.  A ``run_order`` of the input
        is dropped (call :func:`bench_order` again; it keeps the blocks).
    """
    b = np.atleast_1d(np.asarray(bdur_10_90_deg, float))
    m = np.atleast_1d(np.asarray(wiebe_m, float))
    if b.size == 0 or m.size == 0 or np.any(~(b > 0)) or np.any(~(m > -1)):
        raise ValueError("wiebe_grid: need non-empty bdur_10_90_deg > 0 and wiebe_m > -1")
    base = plan.drop(columns=[c for c in ("run_order", "bdur_10_90_deg", "wiebe_m") if c in plan.columns])
    base = base.reset_index(drop=True)
    nb = len(b) * len(m)
    out = base.loc[np.repeat(np.arange(len(base)), nb)].reset_index(drop=True)
    bb, mm = np.meshgrid(b, m, indexing="ij")
    out["bdur_10_90_deg"] = np.tile(bb.ravel(), len(base))
    out["wiebe_m"] = np.tile(mm.ravel(), len(base))
    out["base_point_id"] = out["point_id"]
    out["point_id"] = [f"{p}-b{x:g}-m{y:g}" for p, x, y in zip(out["base_point_id"], out["bdur_10_90_deg"],
                                                              out["wiebe_m"])]
    out.attrs = dict(plan.attrs)
    out.attrs["wiebe_grid"] = {"bdur_10_90_deg": b.tolist(), "wiebe_m": m.tolist()}
    return out














