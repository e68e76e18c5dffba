"""Wiebe identification from spark sweeps: one (BDUR10-90, m) per operating point, all sparks at once.

Per-point identification (:func:`engine_model.calibration.identify.identify`) without a
CA50 constraint is ill-posed along the ridge of maximum power: one torque and
one exhaust temperature are matched by a curve of (BDUR10-90, m), and points
away from MBT can land on the wrong side of the ridge.  The paper's bench
procedure is a spark sweep per (throttle, speed); this module uses it:

* :func:`sweep_plan` crosses operating points (throttle, speed) with spark
  offsets from the MBT prior (:func:`engine_model.priors.spark_estimate`), lambda
  from :func:`engine_model.priors.lambda_target`, ids ``<op>-s<k>``, column
  ``op_id``, rows in bench order (:func:`engine_model.doe.bench_order`).
* :func:`identify_sweeps` sums the per-point chi2 fields of
  :mod:`engine_model.calibration.identify` (power, exhaust temperature, peak pressure,
  BSFC, fuel flow) over the sweep's points on the common fine (BDUR10-90, m)
  mesh, with (BDUR10-90, m) held constant across the sweep.  The shape of the
  torque-versus-spark curve then selects the burn: a burn that is too short
  or too long gives the wrong curvature and the wrong MBT.  At the measured
  MBT of the sweep (torque maximum strictly inside the run sparks, not at the
  most advanced run point and no knock abort there) the CA50 term of the paper
  (CA50 = 9 +- 1 deg ATDC at MBT, Bargende 1995 in [P]) is added at the MBT
  spark found by a parabola through the three highest-torque sparks; its sigma
  is widened by the MBT-spark uncertainty (:data:`MBT_SPARK_SIGMA_DEG`).

Spark dependence of the burn: the hidden law of the virtual bench
(:class:`engine_model.bench.burnlaw.BurnLaw`; advanced spark fires into colder, thinner gas and burns longer,
[H] sec. 9.3) moves BDUR10-90 by +-2.9 to +-5.2 % and m by 0 to +-3.4 % over a -15..+5 deg sweep around
the MBT prior (measured with ``BurnLaw().predict`` on throttle 10-100 %, speed 3000-12000 rpm; e.g. WOT
9000 rpm: 22.9 -> 25.1 deg, m 5.92 -> 6.32), i.e. 0.3-0.5 %/deg.  Small as it is, holding the parameters
constant is *not* good enough: at retarded spark brake power is so sensitive to the burn that the law's
own 0.5 deg / 0.1 change between neighbouring sparks moves power by ~2.7 % (60 % throttle, 9000 rpm,
cycle model), more than the 1 % tolerance, and the constant-parameter fit drifts to long, low-m burns
(BDUR10-90 RMSE 10.5 deg on the 6-point case of docs/sections/identify_sweep.md).  Each point therefore
burns with ``(b (1 + kb ds), m (1 + km ds))``, ``ds`` = its spark minus the sweep's mean spark, and the
relative slopes (kb, km) are profiled over :data:`SPARK_SLOPES` (0-0.8 %/deg each; chi2 minimum over the
candidates).  Reported (BDUR10-90, m) are those at the sweep's mean spark.

[P] Mrda et al., MVM2012-024.  [H] Heywood, ICE Fundamentals, 1988.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np
import pandas as pd

from engine_model.contracts import SWEEP_COLUMNS
from engine_model import wiebe

from engine_model import doe
from engine_model import priors
from engine_model.calibration.identify import CHI2_95_2DOF, Tolerances, chi2_terms, point_surfaces, terms_used

__all__ = ["DEFAULT_OFFSETS", "DEFAULT_TERMS", "SPARK_SLOPES", "MBT_SPARK_SIGMA_DEG", "choose_operating_points",
           "sweep_plan", "measured_mbt",
           "identify_sweeps"]

#: Spark offsets from the MBT prior [deg]; the prior is ~ +-3 deg from the engine's MBT, so -15..+5 brackets it.
DEFAULT_OFFSETS = (-15.0, -10.0, -5.0, 0.0, 5.0)
#: [A] 1-sigma uncertainty of the MBT spark from a parabola through 3 sparks 5 deg apart with 0.5 % torque
#: noise: near MBT torque falls ~0.5-1 % at 5 deg off, so the vertex moves by ~1-2 deg per noise sigma.
MBT_SPARK_SIGMA_DEG = 1.5

#: Per-point terms used by default.  BSFC and fuel flow carry no combustion information beyond power (fuel
#: follows the air at fixed lambda); on a coarse (BDUR10-90, m) grid their surfaces are less accurate than
#: the 1 % meter, and adding them raised the BDUR10-90 RMSE from 1.7 to 3.1 deg on the 6-point case of
#: docs/sections/identify_sweep.md.
DEFAULT_TERMS = ("power", "pmax", "exhaust_temp")

#: Candidate relative spark slopes [1/deg] of (BDUR10-90, m): 0 to 0.8 %/deg.  [H] sec. 9.3: burn angles grow
#: with spark advance (colder, thinner charge at the spark); a constant-parameter fit is biased because power
#: at retarded spark is very sensitive to the burn (see the module docstring), so the slope is profiled.
SPARK_SLOPES = tuple((kb, km) for kb in (0.0, 0.002, 0.004, 0.006, 0.008) for km in (0.0, 0.002, 0.004, 0.006))

#: Result columns of :func:`identify_sweeps` (in this order, then diagnostics).


def choose_operating_points(n: int, feasible: Callable[[pd.DataFrame], np.ndarray] | None = None, seed: int = 0,
                            bounds: dict | None = None, levels: int = 7, fill: int = 0) -> pd.DataFrame:
    """D-optimal (quadratic model) operating points over (throttle, speed), optionally with space-filling ones.

    Parameters
    ----------
    n : int
        Number of operating points; ``n - fill`` D-optimal ones (>= 6, the terms of a 2-factor quadratic).
    feasible : callable(points) -> bool array, optional
        Screen of the ``levels`` x ``levels`` candidate grid; it gets the candidates at the MBT-prior
        spark and target lambda (``speed_rpm, throttle_pct, spark_deg_btdc, lambda``).
    seed : int
    bounds : dict, optional
        ``{"throttle_pct": (lo, hi), "speed_rpm": (lo, hi)}``; default :data:`engine_model.globalmodel.learning.BOUNDS`.
    fill : int
        Of the ``n``, points added after the D-optimal ones where the design is sparsest
        (:func:`engine_model.doe.maximin_augment` over the screened candidates).

    Returns
    -------
    DataFrame
        ``throttle_pct, speed_rpm`` (n rows; the D-optimal ones first).
    """
    from engine_model.globalmodel.learning import BOUNDS
    b = dict(BOUNDS if bounds is None else bounds)
    if isinstance(fill, bool) or not isinstance(fill, (int, np.integer)) or fill < 0:
        raise ValueError(f"choose_operating_points: fill = {fill!r} must be an integer >= 0")
    if n - fill < 6:
        raise ValueError(f"choose_operating_points: n = {n} with fill = {fill} leaves {n - fill} D-optimal points; "
                         "a quadratic over (throttle, speed) needs >= 6")
    g = np.meshgrid(np.linspace(*b["speed_rpm"], levels), np.linspace(*b["throttle_pct"], levels), indexing="ij")
    cand = pd.DataFrame({"speed_rpm": g[0].ravel(), "throttle_pct": g[1].ravel()})
    if feasible is not None:
        spark = priors.spark_estimate(cand["speed_rpm"].to_numpy(), cand["throttle_pct"].to_numpy())
        probe = cand.assign(spark_deg_btdc=spark,
                            **{"lambda": priors.lambda_target(cand["throttle_pct"].to_numpy())})
        cand = cand[np.asarray(feasible(probe), bool)].reset_index(drop=True)
        if len(cand) < n:
            raise ValueError(f"choose_operating_points: only {len(cand)} feasible candidates for {n} points")
    b2 = {k: b[k] for k in ("throttle_pct", "speed_rpm")}
    p = doe.d_optimal(n - fill, model="quadratic", candidates=cand, bounds=b2, seed=seed)
    p = p[["throttle_pct", "speed_rpm"]].reset_index(drop=True)
    if fill:
        p = pd.concat([p, doe.maximin_augment(p, cand, fill, b2)[["throttle_pct", "speed_rpm"]]], ignore_index=True)
    return p


def sweep_plan(op_points: pd.DataFrame, offsets: Sequence[float] = DEFAULT_OFFSETS) -> pd.DataFrame:
    """Spark sweeps at operating points.

    Parameters
    ----------
    op_points : DataFrame
        ``throttle_pct`` [%], ``speed_rpm`` [rpm]; optional ``op_id`` (unique), else 'op01', 'op02', ...
    offsets : sequence of float
        Spark offsets from the MBT prior [deg] (>= 3 distinct values, so the torque curve has a shape).

    Returns
    -------
    DataFrame
        ``point_id`` (``<op_id>-s<k>``, k = index of the offset in ascending order), ``op_id``,
        ``throttle_pct, speed_rpm, spark_deg_btdc, lambda, spark_offset_deg`` and ``run_order``,
        sorted in bench order (throttle, speed, spark ascending).
    """
    offs = np.unique(np.asarray(offsets, float))
    if offs.size < 3:
        raise ValueError(f"sweep_plan: need >= 3 distinct spark offsets, got {list(offsets)}")
    for c in ("throttle_pct", "speed_rpm"):
        if c not in op_points.columns:
            raise ValueError(f"sweep_plan: op_points lacks column {c!r} (has {list(op_points.columns)})")
        v = pd.to_numeric(op_points[c], errors="coerce").to_numpy(float)
        if not np.isfinite(v).all():
            i = int(np.flatnonzero(~np.isfinite(v))[0])
            raise ValueError(f"sweep_plan: op_points row {i}, column {c!r}: value {op_points[c].iloc[i]!r} "
                             "is not a number")
    ops = op_points.reset_index(drop=True)
    ids = ops["op_id"].astype(str) if "op_id" in ops.columns else \
        pd.Series([f"op{i + 1:02d}" for i in range(len(ops))])
    if ids.duplicated().any():
        raise ValueError(f"sweep_plan: duplicate op_id {ids[ids.duplicated()].iloc[0]!r}")
    rows = []
    for oid, r in zip(ids, ops.itertuples()):
        s0 = float(priors.spark_estimate(float(r.speed_rpm), float(r.throttle_pct)))
        lam = float(priors.lambda_target(float(r.throttle_pct)))
        for k, o in enumerate(offs):
            rows.append({"point_id": f"{oid}-s{k}", "op_id": oid, "throttle_pct": float(r.throttle_pct),
                         "speed_rpm": float(r.speed_rpm), "spark_deg_btdc": s0 + float(o), "lambda": lam,
                         "spark_offset_deg": float(o)})
    return doe.bench_order(pd.DataFrame(rows))


def measured_mbt(sweep: pd.DataFrame) -> tuple[float, str]:
    """MBT spark [deg BTDC] of one measured sweep, or NaN with the reason.

    ``sweep``: bench rows of one operating point (``spark_deg_btdc, brake_torque_nm, status``).  The maximum
    of measured torque must lie strictly inside the sparks that ran ('ok' rows); a maximum at the most
    advanced 'ok' spark is "knock-limited" if the sweep has a knock abort (torque still rising where the
    bench stopped), else "not bracketed".  The MBT spark is the vertex of a parabola through the maximum
    and its two neighbours (clipped to that interval).
    """
    s = sweep.sort_values("spark_deg_btdc")
    ok = s[s["status"] == "ok"]
    if len(ok) < 3:
        return math.nan, f"{len(ok)} runnable sparks"
    sp, tq = ok["spark_deg_btdc"].to_numpy(float), ok["brake_torque_nm"].to_numpy(float)
    k = int(np.argmax(tq))
    knock = s.loc[s["status"] == "knock_abort", "spark_deg_btdc"].to_numpy(float)
    if k == len(sp) - 1:
        return math.nan, "knock-limited (torque still rising at the knock limit)" if knock.size else \
            "not bracketed (torque maximum at the most advanced spark)"
    if k == 0:
        return math.nan, "not bracketed (torque maximum at the most retarded spark)"
    x, y = sp[k - 1:k + 2], tq[k - 1:k + 2]
    c = np.polyfit(x, y, 2)
    v = -c[1] / (2 * c[0]) if c[0] < 0 else x[1]
    return float(np.clip(v, x[0], x[2])), "ok"


def _shifted_index(fb, fm, B, M):
    """Fractional fine-mesh indices of (B, M), clipped to the mesh (edge values extend outwards)."""
    ib = np.clip((B - fb[0]) / (fb[1] - fb[0]), 0, len(fb) - 1)
    jm = np.clip((M - fm[0]) / (fm[1] - fm[0]), 0, len(fm) - 1)
    return ib, jm


def _lookup(v, ib, jm):
    """Bilinear interpolation of a fine-mesh field at fractional indices."""
    i0 = np.minimum(np.floor(ib).astype(int), v.shape[0] - 2)
    j0 = np.minimum(np.floor(jm).astype(int), v.shape[1] - 2)
    di, dj = ib - i0, jm - j0
    return ((1 - di) * (1 - dj) * v[i0, j0] + di * (1 - dj) * v[i0 + 1, j0]
            + (1 - di) * dj * v[i0, j0 + 1] + di * dj * v[i0 + 1, j0 + 1])


def _check_inputs(meas: pd.DataFrame, results: pd.DataFrame) -> None:
    need = ("point_id", "op_id", "throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda", "status", "brake_torque_nm")
    miss = [c for c in need if c not in meas.columns]
    if miss:
        raise ValueError(f"identify_sweeps: bench rows lack column(s) {miss} (use sweep_plan, then the bench)")
    if "bench_point_id" not in results.columns:
        raise ValueError("identify_sweeps: results need a 'bench_point_id' column (simulate identification_plan)")
    okids = set(meas.loc[meas["status"] == "ok", "point_id"].astype(str))
    rids = set(results["bench_point_id"].astype(str))
    extra, missing = sorted(rids - okids), sorted(okids - rids)
    if extra or missing:
        raise ValueError(f"identify_sweeps: plan/rows mismatch: results hold bench_point_id(s) {extra[:5]} that are "
                         f"not 'ok' bench rows, and 'ok' bench rows {missing[:5]} have no results "
                         f"({len(extra)} extra, {len(missing)} missing); simulate identification_plan(meas_ok)")
    for oid, g in meas.groupby("op_id", sort=False):
        for c in ("throttle_pct", "speed_rpm", "lambda"):
            if np.ptp(g[c].to_numpy(float)) > 1e-9:
                raise ValueError(f"identify_sweeps: op_id {oid!r}: column {c!r} varies within the sweep "
                                 f"({sorted(g[c].unique())}); a sweep varies spark only")


def identify_sweeps(meas: pd.DataFrame, results: pd.DataFrame, eta_trans: float = 0.95,
                    tol: Tolerances = Tolerances(), surface: str = "spline", use_mbt: bool = True,
                    mbt_spark_sigma_deg: float = MBT_SPARK_SIGMA_DEG, terms: Sequence[str] | None = DEFAULT_TERMS,
                    spark_slopes: Sequence[tuple] = SPARK_SLOPES) -> pd.DataFrame:
    """Joint (BDUR10-90, m) per spark sweep.

    Parameters
    ----------
    meas : DataFrame
        Bench rows of :func:`sweep_plan` (``op_id`` column), all statuses; only 'ok' rows enter the
        likelihood, knock aborts mark a knock-limited sweep.
    results : DataFrame
        Simulated ``identification_plan(meas[meas.status == 'ok'], ...)`` (grouped by ``bench_point_id``).
    eta_trans : float
        Transmission efficiency [-] (measured power / eta_trans is the crank target).
    tol : Tolerances
    surface : {"spline", "cubic", "quadratic"}
    use_mbt : bool
        Add the CA50-at-MBT term where the sweep brackets MBT.
    mbt_spark_sigma_deg : float
        MBT spark uncertainty [deg], added in quadrature to ``tol.ca50_sigma_deg`` for that term.
    terms : sequence of str or None
        Per-point chi2 terms to use where the row has the channel (subset of ``power, pmax, exhaust_temp,
        bsfc, fuel, air``); default :data:`DEFAULT_TERMS`; None = all of
        :func:`engine_model.calibration.identify.terms_used`.
    spark_slopes : sequence of (kb, km)
        Candidate relative spark slopes [1/deg] of BDUR10-90 and m: a point at spark ``s`` burns with
        ``(b (1 + kb (s - s_mean)), m (1 + km (s - s_mean)))``; the pair with the lowest chi2 is used
        (profile over :data:`SPARK_SLOPES`; ``[(0, 0)]`` = constant parameters).

    Returns
    -------
    DataFrame
        One row per op_id (columns :data:`SWEEP_COLUMNS`, then ``chi2_<term>`` sums and ``terms``):
        ``spark_deg_btdc`` is the mean spark of the sweep's 'ok' points (the spark the reported
        parameters belong to), ``mbt_spark_deg_btdc`` the measured MBT (NaN if the
        sweep is knock-limited or does not bracket MBT; ``status`` says which), bounds are the 95 %
        region ``chi2 - chi2_min <= 5.99``, ``bdur_spark_slope_per_deg`` / ``m_spark_slope_per_deg`` the
        chosen relative slopes [1/deg], ``region_at_edge`` whether the region touches the plane's edge.
        ``fit_ok``: at the joint optimum at most half of the sweep's readings (each point's power against
        ``tol.power_rel``, exhaust temperature against ``tol.exhaust_temp_k``) miss their tolerance; the
        misses are listed in ``status``.  Sweeps with < 2 runnable sparks are kept with NaN and a status.
    """
    if not 0.5 < eta_trans <= 1.0:
        raise ValueError(f"identify_sweeps: eta_trans must be in (0.5, 1], got {eta_trans!r}")
    _check_inputs(meas, results)
    blocks = {k: g for k, g in results.groupby(results["bench_point_id"].astype(str), sort=False)}
    out = []
    for oid, g in meas.groupby("op_id", sort=False):
        g = g.sort_values("spark_deg_btdc")
        ok = g[g["status"] == "ok"]
        base = {"op_id": str(oid), "throttle_pct": float(g["throttle_pct"].iloc[0]),
                "speed_rpm": float(g["speed_rpm"].iloc[0]), "lambda": float(g["lambda"].iloc[0]),
                "spark_deg_btdc": float(ok["spark_deg_btdc"].mean()) if len(ok) else math.nan,
                "n_points": int(len(ok)), "n_aborted": int(len(g) - len(ok))}
        mbt, why = measured_mbt(g)
        base["mbt_spark_deg_btdc"] = mbt
        if len(ok) < 2:
            out.append({**base, "fit_ok": False, "mbt_used": False,
                        "status": f"skipped: {len(ok)} runnable spark(s) of {len(g)} "
                                  f"({g['status'].value_counts().to_dict()})"})
            continue
        pts, fb, fm = _sweep_surfaces(oid, ok, blocks, base["spark_deg_btdc"], eta_trans, tol, surface, terms)
        mbt_used = bool(use_mbt and math.isfinite(mbt))
        best = _best_slopes(pts, fb, fm, spark_slopes, mbt if mbt_used else math.nan, base["spark_deg_btdc"],
                            tol, mbt_spark_sigma_deg)
        out.append({**base, "mbt_used": mbt_used, **_sweep_result(best, pts, fb, fm, ok, eta_trans, tol, why)})
    table = pd.DataFrame(out)
    for c in SWEEP_COLUMNS:
        if c not in table.columns:
            table[c] = np.nan
    return table[list(SWEEP_COLUMNS) + [c for c in table.columns if c not in SWEEP_COLUMNS]]


def _sweep_surfaces(oid, ok: pd.DataFrame, blocks: dict, s_mean: float, eta_trans: float, tol: Tolerances,
                    surface: str, terms) -> tuple[list, np.ndarray, np.ndarray]:
    """Per runnable point of one sweep: (row, surfaces, chi2 terms, spark offset from the sweep's mean).

    Also returns the common fine (BDUR10-90, m) mesh; every point of a sweep must share one grid.
    """
    pts, shape = [], None
    for _, row in ok.iterrows():
        row = row.copy()
        row["at_mbt"] = False
        ps = point_surfaces(row, blocks[str(row["point_id"])], surface)
        if shape is None:
            shape, fb, fm = ps.fine["brake_power_kw"].shape, ps.fine_b, ps.fine_m
        elif ps.fine["brake_power_kw"].shape != shape or not (np.allclose(ps.fine_b, fb)
                                                               and np.allclose(ps.fine_m, fm)):
            raise ValueError(f"identify_sweeps: op_id {oid!r}, point {row['point_id']!r}: its (BDUR10-90, m) "
                             "grid differs from the sweep's other points; use one identification_plan grid")
        use = [t for t in terms_used(row) if terms is None or t in terms]
        pts.append((row, ps, chi2_terms(ps, eta_trans, tol, use), float(row["spark_deg_btdc"]) - s_mean))
    return pts, fb, fm


def _best_slopes(pts: list, fb: np.ndarray, fm: np.ndarray, spark_slopes, mbt: float, s_mean: float,
                 tol: Tolerances, mbt_spark_sigma_deg: float):
    """The joint chi2 over the sweep for each candidate spark slope; the slope pair with the lowest minimum.

    ``mbt`` NaN: no CA50-at-MBT term.  Returns (chi2_min, chi2 plane, chi2 per term, per-point shifted
    indices, (kb, km)).
    """
    FB, FM = np.meshgrid(fb, fm, indexing="ij")
    best = None
    for kb, km in spark_slopes:
        total, parts_sum, idx = 0.0, {}, []
        for row, ps, parts, ds in pts:
            ib, jm = _shifted_index(fb, fm, FB * (1 + kb * ds), FM * (1 + km * ds))
            idx.append((ib, jm))
            for k, v in parts.items():
                vv = _lookup(v, ib, jm)
                parts_sum[k] = parts_sum.get(k, 0.0) + vv
                total = total + vv
        if math.isfinite(mbt):
            ds = mbt - s_mean
            ca50 = wiebe.burn_angles(mbt, FB * (1 + kb * ds), FM * (1 + km * ds))["ca50_deg_atdc"]
            sig = math.hypot(tol.ca50_sigma_deg, mbt_spark_sigma_deg)
            parts_sum["ca50"] = ((ca50 - tol.ca50_target_deg) / sig) ** 2
            total = total + parts_sum["ca50"]
        chi2 = np.where(np.isfinite(total), total, np.inf)
        c = float(chi2.min())
        if best is None or c < best[0]:
            best = (c, chi2, parts_sum, idx, (kb, km))
    return best


def _sweep_result(best, pts: list, fb: np.ndarray, fm: np.ndarray, ok: pd.DataFrame, eta_trans: float,
                  tol: Tolerances, why: str) -> dict:
    """The sweep's row: optimum, 95 % region, tolerance check point by point at the joint optimum."""
    cmin, chi2, parts_sum, idx, (kb, km) = best
    i, j = np.unravel_index(int(np.argmin(chi2)), chi2.shape)
    ri, rj = np.nonzero(chi2 <= cmin + CHI2_95_2DOF)
    # tolerance check at the joint optimum, point by point (at each point's own shifted parameters)
    bad = []
    for (row, ps, _, _), (ib, jm) in zip(pts, idx):
        a, b_ = np.round(ib[i, j]).astype(int), np.round(jm[i, j]).astype(int)
        target = float(row["brake_power_kw"]) / eta_trans
        perr = ps.fine["brake_power_kw"][a, b_] / target - 1.0
        if abs(perr) > tol.power_rel:
            bad.append(f"{row['point_id']} power {100 * perr:+.1f} %")
        if pd.notna(row.get("exhaust_temp_k")):
            terr = ps.fine["exhaust_temp_k"][a, b_] - float(row["exhaust_temp_k"])
            if abs(terr) > tol.exhaust_temp_k:
                bad.append(f"{row['point_id']} exhaust T {terr:+.0f} K")
    # a 1-sigma tolerance is missed by ~1/3 of honest readings; the sweep fails if more than half miss
    n_chk = len(pts) * (2 if "exhaust_temp_k" in ok.columns else 1)
    fit_ok = len(bad) <= n_chk // 2
    status = "ok" if fit_ok else "tolerance missed: " + "; ".join(bad)
    if why != "ok":
        status += f" (MBT {why})"
    edge = bool(ri.min() == 0 or ri.max() == len(fb) - 1 or rj.min() == 0 or rj.max() == len(fm) - 1)
    return {"bdur_10_90_deg": float(fb[i]), "wiebe_m": float(fm[j]),
            "bdur_10_90_deg_lo": float(fb[ri.min()]), "bdur_10_90_deg_hi": float(fb[ri.max()]),
            "wiebe_m_lo": float(fm[rj.min()]), "wiebe_m_hi": float(fm[rj.max()]), "chi2_min": cmin,
            "fit_ok": bool(fit_ok), "status": status, "region_at_edge": edge,
            "bdur_spark_slope_per_deg": kb, "m_spark_slope_per_deg": km,
            "terms": ",".join(parts_sum), **{f"chi2_{k}": float(v[i, j]) for k, v in parts_sum.items()}}
