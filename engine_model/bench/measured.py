"""Bench data: the packaged Table 2 of the reference paper and a validating loader for the bench contract.

Contract (:mod:`engine_model.contracts`): required ``point_id, speed_rpm, throttle_pct,
spark_deg_btdc, lambda, brake_torque_nm, brake_power_kw, air_mass_flow_kg_h``;
optional ``exhaust_temp_k, bsfc_g_kwh, fuel_mass_flow_kg_h, knock`` and
``at_mbt`` (the spark was at MBT, i.e. CA50 8-10 deg ATDC applies).

Validation rules
----------------
* Hard errors (ValueError naming file, row, point_id, column, value and what
  was expected): missing required column, a required value that is not a
  finite number, a value outside its physical range, duplicate ``point_id``,
  speeds that look like rad/s instead of rpm.
* Flags (the row is kept, ``bench_ok`` False and ``bench_flags`` saying why;
  calibration skips the row with that reason): brake power not equal to
  torque x angular speed within 1 %, air/fuel ratio inconsistent with lambda,
  BSFC inconsistent with fuel flow and power.
* Optional columns may hold NaN (not measured at that point).

``at_mbt`` defaults to True where no ``knock`` flag says otherwise: the paper
treats every Table 2 point as an MBT point (spark optimised on the bench, no
knock reported).  A knock-limited point (``knock`` true) is not at MBT.
"""

from __future__ import annotations

import math
from importlib import resources

import numpy as np
import pandas as pd

from engine_model.contracts import BENCH_REQUIRED, throttle_to_pct
from engine_model.io import read_table

PACKAGED_TABLE2 = "r6_wot_table2.csv"

POWER_TOLERANCE = 0.01       # P = T * omega within 1 % (issue 4); Table 2 rounding stays within 0.2 %
AFR_STOICH = 14.6            # [H] stoichiometric air/fuel ratio of gasoline (Heywood, App. D), for the check only
AFR_TOLERANCE = 0.10         # [A] air/fuel vs lambda * AFR_stoich within 10 %: lambda probe and two flow meters
BSFC_TOLERANCE = 0.03        # [A] bsfc vs fuel/power within 3 % (rounding of three measured channels)

# Physical ranges (low, high) of the measured channels; values outside are unit or entry mistakes.
_RANGES = {
    "speed_rpm": (300.0, 25000.0),
    "throttle_pct": (0.0, 100.0),
    "spark_deg_btdc": (-30.0, 90.0),
    "lambda": (0.5, 2.0),
    "brake_torque_nm": (0.0, 2000.0),
    "brake_power_kw": (0.0, 2000.0),
    "air_mass_flow_kg_h": (0.0, 5000.0),
    "exhaust_temp_k": (400.0, 1600.0),
    "bsfc_g_kwh": (100.0, 2000.0),
    "fuel_mass_flow_kg_h": (0.0, 500.0),
}
_POSITIVE = ("brake_torque_nm", "brake_power_kw", "air_mass_flow_kg_h", "fuel_mass_flow_kg_h")
_UNITS = {"speed_rpm": "rpm", "throttle_pct": "%", "spark_deg_btdc": "deg BTDC", "lambda": "-",
          "brake_torque_nm": "N m", "brake_power_kw": "kW", "air_mass_flow_kg_h": "kg/h", "exhaust_temp_k": "K",
          "bsfc_g_kwh": "g/kWh", "fuel_mass_flow_kg_h": "kg/h"}


def packaged_bench_path():
    """Path-like of the packaged Table 2 CSV (WOT, lambda 0.9, 8000-11000 rpm)."""
    return resources.files("engine_model.data").joinpath(PACKAGED_TABLE2)


def _where(src: str, df: pd.DataFrame, i: int, col: str) -> str:
    return f"{src}: row {i} (point_id {df['point_id'].iloc[i]!r}), column '{col}'"


