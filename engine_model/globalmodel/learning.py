"""What a DOE plan is worth, measured: map accuracy against the number of bench points.

:func:`learning_curve` builds plans of several designs and sizes (a full grid,
D-optimal, Sobol', Latin hypercube; all from :mod:`engine_model.doe`), asks an
``identify(plan)`` callable for the combustion parameters at their points (in
the pipeline: the virtual bench + Wiebe identification; in tests: the truth
law plus identification-like noise, :func:`noisy_truth`), fits the global
map-wide model (:class:`engine_model.globalmodel.mapmodel.MapModel`) and scores it against
the truth on a held-out test set over the feasible map.  Several seeds per
design and size give the spread.

Plans vary throttle, speed and spark, with spark coded as an *offset from the
MBT prior* :func:`engine_model.priors.spark_estimate` (bench spark sweeps run
around MBT, and MBT moves ~35 deg over the map); lambda follows the target
:func:`engine_model.priors.lambda_target`.

Points the bench cannot run (knock, near-zero load) come back from
``identify`` as NaN and are lost, as on a real bench: a design that puts
points in the corners of the box pays for it.  ``feasible`` lets a design
know the feasible region in advance (the ``d_optimal_feasible`` design picks
its points from feasible candidates only).
"""

from __future__ import annotations

import math
import time
from typing import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import doe
from engine_model import priors
from engine_model.contracts import COMBUSTION_OUTPUTS
from engine_model.globalmodel.mapmodel import MapModel

__all__ = ["DESIGNS", "bench_identify", "bench_feasibility", "design_plan", "grid_levels", "holdout_grid", "noisy_truth", "phasing_noisy_truth", "learning_curve",
           "summarise", "points_to_reach", "plot_learning_curve", "nearest_feasible"]

#: Designs :func:`design_plan` knows.
DESIGNS = ("grid", "d_optimal", "d_optimal_feasible", "sobol", "lhs")

#: Default design space: throttle 5-100 %, speed 2000-13000 rpm, spark 20 deg retarded to 5 deg advanced
#: from the MBT prior.  The ECU tables span 1000-13000 rpm; below the lowest speed the DOE measured, the
#: global model carries the burn of that speed flat, and judged on the virtual truth the tables knocked
#: mostly at 2000-3000 rpm when the DOE started at 3000 (docs/history.md, 2026-11-28).  1000 rpm stays out:
#: the knock screen leaves only the lightest loads runnable there.
BOUNDS = {"throttle_pct": (5.0, 100.0), "speed_rpm": (2000.0, 13000.0)}
SPARK_OFFSET = (-20.0, 5.0)
FACTORS3 = ("throttle_pct", "speed_rpm", "spark_deg_btdc")


def absolute_spark(plan: pd.DataFrame) -> pd.DataFrame:
    """Plan generated with spark as an offset -> absolute spark [deg BTDC] (offset kept as a column)."""
    p = plan.copy()
    p["spark_offset_deg"] = p["spark_deg_btdc"].to_numpy(float)
    p["spark_deg_btdc"] = p["spark_offset_deg"] + np.atleast_1d(
        priors.spark_estimate(p["speed_rpm"].to_numpy(float), p["throttle_pct"].to_numpy(float)))
    return p


def grid_levels(n: int) -> tuple[int, int, int]:
    """(throttle, speed, spark) level counts of a full grid of about ``n`` points.

    2 spark levels below 40 points, 3 from 40 on; throttle and speed share the
    rest (throttle gets the larger half).  The grid's true size is the product.
    """
    if n < 8:
        raise ValueError(f"grid_levels: n = {n} too small for a 3-factor grid (>= 8)")
    ks = 2 if n < 40 else 3
    kt = max(2, math.ceil(math.sqrt(n / ks)))
    kn = max(2, round(n / ks / kt))
    return kt, kn, ks


