"""Where the gap lies: a smooth residual field over the operating map, the shape of the error per output,
and the energy chain from air to brake torque."""

from __future__ import annotations

import numpy as np
import pandas as pd

from engine_model import priors
from engine_model.gap.linear import Linearisation

__all__ = ["coded_map", "field_fit", "shape_label", "energy_chain", "operating_regions", "region_statistics",
           "region_table", "CHAIN_T_MIN"]


def coded_map(points: pd.DataFrame) -> tuple[np.ndarray, list[str]]:
    """Design of the smooth residual field: columns and names (only terms the plan can carry)."""
    n = points["speed_rpm"].to_numpy(float)
    t = points["throttle_pct"].to_numpy(float)
    s = points["spark_deg_btdc"].to_numpy(float)
    ds = s - np.atleast_1d(priors.spark_estimate(n, t))
    cols, names = [np.ones_like(n)], ["offset"]
    sc = (n - 9000.0) / 3000.0
    if np.ptp(n) > 0:
        cols.append(sc)
        names.append("speed")
        if np.unique(n).size >= 3:
            cols.append(sc**2 - np.mean(sc**2))
            names.append("speed^2")
    if np.ptp(t) > 1.0:
        cols.append((t - 100.0) / 50.0)
        names.append("load")
        if np.ptp(n) > 0:
            cols.append(sc * (t - 100.0) / 50.0)
            names.append("speed*load")
    if np.ptp(ds) > 1.0:
        cols.append(ds / 10.0)
        names.append("spark")
    return np.column_stack(cols), names


def field_fit(z: np.ndarray, x: np.ndarray, names: list[str]):
    """Unit-weight LS of normalised residuals z on x (z already in sigma units); coef, se, chi2, dof."""
    good = np.isfinite(z)
    xg, zg = x[good], z[good]
    p = xg.shape[1]
    if zg.size <= p:
        keep = min(p, max(1, zg.size - 1))
        xg, names = xg[:, :keep], names[:keep]
        p = keep
    cov = np.linalg.pinv(xg.T @ xg)
    coef = cov @ xg.T @ zg
    res = zg - xg @ coef
    chi2 = float(res @ res)
    dof = max(1, zg.size - p)
    # residual-scaled uncertainty when the scatter exceeds the measurement noise
    scale = max(1.0, chi2 / dof)
    se = np.sqrt(np.diag(cov) * scale)
    return coef, se, chi2, dof, names


def shape_label(row) -> str:
    terms = {"offset": row["offset_t"], "speed slope": row["speed_t"], "curvature": row["speed2_t"],
             "load": row["load_t"]}
    sig = {k: abs(v) for k, v in terms.items() if np.isfinite(v) and abs(v) > 3.0}
    if row["lack_of_fit_p"] < 0.01:
        return "resonance/local structure (lack of fit of the smooth field)"
    if not sig:
        return "none significant"
    main = max(sig, key=sig.get)
    return main + (" (mixed-sign errors: a missing shape, not a level)" if 0.25 < row["frac_positive"] < 0.75
                   else "")


#: Smallest |mean / s.e.| at which the energy chain books a stage's share (about 0.3 % two-sided per stage
#: for a normal mean; the chain has at most four stages).
CHAIN_T_MIN = 3.0


