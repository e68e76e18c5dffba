"""Where the gap lies: a smooth residual field over the operating map, the shape of the error per output,
and the energy chain from air to brake torque."""

from __future__ import annotations

import numpy as np
import pandas as pd

from engine_model import priors
from engine_model.gap.linear import Linearisation

__all__ = ["coded_map", "field_fit", "shape_label", "energy_chain"]


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
    """
    def rel(c):
        if c not in outputs:
            return None
        k = outputs.index(c)
        v = np.where(valid[:, k], (y[:, k] - fit[:, k]) / fit[:, k] * 100.0, np.nan)
        return v

    def absd(c):
        if c not in outputs:
            return None
        k = outputs.index(c)
        return np.where(valid[:, k], y[:, k] - fit[:, k], np.nan)

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
    stages = []
    stages.append(("air in", air, "airflow (meter)"))
    stages.append(("fuel energy", (fuel - air) if fuel is not None else None, "fuel flow vs airflow"))
    ind = ratio * tex if tex is not None else None
    stages.append(("indicated (combustion, heat)", ind, f"exhaust T x {ratio:.3g} %/K"))
    used = np.zeros_like(tq)
    for _, v, _ in stages:
        if v is not None:
            used = used + np.nan_to_num(v)
    stages.append(("mechanical + transmission", tq - used, "rest of the torque gap"))
    rows = []
    for name, v, how in stages:
        if v is None:
            rows.append({"stage": name, "mean_pct": np.nan, "se_pct": np.nan, "pinned_by": how + " (not measured)"})
            continue
        vv = v[np.isfinite(v)]
        rows.append({"stage": name, "mean_pct": float(np.mean(vv)) if vv.size else np.nan,
                     "se_pct": float(np.std(vv, ddof=1) / np.sqrt(vv.size)) if vv.size > 1 else np.nan,
                     "pinned_by": how})
    tv = tq[np.isfinite(tq)]
    rows.append({"stage": "brake at dyno (total)", "mean_pct": float(np.mean(tv)),
                 "se_pct": float(np.std(tv, ddof=1) / np.sqrt(tv.size)) if tv.size > 1 else np.nan,
                 "pinned_by": "torque (dyno)"})
    return pd.DataFrame(rows)