def design_plan(design: str, n: int, seed: int = 0, bounds: dict | None = None,
                spark_offset: tuple = SPARK_OFFSET,
                feasible: Callable[[pd.DataFrame], np.ndarray] | None = None) -> pd.DataFrame:
    """A plan of ``design`` with about ``n`` points over throttle x speed x spark offset.

    Parameters
    ----------
    design : str
        One of :data:`DESIGNS`.  'grid': full factorial with
        :func:`grid_levels` (its size is the nearest grid, reported in the
        result); 'd_optimal': Fedorov exchange for a quadratic model over a
        7-level candidate grid; 'd_optimal_feasible': the same, candidates
        restricted by ``feasible``; 'sobol', 'lhs': space-filling.
    n : int
        Target number of points.
    seed : int
        Design seed (grid: unused).
    bounds : dict, optional
        Throttle [%] and speed [rpm] ranges; default :data:`BOUNDS`.
    spark_offset : (float, float)
        Spark range relative to the MBT prior [deg].
    feasible : callable(points) -> bool array, optional
        Needed by 'd_optimal_feasible'.

    Returns
    -------
    DataFrame
        A doe plan (``point_id``, plan columns, ``design``) with absolute
        ``spark_deg_btdc`` and ``spark_offset_deg``.
    """
    b = dict(BOUNDS if bounds is None else bounds)
    b["spark_deg_btdc"] = tuple(spark_offset)
    if design == "grid":
        kt, kn, ks = grid_levels(n)
        p = doe.full_factorial(speed_rpm=np.linspace(*b["speed_rpm"], kn),
                               throttle_pct=np.linspace(*b["throttle_pct"], kt),
                               spark_deg_btdc=np.linspace(*spark_offset, ks), lam=None)
    elif design in ("d_optimal", "d_optimal_feasible"):
        cand = None
        if design == "d_optimal_feasible":
            if feasible is None:
                raise ValueError("design_plan: 'd_optimal_feasible' needs a feasible(points) callable")
            grids = [np.linspace(*b[k], 7) for k in ("speed_rpm", "throttle_pct", "spark_deg_btdc")]
            cand = pd.DataFrame(np.array(np.meshgrid(*grids, indexing="ij")).reshape(3, -1).T,
                                columns=["speed_rpm", "throttle_pct", "spark_deg_btdc"])
            probe = absolute_spark(cand.assign(**{"lambda": priors.lambda_target(cand["throttle_pct"].to_numpy())}))
            cand = cand[np.asarray(feasible(probe), bool)].reset_index(drop=True)
        p = doe.d_optimal(n, model="quadratic", candidates=cand, bounds=b, seed=seed)
    elif design == "sobol":
        p = doe.sobol(n, bounds=b, seed=seed)
    elif design == "lhs":
        p = doe.latin_hypercube(n, bounds=b, seed=seed)
    else:
        raise ValueError(f"design_plan: unknown design {design!r}; choose from {list(DESIGNS)}")
    # the generators filled lambda from the target already; spark was generated as an offset
    return absolute_spark(p)


def holdout_grid(throttle_pct=(5, 10, 15, 20, 30, 40, 60, 80, 100), speed_rpm=None,
              spark_offset=(-20, -15, -10, -5, 0, 5)) -> pd.DataFrame:
    """Held-out test points: an ECU-style grid x spark offsets around the MBT prior (648 points by default).

    ``speed_rpm`` None: every 1000 rpm over the speeds of :data:`BOUNDS`.
    """
    if speed_rpm is None:
        lo, hi = BOUNDS["speed_rpm"]
        speed_rpm = tuple(range(int(lo), int(hi) + 1, 1000))
    p = doe.full_factorial(speed_rpm=speed_rpm, throttle_pct=throttle_pct, spark_deg_btdc=spark_offset)
    return absolute_spark(p)


