"""Error structure of joint spark-sweep identification against the virtual bench's hidden law.

Question: are the identification errors in (BDUR10-90, m) independent, or do they lie along the ridge of
constant combustion phasing?  MBT follows the ignition-to-CA50 angle
``phi50 = CA50 + SOC = BDUR (ln2/a)^(1/(m+1))`` (SOC = spark), so that is the combination that matters for
the ECU spark table.

Setup (docs/sections/identify_sweep.md, extended to more operating points): operating points = the 6
D-optimal points of that page (throttle 20/60/100 % x 6000/9000/12000 rpm) plus ``--n-lhs`` Latin-hypercube
points over throttle 20-100 % x 5000-13000 rpm (the box of the fitted-map acceptance test); one bench run
with the 7 spark offsets of case B (-15..+15 deg from the MBT prior, noise on, seed 0); case A is the same
data restricted to offsets -15..+5.  ``identification_plan(..., 6, 6)``, ``doe.QUICK_SOLVER`` for the bench
and the identification.  Errors are joint estimate minus ``BurnLaw.predict`` at the sweep's mean spark.

Writes ``docs/data/identification_error.csv`` (one row per sweep and case) and prints the summary.
Simulations are cached in ``--cache`` (parquet) so the analysis can be re-run without simulating.

    PYTHONPATH=. .venv/bin/python benchmarks/identification_error.py --n-lhs 12
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import wiebe

from engine_model import doe
from engine_model.bench.burnlaw import BurnLaw
from engine_model.calibration.identify import identification_plan
from engine_model.calibration.sweeps import choose_operating_points, identify_sweeps, sweep_plan
from engine_model.bench.virtual import VirtualBench

OFFSETS_B = (-15.0, -10.0, -5.0, 0.0, 5.0, 10.0, 15.0)
A_MAX_OFFSET = 5.0


def phi50(bdur_10_90, m):
    """Ignition-to-CA50 angle [deg] of a Wiebe burn starting at the spark."""
    return wiebe.burn_angles(0.0, bdur_10_90, m)["ca50_deg_atdc"]


def operating_points(n_lhs: int) -> pd.DataFrame:
    d = choose_operating_points(6, bounds={"throttle_pct": (20, 100), "speed_rpm": (6000, 12000)})
    d["op_id"] = [f"d{i}" for i in range(len(d))]
    frames = [d]
    if n_lhs:
        lhs = doe.latin_hypercube(n_lhs, bounds={"throttle_pct": (20.0, 100.0), "speed_rpm": (5000.0, 13000.0),
                                                 "spark_deg_btdc": (0.0, 1.0)}, seed=11)
        lhs = lhs[["throttle_pct", "speed_rpm"]].round({"throttle_pct": 1, "speed_rpm": -1})
        lhs["op_id"] = [f"l{i}" for i in range(len(lhs))]
        frames.append(lhs)
    return pd.concat(frames, ignore_index=True)


def simulate(n_lhs: int, cache: Path):
    cache.mkdir(parents=True, exist_ok=True)
    fm, fr = cache / f"meas_{n_lhs}.parquet", cache / f"res_{n_lhs}.parquet"
    if fm.is_file() and fr.is_file():
        return pd.read_parquet(fm), pd.read_parquet(fr)
    t0 = time.perf_counter()
    plan = sweep_plan(operating_points(n_lhs), OFFSETS_B)
    meas = VirtualBench(law=BurnLaw(), solver=doe.QUICK_SOLVER, seed=0).measure(plan)
    ok = meas[meas["status"] == "ok"].reset_index(drop=True)
    print(f"bench: {len(plan)} points, {meas['status'].value_counts().to_dict()}, {time.perf_counter() - t0:.0f} s",
          flush=True)
    ip = identification_plan(ok, None, 6, 6)
    res = doe.quick_evaluate(ip)
    res["bench_point_id"] = ip["bench_point_id"].to_numpy()
    print(f"identification: {len(ip)} simulations, {time.perf_counter() - t0:.0f} s total", flush=True)
    meas.to_parquet(fm)
    res.to_parquet(fr)
    return meas, res


def errors(meas: pd.DataFrame, res: pd.DataFrame, case: str) -> pd.DataFrame:
    if case == "A":
        meas = meas[meas["spark_offset_deg"] <= A_MAX_OFFSET + 1e-9]
        okids = set(meas.loc[meas["status"] == "ok", "point_id"])
        res = res[res["bench_point_id"].isin(okids)]
    j = identify_sweeps(meas, res, eta_trans=0.95)
    j = j[np.isfinite(j["bdur_10_90_deg"])].reset_index(drop=True)
    law = BurnLaw()
    t = law.predict(j[["throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda"]])
    out = j[["op_id", "throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda", "n_points", "mbt_used", "fit_ok",
             "region_at_edge"]].copy()
    out.insert(0, "case", case)
    out["bdur_true"], out["m_true"] = t["bdur_10_90_deg"].to_numpy(), t["wiebe_m"].to_numpy()
    out["bdur_id"], out["m_id"] = j["bdur_10_90_deg"].to_numpy(), j["wiebe_m"].to_numpy()
    out["phi50_true"] = phi50(out["bdur_true"].to_numpy(), out["m_true"].to_numpy())
    out["phi50_id"] = phi50(out["bdur_id"].to_numpy(), out["m_id"].to_numpy())
    out["err_bdur"] = out["bdur_id"] - out["bdur_true"]
    out["err_m"] = out["m_id"] - out["m_true"]
    out["err_phi50"] = out["phi50_id"] - out["phi50_true"]
    out["err_log_phi50"] = np.log(out["phi50_id"] / out["phi50_true"])
    # along the sweep: each runnable spark burns with the fitted spark slopes, (b (1 + kb ds), m (1 + km ds))
    ok = meas[meas["status"] == "ok"].merge(j[["op_id", "spark_deg_btdc", "bdur_10_90_deg", "wiebe_m",
                                               "bdur_spark_slope_per_deg", "m_spark_slope_per_deg"]]
                                            .rename(columns={"spark_deg_btdc": "s_mean"}), on="op_id")
    ds = ok["spark_deg_btdc"] - ok["s_mean"]
    b_id = ok["bdur_10_90_deg"] * (1 + ok["bdur_spark_slope_per_deg"] * ds)
    m_id = ok["wiebe_m"] * (1 + ok["m_spark_slope_per_deg"] * ds)
    tp = law.predict(ok[["throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda"]])
    along = pd.DataFrame({"case": case, "op_id": ok["op_id"], "spark_offset_deg": ok["spark_offset_deg"],
                          "spark_minus_mean_deg": ds, "err_bdur": b_id - tp["bdur_10_90_deg"].to_numpy(),
                          "err_m": m_id - tp["wiebe_m"].to_numpy(),
                          "err_phi50": phi50(b_id.to_numpy(), m_id.to_numpy())
                          - phi50(tp["bdur_10_90_deg"].to_numpy(), tp["wiebe_m"].to_numpy())})
    return out, along


def summary(e: pd.DataFrame) -> None:
    rm = lambda x: float(np.sqrt(np.mean(np.square(x))))
    for case, g in e.groupby("case"):
        eb, em, ep = g["err_bdur"].to_numpy(), g["err_m"].to_numpy(), g["err_phi50"].to_numpy()
        c = np.corrcoef(np.vstack([eb, em, ep]))
        print(f"case {case}: n = {len(g)} sweeps (MBT term used at {int(g['mbt_used'].sum())})")
        print(f"  RMSE (bias): BDUR10-90 {rm(eb):.2f} ({eb.mean():+.2f}) deg, m {rm(em):.2f} ({em.mean():+.2f}), "
              f"phi50 {rm(ep):.2f} ({ep.mean():+.2f}) deg, log phi50 {rm(g['err_log_phi50']):.3f}")
        print(f"  corr(BDUR, m) {c[0, 1]:+.2f}, corr(BDUR, phi50) {c[0, 2]:+.2f}, corr(m, phi50) {c[1, 2]:+.2f}")
        # what phi50's error would be if (BDUR, m) errors were independent with the same RMSE
        b, m = g["bdur_true"].to_numpy(), g["m_true"].to_numpy()
        h = 1e-4
        db = (phi50(b + h, m) - phi50(b - h, m)) / (2 * h)
        dm = (phi50(b, m + h) - phi50(b, m - h)) / (2 * h)
        print(f"  dphi50/dBDUR {db.mean():.3f}, dphi50/dm {dm.mean():+.2f} deg; phi50 RMSE if independent: "
              f"{float(np.sqrt(np.mean((db * rm(eb)) ** 2 + (dm * rm(em)) ** 2))):.2f} deg")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n-lhs", type=int, default=12)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/identification_error"))
    ap.add_argument("--out", type=Path, default=Path("docs/data/identification_error.csv"))
    a = ap.parse_args()
    meas, res = simulate(a.n_lhs, a.cache)
    (ea, aa), (eb, ab) = errors(meas, res, "A"), errors(meas, res, "B")
    e = pd.concat([ea, eb], ignore_index=True)
    along = pd.concat([aa, ab], ignore_index=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    e.round(4).to_csv(a.out, index=False)
    along.round(4).to_csv(a.out.with_name(a.out.stem + "_along_sweep.csv"), index=False)
    summary(e)
    rm = lambda x: float(np.sqrt(np.mean(np.square(x))))
    print("along the sweep (each runnable spark, fitted spark slopes): RMSE by |spark - sweep mean|")
    along["band"] = pd.cut(along["spark_minus_mean_deg"].abs(), [-0.1, 5, 10, 30], labels=["0-5", "5-10", ">10"])
    print(along.groupby(["case", "band"], observed=True)[["err_bdur", "err_m", "err_phi50"]].agg(rm).round(2)
          .assign(n=along.groupby(["case", "band"], observed=True).size()).to_string())
    pd.set_option("display.width", 200)
    print(e[["case", "op_id", "throttle_pct", "speed_rpm", "n_points", "mbt_used", "err_bdur", "err_m",
             "err_phi50"]].round(2).to_string(index=False))


if __name__ == "__main__":
    main()
