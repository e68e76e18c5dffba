"""ECU table export/import: table model, breakpoints, fuel quantities, every file format.

Reference files in ``tests/tables/data`` are written by hand from the
published format descriptions (TunerStudio's table export, Speeduino's
base-tune msq layout and speeduino.ini, rusEFI's simulator_tune.msq and
rusefi_config.txt, the DCM 2.0 grammar); none comes from the writers tested here.
"""

from __future__ import annotations

import csv
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from engine_model import thermo
from engine_model.spec import default_spec
from engine_model.tables.ecu_files import (
    FORMATS, compare, plot_difference, read_axes, read_dcm, read_table, write_csv, write_dcm, write_table,
    write_tunerstudio_table,
)
from engine_model.tables.ecu_msq import FIRMWARE_TABLES, msq_signature, read_msq, write_msq
from engine_model.tables.ecu_table import (
    R_AIR_J_KG_K, EcuTable, fuel_mg, injection_ms, resample, to_map_kpa, ve_percent,
)

DATA = Path(__file__).parent / "data"
REF_DATE = "Mon Jan 06 10:00:00 2025"
REF_AUTHOR = "hand-written reference"


def spark_3x4(**kw) -> EcuTable:
    """The table of the hand-written 3x4 reference files."""
    values = [[10.0, 12.5, 20.0, 25.0], [15.0, 18.0, 28.5, 32.0], [12.0, 16.0, 26.0, 30.5]]
    args = dict(name="spark_advance", values=values, rpm=[1000, 2000, 4000, 6000], load=[0, 50, 100],
                load_kind="throttle_pct", unit="deg BTDC", decimals=1, description="Spark advance")
    return EcuTable(**(args | kw))


def odd_table(decimals=2) -> EcuTable:
    """A 5x7 table with values finer than its decimals, flags and uncertainty."""
    rng = np.random.default_rng(3)
    rpm = np.array([1000, 2500, 4000, 6000, 8000, 10500, 13000.0])
    load = np.array([0, 12.5, 30, 60, 100.0])
    vals = rng.uniform(-5, 45, (5, 7))
    return EcuTable("spark_advance", vals, rpm, load, "throttle_pct", "deg BTDC", decimals, flags=vals > 30,
                    flag_meaning="knock-limited", uncertainty=rng.uniform(0.1, 2.0, (5, 7)),
                    description="Spark advance, test")


def grid16(kind="throttle_pct"):
    rpm = 1000.0 * np.arange(1, 17)                                  # on Speeduino's 100 rpm step
    load = 5.0 * np.arange(16) if kind == "throttle_pct" else 20.0 + 6.0 * np.arange(16)   # 0.5 % / 2 kPa steps
    return rpm, load


# --------------------------------------------------------------------------- the table

@pytest.mark.parametrize("kw, words", [
    (dict(values=np.zeros((3, 3))), ["values", "(3, 3)", "(3, 4)"]),
    (dict(rpm=[1000, 2000, 2000, 6000]), ["rpm", "2000", "strictly increasing"]),
    (dict(load=[0, 60, 50]), ["load", "50", "60", "strictly increasing"]),
    (dict(values=[[1, 2, 3, 4], [1, np.nan, 3, 4], [1, 2, 3, 4]]), ["values", "[1, 1]", "nan", "2000 rpm"]),
    (dict(load_kind="tps"), ["load_kind", "'tps'"]),
    (dict(decimals=9), ["decimals", "9"]),
    (dict(uncertainty=-np.ones((3, 4))), ["uncertainty", "negative"]),
    (dict(flags=np.full((3, 4), 2)), ["flags"]),
    (dict(rpm=[1000]), ["rpm", "at least 2"]),
])
def test_table_validation_names_field_value_and_expectation(kw, words):
    with pytest.raises(ValueError) as exc:
        spark_3x4(**kw)
    for w in words:
        assert w in str(exc.value)


def test_table_arrays_are_read_only_copies():
    src = np.zeros((3, 4))
    t = spark_3x4(values=src)
    src[0, 0] = 99
    assert t.values[0, 0] == 0
    with pytest.raises(ValueError):
        t.values[0, 0] = 1


def test_from_long_form_builds_grid_and_flags_and_rejects_holes():
    t = odd_table()
    long = t.to_frame().rename(columns={"value": "value"})
    long["table"] = "spark_advance"
    long["unit"] = "deg BTDC"
    long["limited_by"] = np.where(long["flag"], "knock", "mbt")
    back = EcuTable.from_long_form(long, "spark_advance", flag_column="limited_by", flag_value="knock")
    assert np.array_equal(back.values, t.values) and np.array_equal(back.flags, t.flags)
    assert back.unit == "deg BTDC" and back.decimals == 1
    with pytest.raises(ValueError, match="missing"):
        EcuTable.from_long_form(long.iloc[1:], "spark_advance")


