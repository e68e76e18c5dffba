"""Energy chain on Table 2: how the charge sub-models move the burns identified at the paper's eta_trans.

For the calibrated engine of a finished run (its ``engine.toml``) the identification grid is simulated at
every Table 2 point twice: with the charge sub-models as the spec has them (combustion efficiency below 1,
port wall heat transfer, fuel evaporation from the charge) and with all three switched off (combustion
efficiency 1, no port heat transfer, no evaporative cooling).  For each variant it prints

* the brake power the model gives at the paper's burn (BDUR10-90 24 deg, m 6.4, MVM2012-024 sec. 4)
  against the measured power / 0.95 (the paper's transmission efficiency), and
* the (BDUR10-90, m) identified at eta_trans 0.95 and the jointly fitted eta_trans.

    PYTHONPATH=. .venv/bin/python benchmarks/energy_chain.py --run results/<run> [--workers 2] [--grid 11x13]
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import calibration as cal
from engine_model.bench import load_bench
from engine_model.calibrated import CalibratedEngine
from engine_model.sim import simulate
from engine_model.sim.prepare import SolverSettings

PAPER_BURN = (24.0, 6.4)   # MVM2012-024, sec. 4: BDUR10-90 24-25 deg, m 6.1-6.4 at WOT
ETA_PAPER = 0.95           # MVM2012-024: transmission efficiency of the dyno chain
OFF = {"charge.combustion_efficiency_lean": 1.0, "charge.combustion_efficiency_rich": 1.0,
       "charge.evaporation_from_charge": 0.0, "charge.port_heat_transfer_multiplier": 0.0}


def _run_chunk(args):
    spec, plan = args
    return simulate(spec, plan, SolverSettings())


def _simulate(spec, plan, workers):
    chunks = [plan.iloc[i::workers] for i in range(workers)]
    with ProcessPoolExecutor(workers) as pool:
        parts = list(pool.map(_run_chunk, [(spec, c) for c in chunks]))
    return pd.concat(parts).sort_index()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", required=True, type=Path, help="finished mbc run folder (reads engine.toml)")
    ap.add_argument("--bench", type=Path, default=None, help="bench file (default: the packaged Table 2)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--grid", default="11x13", help="identification grid BDURxM (default 11x13, as mbc run)")
    a = ap.parse_args()
    nb, nm = (int(x) for x in a.grid.split("x"))
    engine = CalibratedEngine.load(a.run / "engine.toml")
    meas = load_bench(a.bench) if a.bench else load_bench()
    meas = meas[meas["bench_ok"].to_numpy(bool)] if "bench_ok" in meas.columns else meas
    t0 = time.perf_counter()
    rows, joint = [], {}
    for variant, spec in (("sub-models on", engine.spec), ("sub-models off", engine.spec.with_values(OFF))):
        paper = meas[["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda"]].copy()
        paper["bdur_10_90_deg"], paper["wiebe_m"] = PAPER_BURN
        sim = _simulate(spec, paper.reset_index(drop=True), a.workers)
        plan = cal.identification_plan(meas, n_bdur=nb, n_m=nm)
        res = _simulate(spec, plan, a.workers)
        ident = cal.identify(meas, res, eta_trans=ETA_PAPER)
        joint[variant] = cal.joint_fit(ident)
        tab = ident.table.set_index("point_id")
        for k, r in enumerate(meas.itertuples()):
            rows.append({"variant": variant, "point_id": r.point_id, "speed_rpm": r.speed_rpm,
                         "power_ratio_at_paper_burn": sim["brake_power_kw"].iloc[k] / (r.brake_power_kw / ETA_PAPER),
                         "bdur_10_90_deg": tab.loc[r.point_id, "bdur_10_90_deg"],
                         "wiebe_m": tab.loc[r.point_id, "wiebe_m"],
                         "status": tab.loc[r.point_id, "status"] if "status" in tab.columns else ""})
    out = pd.DataFrame(rows)
    pd.set_option("display.width", 200)
    print(out.round(3).to_string(index=False))
    for variant, j in joint.items():
        print(f"{variant}: joint eta_trans {_joint_text(j)}")
    for variant, g in out.groupby("variant", sort=False):
        print(f"{variant}: model power / (measured / 0.95) at the paper's burn: mean {g['power_ratio_at_paper_burn'].mean():.3f}, "
              f"range {g['power_ratio_at_paper_burn'].min():.3f}-{g['power_ratio_at_paper_burn'].max():.3f}; "
              f"identified at 0.95: BDUR10-90 median {np.nanmedian(g['bdur_10_90_deg']):.1f} deg, "
              f"m median {np.nanmedian(g['wiebe_m']):.2f}")
    print(f"{time.perf_counter() - t0:.0f} s")


def _joint_text(j) -> str:
    return "; ".join(f"{r.eta_best:.3f} (95 % {r.eta_lo:.3f}-{r.eta_hi:.3f}, "
                     f"{'identified' if r.identifiable else 'not identified: ' + r.note})" for r in j.table.itertuples())


if __name__ == "__main__":
    main()
