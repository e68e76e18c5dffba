"""``mbc export`` and ``mbc compare`` on a run folder (in-process, no Prefect or Dask).

The run folder is built by ``conftest.ecu_run_folder``: a map build on a synthetic engine
(write_maps + engine.toml), as the pipeline leaves it.  Expected numbers come from the
cells by scipy interpolation and plain XML/CSV parsing, not from the code under test.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.interpolate import RegularGridInterpolator

from conftest import SYNTHETIC_VE, ecu_run_folder
from engine_model.tables.ecu_files import EcuTable, write_tunerstudio_table
from engine_model.tables.ecu_msq import read_msq
from flows.cli import main

NS = {"ts": "http://www.EFIAnalytics.com/:table"}
DATA = Path(__file__).parents[1] / "tables" / "data"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return ecu_run_folder(tmp_path_factory.mktemp("exp") / "run")


def pivot(cells, col):
    piv = cells.pivot(index="throttle_pct", columns="speed_rpm", values=col).sort_index().sort_index(axis=1)
    return piv.index.to_numpy(float), piv.columns.to_numpy(float), piv.to_numpy(float)


def read_ts(path):
    t = ET.parse(path).getroot().find("ts:table", NS)
    x = np.array(t.find("ts:xAxis", NS).text.split(), float)
    y = np.array(t.find("ts:yAxis", NS).text.split(), float)
    z = np.array(t.find("ts:zValues", NS).text.split(), float).reshape(y.size, x.size)
    return x, y, z


def test_export_all_formats_on_custom_breakpoints(run, tmp_path, capsys):
    folder, _spec, res = run
    out = tmp_path / "ecu"
    assert main(["export", "--run", str(folder), "--out", str(out), "--rpm-bins", "3000:12000:1500",
                 "--load-bins", "20,30,45,60,80,100"]) == 0
    text = capsys.readouterr().out
    assert "on 7 rpm x 6 throttle_pct [%] breakpoints" in text and "speeduino.msq skipped" in text
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["README.txt", "ecu_tables.dcm"] + [f"{n}.{s}" for n in ("spark_advance", "injection_time", "lambda_target")
                                            for s in ("table", "csv")])
    x, y, z = read_ts(out / "spark_advance.table")
    assert list(x) == [3000, 4500, 6000, 7500, 9000, 10500, 12000] and list(y) == [20, 30, 45, 60, 80, 100]
    thr, rpm, spark = pivot(res.cells, "spark_deg_btdc")
    want = RegularGridInterpolator((thr, rpm), spark)(np.array([(t, n) for t in y for n in x])).reshape(6, 7)
    np.testing.assert_allclose(z, np.round(want, 1), atol=0.051)
    # the CSV's units header and grid
    lines = (out / "injection_time.csv").read_text().splitlines()
    assert lines[:4] == ["table,injection_time", "unit,ms", "row_axis,throttle_pct,%", "column_axis,speed_rpm,rpm"]


def test_export_kpa_ve_and_msq_from_the_axes_of_a_tune(run, tmp_path, capsys):
    folder, _spec, res = run
    out = tmp_path / "sd"
    assert main(["export", "--run", str(folder), "--out", str(out), "--load-axis", "kpa", "--fuel", "ve",
                 "--format", "csv"]) == 0
    assert "map_kpa [kPa]" in capsys.readouterr().out
    df = pd.read_csv(out / "ve.csv", skiprows=8, index_col=0)     # past the key lines and [values]
    assert (out / "ve.csv").read_text().splitlines()[2] == "row_axis,map_kpa,kPa"
    np.testing.assert_allclose(df.to_numpy(float), 100 * SYNTHETIC_VE, atol=0.11)
    # breakpoints of a Speeduino tune (16 x 16, TPS): the msq holds them exactly
    assert main(["export", "--run", str(folder), "--out", str(tmp_path / "tps"), "--format", "msq-speeduino",
                 "--axes-from", str(DATA / "speeduino_adv_tps.msq")]) == 0
    ref, got = read_msq(DATA / "speeduino_adv_tps.msq", "ignition"), read_msq(tmp_path / "tps" / "speeduino.msq",
                                                                              "ignition")
    assert list(got.rpm) == list(ref.rpm) and list(got.load) == list(ref.load) and got.shape == (16, 16)


@pytest.mark.parametrize("argv, words", [
    (["--rpm-bins", "6000,3000"], ["rpm breakpoints", "3000", "strictly increasing"]),
    (["--load-bins", "0,50,150"], ["load breakpoint 2", "150"]),
    (["--rpm-bins", "1000,x"], ["rpm breakpoints '1000,x'"]),
    (["--format", "msq-rusefi", "--rpm-bins", "3000,6000", "--load-bins", "20,100"], ["rusefi tables are 16 x 16"]),
    (["--axes-from", "nope.table"], ["nope.table", "file not found"]),
    (["--axes-from", str(DATA / "speeduino_adv_tps.msq"), "--load-axis", "kpa"], ["its load axis is throttle_pct"]),
])
def test_export_bad_input_is_refused_before_anything_is_written(run, tmp_path, capsys, argv, words):
    folder, _spec, _res = run
    out = tmp_path / "never"
    assert main(["export", "--run", str(folder), "--out", str(out), *argv]) == 2
    err = capsys.readouterr().err
    for w in words:
        assert w in err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_export_needs_a_built_run_and_the_engine_for_ve(tmp_path, run, capsys):
    assert main(["export", "--run", str(tmp_path)]) == 2
    assert "no maps/cells.parquet" in capsys.readouterr().err
    folder, _spec, _res = run
    bare = tmp_path / "bare"
    (bare / "maps").mkdir(parents=True)
    (bare / "maps" / "cells.parquet").write_bytes((folder / "maps" / "cells.parquet").read_bytes())
    assert main(["export", "--run", str(bare), "--fuel", "ve"]) == 2
    assert "no engine.toml; --fuel ve needs the engine" in capsys.readouterr().err
    assert not (bare / "exports").exists()


def test_compare_is_proposed_minus_current_cell_by_cell(run, tmp_path, capsys):
    folder, _spec, res = run
    rpm_c, thr_c = np.array([3000.0, 5000, 8000, 12000]), np.array([20.0, 50, 100])
    rng = np.random.default_rng(5)
    current = np.round(rng.uniform(15, 45, (3, 4)), 1)
    cur = tmp_path / "car.table"
    write_tunerstudio_table(EcuTable("spark", current, rpm_c, thr_c, "throttle_pct", "deg", 1), cur, units=False)
    out = tmp_path / "cmp"
    assert main(["compare", "--run", str(folder), "--current", str(cur), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    diff = pd.read_csv(out / "spark_difference.csv")
    thr, rpm, spark = pivot(res.cells, "spark_deg_btdc")
    proposed = RegularGridInterpolator((thr, rpm), spark)(np.array([(t, n) for t in thr_c for n in rpm_c]))
    np.testing.assert_allclose(diff["current"], current.ravel())
    np.testing.assert_allclose(diff["proposed"], proposed, rtol=1e-12)
    np.testing.assert_allclose(diff["difference"], proposed - current.ravel(), rtol=1e-12, atol=1e-12)
    assert {"proposed_uncertainty", "within_uncertainty", "outside"} <= set(diff.columns)
    k = int(np.argmax(np.abs(proposed - current.ravel())))
    assert f"max |difference| {abs(proposed - current.ravel())[k]:.1f} deg" in text
    assert f"at {thr_c[k // 4]:g} %, {rpm_c[k % 4]:g} rpm" in text
    assert (out / "spark_difference.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_compare_lambda_against_an_afr_tune_on_a_kpa_axis(run, tmp_path, capsys):
    folder, _spec, res = run
    out = tmp_path / "lam"
    assert main(["export", "--run", str(folder), "--out", str(out), "--load-axis", "kpa",
                 "--format", "msq-speeduino"]) == 0
    # a kPa tune on those 16 x 16 breakpoints, straight from the model (no intermediate grid)
    assert main(["export", "--run", str(folder), "--out", str(tmp_path / "tune"), "--format", "msq-speeduino",
                 "--axes-from", str(out / "speeduino.msq")]) == 0
    capsys.readouterr()
    assert main(["compare", "--run", str(folder), "--current", str(tmp_path / "tune" / "speeduino.msq"),
                 "--table", "lambda", "--out", str(tmp_path / "c")]) == 0
    assert "proposed lambda x 14.7" in capsys.readouterr().out
    diff = pd.read_csv(tmp_path / "c" / "lambda_difference.csv")
    assert "map_kpa" in diff.columns and len(diff) == 256
    tune = read_msq(tmp_path / "tune" / "speeduino.msq", "lambda")
    np.testing.assert_allclose(diff["current"], tune.values.ravel())
    # the current table is the proposed one stored to 0.1 AFR: every cell within half a step
    assert np.abs(diff["difference"]).max() <= 0.05 + 1e-9
    assert np.abs(diff["difference"]).max() > 0          # and the rounding is seen