# --------------------------------------------------------------------------- breakpoints

def bilinear(rpm, load):
    return 3.0 + 0.004 * rpm - 0.25 * load + 2e-5 * rpm * load


def test_resample_reproduces_bilinear_function_exactly_inside():
    rpm, load = np.array([1000, 3000, 7000, 13000.0]), np.array([0, 20, 55, 100.0])
    t = EcuTable("f", bilinear(rpm[None, :], load[:, None]), rpm, load, unit="-")
    nr, nl = np.array([1000, 1500, 2600, 6100, 9999, 13000.0]), np.array([0, 7.5, 33, 99, 100.0])
    res, outside = resample(t, nr, nl)
    assert np.allclose(res.values, bilinear(nr[None, :], nl[:, None]), rtol=0, atol=1e-9)
    assert not outside.any()
    assert np.array_equal(res.rpm, nr) and np.array_equal(res.load, nl)


def test_resample_holds_edges_and_reports_outside_cells():
    rpm, load = np.array([2000, 4000, 6000.0]), np.array([10, 50, 90.0])
    t = EcuTable("f", bilinear(rpm[None, :], load[:, None]), rpm, load, unit="-")
    nr, nl = np.array([1000, 3000, 6000, 8000.0]), np.array([0, 50, 95.0])
    res, outside = resample(t, nr, nl)
    expect_out = (nl[:, None] < 10) | (nl[:, None] > 90) | (nr[None, :] < 2000) | (nr[None, :] > 6000)
    assert np.array_equal(outside, expect_out)
    clamped = bilinear(np.clip(nr, 2000, 6000)[None, :], np.clip(nl, 10, 90)[:, None])
    assert np.allclose(res.values, clamped, atol=1e-9)


def test_resample_flags_any_contributing_corner_and_keeps_worst_uncertainty():
    t = EcuTable("f", np.zeros((2, 2)), [1000, 2000], [0, 100], flags=[[False, True], [False, False]],
                 uncertainty=[[0.1, 0.5], [0.2, 0.3]])
    res, _ = resample(t, [1000, 1500, 2000], [0, 50, 100])
    assert res.flags.tolist() == [[False, True, True], [False, True, True], [False, False, False]]
    assert res.uncertainty[0].tolist() == [0.1, 0.5, 0.5]
    assert res.uncertainty[1].tolist() == [0.2, 0.5, 0.5]
    assert res.uncertainty[2].tolist() == [0.2, 0.3, 0.3]


def test_to_map_kpa_inverts_a_monotone_pressure_map_exactly():
    thr = np.array([0, 10, 25, 50, 100.0])
    rpm = np.array([2000, 6000, 11000.0])
    p0, s = np.array([25.0, 30.0, 35.0]), np.array([0.7, 0.6, 0.5])          # kPa, kPa per % throttle
    p = p0[None, :] + s[None, :] * thr[:, None]
    a, b = np.array([5.0, 10.0, 20.0]), np.array([0.3, 0.2, 0.1])
    t = EcuTable("spark", a[None, :] + b[None, :] * thr[:, None], rpm, thr, "throttle_pct", "deg", 1)
    kpa = np.array([35.0, 40, 55, 70, 84])                                   # inside every column's range
    res, outside = to_map_kpa(t, p, kpa)
    expect = a[None, :] + b[None, :] * (kpa[:, None] - p0[None, :]) / s[None, :]
    assert res.load_kind == "map_kpa" and np.array_equal(res.load, kpa)
    assert np.allclose(res.values, expect, atol=1e-9)
    assert not outside.any()


def test_to_map_kpa_flags_outside_plateau_and_dip():
    thr = np.array([0, 20, 40, 60, 80.0])
    p = np.array([[30, 30, 30], [60, 60, 60], [90, 55, 80], [95, 80, 80], [95, 90, 80.0]])
    v = np.array([[1.0] * 3, [2.0] * 3, [3.0] * 3, [4.0] * 3, [5.0] * 3])
    t = EcuTable("x", v, [1000, 2000, 3000], thr, "throttle_pct", "-", 3)
    kpa = [20.0, 57, 70, 80, 92, 95, 100]
    res, out = to_map_kpa(t, p, kpa)
    # column 0 (plateau at 95 kPa): 95 ambiguous, 92 unique on the 90->95 stretch, 20/100 outside
    assert out[:, 0].tolist() == [True, False, False, False, False, True, True]
    assert res.values[4, 0] == pytest.approx(3 + (92 - 90) / 5)
    assert res.values[5, 0] == pytest.approx(4.0)           # lowest throttle reaching 95 kPa
    assert res.values[6, 0] == pytest.approx(4.0)           # held at the first row of the highest pressure
    assert res.values[0, 0] == pytest.approx(1.0)           # held at the lowest pressure
    # column 1 (dip 60 -> 55): 57 reached three times; 70 only on 55->80; 80 at one vertex
    assert out[:, 1].tolist() == [True, True, False, False, True, True, True]
    assert res.values[1, 1] == pytest.approx(1 + 27 / 30)
    assert res.values[2, 1] == pytest.approx(3 + 15 / 25)
    assert res.values[3, 1] == pytest.approx(4.0)
    # column 2 (flat at 80 from 40 % on): 80 ambiguous
    assert out[3, 2] and not out[2, 2]


