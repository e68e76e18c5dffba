"""Refit the global model of a finished ``mbc run`` with other MapModel settings and score it the pipeline's way.

Reads ``<run>/virtual_bench/identified.parquet`` (the sweeps' identifications; fit_ok rows, as the pipeline),
``<run>/virtual_bench/holdout_status.parquet`` (the hold-out grid and where the truth engine ran) and the
calibrated airflow parameters (``<run>/manifest.json``), builds the load table in process (the table's default
grid, 1 deg step, 1 % tolerance: what the pipeline would build with its Dask evaluator) and prints, per variant,
the hold-out RMSE against the hidden law of BDUR10-90, m and the CA50 offset (ignition-to-CA50 angle).

    PYTHONPATH=. .venv/bin/python benchmarks/pipeline_model_replay.py /tmp/fresh/results/<run-id>
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import default_spec
from engine_model.bench.burnlaw import BurnLaw
from engine_model.globalmodel.load_table import build_load_table
from engine_model.globalmodel.mapmodel import ca50_offset_deg, fit_map_model

VARIANTS = {
    "default": {},
    "log + load table": {"output_transform": "log", "load": True},
    "log + load table + phasing": {"output_transform": "log", "load": True, "parametrisation": "phasing"},
    "phasing": {"parametrisation": "phasing"},
    "log + phasing": {"output_transform": "log", "parametrisation": "phasing"},
}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path)
    a = ap.parse_args()
    man = json.loads((a.run / "manifest.json").read_text())
    cal_spec = default_spec().with_values({k: float(v) for k, v in
                                           man["calibration"]["airflow"]["parameters"].items()})
    ident = pd.read_parquet(a.run / "virtual_bench" / "identified.parquet")
    good = ident[ident["fit_ok"].astype(bool)]
    hold = pd.read_parquet(a.run / "virtual_bench" / "holdout_status.parquet")
    test = hold[hold["status"] == "ok"][["throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda"]].reset_index(drop=True)
    law = BurnLaw()
    tru = law.predict(test)
    off_t = ca50_offset_deg(tru["bdur_10_90_deg"].to_numpy(), tru["wiebe_m"].to_numpy())
    t0 = time.perf_counter()
    table = build_load_table(cal_spec)
    print(f"load table: {table.array.size} nodes, {time.perf_counter() - t0:.0f} s; filled {len(table.filled)}; "
          f"{len(good)} identified sweeps, {len(test)} hold-out points")
    rm = lambda e: float(np.sqrt(np.mean(np.square(e))))
    for name, v in VARIANTS.items():
        v = dict(v)
        kw = {**{k: x for k, x in v.items() if k != "load"}, **({"load_table": table} if v.get("load") else {})}
        m = fit_map_model(good, spec=cal_spec, **kw)
        p = m.predict(test)
        off_p = ca50_offset_deg(p["bdur_10_90_deg"].to_numpy(), p["wiebe_m"].to_numpy())
        print(f"{name:30s} BDUR10-90 {rm(p['bdur_10_90_deg'] - tru['bdur_10_90_deg']):.2f} deg, m "
              f"{rm(p['wiebe_m'] - tru['wiebe_m']):.2f}, CA50 offset {rm(off_p - off_t):.2f} deg; chosen {m.chosen_}")


if __name__ == "__main__":
    main()
