"""Bench readings against the model: measurement uncertainty, usable outputs, alignment by point."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

from engine_model.contracts import PLAN_COLUMNS, check_combustion_inputs

__all__ = ["UNCERTAINTY", "REQUIRED_OUTPUTS", "sigma_of", "check_bench_outputs", "check_gap_bench", "align_measured"]


#: Measurement uncertainty (1 sigma) per output: ('rel', fraction) or ('abs', value in the output's unit).
#: Torque +-0.5 %, airflow +-1 %, exhaust temperature +-5 K (the issue's bench accuracy), fuel flow +-1 %
#: (gravimetric/Coriolis class), BSFC from fuel flow and torque combined (~1.1 %).
UNCERTAINTY = {
    "air_mass_flow_kg_h": ("rel", 0.01),
    "brake_torque_nm": ("rel", 0.005),
    "exhaust_temp_k": ("abs", 5.0),
    "fuel_mass_flow_kg_h": ("rel", 0.01),
    "bsfc_g_kwh": ("rel", 0.011),
}


REQUIRED_OUTPUTS = ("air_mass_flow_kg_h", "brake_torque_nm")


def sigma_of(output: str, values: np.ndarray, uncertainty: dict | None = None,
             model_error: dict | None = None) -> np.ndarray:
    """1-sigma uncertainty of ``values`` of ``output`` [output unit]: measurement (+ model error in quadrature)."""
    vals = np.asarray(values, dtype=float)

    def one(table):
        kind, v = table[output]
        return np.abs(vals) * v if kind == "rel" else np.full(vals.shape, float(v))

    s = one(uncertainty or UNCERTAINTY)
    if model_error and output in model_error:
        s = np.hypot(s, one(model_error))
    return s + 1e-12


def check_bench_outputs(measured: pd.DataFrame, source: str = "bench") -> list[str]:
    """Outputs of the bench table the diagnosis can use; ValueError when a required one is missing.

    Raises
    ------
    ValueError
        Naming the source, the missing columns and what is required.
    """
    if not isinstance(measured, pd.DataFrame):
        raise ValueError(f"{source}: expected a DataFrame, got {type(measured).__name__}")
    missing = [c for c in ("point_id",) + REQUIRED_OUTPUTS if c not in measured.columns]
    if missing:
        raise ValueError(f"{source}: missing column(s) {missing} needed for the gap diagnosis; required: "
                         f"point_id and the measured outputs {list(REQUIRED_OUTPUTS)}, optional "
                         "exhaust_temp_k, fuel_mass_flow_kg_h, bsfc_g_kwh")
    usable = []
    for c in UNCERTAINTY:
        if c in measured.columns:
            v = pd.to_numeric(measured[c], errors="coerce").to_numpy(float)
            if np.isfinite(v).any():
                usable.append(c)
            elif c in REQUIRED_OUTPUTS:
                raise ValueError(f"{source}: column {c!r} has no finite value")
    # BSFC is fuel flow / power: redundant when fuel flow and torque are both measured
    if "fuel_mass_flow_kg_h" in usable and "bsfc_g_kwh" in usable:
        usable.remove("bsfc_g_kwh")
    return usable


def check_gap_bench(bench: pd.DataFrame, source: str = "bench") -> list[str]:
    """Everything the diagnosis needs of a bench table, checked before any work; returns the usable outputs.

    The operating point of every row (``point_id, speed_rpm, throttle_pct, spark_deg_btdc, lambda``)
    and the measured outputs (:func:`check_bench_outputs`).

    Raises
    ------
    ValueError
        Naming ``source``, the row, the column and the value, and what was expected.
    """
    usable = check_bench_outputs(bench, source)
    missing = [c for c in PLAN_COLUMNS if c not in bench.columns]
    if missing:
        raise ValueError(f"{source}: missing column(s) {missing}; the operating point of each row is needed "
                         f"({', '.join(PLAN_COLUMNS)})")
    ids = bench["point_id"]
    empty = np.flatnonzero(ids.isna().to_numpy() | (ids.astype(str).str.strip() == "").to_numpy())
    if empty.size:
        raise ValueError(f"{source}: row {int(empty[0])}, column 'point_id': empty point id")
    dup = ids.astype(str).duplicated(keep="first").to_numpy()
    if dup.any():
        i = int(np.flatnonzero(dup)[0])
        raise ValueError(f"{source}: row {i}, column 'point_id': value {str(ids.iloc[i])!r} appears twice; "
                         "ids must be unique")
    check_combustion_inputs(bench, "gap", source)
    return usable


def align_measured(points: pd.DataFrame, measured: pd.DataFrame, outputs: Sequence[str]) -> pd.DataFrame:
    """Measured rows in the order of ``points`` (by ``point_id``); NaN where not ok or missing."""
    m = measured.copy()
    m["point_id"] = m["point_id"].astype(str)
    if m["point_id"].duplicated().any():
        raise ValueError(f"bench: point_id {m['point_id'][m['point_id'].duplicated()].iloc[0]!r} appears twice")
    m = m.set_index("point_id")
    missing = [p for p in points["point_id"] if p not in m.index]
    if missing:
        raise ValueError(f"bench: no measured row for plan point(s) {missing[:5]}")
    m = m.loc[list(points["point_id"])]
    out = pd.DataFrame({"point_id": list(points["point_id"])})
    ok = np.ones(len(m), bool)
    if "status" in m.columns:
        ok = (m["status"].astype(str) == "ok").to_numpy()
    for c in outputs:
        v = pd.to_numeric(m[c], errors="coerce").to_numpy(float) if c in m.columns else np.full(len(m), np.nan)
        out[c] = np.where(ok, v, np.nan)
    out["bench_status"] = m["status"].astype(str).to_numpy() if "status" in m.columns else "ok"
    return out