def test_to_map_kpa_refuses_map_tables_and_bad_pressures():
    t = spark_3x4()
    with pytest.raises(ValueError, match="map_kpa_per_cell.*shape"):
        to_map_kpa(t, np.ones((2, 4)), [30, 40])
    with pytest.raises(ValueError, match=r"cell \[0, 0\] = 0 kPa"):
        to_map_kpa(t, np.zeros((3, 4)), [30, 40])
    with pytest.raises(ValueError, match="only a throttle_pct"):
        to_map_kpa(t.replace(load_kind="map_kpa"), np.ones((3, 4)), [30, 40])


# --------------------------------------------------------------------------- fuel

def test_injection_time_matches_formula():
    spec = default_spec()
    inj, z = spec.injector, spec.geometry.n_cylinders
    rpm, lam, air_mg = np.array([3000.0, 9000.0]), np.array([1.0, 0.9]), np.array([80.0, 140.0])
    for battery in (12.0, 14.0):
        t = injection_ms(rpm, lam, spec, air_mg_per_cycle=air_mg, battery_v=battery)
        fuel_kg = air_mg * 1e-6 / (lam * thermo.stoich_afr(spec.fuel))
        dead = max(0.0, inj.dead_time_s + inj.dead_time_slope_s_per_v * (battery - inj.dead_time_ref_v))
        assert np.allclose(t, (fuel_kg / (inj.per_cylinder * inj.static_flow_kg_s) + dead) * 1e3, rtol=1e-12)
    ga = air_mg * 1e-6 * z * rpm / 120 * 3600                     # same air as engine flow [kg/h]
    assert np.allclose(injection_ms(rpm, lam, spec, air_flow_kg_h=ga), injection_ms(rpm, lam, spec,
                                                                                      air_mg_per_cycle=air_mg))
    assert np.allclose(fuel_mg(rpm, lam, spec, air_mg_per_cycle=air_mg),
                       air_mg / (lam * thermo.stoich_afr(spec.fuel)))
    with pytest.raises(ValueError, match="exactly one"):
        fuel_mg(rpm, lam, spec)


def test_ve_is_100_percent_for_a_cylinder_filled_at_manifold_density():
    spec = default_spec()
    vd = spec.geometry.displacement_m3
    map_kpa, temp = np.array([40.0, 70.0, 101.3]), 300.0
    full_mg = map_kpa * 1e3 * vd / (R_AIR_J_KG_K * temp) * 1e6
    assert np.allclose(ve_percent(8000, spec, map_kpa=map_kpa, air_mg_per_cycle=full_mg, ref_temp_k=temp), 100.0)
    half = ve_percent(8000, spec, air_mg_per_cycle=full_mg / 2, ref_pressure_kpa=40.0, ref_temp_k=temp)
    assert np.allclose(half, [50.0, 87.5, 126.625])               # relative to a fixed 40 kPa
    assert R_AIR_J_KG_K == pytest.approx(287.05, abs=0.02)
    with pytest.raises(ValueError, match="map_kpa"):
        ve_percent(8000, spec, air_mg_per_cycle=full_mg)


# --------------------------------------------------------------------------- XML helpers

def xml_tree(path, drop_attrs=(), ignore_attrs_of=()):
    """(tag, attrs, text tokens as floats or strings, children) of every element."""

    def tok(t):
        try:
            return float(t)
        except ValueError:
            return t

    def node(e):
        local = e.tag.split("}")[-1]
        attrs = {} if local in ignore_attrs_of else {k: v for k, v in e.attrib.items() if k not in drop_attrs}
        return e.tag, attrs, [tok(t) for t in (e.text or "").split()], [node(c) for c in e]

    return node(ET.parse(path).getroot())


def msq_constants(path) -> dict:
    ns = {"m": "http://www.msefi.com/:msq"}
    root = ET.parse(path).getroot()
    out = {}
    for c in root.findall(".//m:constant", ns):
        toks = (c.text or "").split()
        try:
            arr = np.array(toks, float)
        except ValueError:
            arr = np.array(toks)
        out[c.get("name")] = (dict(c.attrib), arr)
    return out


