"""Bench data: the packaged Table 2 of the reference paper and a loader for the bench contract.

Only what the simulator core needs for now: reading and basic validation
(required columns present, numeric, finite).  Fuller validation (torque/power
consistency, units, ranges) arrives with calibration.
"""

from __future__ import annotations

from importlib import resources

import numpy as np
import pandas as pd

from .io import read_table

BENCH_REQUIRED = ("point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda", "brake_torque_nm",
                  "brake_power_kw", "air_mass_flow_kg_h")
PACKAGED_TABLE2 = "r6_wot_table2.csv"


def packaged_bench_path():
    """Path-like of the packaged Table 2 CSV (WOT, lambda 0.9, 8000-11000 rpm)."""
    return resources.files("engine_model.data").joinpath(PACKAGED_TABLE2)


def load_bench(path=None) -> pd.DataFrame:
    """Load bench data in the bench contract; ``None`` loads the packaged Table 2.

    Raises
    ------
    ValueError
        Naming the file, row and column of a missing or non-numeric value.
    """
    if path is None:
        with resources.as_file(packaged_bench_path()) as p:
            df, src = pd.read_csv(p), f"engine_model/data/{PACKAGED_TABLE2}"
    else:
        df, src = read_table(path), str(path)
    missing = [c for c in BENCH_REQUIRED if c not in df.columns]
    if missing:
        raise ValueError(f"{src}: missing bench column(s) {missing}; required: {list(BENCH_REQUIRED)}")
    for col in BENCH_REQUIRED[1:]:
        vals = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(vals))
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"{src}: row {i} (point_id {df['point_id'].iloc[i]!r}), column '{col}': "
                             f"value {df[col].iloc[i]!r} is not a finite number")
        df[col] = vals
    return df


# The virtual bench (truth engine + measurement chain) lives in its own module; re-exported here.
from .virtual_bench import NoiseModel, VirtualBench, run_virtual_bench  # noqa: E402,F401
