"""Identifiability check: recover known (BDUR10-90, m, eta_trans) from model-generated noisy bench data.

The truth points are simulated at known Wiebe parameters (spark set so that
CA50 = 9 deg ATDC, i.e. MBT points, unless a spark is given), the crank power
is turned into "measured" power with a known eta_trans, and noise is added
per draw:

* torque (hence power): 0.5 % (1 sigma) [issue 4];
* airflow: 1 % (1 sigma) [issue 4].  Airflow noise acts through the airflow
  match: a point whose air mass is mis-matched by eps has its fuelled charge,
  hence gross indicated work, off by eps, i.e. brake power off by
  ``eps * imep_gross / bmep``.  It is applied as that equivalent error of the
  measured power (first-order propagation; the airflow match itself is not
  re-run per draw);
* exhaust temperature: 5 K (1 sigma) [issue 4].

Each draw is identified with the same response surfaces (one identification
sweep per truth point), once at the true eta_trans and once with eta_trans
from the joint fit across the truth points (shared eta).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from engine_model import wiebe
from engine_model.priors import CA50_TARGET_DEG_ATDC
from engine_model.calibration.identify import Identification, Tolerances, identification_plan, identify, identify_point
from engine_model.calibration.eta import joint_fit


@dataclass(frozen=True)
class Noise:
    """1-sigma measurement noise: torque_rel [-], air_rel [-], exhaust_temp_k [K]."""

    torque_rel: float = 0.005
    air_rel: float = 0.01
    exhaust_temp_k: float = 5.0


def synthetic_bench(truths: pd.DataFrame, evaluate, eta_trans: float = 0.95, overrides: dict | None = None,
                    exhaust_temp: bool = True) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Noise-free bench rows simulated at known Wiebe parameters.

    Parameters
    ----------
    truths : DataFrame
        ``speed_rpm, throttle_pct, lambda, bdur_10_90_deg, wiebe_m`` and optional ``spark_deg_btdc``
        (default: the MBT spark, CA50 = 9 deg ATDC) and ``point_id``.
    evaluate : callable(plan) -> results
    eta_trans : float
        True transmission efficiency [-]: measured power = crank power x eta_trans.
    overrides : dict, optional
        Spec override columns (``spec.<section>.<field>``).
    exhaust_temp : bool
        Include the ``exhaust_temp_k`` channel.

    Returns
    -------
    bench, sim : DataFrame
        The bench table (contract columns, ``at_mbt``, ``bench_ok``) and the truth simulation.
    """
    t = truths.reset_index(drop=True).copy()
    if "point_id" not in t.columns:
        t["point_id"] = [f"truth{i:02d}" for i in range(len(t))]
    given = "spark_deg_btdc" in t.columns
    if not given:
        bdur = wiebe.bdur_10_90_to_bdur(t["bdur_10_90_deg"].to_numpy(float), t["wiebe_m"].to_numpy(float))
        t["spark_deg_btdc"] = wiebe.soc_for_ca50(CA50_TARGET_DEG_ATDC, bdur, t["wiebe_m"].to_numpy(float))
    plan = t.copy()
    for k, v in (overrides or {}).items():
        plan[k] = float(v)
    sim = evaluate(plan).reset_index(drop=True)
    if not sim["converged"].all():
        bad = sim.loc[~sim["converged"], "point_id"].tolist()
        raise ValueError(f"synthetic_bench: truth points did not converge: {bad}")
    p = sim["brake_power_kw"].to_numpy(float) * eta_trans
    omega = t["speed_rpm"].to_numpy(float) * 2 * math.pi / 60
    bench = pd.DataFrame({
        "point_id": t["point_id"].astype(str), "speed_rpm": t["speed_rpm"].to_numpy(float),
        "throttle_pct": t["throttle_pct"].to_numpy(float), "spark_deg_btdc": t["spark_deg_btdc"].to_numpy(float),
        "lambda": t["lambda"].to_numpy(float), "brake_torque_nm": p * 1e3 / omega, "brake_power_kw": p,
        "air_mass_flow_kg_h": sim["air_mass_flow_kg_h"].to_numpy(float),
        "at_mbt": not given, "bench_ok": True, "bench_flags": ""})
    if exhaust_temp:
        bench["exhaust_temp_k"] = sim["exhaust_temp_k"].to_numpy(float)
    return bench, sim