# --------------------------------------------------------------------------- TunerStudio .table

def test_tunerstudio_table_matches_hand_written_reference(tmp_path):
    out = write_tunerstudio_table(spark_3x4(), tmp_path / "a.table", units=False, author=REF_AUTHOR,
                                  write_date=REF_DATE)
    assert xml_tree(out) == xml_tree(DATA / "ts_spark_3x4.table")
    with_units = write_tunerstudio_table(spark_3x4(), tmp_path / "b.table", author=REF_AUTHOR, write_date=REF_DATE)
    assert xml_tree(with_units, drop_attrs=("units",)) == xml_tree(DATA / "ts_spark_3x4.table")


def test_tunerstudio_table_round_trip(tmp_path):
    t = odd_table(decimals=2)
    path = write_table(t, tmp_path / "spark.table")
    root = ET.parse(path).getroot()                              # independent parse
    ns = {"t": "http://www.EFIAnalytics.com/:table"}
    x = np.array(root.find(".//t:xAxis", ns).text.split(), float)
    y = np.array(root.find(".//t:yAxis", ns).text.split(), float)
    z = np.array(root.find(".//t:zValues", ns).text.split(), float).reshape(5, 7)
    assert np.array_equal(x, t.rpm) and np.array_equal(y, t.load)
    assert np.array_equal(z, np.round(t.values, 2))
    assert root.find(".//t:zValues", ns).get("units") == "deg BTDC"
    assert root.find(".//t:table", ns).attrib == {"cols": "7", "rows": "5"}
    back = read_table(path)
    assert back.name == "spark" and back.unit == "deg BTDC" and back.load_kind == "throttle_pct"
    assert back.decimals == 2 and np.array_equal(back.values, np.round(t.values, 2))


def test_tunerstudio_table_reference_reads_with_load_kind_from_axis_name():
    t = read_table(DATA / "ts_spark_3x4.table")
    assert t.load_kind == "throttle_pct" and t.unit == "" and t.decimals == 1
    assert np.array_equal(t.values, spark_3x4().values)


# --------------------------------------------------------------------------- msq

def speeduino_adv() -> EcuTable:
    rpm, load = grid16()
    i, j = np.mgrid[0:16, 0:16]
    return EcuTable("spark_advance", 10.0 + i + j, rpm / 2, load, "throttle_pct", "deg BTDC", 1)


def test_speeduino_msq_matches_hand_written_reference(tmp_path):
    rep = write_msq(speeduino_adv(), tmp_path / "s.msq", "speeduino", author=REF_AUTHOR, write_date=REF_DATE)
    assert rep.constants == ["advTable1", "rpmBins2", "mapBins1"]
    assert xml_tree(rep.path, ignore_attrs_of=("bibliography",)) == \
        xml_tree(DATA / "speeduino_adv_tps.msq", ignore_attrs_of=("bibliography",))


def rusefi_ve() -> EcuTable:
    i, j = np.mgrid[0:16, 0:16]
    return EcuTable("ve", 40.0 + 2.5 * i + 0.5 * j, 1000.0 * np.arange(1, 17), 20.0 + 5 * np.arange(16),
                    "map_kpa", "%", 1)


def test_rusefi_msq_matches_hand_written_reference(tmp_path):
    sig = msq_signature(DATA / "rusefi_ve_map.msq")
    rep = write_msq(rusefi_ve(), tmp_path / "r.msq", "rusefi", signature=sig)
    assert xml_tree(rep.path, ignore_attrs_of=("bibliography",)) == \
        xml_tree(DATA / "rusefi_ve_map.msq", ignore_attrs_of=("bibliography",))