def nearest_feasible(reference: pd.DataFrame, ok: np.ndarray, bounds: dict | None = None,
                     spark_offset: tuple = SPARK_OFFSET) -> Callable[[pd.DataFrame], np.ndarray]:
    """Feasibility lookup: a point is feasible if its nearest ``reference`` point (coded space) is ``ok``.

    ``reference`` must carry ``throttle_pct, speed_rpm, spark_offset_deg`` (e.g. a
    :func:`holdout_grid` run once through the virtual bench, ``ok = status == 'ok'``).
    A cheap stand-in for running the bench at every plan point.
    """
    b = dict(BOUNDS if bounds is None else bounds)
    lo = np.array([b["throttle_pct"][0], b["speed_rpm"][0], spark_offset[0]])
    hi = np.array([b["throttle_pct"][1], b["speed_rpm"][1], spark_offset[1]])

    def code(df):
        off = df["spark_offset_deg"].to_numpy(float) if "spark_offset_deg" in df.columns else (
            df["spark_deg_btdc"].to_numpy(float) - np.atleast_1d(priors.spark_estimate(
                df["speed_rpm"].to_numpy(float), df["throttle_pct"].to_numpy(float))))
        x = np.column_stack([df["throttle_pct"].to_numpy(float), df["speed_rpm"].to_numpy(float), off])
        return (x - lo) / (hi - lo)

    ref = code(reference)
    ok = np.asarray(ok, bool)

    def feasible(points: pd.DataFrame) -> np.ndarray:
        x = code(points)
        d = ((x[:, None, :] - ref[None, :, :]) ** 2).sum(-1)
        return ok[np.argmin(d, axis=1)]

    return feasible


def bench_feasibility(bench, evaluate: Callable[[pd.DataFrame], pd.DataFrame] | None = None
                      ) -> Callable[[pd.DataFrame], np.ndarray]:
    """Feasibility by running the points on the (noise-free) virtual bench: True where status is 'ok'.

    Results are cached by (throttle, speed, spark, lambda) rounded to 1e-6, so
    a point is simulated once however many plans contain it.  The callable
    carries ``cache`` (dict key -> status) for inspection.
    """
    import dataclasses

    from engine_model.bench.virtual import NoiseModel

    quiet = dataclasses.replace(bench, noise=NoiseModel.none())
    cache: dict[tuple, str] = {}

    def key(r):
        return tuple(round(float(v), 6) for v in r)

    def feasible(points: pd.DataFrame) -> np.ndarray:
        cols = ["throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda"]
        keys = [key(r) for r in points[cols].itertuples(index=False, name=None)]
        new = sorted({k for k in keys if k not in cache})
        if new:
            todo = pd.DataFrame(new, columns=cols)
            todo.insert(0, "point_id", [f"feas-{len(cache) + i}" for i in range(len(todo))])
            todo = todo.sort_values(["throttle_pct", "speed_rpm", "spark_deg_btdc"]).reset_index(drop=True)
            res = quiet.measure(todo, evaluate=evaluate)
            for k, st in zip((key(r) for r in todo[cols].itertuples(index=False, name=None)), res["status"]):
                cache[k] = str(st)
        return np.array([cache[k] == "ok" for k in keys])

    feasible.cache = cache
    return feasible


