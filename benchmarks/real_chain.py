"""The real chain on one small plan: virtual bench -> Wiebe identification -> map model -> held-out error.

16-point D-optimal plan from feasible candidates (feasibility from
docs/learning_curve_feasibility.csv), bench noise on, identification on the
default 11 x 13 grid, quick solver for bench and identification alike
(~2300 simulations).  Prints per-point identification errors and the map's
held-out RMSE against the hidden law on the feasible hold-out grid.

    PYTHONPATH=. .venv/bin/python benchmarks/real_chain.py [n] [seed]
"""

import sys
import time

import numpy as np
import pandas as pd

from engine_model.globalmodel import learning as L
from engine_model.bench import VirtualBench
from engine_model.bench.burnlaw import BurnLaw
from engine_model.doe import QUICK_SOLVER
from engine_model.globalmodel.mapmodel import MapModel


def main(n=16, seed=0):
    t0 = time.perf_counter()
    law = BurnLaw()
    feas_tab = pd.read_csv("docs/learning_curve_feasibility.csv")
    feasible = L.nearest_feasible(feas_tab, (feas_tab["status"] == "ok").to_numpy())
    plan = L.design_plan("d_optimal_feasible", n, seed, feasible=feasible)
    bench = VirtualBench(law=law, solver=QUICK_SOLVER, seed=seed)
    ident = L.bench_identify(bench)(plan)
    truth = bench.hidden_law(plan)
    ident["bdur_true"] = truth["bdur_10_90_deg"].to_numpy()
    ident["m_true"] = truth["wiebe_m"].to_numpy()
    pd.set_option("display.width", 250)
    pd.set_option("display.max_columns", 30)
    print(ident[["point_id", "throttle_pct", "speed_rpm", "spark_deg_btdc", "bench_status", "bdur_10_90_deg",
                 "bdur_true", "wiebe_m", "m_true", "identify_status"]].round(2).to_string())
    ok = ident["bdur_10_90_deg"].notna()
    eb = ident.loc[ok, "bdur_10_90_deg"] - ident.loc[ok, "bdur_true"]
    em = ident.loc[ok, "wiebe_m"] - ident.loc[ok, "m_true"]
    print(f"identified {ok.sum()} of {len(plan)}; identification error RMS {np.sqrt(np.mean(eb**2)):.2f} deg, "
          f"{np.sqrt(np.mean(em**2)):.2f} (m); {time.perf_counter() - t0:.0f} s")
    test = L.holdout_grid()
    test = test[feasible(test)].reset_index(drop=True)
    y = law.predict(test)
    try:
        model = MapModel(factors=L.FACTORS3).fit(ident[ok].drop(columns=["bdur_10_90_deg_std", "wiebe_m_std"]))
    except ValueError as exc:
        print("map model not fitted:", exc)
        return
    p = model.predict(test)
    for o in ("bdur_10_90_deg", "wiebe_m"):
        print(o, "held-out RMSE", round(float(np.sqrt(np.mean((p[o] - y[o]) ** 2))), 3), "CV", model.cv_rmse_[o])
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:]))