@pytest.mark.parametrize("firmware, kind, values, unit, step, names", [
    ("speeduino", "ignition", lambda i, j: -5.3 + 3.1 * i + 0.7 * j, "deg BTDC", 1.0,
     ("advTable1", "rpmBins2", "mapBins1")),
    ("speeduino", "ve", lambda i, j: 30.2 + 4.4 * i + 1.3 * j, "%", 1.0, ("veTable", "rpmBins", "fuelLoadBins")),
    ("rusefi", "ignition", lambda i, j: -5.33 + 3.17 * i + 0.71 * j, "deg BTDC", 0.1,
     ("ignitionTable", "ignitionRpmBins", "ignitionLoadBins")),
    ("rusefi", "ve", lambda i, j: 30.22 + 4.41 * i + 1.37 * j, "%", 0.1, ("veTable", "veRpmBins", "veLoadBins")),
])
@pytest.mark.parametrize("load_kind", ["throttle_pct", "map_kpa"])
def test_msq_round_trip_to_firmware_precision(tmp_path, firmware, kind, values, unit, step, names, load_kind):
    rpm, load = grid16(load_kind)
    i, j = np.mgrid[0:16, 0:16]
    t = EcuTable("t", values(i, j) + 0.01 * np.sqrt(2), rpm, load, load_kind, unit, 2)   # no exact halves
    rep = write_msq(t, tmp_path / "t.msq", firmware)
    stored = np.floor(t.values / step + 0.5) * step
    assert rep.max_rounding[names[0]] == pytest.approx(np.max(np.abs(stored - t.values)))
    consts = msq_constants(rep.path)                              # independent parse
    assert list(consts) == list(names)
    assert np.allclose(consts[names[0]][1].reshape(16, 16), stored, atol=1e-9)
    assert np.array_equal(consts[names[1]][1], rpm) and np.array_equal(consts[names[2]][1], load)
    assert consts[names[0]][0]["rows"] == "16" and consts[names[0]][0]["cols"] == "16"
    back = read_msq(rep.path)
    assert back.name == names[0] and back.load_kind == load_kind
    assert np.allclose(back.values, stored, atol=1e-9) and np.array_equal(back.rpm, rpm)
    assert read_table(rep.path, table=kind).name == names[0]


def test_lambda_goes_to_speeduino_afr_and_rusefi_lambda(tmp_path):
    rpm, load = grid16("map_kpa")
    lam = EcuTable("lambda_target", np.linspace(0.85, 1.05, 256).reshape(16, 16), rpm, load, "map_kpa", "-", 3)
    sp = write_msq(lam, tmp_path / "s.msq", "speeduino", stoich=14.7)
    afr = msq_constants(sp.path)["afrTable"][1].reshape(16, 16)
    assert np.allclose(afr, np.floor(lam.values * 147 + 0.5) / 10, atol=1e-9)
    assert read_msq(sp.path).unit == "AFR"
    re = write_msq(lam, tmp_path / "r.msq", "rusefi")
    stored = np.floor(lam.values * 147 + 0.5) / 147
    back = read_msq(re.path)
    assert back.unit == "-" and np.allclose(back.values, stored, atol=5e-5)   # 4 decimals identify the raw count
    assert np.array_equal(np.floor(back.values * 147 + 0.5), np.floor(lam.values * 147 + 0.5))
    as_afr = write_msq(lam, tmp_path / "ra.msq", "rusefi", lambda_units="afr")
    assert msq_constants(as_afr.path)["lambdaTable"][0]["units"] == "afr"


def test_msq_refuses_wrong_size_unless_resampled(tmp_path):
    t = spark_3x4()
    with pytest.raises(ValueError) as exc:
        write_msq(t, tmp_path / "x.msq", "speeduino")
    for w in ("advTable1", "16x16", "'spark_advance'", "3x4", "resample_to"):
        assert w in str(exc.value)
    rpm, load = grid16()
    rep = write_msq(t, tmp_path / "x.msq", "rusefi", resample_to=(rpm / 2, load))
    out = rep.outside["ignitionTable"]
    # 500 rpm and 7000-8000 rpm lie outside the 1000-6000 rpm of the table; its 0-100 % cover 0-75 %
    assert out.shape == (16, 16) and out[:, 0].all() and out[:, 12:].all() and not out[:, 1:12].any()


@pytest.mark.parametrize("change, words", [
    (dict(rpm=1000.0 * np.arange(1, 17) + 50), ["rpmBins2", "1050", "steps of 100"]),
    (dict(load=np.arange(16) * 5.0 + 0.25), ["mapBins1", "0.25", "steps of 0.5"]),
    (dict(values=np.full((16, 16), 75.0)), ["advTable1", "75", "-40..70"]),
])
def test_msq_refuses_values_and_breakpoints_the_firmware_cannot_store(tmp_path, change, words):
    with pytest.raises(ValueError) as exc:
        write_msq(speeduino_adv().replace(**change), tmp_path / "x.msq", "speeduino")
    for w in words:
        assert w in str(exc.value)


