"""Bench-data validation: bad input gives a clear error or a flagged row, never a silent fit."""

import math

import numpy as np
import pandas as pd
import pytest

from engine_model.bench import load_bench, validate_bench


@pytest.fixture
def table2():
    return load_bench()


def _csv(tmp_path, df, name="bench.csv"):
    p = tmp_path / name
    df.to_csv(p, index=False)
    return p


def test_packaged_table2_is_clean(table2):
    assert len(table2) == 7
    assert table2["bench_ok"].all() and table2["at_mbt"].all()
    # P = T * omega holds for the paper's numbers within their rounding (0.2 %)
    omega = table2["speed_rpm"] * 2 * math.pi / 60
    assert np.allclose(table2["brake_torque_nm"] * omega / 1e3, table2["brake_power_kw"], rtol=2e-3)


def test_missing_column_names_file_and_column(tmp_path, table2):
    p = _csv(tmp_path, table2.drop(columns=["air_mass_flow_kg_h", "bench_ok", "bench_flags", "at_mbt"]))
    with pytest.raises(ValueError, match=r"bench\.csv.*missing bench column.*air_mass_flow_kg_h"):
        load_bench(p)


def test_nan_required_value_names_row_and_column(tmp_path, table2):
    df = table2.copy()
    df.loc[3, "brake_torque_nm"] = np.nan
    with pytest.raises(ValueError, match=r"bench\.csv: row 3 \(point_id 'wot_9500'\), column 'brake_torque_nm'"):
        load_bench(_csv(tmp_path, df))


def test_text_in_numeric_column(table2):
    df = table2.astype({"lambda": object})
    df.loc[1, "lambda"] = "rich"
    with pytest.raises(ValueError, match=r"row 1 .*column 'lambda': value 'rich' is not a finite number"):
        validate_bench(df, "x.csv")


def test_speed_in_rad_per_s_is_recognised(table2):
    df = table2.copy()
    df["speed_rpm"] = df["speed_rpm"] * 2 * math.pi / 60      # 837.8 ... rad/s, still inside the rpm range
    with pytest.raises(ValueError, match=r"row 0 .*'speed_rpm'.*looks like rad/s.*8000 rpm"):
        validate_bench(df, "x.csv")


def test_inconsistent_torque_power_is_flagged_not_dropped(table2):
    df = table2.copy()
    df.loc[2, "brake_power_kw"] = 41.5 * 1.03
    out = validate_bench(df, "x.csv")
    assert len(out) == 7
    assert out["bench_ok"].tolist() == [True, True, False, True, True, True, True]
    assert "torque x omega" in out.loc[2, "bench_flags"] and "+3.1 %" in out.loc[2, "bench_flags"]  # 42.745 / 41.47


@pytest.mark.parametrize("col,val,msg", [
    ("throttle_pct", 120.0, "outside the physical range"),
    ("lambda", 14.7, "outside the physical range"),          # AFR entered instead of lambda
    ("air_mass_flow_kg_h", -5.0, "outside the physical range"),
    ("exhaust_temp_k", 850.0 - 273.15 - 300, "outside the physical range"),  # 276.85: far too cold, wrong unit
])
def test_ranges(table2, col, val, msg):
    df = table2.copy()
    df[col] = df.get(col, np.nan)
    df.loc[4, col] = val
    with pytest.raises(ValueError, match=rf"row 4 .*'{col}'.*{msg}"):
        validate_bench(df, "x.csv")


def test_optional_columns_may_be_missing_per_row_and_knock_clears_mbt(table2):
    df = table2.drop(columns=["at_mbt"]).copy()
    df["exhaust_temp_k"] = [np.nan] * 6 + [1150.0]
    df["knock"] = ["no"] * 5 + ["yes", "no"]
    out = validate_bench(df, "x.csv")
    assert out["at_mbt"].tolist() == [True] * 5 + [False, True]
    assert np.isnan(out.loc[0, "exhaust_temp_k"]) and out.loc[6, "exhaust_temp_k"] == 1150.0


def test_fuel_flow_inconsistent_with_lambda_is_flagged(table2):
    df = table2.copy()
    df["fuel_mass_flow_kg_h"] = df["air_mass_flow_kg_h"] / (0.9 * 14.6)
    df.loc[5, "fuel_mass_flow_kg_h"] *= 1.5
    out = validate_bench(df, "x.csv")
    assert out["bench_ok"].sum() == 6 and "air/fuel" in out.loc[5, "bench_flags"]


def test_duplicate_ids_rejected(table2):
    df = pd.concat([table2, table2.iloc[[0]]])
    with pytest.raises(ValueError, match="duplicate point_id"):
        validate_bench(df, "x.csv")
