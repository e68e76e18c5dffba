"""Judge the spark tables of finished ``mbc run`` folders with the virtual bench's hidden law.

For the run's calibrated engine (airflow parameters from ``<run>/manifest.json``) the table builder is run once
with the truth law (:class:`engine_model.bench.burnlaw.BurnLaw`) as the combustion model on the same default ECU grid
and solver step (0.5 deg): the truth's own table.  Then, for each run, the truth engine is simulated at the run's
table spark in every cell both call feasible, and compared with the truth's table cell: torque ratio, knock
index, spark difference (all cells; and the cells the truth table calls MBT-limited).
``--lambda-table CSV``: the truth's table at that target lambda (as ``mbc maps --lambda-table``) instead of the
default one; judge runs whose maps were built with the same table.

    PYTHONPATH=. .venv/bin/python benchmarks/pipeline_map_vs_truth.py RUN_A RUN_B ...
    PYTHONPATH=. .venv/bin/python benchmarks/pipeline_map_vs_truth.py --lambda-table lambda.csv RUN_C
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import SolverSettings, default_spec

from engine_model.sim import simulate
from engine_model.bench.burnlaw import BurnLaw
from engine_model.tables import EcuGrid, LambdaTable, MapSettings, build_maps

SOLVER = SolverSettings(step_deg=0.5)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/pipeline_map_vs_truth"))
    ap.add_argument("--lambda-table", type=Path, default=None,
                    help="target-lambda wide CSV (default: the default table)")
    a = ap.parse_args()
    man = json.loads((a.runs[0] / "manifest.json").read_text())
    params = {k: float(v) for k, v in man["calibration"]["airflow"]["parameters"].items()}
    spec = default_spec().with_values(params)
    law = BurnLaw()
    a.cache.mkdir(parents=True, exist_ok=True)
    lam_table, lam_tag = None, ""
    if a.lambda_table is not None:
        lam_table = LambdaTable.from_csv(a.lambda_table)
        lam_tag = "_lam" + hashlib.sha256(a.lambda_table.read_bytes()).hexdigest()[:12]
    tc = a.cache / f"truth_cells_{spec.spec_hash()}{lam_tag}.parquet"
    if tc.is_file():
        truth = pd.read_parquet(tc)
    else:
        t0 = time.perf_counter()
        # the truth's own MBT in every cell (no load-trend fit: the truth's estimates carry no error)
        res = build_maps(spec, law, grid=EcuGrid(), lambda_table=lam_table,
                         settings=MapSettings(mbt_monotone_in_load=False),
                         evaluate=lambda p: simulate(spec, p, SOLVER))
        truth = res.cells
        truth.to_parquet(tc)
        print(f"truth table: {res.stats['simulated_points']} simulations, {time.perf_counter() - t0:.0f} s")
    key = ["throttle_pct", "speed_rpm"]
    for run in a.runs:
        cells = pd.read_parquet(run / "maps" / "cells.parquet")
        m = cells.merge(truth, on=key, suffixes=("", "_truth"))
        both = m[m["feasible"].astype(bool) & m["feasible_truth"].astype(bool)].reset_index(drop=True)
        pts = both[key + ["spark_deg_btdc", "lambda"]].copy()
        pred = law.predict(pts)
        pts["bdur_10_90_deg"], pts["wiebe_m"] = pred["bdur_10_90_deg"].to_numpy(), pred["wiebe_m"].to_numpy()
        sim = simulate(spec, pts, SOLVER)
        ratio = sim["brake_torque_nm"].to_numpy() / both["brake_torque_nm_truth"].to_numpy()
        ds = both["spark_deg_btdc"] - both["spark_deg_btdc_truth"]
        mbt = (both["limited_by_truth"] == "mbt").to_numpy()
        knock = sim["knock_index"].to_numpy()
        print(f"{run}: {len(both)} cells feasible in both (run {int(cells['feasible'].sum())}, truth "
              f"{int(truth['feasible'].sum())}); truth torque at the run's spark / at the truth table's: mean "
              f"{np.nanmean(ratio):.3f}, min {np.nanmin(ratio):.3f}, cells below 0.99: {int((ratio < 0.99).sum())}; "
              f"spark - truth table: RMS {np.sqrt(np.mean(ds ** 2)):.1f} deg (MBT cells of the truth, n = {int(mbt.sum())}: "
              f"{np.sqrt(np.mean(ds[mbt] ** 2)):.1f} deg); truth knock index >= {1.0} at {int((knock >= 1.0).sum())} cells")
        kn = (both["limited_by_truth"] == "knock").to_numpy()
        print(f"    truth knock-limited cells (n = {int(kn.sum())}): run spark - truth border mean {ds[kn].mean():+.1f} deg, "
              f"{int((ds[kn] > 1.0).sum())} more than 1 deg past it, max {ds[kn].max():+.1f}; truth knock index at "
              f"the run's spark there: median {np.median(knock[kn]):.2f}, max {knock[kn].max():.2f}")


if __name__ == "__main__":
    main()
