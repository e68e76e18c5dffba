"""Measure the learning curve of issue 5 (map accuracy vs bench points per DOE design).

1. The virtual bench (truth engine, noise-free, QUICK_SOLVER) runs the default (648-point)
   hold-out grid once: its status (ok / knock_abort / low_load_abort) defines the
   feasible map.
2. identify = truth law + identification noise (sigma 1.5 deg BDUR10-90, 0.4 m;
   see docs/sections/mapmodel.md), NaN at every plan point the truth engine
   aborts (each plan point is run on the noise-free virtual bench, cached).
   The 'd_optimal_feasible' design picks candidates by the nearest hold-out grid
   point's status (what a planner could know beforehand), so it can still lose
   points at the boundary.
3. learning_curve over grid, D-optimal (box and feasible candidates), Sobol', LHS;
   sizes 16..128; 5 seeds.  Writes docs/learning_curve.png, docs/learning_curve.csv
   and prints the summary.

    PYTHONPATH=. .venv/bin/python benchmarks/learning_curve.py   # ~10 min on 2 busy cores
"""

import sys
import time
from pathlib import Path

import pandas as pd

from engine_model import io
from engine_model.globalmodel import learning as L
from engine_model.bench.burnlaw import BurnLaw
from engine_model.doe import QUICK_SOLVER
from engine_model.bench.virtual import NoiseModel, VirtualBench

SIGMA_B, SIGMA_M = 1.5, 0.4
TARGET = {"bdur_10_90_deg": 1.0, "wiebe_m": 0.3}


def main(out=Path("docs")):
    t0 = time.perf_counter()
    law = BurnLaw()
    grid = L.holdout_grid()
    bench = VirtualBench(law=law, noise=NoiseModel.none(), solver=QUICK_SOLVER)
    meas = bench.measure(grid)
    ok = (meas["status"] == "ok").to_numpy()
    print(f"hold-out grid on the virtual bench: {len(grid)} points, {time.perf_counter() - t0:.0f} s, "
          f"status counts {meas['status'].value_counts().to_dict()}", flush=True)
    io.write_csv(meas[["point_id", "throttle_pct", "speed_rpm", "spark_deg_btdc", "spark_offset_deg", "status"]],
                 out / "learning_curve_feasibility.csv")
    feasible = L.nearest_feasible(grid, ok)
    runs = L.bench_feasibility(bench)
    t1 = time.perf_counter()
    curve = L.learning_curve(
        None, law, sizes=(16, 24, 32, 48, 64, 96, 128),
        designs=("grid", "d_optimal", "d_optimal_feasible", "sobol", "lhs"), seeds=(0, 1, 2, 3, 4),
        feasible=feasible, identify_seeded=lambda s: L.noisy_truth(law, SIGMA_B, SIGMA_M, seed=s, feasible=runs),
        progress=lambda r: print(r["design"], r["n_points"], r["n_identified"], r["seed"],
                                 f"{r['rmse_bdur_10_90_deg']:.3f} {r['rmse_wiebe_m']:.3f} {r['fit_s']:.1f}s",
                                 flush=True))
    print(f"learning curve: {time.perf_counter() - t1:.0f} s; n_test = {curve.attrs['n_test']}; "
          f"{len(runs.cache)} distinct plan points run on the bench")
    io.write_csv(curve, out / "learning_curve.csv")
    L.plot_learning_curve(curve, out / "learning_curve.png", target=TARGET,
                          title=f"Held-out map error vs bench points (identification noise {SIGMA_B} deg / {SIGMA_M}; "
                                f"5 seeds)")
    pd.set_option("display.width", 250)
    print(L.summarise(curve).round(3).to_string())
    for tgt in (TARGET, {"bdur_10_90_deg": 1.5, "wiebe_m": 0.4}, {"bdur_10_90_deg": 1.2, "wiebe_m": 0.35}):
        print("points to reach", tgt)
        print(L.points_to_reach(curve, tgt).to_string())
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs"))
