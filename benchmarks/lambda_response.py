"""How the cycle model answers a change of mixture strength, and a target-lambda table that follows the charge.

1. At a fixed burn (BDUR10-90 30 deg, m 2) and fixed spark, brake torque, knock index and exhaust temperature
   against lambda 0.8-1.05 at WOT 9000 rpm (spark 50 deg) and at 3000 rpm WOT and 50 % (spark 13 deg), on the
   run's calibrated engine (or the default one), once with the spec's combustion efficiency and once with the
   rich side held at the lean value (what is left is the gas model's own answer).  Engines make their best
   torque a little rich (lambda ~0.85-0.9); this prints where the model puts it.
2. ``--charge-table OUT.csv``: a target-lambda table on the run's grid that follows the charge instead of the
   throttle: 1.0 up to 90 % of the WOT trapped mass at the cell's speed, 0.9 from 95 % (linear between), never
   leaner than the default target.  Give it to ``mbc maps --lambda-table`` and judge the result with
   ``benchmarks/pipeline_map_vs_truth.py --lambda-table``.

    PYTHONPATH=. .venv/bin/python benchmarks/lambda_response.py [--run RUN] [--charge-table OUT.csv]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import SolverSettings, default_spec
from engine_model.sim import simulate
from engine_model.tables import EcuGrid, LambdaTable

SOLVER = SolverSettings(step_deg=0.5)
LAMBDAS = (0.8, 0.85, 0.9, 0.95, 1.0, 1.05)
POINTS = ((9000.0, 100.0, 50.0), (3000.0, 100.0, 13.0), (3000.0, 50.0, 13.0))   # rpm, throttle %, spark deg BTDC
BURN = {"bdur_10_90_deg": 30.0, "wiebe_m": 2.0}
CHARGE_RAMP = ([0.90, 0.95], [1.0, 0.9])   # WOT-charge fraction -> lambda (this benchmark's choice, see docstring)


def run_spec(run: Path | None):
    if run is None:
        return default_spec()
    man = json.loads((run / "manifest.json").read_text())
    return default_spec().with_values({k: float(v) for k, v in man["calibration"]["airflow"]["parameters"].items()})


def response(spec) -> pd.DataFrame:
    rows = [{"speed_rpm": n, "throttle_pct": t, "spark_deg_btdc": s, "lambda": lam, **BURN}
            for n, t, s in POINTS for lam in LAMBDAS]
    plan = pd.DataFrame(rows)
    plan["point_id"] = np.arange(len(plan))
    out = simulate(spec, plan, SOLVER)
    ref = out[out["lambda"] == 1.0].set_index(["speed_rpm", "throttle_pct"])["brake_torque_nm"]
    key = pd.MultiIndex.from_frame(out[["speed_rpm", "throttle_pct"]])
    out["torque_vs_lambda_1_pct"] = 100.0 * (out["brake_torque_nm"].to_numpy() / ref.reindex(key).to_numpy() - 1.0)
    return out[["speed_rpm", "throttle_pct", "lambda", "brake_torque_nm", "torque_vs_lambda_1_pct", "knock_index",
                "exhaust_temp_k", "converged"]]


def charge_table(run: Path) -> pd.DataFrame:
    cells = pd.read_parquet(run / "maps" / "cells.parquet")
    wot = cells[cells["throttle_pct"] == cells["throttle_pct"].max()].set_index("speed_rpm")["trapped_mass_mg"]
    frac = cells["trapped_mass_mg"].to_numpy() / cells["speed_rpm"].map(wot).to_numpy()
    th, sp = np.unique(cells["throttle_pct"].to_numpy(float)), np.unique(cells["speed_rpm"].to_numpy(float))
    default = LambdaTable.from_csv(run / "maps" / "lambda_target.csv").on_grid(EcuGrid(th, sp))
    base = default[np.searchsorted(th, cells["throttle_pct"].to_numpy(float)),
                   np.searchsorted(sp, cells["speed_rpm"].to_numpy(float))]
    lam = np.minimum(np.interp(frac, *CHARGE_RAMP), base)
    wide = (cells.assign(lam=np.round(lam, 3))
            .pivot(index="throttle_pct", columns="speed_rpm", values="lam"))
    wide.columns = [str(int(c)) for c in wide.columns]
    return wide


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--run", type=Path, default=None, help="finished mbc run: its calibrated engine (and maps)")
    ap.add_argument("--charge-table", type=Path, default=None, help="write the charge-following lambda table here")
    a = ap.parse_args()
    pd.set_option("display.width", 200)
    spec = run_spec(a.run)
    for name, s in (("spec's combustion efficiency", spec),
                    ("rich combustion efficiency = lean",
                     spec.with_values({"charge.combustion_efficiency_rich": spec.charge.combustion_efficiency_lean}))):
        print(f"fixed burn (BDUR10-90 {BURN['bdur_10_90_deg']} deg, m {BURN['wiebe_m']}), {name}:")
        print(response(s).round(4).to_string(index=False))
    if a.charge_table is not None:
        if a.run is None:
            ap.error("--charge-table needs --run (the run's cells give the charge)")
        wide = charge_table(a.run)
        a.charge_table.parent.mkdir(parents=True, exist_ok=True)
        wide.to_csv(a.charge_table)
        print(f"charge-following lambda table -> {a.charge_table}")
        print(wide.to_string())


if __name__ == "__main__":
    main()