def noisy_truth(law, sigma_bdur_deg: float = 1.5, sigma_m: float = 0.4, seed: int = 0,
                feasible: Callable[[pd.DataFrame], np.ndarray] | None = None) -> Callable[[pd.DataFrame], pd.DataFrame]:
    """A cheap ``identify``: the truth law plus independent normal identification noise.

    Parameters
    ----------
    law : object with ``predict(points)``
        The truth (e.g. :class:`engine_model.bench.burnlaw.BurnLaw`).
    sigma_bdur_deg, sigma_m : float
        Identification noise, 1 sigma [deg], [-].  See the learning-curve
        section of the docs for how the defaults follow from the bench noise.
    seed : int
        Noise seed (combined with the plan's point ids, so the same plan gives
        the same identification).
    feasible : callable(points) -> bool array, optional
        Points outside come back NaN (knock-aborted or unholdable on the bench).

    Returns
    -------
    callable(plan) -> DataFrame
        The plan with ``bdur_10_90_deg`` and ``wiebe_m`` (NaN where infeasible).
    """
    from engine_model.bench.virtual import point_rng

    def identify(plan: pd.DataFrame) -> pd.DataFrame:
        out = plan.reset_index(drop=True).copy()
        y = law.predict(out)
        z = np.array([point_rng(seed, f"{pid}|{r.throttle_pct:.6g}|{r.speed_rpm:.6g}|{r.spark_deg_btdc:.6g}")
                      .standard_normal(2) for pid, r in zip(out["point_id"], out.itertuples())]).reshape(-1, 2)
        out["bdur_10_90_deg"] = y["bdur_10_90_deg"].to_numpy() + sigma_bdur_deg * z[:, 0]
        out["wiebe_m"] = y["wiebe_m"].to_numpy() + sigma_m * z[:, 1]
        if feasible is not None:
            bad = ~np.asarray(feasible(out), bool)
            out.loc[bad, ["bdur_10_90_deg", "wiebe_m"]] = np.nan
        return out

    return identify


#: Joint spark-sweep identification's error, measured on the virtual bench (benchmarks/identification_error.py,
#: docs/data/identification_error.csv: 16 sweeps, throttle 20-100 % x 5000-13000 rpm, 5 sparks -15..+5 deg
#: from the MBT prior, bench noise on, quick solver): RMSE of the CA50 offset 0.65 deg, of m 0.90, their
#: correlation +0.75 (BDUR10-90 2.81 deg, correlated -0.99 with m: the errors lie along the iso-phasing ridge).
IDENT_SIGMA_CA50_OFFSET_DEG = 0.65
IDENT_SIGMA_M = 0.90
IDENT_RHO_CA50_OFFSET_M = 0.75


def phasing_noisy_truth(law, sigma_ca50_offset_deg: float = IDENT_SIGMA_CA50_OFFSET_DEG,
                        sigma_m: float = IDENT_SIGMA_M, rho: float = IDENT_RHO_CA50_OFFSET_M, seed: int = 0,
                        feasible: Callable[[pd.DataFrame], np.ndarray] | None = None
                        ) -> Callable[[pd.DataFrame], pd.DataFrame]:
    """A cheap ``identify`` whose errors have the structure of real sweep identification.

    The truth's (BDUR10-90, m) are converted to (CA50 offset, m) (the ignition-to-CA50 angle,
    :func:`engine_model.globalmodel.mapmodel.ca50_offset_deg`), both get bivariate normal noise (sigmas
    ``sigma_ca50_offset_deg`` [deg], ``sigma_m`` [-], correlation ``rho``), and BDUR10-90 is the burn with the
    noisy offset and m (:func:`engine_model.globalmodel.mapmodel.bdur_10_90_from_ca50_offset`).  The defaults are the
    measured ones (:data:`IDENT_SIGMA_CA50_OFFSET_DEG`, :data:`IDENT_SIGMA_M`, :data:`IDENT_RHO_CA50_OFFSET_M`).
    Seeding, masking and the returned columns as in :func:`noisy_truth`; ``ca50_offset_deg`` is added.
    """
    from engine_model.globalmodel.mapmodel import bdur_10_90_from_ca50_offset, ca50_offset_deg
    from engine_model.bench.virtual import point_rng

    if not (sigma_ca50_offset_deg >= 0 and sigma_m >= 0 and -1 <= rho <= 1):
        raise ValueError(f"phasing_noisy_truth: sigmas must be >= 0 and rho in [-1, 1], got "
                         f"{sigma_ca50_offset_deg!r}, {sigma_m!r}, {rho!r}")

    def identify(plan: pd.DataFrame) -> pd.DataFrame:
        out = plan.reset_index(drop=True).copy()
        y = law.predict(out)
        z = np.array([point_rng(seed, f"{pid}|{r.throttle_pct:.6g}|{r.speed_rpm:.6g}|{r.spark_deg_btdc:.6g}")
                      .standard_normal(2) for pid, r in zip(out["point_id"], out.itertuples())]).reshape(-1, 2)
        m = y["wiebe_m"].to_numpy() + sigma_m * z[:, 0]
        off = ca50_offset_deg(y["bdur_10_90_deg"].to_numpy(), y["wiebe_m"].to_numpy()) + sigma_ca50_offset_deg * (
            rho * z[:, 0] + math.sqrt(1.0 - rho * rho) * z[:, 1])
        out["bdur_10_90_deg"] = bdur_10_90_from_ca50_offset(off, m)
        out["wiebe_m"] = m
        out["ca50_offset_deg"] = off
        if feasible is not None:
            bad = ~np.asarray(feasible(out), bool)
            out.loc[bad, ["bdur_10_90_deg", "wiebe_m", "ca50_offset_deg"]] = np.nan
        return out

    return identify


