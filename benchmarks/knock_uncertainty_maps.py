"""Rebuild a finished ``mbc run``'s spark table from its saved model at several ``knock_uncertainty_z`` values.

Each table is written as a run-like folder ``OUT/z<z>/`` (``manifest.json`` copied, ``maps/cells.parquet``) that
``benchmarks/pipeline_map_vs_truth.py`` judges against the truth engine.  Same engine (the run's calibrated
airflow parameters), default ECU grid and 0.5 deg solver step as the pipeline.  The evaluations are memoised
(cell inputs and burn rounded to 1e-9) and kept in ``OUT/evaluations_cache.parquet``: the search stages are the
same for every z, so only the extra knock-sensitivity points and the verification of each table are new.

    PYTHONPATH=. .venv/bin/python benchmarks/knock_uncertainty_maps.py RUN --z 0 0.5 1 1.64 --out /tmp/knock4
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import pandas as pd

from engine_model import SolverSettings, default_spec

from engine_model.sim import simulate
from engine_model.tables import EcuGrid, MapSettings, build_maps, load_model

SOLVER = SolverSettings(step_deg=0.5)
KEY = ("throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda", "bdur_10_90_deg", "wiebe_m")


class CachedEvaluator:
    def __init__(self, spec, path: Path):
        self.spec, self.path, self.new = spec, path, 0
        self.memo = {}
        if path.is_file():
            for _, r in pd.read_parquet(path).iterrows():
                self.memo[self._key(r)] = r.drop(labels=["point_id"], errors="ignore")

    @staticmethod
    def _key(r):
        return tuple(round(float(r[k]), 9) for k in KEY)

    def __call__(self, plan: pd.DataFrame) -> pd.DataFrame:
        keys = [self._key(r) for _, r in plan.iterrows()]
        todo = plan[[k not in self.memo for k in keys]]
        if len(todo):
            sim = simulate(self.spec, todo.reset_index(drop=True), SOLVER)
            for k, (_, r) in zip([self._key(r) for _, r in todo.iterrows()], sim.iterrows()):
                self.memo[k] = r.drop(labels=["point_id"], errors="ignore")
            self.new += len(todo)
        out = pd.DataFrame([self.memo[k] for k in keys]).reset_index(drop=True)
        out.insert(0, "point_id", plan["point_id"].to_numpy())
        return out

    def save(self):
        df = pd.DataFrame(list(self.memo.values())).reset_index(drop=True)
        df.insert(0, "point_id", [f"c{i}" for i in range(len(df))])
        tmp = self.path.with_suffix(".tmp.parquet")
        df.to_parquet(tmp)
        tmp.replace(self.path)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    ap.add_argument("--z", type=float, nargs="+", default=[0.0, 1.0, 1.64])
    ap.add_argument("--out", type=Path, default=Path("/tmp/knock_uncertainty_maps"))
    a = ap.parse_args()
    man = json.loads((a.run / "manifest.json").read_text())
    params = {k: float(v) for k, v in man["calibration"]["airflow"]["parameters"].items()}
    spec = default_spec().with_values(params)
    model = load_model(a.run / "model" / "model.json")
    a.out.mkdir(parents=True, exist_ok=True)
    ev = CachedEvaluator(spec, a.out / "evaluations_cache.parquet")
    for z in a.z:
        t0, n0 = time.perf_counter(), ev.new
        res = build_maps(spec, model, grid=EcuGrid(), evaluate=ev, settings=MapSettings(knock_uncertainty_z=z))
        ev.save()
        d = a.out / f"z{z:g}"
        (d / "maps").mkdir(parents=True, exist_ok=True)
        shutil.copy(a.run / "manifest.json", d / "manifest.json")
        res.cells.to_parquet(d / "maps" / "cells.parquet")
        c = res.cells[res.cells["feasible"]]
        k = c[c["knock_uncertainty_retard_deg"] > 0]
        print(f"z = {z:g}: {res.stats['simulated_points']} points ({ev.new - n0} new, {time.perf_counter() - t0:.0f} s); "
              f"{len(c)} feasible, limited_by {res.stats['limited_by']}; retarded for uncertainty {len(k)} cells, "
              f"retard mean {k['knock_uncertainty_retard_deg'].mean() if len(k) else 0:.1f} / max "
              f"{k['knock_uncertainty_retard_deg'].max() if len(k) else 0:.1f} deg; sigma(CA50 offset) at the border "
              f"median {c['phasing_std_deg'].median():.1f} deg, gain median {c['knock_phasing_gain'].median():.2f}; "
              f"model torque sum {c['brake_torque_nm'].sum():.0f} N m", flush=True)


if __name__ == "__main__":
    main()