def identifiability_check(truths: pd.DataFrame, evaluate, eta_trans: float = 0.95, noise: Noise = Noise(),
                          n_draws: int = 30, seed: int = 0, n_bdur: int = 11, n_m: int = 13,
                          overrides: dict | None = None, tol: Tolerances = Tolerances(),
                          exhaust_temp: bool = True, etas=None) -> dict:
    """Recover known (BDUR10-90, m, eta_trans) from noisy synthetic bench data.

    Returns
    -------
    dict
        ``draws``: one row per (draw, point) with truth, estimate at the true eta, estimate at the
        jointly fitted eta, and the jointly fitted eta; ``summary``: bias and spread (std) of each
        estimate per point; ``bench``: the noise-free synthetic bench; ``simulations``: number run.
    """
    bench, sim = synthetic_bench(truths, evaluate, eta_trans, overrides, exhaust_temp)
    plan = identification_plan(bench, overrides, n_bdur, n_m)
    res = evaluate(plan)
    base = identify(bench, res, eta_trans, tol)
    k_air = (sim["imep_gross_bar"] / sim["bmep_bar"]).to_numpy(float)
    rng = np.random.default_rng(seed)
    etas = np.round(np.arange(0.85, 1.0001, 0.005), 4) if etas is None else etas
    rows = []
    for d in range(n_draws):
        e_t = rng.normal(0, noise.torque_rel, len(bench))
        e_a = rng.normal(0, noise.air_rel, len(bench))
        e_x = rng.normal(0, noise.exhaust_temp_k, len(bench))
        surfs, pmeas = {}, {}
        for i, r in bench.iterrows():
            row = base.surfaces[r["point_id"]].row.copy()
            if exhaust_temp:
                row["exhaust_temp_k"] = float(r["exhaust_temp_k"]) + e_x[i]
            pmeas[r["point_id"]] = float(r["brake_power_kw"]) * (1 + e_t[i]) * (1 + e_a[i] * k_air[i])
            surfs[r["point_id"]] = dataclasses.replace(base.surfaces[r["point_id"]], row=row)
        jf = joint_fit(Identification(base.table, surfs, eta_trans, tol), etas=etas, power_meas=pmeas)
        eta_hat = float(jf.table["eta_best"].iloc[0])
        for i, r in bench.iterrows():
            pid = r["point_id"]
            a = identify_point(surfs[pid], eta_trans, tol, power_meas_kw=pmeas[pid])
            b = identify_point(surfs[pid], eta_hat, tol, power_meas_kw=pmeas[pid])
            rows.append({"draw": d, "point_id": pid, "bdur_true": float(truths["bdur_10_90_deg"].iloc[i]),
                         "m_true": float(truths["wiebe_m"].iloc[i]), "eta_true": eta_trans,
                         "bdur_hat": a["bdur_10_90_deg"], "m_hat": a["wiebe_m"], "eta_hat": eta_hat,
                         "eta_identifiable": bool(jf.table["identifiable"].iloc[0]),
                         "bdur_hat_joint": b["bdur_10_90_deg"], "m_hat_joint": b["wiebe_m"]})
    draws = pd.DataFrame(rows)
    g = draws.groupby("point_id", sort=False)
    summary = pd.DataFrame({
        "bdur_true": g["bdur_true"].first(), "m_true": g["m_true"].first(),
        "bdur_bias": g.apply(lambda x: (x["bdur_hat"] - x["bdur_true"]).mean()),
        "bdur_std": g["bdur_hat"].std(), "m_bias": g.apply(lambda x: (x["m_hat"] - x["m_true"]).mean()),
        "m_std": g["m_hat"].std(),
        "bdur_bias_joint": g.apply(lambda x: (x["bdur_hat_joint"] - x["bdur_true"]).mean()),
        "bdur_std_joint": g["bdur_hat_joint"].std(),
        "m_bias_joint": g.apply(lambda x: (x["m_hat_joint"] - x["m_true"]).mean()),
        "m_std_joint": g["m_hat_joint"].std(),
        "eta_bias": g.apply(lambda x: (x["eta_hat"] - x["eta_true"]).mean()), "eta_std": g["eta_hat"].std(),
    }).reset_index()
    return {"draws": draws, "summary": summary, "bench": bench, "simulations": len(plan) + len(bench)}