def energy_chain(lin: Linearisation, outputs, y, fit, valid) -> pd.DataFrame:
    """Waterfall of the relative torque gap along the energy chain (mean over points, % of torque).

    * air in: the airflow residual (torque follows the trapped air at a fixed efficiency);
    * fuel energy: fuel-flow residual minus airflow residual (a mixture/lambda or meter gap), when measured;
    * indicated (combustion, heat): from the exhaust-temperature residual, through the model's own ratio of
      torque change to exhaust-temperature change for a combustion-efficiency loss (the
      ``combustion_efficiency`` Jacobian column; a documented fallback 0.2 %/K otherwise);
    * mechanical + transmission (pumping, friction, gearbox): the rest of the torque gap, which no other
      measured quantity pins down;
    * brake at the dyno: the total torque residual.

    A share is *booked* only when its mean is at least :data:`CHAIN_T_MIN` standard errors from zero, and
    only when the total torque gap itself is: a torque that agrees with the model has no gap to
    distribute, and a residual on another channel is then not a torque loss (a sensor, or two effects that
    cancel).  The mechanical share is the torque gap minus the booked upstream shares, so no stage is
    invented to compensate a share that was not booked.
    """
    def rel(c):
        if c not in outputs:
            return None
        k = outputs.index(c)
        return np.where(valid[:, k], (y[:, k] - fit[:, k]) / fit[:, k] * 100.0, np.nan)

    def absd(c):
        if c not in outputs:
            return None
        k = outputs.index(c)
        return np.where(valid[:, k], y[:, k] - fit[:, k], np.nan)

    def stats(v):
        vv = v[np.isfinite(v)]
        m = float(np.mean(vv)) if vv.size else np.nan
        se = float(np.std(vv, ddof=1) / np.sqrt(vv.size)) if vv.size > 1 else np.nan
        t = abs(m) / se if se and np.isfinite(se) and se > 0 else 0.0
        return m, se, t

    tq = rel("brake_torque_nm")
    air = rel("air_mass_flow_kg_h")
    fuel = rel("fuel_mass_flow_kg_h")
    tex = absd("exhaust_temp_k")
    ratio = 0.2
    j = lin.column_index("combustion_efficiency")
    if j:
        jt = lin.jac[:, lin.outputs.index("brake_torque_nm"), j[0]] / lin.y_ref[:, 1] * 100.0
        je = lin.jac[:, lin.outputs.index("exhaust_temp_k"), j[0]]
        good = lin.ok & (np.abs(je) > 1e-9)
        if good.any():
            ratio = float(np.median(jt[good] / je[good]))
    t_m, t_se, t_t = stats(tq)
    total_sig = t_t >= CHAIN_T_MIN
    upstream = [("air in", air, "airflow (meter)"),
                ("fuel energy", (fuel - air) if fuel is not None and air is not None else None,
                 "fuel flow vs airflow"),
                ("indicated (combustion, heat)", ratio * tex if tex is not None else None,
                 f"exhaust T x {ratio:.3g} %/K")]
    rows = []
    used = np.zeros_like(tq)
    for name, v, how in upstream:
        if v is None:
            rows.append({"stage": name, "mean_pct": np.nan, "se_pct": np.nan, "t": np.nan, "booked": False,
                         "pinned_by": how + " (not measured)"})
            continue
        m, se, t = stats(v)
        booked = bool(total_sig and t >= CHAIN_T_MIN)
        if booked:
            used = used + np.nan_to_num(v)
        rows.append({"stage": name, "mean_pct": m, "se_pct": se, "t": t, "booked": booked, "pinned_by": how})
    m, se, t = stats(tq - used)
    rows.append({"stage": "mechanical + transmission", "mean_pct": m, "se_pct": se, "t": t,
                 "booked": bool(total_sig and t >= CHAIN_T_MIN), "pinned_by": "rest of the torque gap"})
    rows.append({"stage": "brake at dyno (total)", "mean_pct": t_m, "se_pct": t_se, "t": t_t,
                 "booked": bool(total_sig), "pinned_by": "torque (dyno)"})
    return pd.DataFrame(rows)