def bench_identify(bench, evaluate: Callable[[pd.DataFrame], pd.DataFrame] | None = None, n_bdur: int = 11,
                   n_m: int = 13, surface: str = "spline",
                   eta_trans: float | None = None) -> Callable[[pd.DataFrame], pd.DataFrame]:
    """The real ``identify``: run the plan on a virtual bench, then Wiebe identification per point.

    Parameters
    ----------
    bench : VirtualBench
        The truth engine.
    evaluate : callable(points) -> results, optional
        Cycle model for both the bench and the identification sweeps
        (default: the bench's in-process evaluator); the flow layer passes a
        Dask-backed one.
    n_bdur, n_m : int
        Identification grid (:func:`engine_model.calibration.identify.identification_plan`);
        costs ``n_bdur * n_m`` simulations per bench point.  Measured on the
        virtual bench: a 7 x 7 grid missed the hidden law by 8-20 deg at 5 of 8
        points, the default 11 x 13 recovered WOT 9000 rpm within 0.3 deg /
        0.1 (see docs/sections/mapmodel.md).
    surface : str
        Response-surface kind of :func:`engine_model.calibration.identify.identify`.
    eta_trans : float, optional
        Transmission efficiency assumed by the identification; default the
        bench's own (a perfectly known gearbox).

    Returns
    -------
    callable(plan) -> DataFrame
        The plan (``point_id`` added if missing) with ``bdur_10_90_deg``,
        ``wiebe_m`` (NaN where the bench aborted the point or the fit missed
        its tolerances), ``*_std`` from the 95 % region (half-width / 2.45:
        chi2 with 2 degrees of freedom), ``bench_status``, ``identify_status``.
    """
    from engine_model.calibration.identify import identification_plan
    from engine_model.calibration.identify import identify as identify_points
    from engine_model.bench import validate_bench

    ev = bench.default_evaluate if evaluate is None else evaluate

    def identify(plan: pd.DataFrame) -> pd.DataFrame:
        meas = bench.measure(plan, evaluate=evaluate)
        out = meas[["point_id", "throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda"]].copy()
        out["bench_status"] = meas["status"].to_numpy()
        for c in ("bdur_10_90_deg", "wiebe_m", "bdur_10_90_deg_std", "wiebe_m_std"):
            out[c] = np.nan
        out["identify_status"] = "not run: " + meas["status"].astype(str)
        ok = meas[meas["status"] == "ok"].copy()
        if len(ok):
            ok["at_mbt"] = False  # spark is a plan factor: no CA50 = MBT constraint
            v = validate_bench(ok, "virtual bench")
            res = ev(identification_plan(v, n_bdur=n_bdur, n_m=n_m))
            tab = identify_points(v, res, bench.eta_trans if eta_trans is None else eta_trans,
                                  surface=surface).table.set_index("point_id")
            idx = out.index[out["point_id"].isin(tab.index)]
            t = tab.loc[out.loc[idx, "point_id"]]
            good = t["fit_ok"].to_numpy(bool)
            for c in ("bdur_10_90_deg", "wiebe_m"):
                out.loc[idx, c] = np.where(good, t[c].to_numpy(float), np.nan)
                out.loc[idx, f"{c}_std"] = np.where(good, (t[f"{c}_hi"] - t[f"{c}_lo"]).to_numpy(float) / (2 * 2.45),
                                                    np.nan)
            out.loc[idx, "identify_status"] = t["status"].astype(str).to_numpy()
        return out

    return identify


