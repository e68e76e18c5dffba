"""ECU exports of a map build (engine_model.tables.ecu_export): breakpoints, kPa axis, fuel forms, the files of maps/ecu/.

The map is built in-process on the synthetic engine of ``conftest.synthetic_map`` (plenum
pressure known per cell, VE exactly 90 % of the plenum density), so the expected numbers are
computed here independently: bilinear interpolation with scipy, the VE and fuel formulas by hand.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from conftest import SYNTHETIC_VE, ecu_run_folder, synthetic_map, synthetic_plenum_bar
from engine_model import thermo
from engine_model.tables.ecu_dcm import read_dcm
from engine_model.tables.ecu_export import ExportOptions, export_tables, plenum_kpa, write_exports
from engine_model.tables.ecu_msq import read_msq

NS = {"ts": "http://www.EFIAnalytics.com/:table"}


@pytest.fixture(scope="module")
def built():
    return synthetic_map()


def grid_of(cells, col):
    """(throttle, rpm, values[throttle, rpm]) of a cells column, by pivot (not by the code under test)."""
    piv = cells.pivot(index="throttle_pct", columns="speed_rpm", values=col).sort_index().sort_index(axis=1)
    return piv.index.to_numpy(float), piv.columns.to_numpy(float), piv.to_numpy(float)


def test_cells_carry_the_plenum_pressure_and_air_of_every_cell(built):
    _spec, res = built
    c = res.cells
    np.testing.assert_allclose(c["plenum_pressure_bar"], synthetic_plenum_bar(c["throttle_pct"], c["speed_rpm"]),
                               rtol=1e-12)
    for col in ("trapped_mass_mg", "vol_eff"):
        assert col in c.columns        # NaN here: the synthetic engine does not report them
    p, filled = plenum_kpa(c)
    assert filled == 0 and p.shape == res.grid.shape
    np.testing.assert_allclose(p, 100 * grid_of(c, "plenum_pressure_bar")[2])


def test_custom_breakpoints_are_bilinear_in_the_build_cells(built):
    spec, res = built
    rpm_bins, load_bins = (3000, 4500, 7000, 8000, 11000, 12000), (20, 30, 55, 90, 100)
    es = export_tables(res.cells, spec, ExportOptions(rpm_bins, load_bins))
    assert not es.outside.any()
    pts = np.array([(t, n) for t in load_bins for n in rpm_bins])
    for name, col in (("spark_advance", "spark_deg_btdc"), ("injection_time", "injection_time_ms"),
                      ("lambda_target", "lambda")):
        thr, rpm, v = grid_of(res.cells, col)
        want = RegularGridInterpolator((thr, rpm), v)(pts).reshape(len(load_bins), len(rpm_bins))
        t = es.table(name)
        assert t.shape == (5, 6) and list(t.rpm) == list(rpm_bins) and list(t.load) == list(load_bins)
        np.testing.assert_allclose(t.values, want, rtol=1e-12, atol=1e-12)


def test_breakpoints_outside_the_build_hold_the_edge_and_are_counted(built):
    spec, res = built
    es = export_tables(res.cells, spec, ExportOptions((1000, 3000, 12000, 14000), (0, 20, 100)))
    assert es.outside.sum() == 3 * 4 - 2 * 2          # row 0 and columns 0, 3 are outside: all but 2 x 2 cells
    assert not es.outside[1:, 1:3].any()
    thr, rpm, v = grid_of(res.cells, "spark_deg_btdc")
    sp = es.table("spark_advance").values
    assert sp[0, 0] == v[0, 0] and sp[2, 3] == v[-1, -1]
    assert any("outside the build's grid" in n for n in es.notes)


def test_kpa_axis_gives_each_cell_its_own_value_at_its_own_pressure(built):
    spec, res = built
    thr, rpm, p = grid_of(res.cells, "plenum_pressure_bar")
    for j in range(rpm.size):
        es = export_tables(res.cells, spec, ExportOptions(None, tuple(100 * p[:, j]), "kpa"))
        for name, col in (("spark_advance", "spark_deg_btdc"), ("injection_time", "injection_time_ms"),
                          ("lambda_target", "lambda")):
            t = es.table(name)
            assert t.load_kind == "map_kpa" and t.load_unit == "kPa"
            np.testing.assert_allclose(t.values[:, j], grid_of(res.cells, col)[2][:, j], rtol=1e-9)


def test_kpa_axis_fuel_is_monotone_in_pressure_and_ve_is_the_engines(built):
    spec, res = built
    kpa = tuple(np.arange(62.0, 94.0, 2.0))
    es = export_tables(res.cells, spec, ExportOptions((3000, 6000, 9000, 12000), kpa, "kpa", "ve"))
    ve = es.table("ve")
    assert ve.unit == "%" and "MAP" in ve.description
    np.testing.assert_allclose(ve.values, 100 * SYNTHETIC_VE, rtol=1e-3)   # the engine's VE at every pressure
    inj = export_tables(res.cells, spec, ExportOptions((3000, 6000, 9000, 12000), kpa, "kpa")).table("injection_time")
    _thr, _rpm, p = grid_of(res.cells, "plenum_pressure_bar")
    for j in range(4):
        inside = (np.array(kpa) >= 100 * p[:, j].min()) & (np.array(kpa) <= 100 * p[:, j].max())
        assert inside.sum() >= 3
        assert np.all(np.diff(inj.values[inside, j]) > 0), j
    # alpha-N VE: relative to a standard atmosphere, so 90 % x plenum / 101.325 kPa
    ve_tps = export_tables(res.cells, spec, ExportOptions(fuel="ve")).table("ve")
    np.testing.assert_allclose(ve_tps.values, 100 * SYNTHETIC_VE * 100 * p / 101.325, rtol=1e-3)


def test_fuel_mass_and_injection_time_at_another_battery_voltage(built):
    spec, res = built
    _t, _r, t_inj = grid_of(res.cells, "injection_time_ms")
    _t, _r, dead = grid_of(res.cells, "dead_time_ms")
    inj = spec.injector
    mg = export_tables(res.cells, spec, ExportOptions(fuel="fuel-mass")).table("fuel_mass")
    np.testing.assert_allclose(mg.values, (t_inj - dead) * 1e-3 * inj.per_cylinder * inj.static_flow_kg_s * 1e6)
    _t, _r, lam = grid_of(res.cells, "lambda")
    _t, _r, air = grid_of(res.cells, "air_mg")
    np.testing.assert_allclose(mg.values, air / (lam * thermo.stoich_afr(spec.fuel)), rtol=1e-6)
    at12 = export_tables(res.cells, spec, ExportOptions(fuel="injection-time", battery_v=12.0)).table("injection_time")
    dead12 = 1e3 * max(0.0, inj.dead_time_s + inj.dead_time_slope_s_per_v * (12.0 - inj.dead_time_ref_v))
    np.testing.assert_allclose(at12.values, t_inj - dead + dead12, rtol=1e-12)
    with pytest.raises(ValueError, match=r"fuel 've' needs the engine"):
        export_tables(res.cells, None, ExportOptions(fuel="ve"))


def test_spark_carries_knock_flags_and_the_models_uncertainty(built):
    spec, res = built
    cells = res.cells.assign(phasing_std_deg=0.5, knock_phasing_gain=2.0)
    sp = export_tables(cells, spec, ExportOptions()).table("spark_advance")
    _t, _r, lim = grid_of(cells.assign(k=(cells["limited_by"] == "knock").astype(float)), "k")
    assert sp.flags.any() and (sp.flags == (lim > 0)).all()
    np.testing.assert_allclose(sp.uncertainty, np.where(lim > 0, 1.0, 0.0))


@pytest.mark.parametrize("kw, words", [
    (dict(load_axis="map"), ["load axis", "'map'"]),
    (dict(fuel="pulse"), ["fuel", "'pulse'"]),
    (dict(battery_v=40.0), ["battery voltage", "40"]),
    (dict(rpm_bins=(3000, 2000)), ["rpm breakpoints", "2000", "strictly increasing"]),
    (dict(load_bins=(0, 50, 120)), ["load breakpoint 2", "120", "100"]),
    (dict(load_bins=(0, 50), load_axis="kpa"), ["load breakpoint 0", "0 kPa"]),
    (dict(rpm_bins=(3000,)), ["rpm breakpoints", "at least 2"]),
])
def test_export_options_name_the_bad_value(kw, words):
    with pytest.raises(ValueError) as exc:
        ExportOptions(**kw)
    for w in words:
        assert w in str(exc.value)


def test_cells_with_holes_are_refused_naming_cell_and_column(built):
    spec, res = built
    cells = res.cells.copy()
    cells.loc[5, "spark_deg_btdc"] = np.nan
    with pytest.raises(ValueError, match=r"src: cell \(throttle 40 %, 6000 rpm\), column 'spark_deg_btdc'"):
        export_tables(cells, spec, ExportOptions(), source="src")
    with pytest.raises(ValueError, match=r"src: 15 rows are not one per cell of a 4 x 4"):
        export_tables(res.cells.drop(index=3), spec, ExportOptions(), source="src")
    with pytest.raises(ValueError, match=r"no 'plenum_pressure_bar' column"):
        export_tables(res.cells.drop(columns="plenum_pressure_bar"), spec, ExportOptions(load_axis="kpa"))


def test_msq_alone_on_user_breakpoints_of_another_size_is_refused_and_nothing_written(built, tmp_path):
    spec, res = built
    es = export_tables(res.cells, spec, ExportOptions((3000, 6000, 12000), (20, 100)))
    with pytest.raises(ValueError, match=r"speeduino tables are 16 x 16 .*make 2 x 3"):
        write_exports(es, tmp_path / "x", ["msq-speeduino"])
    assert list(tmp_path.iterdir()) == []
    # among several formats the msq is skipped with the reason, the rest is written
    res2 = write_exports(es, tmp_path / "y", ["table", "msq-rusefi"])
    assert sorted(res2["files"]) == ["README.txt", "injection_time.table", "lambda_target.table", "spark_advance.table"]
    assert any(n.startswith("rusefi.msq skipped: rusefi tables are 16 x 16") for n in res2["notes"])
    assert "rusefi.msq skipped" in (tmp_path / "y" / "README.txt").read_text()


def test_every_map_folder_gets_the_ecu_files(tmp_path):
    run, spec, res = ecu_run_folder(tmp_path / "run")
    ecu = run / "maps" / "ecu"
    assert sorted(p.name for p in ecu.iterdir()) == sorted(
        ["README.txt", "ecu_tables.dcm", "rusefi.msq", "speeduino.msq"]
        + [f"{n}.{s}" for n in ("spark_advance", "injection_time", "lambda_target") for s in ("table", "csv")])
    summary = json.loads((run / "maps" / "maps.json").read_text())
    assert "speeduino.msq" in summary["ecu_files"]["files"]
    assert any("resampled (bilinear) to the firmware's 16 x 16" in n for n in summary["ecu_files"]["notes"])
    # the .table on the build's own grid, read with a plain XML parser
    thr, rpm, spark = grid_of(res.cells, "spark_deg_btdc")
    root = ET.parse(ecu / "spark_advance.table").getroot()
    assert [float(v) for v in root.find("ts:table/ts:xAxis", NS).text.split()] == list(rpm)
    assert [float(v) for v in root.find("ts:table/ts:yAxis", NS).text.split()] == list(thr)
    z = np.array(root.find("ts:table/ts:zValues", NS).text.split(), float).reshape(thr.size, rpm.size)
    np.testing.assert_allclose(z, np.round(spark, 1))
    # msq: 16 x 16 over the build's range, values the bilinear resampling rounded to the firmware's step
    adv = read_msq(ecu / "speeduino.msq", "ignition")
    assert adv.shape == (16, 16) and adv.rpm[0] == rpm[0] and adv.rpm[-1] == rpm[-1] and adv.load[-1] == thr[-1]
    want = RegularGridInterpolator((thr, rpm), spark)(np.array([(t, n) for t in adv.load for n in adv.rpm]))
    assert np.max(np.abs(adv.values - want.reshape(16, 16))) <= 0.5 + 1e-9
    ve = read_msq(ecu / "rusefi.msq", "ve")
    _t, _r, p = grid_of(res.cells, "plenum_pressure_bar")
    want_ve = RegularGridInterpolator((thr, rpm), 100 * SYNTHETIC_VE * 100 * p / 101.325)(
        np.array([(t, n) for t in ve.load for n in ve.rpm])).reshape(16, 16)
    assert np.max(np.abs(ve.values - want_ve)) < 0.1
    dcm = read_dcm(ecu / "ecu_tables.dcm", "injection_time")
    np.testing.assert_allclose(dcm.values, np.round(grid_of(res.cells, "injection_time_ms")[2], 3))