def operating_regions(points: pd.DataFrame) -> tuple[np.ndarray, list[str]]:
    """Operating region of every plan point: speed band x load band.

    Speed: three bands with equal numbers of operating points (terciles of the plan's speeds; fewer when
    the plan has fewer distinct speeds).  Load: two bands split at the median throttle when the plan's
    throttle spans more than 10 %-points, else one.

    Returns
    -------
    labels : ndarray of int (n,)
    names : list of str
        ``"<lo>-<hi> rpm, <lo>-<hi> % throttle"`` per label.
    """
    n = points["speed_rpm"].to_numpy(float)
    t = points["throttle_pct"].to_numpy(float)
    ns = min(3, np.unique(np.round(n)).size)
    s_edges = np.quantile(n, np.linspace(0, 1, ns + 1)) if ns > 1 else np.array([n.min(), n.max()])
    sb = np.clip(np.searchsorted(s_edges[1:-1], n, side="right"), 0, max(0, ns - 1))
    split = np.ptp(t) > 10.0
    t_mid = float(np.median(t))
    lb = (t > t_mid).astype(int) if split else np.zeros(n.size, int)
    labels = sb * 2 + lb
    names = {}
    for lab in np.unique(labels):
        m = labels == lab
        names[lab] = (f"{n[m].min():.0f}-{n[m].max():.0f} rpm, {t[m].min():.0f}-{t[m].max():.0f} % throttle")
    uniq = sorted(names)
    remap = {lab: i for i, lab in enumerate(uniq)}
    return np.array([remap[v] for v in labels]), [names[lab] for lab in uniq]


def region_statistics(z: np.ndarray, point: np.ndarray, output: np.ndarray, labels: np.ndarray,
                      n_outputs: int) -> np.ndarray:
    """Standardised mean residual per (output, region): sum of ``z`` over the cell / sqrt(count).

    ``z`` may be (nobs,) or (nobs, draws); cells without observations are 0.  Rows with ``point < 0``
    (prior pseudo-observations) are ignored.
    """
    z2 = z.reshape(z.shape[0], -1)
    keep = point >= 0
    cell = output[keep] * (labels.max() + 1) + labels[point[keep]]
    n_cells = n_outputs * (labels.max() + 1)
    sums = np.zeros((n_cells, z2.shape[1]))
    np.add.at(sums, cell, z2[keep])
    cnt = np.bincount(cell, minlength=n_cells).astype(float)
    return sums / np.sqrt(np.maximum(cnt, 1.0))[:, None]


def region_table(z: np.ndarray, null_z: np.ndarray, point: np.ndarray, output: np.ndarray,
                 points: pd.DataFrame, outputs: list[str], alpha: float = 0.05) -> pd.DataFrame:
    """Where the gap is: per output and operating region, the mean residual and whether it beats noise.

    Parameters
    ----------
    z : (nobs,)
        Residuals of the base fit in sigma units (diagonal), rows as ``point``/``output``.
    null_z : (nobs, draws)
        The same residuals for pure-noise data sets on the same plan (noise drawn with the error model's
        covariance, the base refitted to each).
    alpha : float
        Family-wise false-localisation rate: a cell is significant when its standardised mean exceeds the
        (1 - alpha) quantile of the *largest* such statistic over all cells under pure noise.

    Returns
    -------
    DataFrame
        output, region, n_obs, mean_z, se_z (from the noise draws), stat, threshold, significant.
    """
    labels, names = operating_regions(points)
    st = region_statistics(z, point, output, labels, len(outputs))[:, 0]
    nul = region_statistics(null_z, point, output, labels, len(outputs))
    thr = float(np.quantile(np.abs(nul).max(axis=0), 1.0 - alpha))
    keep = point >= 0
    cell = output[keep] * (labels.max() + 1) + labels[point[keep]]
    cnt = np.bincount(cell, minlength=st.size)
    rows = []
    for k, out in enumerate(outputs):
        for lab, name in enumerate(names):
            c = k * (labels.max() + 1) + lab
            if cnt[c] == 0:
                continue
            sd = float(np.std(nul[c]))
            rows.append({"output": out, "region": name, "n_obs": int(cnt[c]),
                         "mean_z": float(st[c] / np.sqrt(cnt[c])), "se_z": sd / np.sqrt(cnt[c]),
                         "stat": float(st[c]), "threshold": thr, "significant": bool(abs(st[c]) > thr)})
    return pd.DataFrame(rows)