def test_msq_merge_into_full_tune_replaces_only_our_constants(tmp_path):
    base = DATA / "rusefi_base_full.msq"
    rep = write_msq(rusefi_ve(), tmp_path / "merged.msq", "rusefi", merge_into=base)
    assert rep.signature == msq_signature(base)
    got, was = msq_constants(rep.path), msq_constants(base)
    assert list(got) == list(was)
    for name in was:
        if name == "veTable":
            assert np.allclose(got[name][1].reshape(16, 16), rusefi_ve().values)
        else:
            assert got[name][0] == was[name][0] and np.array_equal(got[name][1], was[name][1])
    assert ET.parse(rep.path).getroot().find("{http://www.msefi.com/:msq}settings") is not None
    psi = tmp_path / "psi.msq"
    psi.write_text(base.read_text(encoding="latin-1").replace('name="veLoadBins" rows="16" units="kPa"',
                                                              'name="veLoadBins" rows="16" units="psi"'),
                   encoding="latin-1")
    with pytest.raises(ValueError, match="veLoadBins is in 'psi'"):
        write_msq(rusefi_ve(), tmp_path / "m2.msq", "rusefi", merge_into=psi)
    with pytest.raises(ValueError, match="not a speeduino tune"):
        write_msq(speeduino_adv(), tmp_path / "m3.msq", "speeduino", merge_into=base)


def test_msq_reader_needs_a_table_choice_and_a_known_load(tmp_path):
    base = DATA / "rusefi_base_full.msq"
    t = read_msq(base)                                             # only one known table; fuelAlgorithm says MAP
    assert t.name == "veTable" and t.load_kind == "map_kpa" and (t.values == 50).all()
    both = tmp_path / "both.msq"
    write_msq([rusefi_ve(), rusefi_ve().replace(name="spark", unit="deg", values=np.full((16, 16), 20.0))],
              both, "rusefi")
    with pytest.raises(ValueError, match="pass table="):
        read_msq(both)
    assert read_msq(both, "ignition").name == "ignitionTable"
    assert read_msq(both, "veTable").name == "veTable"
    with pytest.raises(ValueError, match="duplicate|both go"):
        write_msq([rusefi_ve(), rusefi_ve()], both, "rusefi")


# --------------------------------------------------------------------------- DCM

def dcm_tokens(path):
    out = []
    for line in Path(path).read_text().splitlines():
        s = line.strip()
        if not s or s[0] in "*!.":
            continue
        for tok in (a or b for a, b in re.findall(r'"([^"]*)"|(\S+)', s)):
            try:
                out.append(float(tok))
            except ValueError:
                out.append(tok)
    return out


def test_dcm_matches_hand_written_reference(tmp_path):
    out = write_dcm(spark_3x4(), tmp_path / "a.dcm")
    assert dcm_tokens(out) == dcm_tokens(DATA / "spark_3x4.dcm")
    ref = read_dcm(DATA / "spark_3x4.dcm")
    assert ref.description == "Spark advance" and ref.unit == "deg BTDC" and ref.decimals == 1
    assert np.array_equal(ref.values, spark_3x4().values) and ref.load_kind == "throttle_pct"


def test_dcm_round_trip_with_flags_uncertainty_and_several_maps(tmp_path):
    t = odd_table(decimals=2)
    inj = EcuTable("injection_time", np.linspace(1, 9, 35).reshape(5, 7) + 1e-4, t.rpm,
                   [20, 40, 60, 80, 100.0], "map_kpa", "ms", 3)
    path = write_table([t, inj], tmp_path / "maps.dcm")
    text = path.read_text()
    assert "KONSERVIERUNG_FORMAT 2.0" in text and "KENNFELD spark_advance 7 5" in text
    assert "KENNFELD spark_advance_flag 7 5" in text and "KENNFELD injection_time 7 5" in text
    with pytest.raises(ValueError, match="pass name="):
        read_table(path)
    back = read_table(path, table="spark_advance")
    assert np.array_equal(back.values, np.round(t.values, 2)) and back.decimals == 2
    assert np.array_equal(back.rpm, t.rpm) and np.array_equal(back.load, t.load)
    assert np.array_equal(back.flags, t.flags) and back.flag_meaning == "knock-limited"
    assert np.allclose(back.uncertainty, t.uncertainty, atol=0.0005 + 1e-12)
    i2 = read_dcm(path, "injection_time")
    assert i2.load_kind == "map_kpa" and i2.unit == "ms" and np.allclose(i2.values, np.round(inj.values, 3))