def learning_curve(identify: Callable[[pd.DataFrame], pd.DataFrame], truth, sizes: Sequence[int] = (16, 24, 32, 48, 64, 96),
                   designs: Sequence[str] = ("grid", "d_optimal", "sobol", "lhs"), seeds: Sequence[int] = (0, 1, 2),
                   test_points: pd.DataFrame | None = None, feasible: Callable[[pd.DataFrame], np.ndarray] | None = None,
                   families: Sequence[str] = ("poly", "gp"), factors: Sequence[str] = FACTORS3,
                   identify_seeded: Callable[[int], Callable[[pd.DataFrame], pd.DataFrame]] | None = None,
                   progress: Callable[[dict], None] | None = None) -> pd.DataFrame:
    """Held-out map accuracy vs number of bench points, per design and seed.

    Parameters
    ----------
    identify : callable(plan) -> DataFrame
        Identified ``bdur_10_90_deg``, ``wiebe_m`` per plan row (same order;
        NaN for points the bench could not run).  Ignored where
        ``identify_seeded`` is given.
    truth : object with ``predict(points)``
        The law the map model should recover.
    sizes : sequence of int
        Target plan sizes (the grid rounds to the nearest full grid).
    designs : sequence of str
        From :data:`DESIGNS`.
    seeds : sequence of int
        Design seeds (and identification seeds with ``identify_seeded``).
    test_points : DataFrame, optional
        Scoring points; default :func:`holdout_grid`, restricted to ``feasible``.
    feasible : callable(points) -> bool array, optional
        The feasible map (test set restriction; 'd_optimal_feasible' candidates).
    families, factors : sequence of str
        Passed to :class:`MapModel`.
    identify_seeded : callable(seed) -> identify, optional
        Fresh identification noise per seed (e.g. ``lambda s: noisy_truth(law, seed=s)``).
    progress : callable(row dict), optional

    Returns
    -------
    DataFrame
        One row per (design, size, seed): ``design, n_target, n_points,
        n_identified, seed, rmse_bdur_10_90_deg, rmse_wiebe_m,
        family_bdur_10_90_deg, family_wiebe_m, cv_rmse_bdur_10_90_deg,
        cv_rmse_wiebe_m, fit_s``; ``attrs['n_test']``.  A fit that fails
        (too few identified points) has NaN errors and its reason in ``note``.
    """
    test = holdout_grid() if test_points is None else test_points.reset_index(drop=True)
    if feasible is not None:
        test = test[np.asarray(feasible(test), bool)].reset_index(drop=True)
    if len(test) == 0:
        raise ValueError("learning_curve: no feasible test points")
    y_test = truth.predict(test)
    rows = []
    for design in designs:
        for n in sizes:
            for seed in seeds:
                plan = design_plan(design, n, seed, feasible=feasible)
                ident = (identify_seeded(seed) if identify_seeded is not None else identify)(plan)
                n_id = int(np.all(np.isfinite(ident[list(COMBUSTION_OUTPUTS)].to_numpy(float)), axis=1).sum())
                row = {"design": design, "n_target": int(n), "n_points": len(plan), "n_identified": n_id,
                       "seed": int(seed), "note": ""}
                t0 = time.perf_counter()
                try:
                    model = MapModel(families=families, factors=factors, seed=seed).fit(ident)
                except ValueError as exc:
                    row.update({f"rmse_{o}": math.nan for o in COMBUSTION_OUTPUTS}, note=str(exc)[:200])
                else:
                    pred = model.predict(test)
                    for o in COMBUSTION_OUTPUTS:
                        row[f"rmse_{o}"] = float(np.sqrt(np.mean((pred[o] - y_test[o]) ** 2)))
                        row[f"family_{o}"] = model.chosen_[o]
                        row[f"cv_rmse_{o}"] = model.cv_rmse_[o][model.chosen_[o]]
                row["fit_s"] = time.perf_counter() - t0
                rows.append(row)
                if progress is not None:
                    progress(row)
    out = pd.DataFrame(rows)
    out.attrs["n_test"] = len(test)
    return out


