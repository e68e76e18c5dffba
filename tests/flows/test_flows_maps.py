"""`mbc maps` through real Prefect + Dask: a 3 x 3 grid from a prior-model file writes every table file."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

from engine_model import default_spec
from engine_model.tables import LambdaTable, PriorModel
from flows.cli import main


def test_mbc_maps_writes_all_tables(prefect_api, tmp_path, capsys):
    model = PriorModel(default_spec().spec_hash()).save(tmp_path / "prior.json")
    out = tmp_path / "run"
    # 1 deg steps: cheap on the shared machine; throttle from 20 % (the 1 deg step fails below ~10 %)
    assert main(["maps", "--model", str(model), "--out", str(out), "--throttle", "20,60,100",
                 "--speed", "4000:12000:4000", "--step-deg", "1", "--workers", "2"]) == 0
    maps = out / "maps"
    for name in ("ecu_tables.parquet", "spark_advance.csv", "injection_time.csv", "lambda_target.csv",
                 "spark_start_retarded.csv", "spark_advance.png", "injection_time.png", "lambda_target.png",
                 "maps.json", "run.json"):
        assert (maps / name).is_file(), name
    lf = pd.read_parquet(maps / "ecu_tables.parquet")
    assert list(lf.columns) == ["table", "throttle_pct", "speed_rpm", "value", "unit", "source", "limited_by"]
    spark = lf[lf["table"] == "spark_advance"]
    assert len(spark) == 9 and np.isfinite(spark["value"]).all()
    assert set(spark["limited_by"]) <= {"mbt", "knock", "retard", "spark_max", "infeasible"}
    run = json.loads((maps / "run.json").read_text())
    assert run["stats"]["evaluate_calls"] == len(list((out / "sweeps").glob("maps-*")))   # each batch a sweep
    assert run["stats"]["simulated_points"] >= 9 * 6
    # the model's plenum pressure per cell (the MAP axis of the ECU exports), and the ECU files on the run's grid
    cells = pd.read_parquet(maps / "cells.parquet")
    assert cells["plenum_pressure_bar"].between(0.1, 1.2).all() and cells["trapped_mass_mg"].gt(0).all()
    assert {"spark_advance.table", "speeduino.msq", "rusefi.msq", "ecu_tables.dcm"} <= {p.name for p in (maps / "ecu").iterdir()}
    lam = LambdaTable.from_csv(maps / "lambda_target.csv")
    assert lam.values[-1][0] == 0.9 and lam.values[0][0] == 1.0
    assert "9 cells" in capsys.readouterr().out
    # the same command again reads every batch back from its sweep folder (nothing recomputed), same tables
    before = pd.read_parquet(maps / "ecu_tables.parquet")
    assert main(["maps", "--model", str(model), "--out", str(out), "--throttle", "20,60,100",
                 "--speed", "4000:12000:4000", "--step-deg", "1", "--workers", "2"]) == 0
    for man in (out / "sweeps").glob("maps-*/manifest.json"):
        m = json.loads(man.read_text())
        assert m["chunks_computed"] == 0 and m["chunks_skipped"] == m["chunks"], man
    pd.testing.assert_frame_equal(pd.read_parquet(maps / "ecu_tables.parquet"), before)


def test_mbc_maps_bad_input_is_refused_before_any_work(tmp_path, capsys):
    model = PriorModel("0000000000000000").save(tmp_path / "other.json")
    assert main(["maps", "--model", str(model), "--out", str(tmp_path / "x")]) == 2
    assert "built for engine spec 0000000000000000" in capsys.readouterr().err
    good = PriorModel(default_spec().spec_hash()).save(tmp_path / "prior.json")
    assert main(["maps", "--model", str(good), "--out", str(tmp_path / "x"), "--speed", "3000,2000"]) == 2
    assert "speed_rpm: breakpoints must be sorted ascending" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
