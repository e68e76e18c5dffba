"""Column names and units of every table that crosses a boundary (plans, results, bench data, tables).

Column names carry their unit as a suffix (``_rpm, _pct, _deg_btdc, _deg_atdc,
_deg, _nm, _kw, _kg_h, _k, _bar, _g_kwh, _ms, _mg``); :data:`UNITS` spells the
unit of each for reports and exports.  Spark is given in degrees before top
dead centre (positive = advanced), as an ECU shows it; burn angles and the
location of peak pressure in degrees after top dead centre.

Every module that reads or writes one of these tables takes its column names
from here, so a name changes in one place.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = [
    "PLAN_COLUMNS", "OPERATING_POINT_COLUMNS", "RESULT_COLUMNS", "BENCH_REQUIRED", "BENCH_OPTIONAL",
    "MEASURED_COLUMNS", "BENCH_STATUSES", "COMBUSTION_INPUTS", "COMBUSTION_OUTPUTS", "IDENTIFICATION_COLUMNS",
    "SWEEP_COLUMNS", "TABLE_COLUMNS", "UNITS", "THROTTLE_UNITS", "check_breakpoints", "check_combustion_inputs",
    "throttle_to_pct",
]

#: Columns every DOE plan carries.
PLAN_COLUMNS = ("point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda")

#: Operating point: what :func:`engine_model.simulate` needs per row (optional: ``wiebe_a``,
#: ``p_amb_pa``, ``t_amb_k``, ``spec.<section>.<field>`` overrides and effect parameters).
OPERATING_POINT_COLUMNS = ("speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda", "bdur_10_90_deg", "wiebe_m")

#: Simulation result, one row per point (inputs are echoed before these).
RESULT_COLUMNS = (
    "air_mass_flow_kg_h", "vol_eff", "fuel_mass_flow_kg_h", "imep_gross_bar", "pmep_bar", "imep_net_bar",
    "fmep_bar", "bmep_bar", "brake_torque_nm", "brake_power_kw", "bsfc_g_kwh", "exhaust_temp_k",
    "pmax_bar", "pmax_deg_atdc", "ca10_deg_atdc", "ca50_deg_atdc", "ca90_deg_atdc", "residual_fraction",
    "heat_loss_fraction", "knock_index", "converged", "cycles_run", "mass_balance_error",
    "energy_balance_error", "status", "trapped_mass_mg", "plenum_pressure_bar",
)

#: Bench data (measured): required columns.  Torque is measured behind the gearbox.
BENCH_REQUIRED = ("point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda", "brake_torque_nm",
                  "brake_power_kw", "air_mass_flow_kg_h")
#: Bench data: optional columns (NaN where not measured).  ``knock``: 0/1 (or true/false) per point;
#: ``at_mbt``: the spark was set at MBT on the bench.
BENCH_OPTIONAL = ("exhaust_temp_k", "bsfc_g_kwh", "fuel_mass_flow_kg_h", "knock", "at_mbt")

#: Channels the virtual bench measures (with noise) at every point it runs.
MEASURED_COLUMNS = ("brake_torque_nm", "brake_power_kw", "air_mass_flow_kg_h", "exhaust_temp_k",
                    "bsfc_g_kwh", "fuel_mass_flow_kg_h")
#: Values of a bench table's ``status`` column.
BENCH_STATUSES = ("ok", "knock_abort", "low_load_abort", "not_converged", "failed")

#: Inputs of a combustion law or a global combustion model (the hidden truth and the fitted model alike).
COMBUSTION_INPUTS = ("throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda")
#: What a combustion law or model returns.
COMBUSTION_OUTPUTS = ("bdur_10_90_deg", "wiebe_m")
#: Allowed range of each combustion input (low, high).
COMBUSTION_INPUT_LIMITS = {"throttle_pct": (0.0, 100.0), "speed_rpm": (1.0, 20000.0),
                           "spark_deg_btdc": (-30.0, 90.0), "lambda": (0.5, 2.0)}

#: Identified combustion parameters per bench point (the calibration's output).
IDENTIFICATION_COLUMNS = ("point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "bdur_10_90_deg", "wiebe_m")

#: Joint spark-sweep identification, one row per operating point.
SWEEP_COLUMNS = ("op_id", "throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda", "bdur_10_90_deg", "wiebe_m",
                 "bdur_10_90_deg_lo", "bdur_10_90_deg_hi", "wiebe_m_lo", "wiebe_m_hi", "chi2_min", "n_points",
                 "n_aborted", "mbt_spark_deg_btdc", "mbt_used", "fit_ok", "status")

#: ECU tables in long form (Parquet): one row per table and cell.
TABLE_COLUMNS = ("table", "throttle_pct", "speed_rpm", "value", "unit", "source", "limited_by")

#: Unit of each column with a physical unit (for reports and exports).
UNITS = {
    "speed_rpm": "rpm", "throttle_pct": "%", "spark_deg_btdc": "deg BTDC", "lambda": "-",
    "bdur_10_90_deg": "deg CA", "wiebe_m": "-", "brake_torque_nm": "N m", "brake_power_kw": "kW",
    "air_mass_flow_kg_h": "kg/h", "fuel_mass_flow_kg_h": "kg/h", "exhaust_temp_k": "K", "bsfc_g_kwh": "g/kWh",
    "vol_eff": "-", "imep_gross_bar": "bar", "pmep_bar": "bar", "imep_net_bar": "bar", "fmep_bar": "bar",
    "bmep_bar": "bar", "pmax_bar": "bar", "pmax_deg_atdc": "deg ATDC", "ca10_deg_atdc": "deg ATDC",
    "ca50_deg_atdc": "deg ATDC", "ca90_deg_atdc": "deg ATDC", "residual_fraction": "-",
    "heat_loss_fraction": "-", "knock_index": "-", "trapped_mass_mg": "mg", "plenum_pressure_bar": "bar",
    "injection_time_ms": "ms",
}


def check_combustion_inputs(points: pd.DataFrame, who: str, source: str = "points") -> dict[str, np.ndarray]:
    """The :data:`COMBUSTION_INPUTS` of ``points`` as float arrays; ValueError naming row, column and value.

    Parameters
    ----------
    points : DataFrame
        Needs ``throttle_pct`` [%], ``speed_rpm`` [rpm], ``spark_deg_btdc``
        [deg BTDC], ``lambda`` [-].
    who : str
        Caller name for the message.
    source : str
        What the table is, for the message.
    """
    if not isinstance(points, pd.DataFrame):
        raise ValueError(f"{who}: {source} must be a pandas DataFrame, got {type(points).__name__}")
    missing = [c for c in COMBUSTION_INPUTS if c not in points.columns]
    if missing:
        raise ValueError(f"{who}: {source} lack column(s) {missing}; required: {list(COMBUSTION_INPUTS)}")
    out = {}
    for col in COMBUSTION_INPUTS:
        vals = pd.to_numeric(points[col], errors="coerce").to_numpy(dtype=float)
        lo, hi = COMBUSTION_INPUT_LIMITS[col]
        bad = np.flatnonzero(~(np.isfinite(vals) & (vals >= lo) & (vals <= hi)))
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"{who}: {source} row {i}, column '{col}': value {points[col].iloc[i]!r} is not a "
                             f"finite number in [{lo:g}, {hi:g}]")
        out[col] = vals
    return out


#: How a table's ``throttle_pct`` column may be given: percent (the contract) or a 0-1 fraction (converted on load).
THROTTLE_UNITS = ("pct", "fraction")


def throttle_to_pct(table: pd.DataFrame, source: str, unit: str = "pct") -> pd.DataFrame:
    """``table`` with ``throttle_pct`` in percent; ValueError when the column looks like a 0-1 fraction.

    Parameters
    ----------
    table : DataFrame
        A bench file or plan read from ``source``; a table without ``throttle_pct`` is returned as it is
        (the caller's column check names the missing column).
    source : str
        What the table is and where it came from (e.g. ``"bench file data/run3.csv"``), for the message.
    unit : {"pct", "fraction"}
        ``"pct"`` (the contract): values all within 0-1 are refused, since a 0-1 fraction read as percent
        would run every point nearly closed.  ``"fraction"``: values must lie in [0, 1] and are
        multiplied by 100.

    Raises
    ------
    ValueError
        Naming the source, the column, the values seen and the two ways to fix it.
    """
    if unit not in THROTTLE_UNITS:
        raise ValueError(f"throttle unit {unit!r}: choose one of {list(THROTTLE_UNITS)}")
    if not isinstance(table, pd.DataFrame) or "throttle_pct" not in table.columns or len(table) == 0:
        return table
    vals = pd.to_numeric(table["throttle_pct"], errors="coerce").to_numpy(dtype=float)
    finite = vals[np.isfinite(vals)]
    if unit == "fraction":
        bad = np.flatnonzero(np.isfinite(vals) & ((vals < 0.0) | (vals > 1.0)))
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"{source}: row {i}, column 'throttle_pct': value {vals[i]:g} is not a fraction in "
                             "[0, 1], but --throttle-unit fraction was given; leave the option out for a "
                             "column in percent (0-100)")
        out = table.copy()
        out["throttle_pct"] = vals * 100.0
        return out
    if finite.size and float(finite.max()) <= 1.0:
        seen = f"all {finite.max():g}" if finite.min() == finite.max() else f"{finite.min():g} to {finite.max():g}"
        raise ValueError(f"{source}: column 'throttle_pct' holds only values within 0-1 ({seen}); this looks like "
                         "a fraction, but the column is "
                         "throttle opening in percent (0-100, WOT = 100).  Multiply the column by 100, or pass "
                         "--throttle-unit fraction to convert it on load")
    return table


def check_breakpoints(where: str, values, unit: str = "", lo: float = -np.inf, hi: float = np.inf,
                      min_count: int = 2) -> np.ndarray:
    """Table breakpoints as a float array; ValueError naming ``where`` and the offending breakpoint.

    The one rule every table axis of the project follows (ECU grids, ECU files, load tables): at least
    ``min_count`` finite numbers, strictly ascending (a duplicate and a step back are told apart), all
    within ``[lo, hi]`` (in ``unit``).
    """
    u = f" {unit}" if unit else ""
    try:
        arr = np.array([float(v) for v in np.ravel(np.asarray(values, dtype=object))], dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {values!r} must be a sequence of numbers [{unit or '-'}]") from None
    if arr.size < min_count:
        raise ValueError(f"{where}: needs at least {min_count} breakpoints, got {arr.size}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise ValueError(f"{where}: breakpoint {bad[0]} = {arr[bad[0]]} is not a finite number")
    d = np.diff(arr)
    if np.any(d == 0):
        k = int(np.flatnonzero(d == 0)[0])
        raise ValueError(f"{where}: duplicate breakpoint {arr[k]:g}{u} at positions {k} and {k + 1} (breakpoints "
                         "must be strictly increasing)")
    if np.any(d < 0):
        k = int(np.flatnonzero(d < 0)[0])
        raise ValueError(f"{where}: breakpoints must be sorted ascending; {arr[k]:g}{u} (position {k}) is followed "
                         f"by {arr[k + 1]:g}{u} (they must be strictly increasing)")
    if arr[0] < lo or arr[-1] > hi:
        raise ValueError(f"{where}: breakpoints {arr[0]:g}..{arr[-1]:g}{u} leave the allowed range "
                         f"[{lo:g}, {hi:g}]{u}")
    return arr