@pytest.mark.parametrize("body, words", [
    ("KENNFELD m 2 1\n EINHEIT_Y \"%\"\n ST/X 1 2 3\n ST/Y 0\n WERT 1 2\nEND\n", ["ST/X", "nx = 2"]),
    ("KENNFELD m 2 2\n EINHEIT_Y \"%\"\n ST/X 1 2\n ST/Y 0\n WERT 1 2\nEND\n", ["ST/Y", "ny = 2"]),
    ("KENNFELD m 2 1\n EINHEIT_Y \"%\"\n ST/X 1 2\n ST/Y 0\n WERT 1 x\nEND\n", ["'x'", "line"]),
    ("KENNFELD m 2 1\n EINHEIT_Y \"%\"\n ST/X 1 2\n ST/Y 0\n WERT 1 2\n", ["not closed"]),
    ("KENNFELD m 2 1\n EINHEIT_Y \"rpm\"\n ST/X 1 2\n ST/Y 0\n WERT 1 2\nEND\n", ["'rpm'", "load_kind"]),
    ("KENNFELD m 2 1\n EINHEIT_Y \"%\"\n ST/X 2 1\n ST/Y 0\n WERT 1 2\nEND\n", ["rpm", "strictly increasing"]),
])
def test_dcm_reader_rejects_broken_files_naming_the_file(tmp_path, body, words):
    p = tmp_path / "bad.dcm"
    p.write_text("KONSERVIERUNG_FORMAT 2.0\n\n" + body)
    with pytest.raises(ValueError) as exc:
        read_table(p)
    assert str(p) in str(exc.value)
    for w in words:
        assert w in str(exc.value)


# --------------------------------------------------------------------------- CSV

def test_csv_matches_hand_written_reference(tmp_path):
    out = write_csv(spark_3x4(), tmp_path / "a.csv")
    with open(out, newline="") as a, open(DATA / "spark_3x4.csv", newline="") as b:
        assert list(csv.reader(a)) == list(csv.reader(b))


def test_csv_round_trip_with_independent_parser(tmp_path):
    t = odd_table(decimals=1)
    path = write_table(t, tmp_path / "spark.csv")
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    meta = {r[0]: r[1:] for r in rows[:rows.index(["[values]"])]}
    assert meta["table"] == ["spark_advance"] and meta["unit"] == ["deg BTDC"]
    assert meta["row_axis"] == ["throttle_pct", "%"] and meta["column_axis"] == ["speed_rpm", "rpm"]
    k = rows.index(["[values]"])
    assert np.array_equal(np.array(rows[k + 1][1:], float), t.rpm)
    grid = np.array([r for r in rows[k + 2:k + 7]], float)
    assert np.array_equal(grid[:, 0], t.load) and np.array_equal(grid[:, 1:], np.round(t.values, 1))
    back = read_table(path)
    assert back.name == "spark_advance" and back.decimals == 1 and back.unit == "deg BTDC"
    assert np.array_equal(back.values, np.round(t.values, 1)) and np.array_equal(back.flags, t.flags)
    assert np.allclose(back.uncertainty, t.uncertainty, atol=0.005 + 1e-12)
    assert back.flag_meaning == "knock-limited" and back.description == t.description


def test_reads_maps_io_wide_csv(tmp_path):
    wide = pd.DataFrame([[0.0, 10.0, 12.0], [50.0, 15.0, 18.5]], columns=["throttle_pct", "1000", "2000"])
    p = tmp_path / "spark_advance.csv"
    wide.to_csv(p, index=False)
    t = read_table(p)
    assert t.name == "spark_advance" and t.unit == "deg BTDC" and t.load_kind == "throttle_pct"
    assert np.array_equal(t.values, [[10, 12], [15, 18.5]]) and np.array_equal(t.rpm, [1000, 2000])


def test_csv_reader_rejects_holes(tmp_path):
    p = tmp_path / "hole.csv"
    p.write_text((DATA / "spark_3x4.csv").read_text().replace("15.0,18.0,", "15.0,,"))
    with pytest.raises(ValueError, match=r"hole\.csv.*3 values for 4 rpm"):
        read_table(p)


# --------------------------------------------------------------------------- detection, axes, bad files

@pytest.mark.parametrize("name", ["ts_spark_3x4.table", "spark_3x4.dcm", "spark_3x4.csv"])
def test_read_axes_of_every_reference(name):
    ax = read_axes(DATA / name)
    assert np.array_equal(ax.rpm, [1000, 2000, 4000, 6000]) and np.array_equal(ax.load, [0, 50, 100])
    assert ax.load_kind == "throttle_pct"


def test_read_axes_of_msq_references():
    ax = read_axes(DATA / "speeduino_adv_tps.msq")
    assert ax.load_kind == "throttle_pct" and ax.rpm[0] == 500 and ax.load[-1] == 75
    ax = read_axes(DATA / "rusefi_ve_map.msq")
    assert ax.load_kind == "map_kpa" and ax.load[0] == 20 and ax.rpm[-1] == 16000


def test_format_detection_from_content_without_suffix(tmp_path):
    for src in ("spark_3x4.dcm", "ts_spark_3x4.table", "speeduino_adv_tps.msq"):
        p = tmp_path / f"current_{src.split('.')[0]}"
        p.write_bytes((DATA / src).read_bytes())
        assert read_table(p).shape in ((3, 4), (16, 16))