def _bool_column(df: pd.DataFrame, col: str, src: str) -> np.ndarray:
    out = np.zeros(len(df), dtype=bool)
    for i, v in enumerate(df[col].tolist()):
        if isinstance(v, str):
            s = v.strip().lower()
            if s in ("1", "true", "yes", "y"):
                out[i] = True
            elif s in ("0", "false", "no", "n", ""):
                out[i] = False
            else:
                raise ValueError(f"{_where(src, df, i, col)}: value {v!r} is not a yes/no flag "
                                 "(expected true/false, yes/no or 1/0)")
        elif v is None or (isinstance(v, float) and math.isnan(v)):
            out[i] = False
        else:
            f = pd.to_numeric(pd.Series([v]), errors="coerce").iloc[0]
            if f not in (0.0, 1.0):
                raise ValueError(f"{_where(src, df, i, col)}: value {v!r} is not a yes/no flag "
                                 "(expected true/false, yes/no or 1/0)")
            out[i] = bool(f)
    return out


def validate_bench(df: pd.DataFrame, source: str = "bench") -> pd.DataFrame:
    """Validate a bench table; return a copy with numeric columns, ``at_mbt``, ``bench_ok``, ``bench_flags``.

    Parameters
    ----------
    df : DataFrame
        Bench data in the contract (see module docstring).
    source : str
        Name used in error messages (file name).

    Returns
    -------
    DataFrame
        Same rows; numeric channels as float64; ``point_id`` as text;
        ``knock`` and ``at_mbt`` as bool; ``bench_ok`` (bool) and
        ``bench_flags`` (text, '' when fine).

    Raises
    ------
    ValueError
        Naming the source, row, point_id, column and value, and what was expected.
    """
    if not isinstance(df, pd.DataFrame):
        raise ValueError(f"{source}: expected a table, got {type(df).__name__}")
    missing = [c for c in BENCH_REQUIRED if c not in df.columns]
    if missing:
        raise ValueError(f"{source}: missing bench column(s) {missing}; required: {list(BENCH_REQUIRED)}")
    if len(df) == 0:
        raise ValueError(f"{source}: no rows")
    df = df.reset_index(drop=True).copy()
    if df["point_id"].isna().any():
        i = int(np.flatnonzero(df["point_id"].isna().to_numpy())[0])
        raise ValueError(f"{source}: row {i}, column 'point_id': empty point id")
    df["point_id"] = df["point_id"].astype(str)
    dup = df["point_id"].duplicated(keep=False).to_numpy()
    if dup.any():
        raise ValueError(f"{source}: duplicate point_id(s) {sorted(set(df['point_id'][dup]))}; ids must be unique")
    numeric = [c for c in BENCH_REQUIRED[1:]] + [c for c in _UNITS if c in df.columns and c not in BENCH_REQUIRED]
    for col in numeric:
        raw = df[col]
        vals = pd.to_numeric(raw, errors="coerce").to_numpy(dtype=float)
        required = col in BENCH_REQUIRED
        bad = np.flatnonzero(~np.isfinite(vals) & (required | raw.notna().to_numpy()))
        if bad.size:
            i = int(bad[0])
            what = "a required value" if required else "an optional value (leave it empty if not measured)"
            raise ValueError(f"{_where(source, df, i, col)}: value {raw.iloc[i]!r} is not a finite number; "
                             f"expected {what} in {_UNITS[col]}")
        lo, hi = _RANGES[col]
        strict = col in _POSITIVE
        out = np.flatnonzero(np.isfinite(vals) & (((vals <= lo) if strict else (vals < lo)) | (vals > hi)))
        if out.size:
            i = int(out[0])
            raise ValueError(f"{_where(source, df, i, col)}: value {vals[i]:g} {_UNITS[col]} is outside the "
                             f"physical range {'(' if strict else '['}{lo:g}, {hi:g}] {_UNITS[col]}")
        df[col] = vals
    # speed given in rad/s instead of rpm: P = T * n matches where P = T * n * 2 pi / 60 does not
    t, p, n = (df[c].to_numpy(float) for c in ("brake_torque_nm", "brake_power_kw", "speed_rpm"))
    p_rpm = t * n * 2.0 * math.pi / 60.0 / 1e3
    p_rads = t * n / 1e3
    rel = np.abs(p / p_rpm - 1.0)
    rads = (rel > POWER_TOLERANCE) & (np.abs(p / p_rads - 1.0) <= POWER_TOLERANCE)
    if rads.any():
        i = int(np.flatnonzero(rads)[0])
        raise ValueError(f"{_where(source, df, i, 'speed_rpm')}: value {n[i]:g} looks like rad/s, not rpm "
                         f"(brake power {p[i]:g} kW = torque {t[i]:g} N m x speed {n[i]:g}); "
                         f"convert to rpm (x 60 / 2 pi = {n[i] * 60 / (2 * math.pi):.0f} rpm)")
    flags = [[] for _ in range(len(df))]
    for i in np.flatnonzero(rel > POWER_TOLERANCE):
        flags[i].append(f"brake power {p[i]:g} kW != torque x omega {p_rpm[i]:.2f} kW "
                        f"({100 * (p[i] / p_rpm[i] - 1):+.1f} %, tolerance 1 %)")
    if "fuel_mass_flow_kg_h" in df.columns:
        fuel = df["fuel_mass_flow_kg_h"].to_numpy(float)
        afr = df["air_mass_flow_kg_h"].to_numpy(float) / fuel
        expect = df["lambda"].to_numpy(float) * AFR_STOICH
        for i in np.flatnonzero(np.isfinite(afr) & (np.abs(afr / expect - 1.0) > AFR_TOLERANCE)):
            flags[i].append(f"air/fuel {afr[i]:.2f} inconsistent with lambda x {AFR_STOICH} = {expect[i]:.2f}")
        if "bsfc_g_kwh" in df.columns:
            bsfc = df["bsfc_g_kwh"].to_numpy(float)
            calc = fuel * 1e3 / p
            for i in np.flatnonzero(np.isfinite(bsfc) & np.isfinite(calc) & (np.abs(bsfc / calc - 1) > BSFC_TOLERANCE)):
                flags[i].append(f"bsfc {bsfc[i]:g} g/kWh != fuel/power {calc[i]:.1f} g/kWh")
    knock = _bool_column(df, "knock", source) if "knock" in df.columns else np.zeros(len(df), bool)
    if "knock" in df.columns:
        df["knock"] = knock
    if "at_mbt" in df.columns:
        at_mbt = _bool_column(df, "at_mbt", source)
        both = at_mbt & knock
        if both.any():
            i = int(np.flatnonzero(both)[0])
            raise ValueError(f"{_where(source, df, i, 'at_mbt')}: a knock-limited point cannot be at MBT "
                             "(knock and at_mbt both true)")
    else:
        at_mbt = ~knock
    df["at_mbt"] = at_mbt
    df["bench_flags"] = ["; ".join(f) for f in flags]
    df["bench_ok"] = [not f for f in flags]
    return df


def load_bench(path=None, throttle_unit: str = "pct") -> pd.DataFrame:
    """Load and validate bench data (CSV or Parquet); ``None`` loads the packaged Table 2.

    ``throttle_unit`` "pct" (the contract) refuses a ``throttle_pct`` column whose values all lie
    within 0-1 (a fraction by mistake); "fraction" converts such a column to percent on load
    (:func:`engine_model.contracts.throttle_to_pct`).

    Returns
    -------
    DataFrame
        See :func:`validate_bench`.

    Raises
    ------
    ValueError
        Naming the file, row and column of a missing, non-numeric or out-of-range value.
    """
    if path is None:
        with resources.as_file(packaged_bench_path()) as p:
            df, src = read_table(p), f"engine_model/data/{PACKAGED_TABLE2}"
    else:
        df, src = read_table(path), str(path)
    df = throttle_to_pct(df, f"bench file {src}", throttle_unit)
    return validate_bench(df, src)


# The virtual bench (truth engine + measurement chain) lives in its own module; re-exported here.
from engine_model.bench.virtual import NoiseModel, VirtualBench, run_virtual_bench  # noqa: E402,F401
