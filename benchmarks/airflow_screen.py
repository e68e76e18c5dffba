"""Which three global parameters can match Table 2 airflow?  Cheap screen, then real matches.

    .venv/bin/python benchmarks/airflow_screen.py screen [--out docs/data/airflow_screen]
    .venv/bin/python benchmarks/airflow_screen.py match NAME1,NAME2,NAME3 [--start NAME=V ...] [--nfev 12]

``screen``: Ga_REL at the base parameter set and central differences for every
candidate of :data:`engine_model.calibration.screen.CANDIDATES` (one batch,
2 processes), the data's smooth-curve floor, and every triple ranked by its
linearised minimax / least-squares fit.  ``match``: the real bounded least
squares (:func:`engine_model.calibration.airflow.match_airflow`) for one triple,
started at the base (no coarse grid), in-process on 2 processes, 1 deg step.
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import SolverSettings, default_spec

from engine_model.sim import simulate
from engine_model.bench import load_bench
from engine_model.calibration.airflow import match_airflow
from engine_model.calibration.screen import CANDIDATES, rank_subsets, sensitivities, smooth_floor

SOLVER = SolverSettings(step_deg=1.0)
# the match on main before this screen (exhaust, intake runner, restrictor Cd)
BASE = {"exhaust.runner_length_m": 0.284, "intake.runner_length_m": 0.1785, "intake.restrictor_cd": 0.862}


def _sim(args):
    spec, plan = args
    return simulate(spec, plan, SOLVER).set_axis(plan.index)


class TwoProc:
    """evaluate(plan) on 2 processes, split by parameter set (consecutive rows stay together)."""

    def __init__(self, spec, workers=2):
        self.spec = spec
        self.pool = ProcessPoolExecutor(workers)
        self.workers = workers
        self.points = 0

    def __call__(self, plan):
        sets = plan["param_set"].unique()
        chunks = [plan[plan["param_set"].isin(s)] for s in np.array_split(sets, min(self.workers * 3, len(sets)))]
        self.points += len(plan)
        out = list(self.pool.map(_sim, [(self.spec, c) for c in chunks if len(c)]))
        return pd.concat(out).loc[plan.index]


def _spec_value(spec, name):
    sec, f = name.split(".")
    return float(spec.to_dict()[sec][f])


def screen(out: Path):
    spec = default_spec()
    meas = load_bench()
    base = {p.name: BASE.get(p.name, _spec_value(spec, p.name)) for p in CANDIDATES}
    ev = TwoProc(spec)
    t0 = time.perf_counter()
    sens = sensitivities(meas, ev, base)
    dt = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    sens.table().to_csv(out / "sensitivities.csv", index=False)
    print(f"{sens.simulations} simulations in {dt:.0f} s")
    print("Ga_REL at base:", np.round(sens.r0, 2))
    steps = {p.name: p.step for p in CANDIDATES}
    print("\nchange of Ga_REL [%] per parameter step:")
    print(pd.DataFrame({n: np.round(sens.jac[:, j] * steps[n], 3) for j, n in enumerate(sens.names)},
                       index=sens.speed_rpm.astype(int)).T.to_string())
    for d in range(4):
        f, r = smooth_floor(meas["speed_rpm"], meas["air_mass_flow_kg_h"], d)
        print(f"floor, VE polynomial of degree {d}: max |Ga_REL| {f:.3f} %  {np.round(r, 2)}")
    spec_values = {p.name: _spec_value(spec, p.name) for p in CANDIDATES}
    pd.set_option("display.width", 250)
    for trust in (0.1, 0.25):
        rk = rank_subsets(sens, CANDIDATES, 3, spec_values=spec_values, trust=trust)
        rk.to_csv(out / f"triples_trust{trust:g}.csv", index=False)
        cols = ["parameters", "max_abs_minimax_pct", "max_abs_ls_pct", "rms_ls_pct", "max_abs_corr", "cond"]
        print(f"\ntrust {trust}: best 25 triples of {len(rk)}")
        print(rk[cols].head(25).round(3).to_string())
    ev.pool.shutdown()


def match(names, start, nfev, grid=None, starts=1):
    spec = default_spec()
    meas = load_bench()
    by = {p.name: p for p in CANDIDATES}
    params = tuple(by[n] for n in names)
    st = {n: BASE.get(n, _spec_value(spec, n)) for n in names}
    st.update(start)
    base_spec = spec.with_values({k: v for k, v in st.items()})
    ev = TwoProc(base_spec)
    t0 = time.perf_counter()
    m = match_airflow(meas, ev, spec=base_spec, parameters=params, grid=grid or (1,) * len(params), starts=starts,
                      max_nfev=nfev)
    dt = time.perf_counter() - t0
    print(m.summary())
    print("Ga_REL:", np.round(m.table["ga_rel_pct"].to_numpy(), 2), "corr:", np.round(m.correlation, 2).tolist())
    print(f"{m.simulations} simulations, {dt:.0f} s")
    print(json.dumps({"values": m.values, "ci95": m.ci95, "ga_rel": m.table["ga_rel_pct"].round(3).tolist(),
                      "runs": m.optimizer["runs"]}, default=str))
    ev.pool.shutdown()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("screen")
    s.add_argument("--out", default="docs/data/airflow_screen")
    mm = sub.add_parser("match")
    mm.add_argument("names")
    mm.add_argument("--start", nargs="*", default=[])
    mm.add_argument("--nfev", type=int, default=12)
    mm.add_argument("--grid", default=None, help="coarse grid per parameter, e.g. 6x6x1 (default: none, start at base)")
    mm.add_argument("--starts", type=int, default=1)
    a = ap.parse_args()
    if a.cmd == "screen":
        screen(Path(a.out))
    else:
        match(a.names.split(","), {k: float(v) for k, v in (x.split("=") for x in a.start)}, a.nfev,
              tuple(int(v) for v in a.grid.split("x")) if a.grid else None, a.starts)