@pytest.mark.parametrize("name, content, words", [
    ("missing.table", None, ["missing.table", "not found"]),
    ("broken.table", "<tableData><table>", ["broken.table", "XML"]),
    ("nozvalues.table", "<tableData><table><xAxis>1 2</xAxis><yAxis>1 2</yAxis></table></tableData>",
     ["nozvalues.table", "zValues"]),
    ("count.table", ("<tableData><table><xAxis cols='2'>1 2</xAxis><yAxis rows='2'>0 10</yAxis>"
                     "<zValues>1 2 3</zValues></table></tableData>"), ["count.table", "3 numbers"]),
    ("noload.table", ("<tableData><table><xAxis>1 2</xAxis><yAxis name='fuelLoad'>0 10</yAxis>"
                      "<zValues>1 2 3 4</zValues></table></tableData>"), ["noload.table", "load_kind"]),
    ("other.msq", "<msq xmlns='http://www.msefi.com/:msq'><versionInfo signature='MS3 Format 0566'/></msq>",
     ["other.msq", "neither"]),
    ("notxml.msq", "speeduino", ["notxml.msq", "XML"]),
    ("garbage.bin", "\x00\x01garbage", ["garbage.bin", "unknown table file format"]),
    ("empty.csv", "", ["empty.csv", "empty"]),
    ("plain.csv", "a,b\n1,2\n", ["plain.csv", "not an ECU table CSV"]),
])
def test_unreadable_files_raise_value_error_naming_the_file(tmp_path, name, content, words):
    p = tmp_path / name
    if content is not None:
        p.write_text(content)
    with pytest.raises(ValueError) as exc:
        read_table(p)
    for w in words:
        assert w in str(exc.value)


def test_write_table_dispatch_and_format_names(tmp_path):
    assert set(FORMATS) == {"tunerstudio-table", "speeduino-msq", "rusefi-msq", "dcm", "csv"}
    with pytest.raises(ValueError, match="pass fmt="):
        write_table(spark_3x4(), tmp_path / "x.msq")
    with pytest.raises(ValueError, match="one table per file"):
        write_table([spark_3x4(), spark_3x4()], tmp_path / "x.csv")
    rep = write_table(speeduino_adv(), tmp_path / "x.msq", "speeduino-msq")
    assert rep.firmware == "speeduino" and rep.path.exists()
    assert FIRMWARE_TABLES[("speeduino", "ignition")].z.name == "advTable1"


# --------------------------------------------------------------------------- compare

def test_compare_puts_proposed_on_current_breakpoints(tmp_path):
    rpm, load = np.array([1000, 3000, 7000, 13000.0]), np.array([0, 20, 55, 100.0])
    current = EcuTable("spark_advance", np.full((4, 4), 20.0), rpm, load, "throttle_pct", "deg BTDC", 1,
                       flags=np.eye(4, dtype=bool))
    prpm, pload = np.array([1000, 5000, 9000.0]), np.array([0, 50, 100.0])
    proposed = EcuTable("proposed", bilinear(prpm[None, :], pload[:, None]), prpm, pload, "throttle_pct", "deg",
                        1, flags=np.zeros((3, 3), bool), uncertainty=np.full((3, 3), 1.5))
    diff = compare(current, proposed)
    assert len(diff) == 16 and diff.attrs["unit"] == "deg BTDC"
    inside = ~diff["outside"].to_numpy()
    expect = bilinear(diff["speed_rpm"].to_numpy(), diff["throttle_pct"].to_numpy()) - 20.0
    assert np.allclose(diff["difference"].to_numpy()[inside], expect[inside], atol=1e-9)
    assert diff.loc[diff["speed_rpm"] == 13000, "outside"].all()
    assert not diff.loc[diff["speed_rpm"] < 13000, "outside"].any()
    assert (diff["proposed_uncertainty"] == 1.5).all()
    assert (diff["within_uncertainty"] == (diff["difference"].abs() <= 1.5)).all()
    assert diff["current_flag"].sum() == 4
    png = plot_difference(diff, tmp_path / "diff.png")
    assert png.stat().st_size > 1000 and png.read_bytes()[:4] == b"\x89PNG"


def test_compare_refuses_other_units_or_load_axis():
    t = spark_3x4()
    with pytest.raises(ValueError, match="'ms'"):
        compare(t, t.replace(unit="ms"))
    with pytest.raises(ValueError, match="map_kpa"):
        compare(t, t.replace(load_kind="map_kpa"))


def test_compare_against_the_current_map_file(tmp_path):
    current = read_table(DATA / "speeduino_adv_tps.msq")          # what the ECU runs
    proposed = speeduino_adv().replace(values=speeduino_adv().values + 2.0)
    diff = compare(current, proposed)
    inside = ~diff["outside"]
    assert np.allclose(diff.loc[inside, "difference"], 2.0)