def summarise(curve: pd.DataFrame) -> pd.DataFrame:
    """Per design and target size: mean plan size, mean identified points, mean/min/max RMSE over seeds."""
    g = curve.groupby(["design", "n_target"], sort=False)
    out = g[["n_points", "n_identified"]].mean()
    for o in COMBUSTION_OUTPUTS:
        c = f"rmse_{o}"
        out[f"{c}_mean"], out[f"{c}_min"], out[f"{c}_max"] = g[c].mean(), g[c].min(), g[c].max()
    return out.reset_index()


def points_to_reach(curve: pd.DataFrame, target: dict[str, float]) -> pd.DataFrame:
    """Smallest mean plan size per design whose seed-mean RMSE meets every target.

    Parameters
    ----------
    curve : DataFrame
        :func:`learning_curve` output.
    target : dict output -> RMSE
        E.g. ``{'bdur_10_90_deg': 1.0, 'wiebe_m': 0.3}``.

    Returns
    -------
    DataFrame
        ``design, n_points`` (NaN if never reached within the sizes tried).
    """
    s = curve.groupby(["design", "n_target"]).mean(numeric_only=True).reset_index()
    rows = []
    for design, g in s.groupby("design", sort=False):
        ok = np.all([g[f"rmse_{o}"].to_numpy() <= t for o, t in target.items()], axis=0)
        g = g[ok].sort_values("n_points")
        rows.append({"design": design, "n_points": float(g["n_points"].iloc[0]) if len(g) else math.nan})
    return pd.DataFrame(rows)


def plot_learning_curve(curve: pd.DataFrame, path, target: dict[str, float] | None = None,
                        title: str = "Map accuracy vs bench points") -> "Path":
    """PNG: held-out RMSE of BDUR10-90 and m vs plan size, one line per design (mean, min-max band)."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from engine_model import io as _io

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    labels = {"bdur_10_90_deg": "BDUR10-90 RMSE [deg CA]", "wiebe_m": "Wiebe m RMSE [-]"}
    for ax, o in zip(axes, COMBUSTION_OUTPUTS):
        for design, g in curve.groupby("design", sort=False):
            s = g.groupby("n_target").agg(n=("n_points", "mean"), mean=(f"rmse_{o}", "mean"),
                                          lo=(f"rmse_{o}", "min"), hi=(f"rmse_{o}", "max"))
            line, = ax.plot(s["n"], s["mean"], "o-", label=design)
            ax.fill_between(s["n"], s["lo"], s["hi"], color=line.get_color(), alpha=0.15)
        if target and o in target:
            ax.axhline(target[o], color="k", ls="--", lw=1, label="target")
        ax.set_xlabel("bench points in the plan")
        ax.set_ylabel(labels[o])
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend()
    fig.suptitle(title)
    fig.tight_layout()

    def write(tmp):
        fig.savefig(tmp, dpi=110, format="png")

    try:
        return _io.atomic_write(path, write)
    finally:
        plt.close(fig)
