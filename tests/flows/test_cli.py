"""The command line: `mbc simulate` and `mbc run` write complete results, or nothing."""

import json

import pandas as pd
import pytest

from engine_model.bench import packaged_bench_path
from flows.cli import main


def test_mbc_simulate_writes_parquet(tmp_path):
    pts = pd.DataFrame({"point_id": ["a"], "speed_rpm": [10000.0], "throttle_pct": [100.0],
                        "spark_deg_btdc": [49.5], "lambda": [0.9], "bdur_10_90_deg": [24.0], "wiebe_m": [6.4]})
    src = tmp_path / "points.csv"
    pts.to_csv(src, index=False)
    out = tmp_path / "res.parquet"
    assert main(["simulate", "--points", str(src), "--out", str(out)]) == 0
    res = pd.read_parquet(out)
    assert res["point_id"].tolist() == ["a"] and res["air_mass_flow_kg_h"].iloc[0] > 0


def test_mbc_simulate_bad_input_writes_nothing(tmp_path, capsys):
    pts = pd.DataFrame({"speed_rpm": [10000.0, -1.0], "throttle_pct": [100.0, 100.0],
                        "spark_deg_btdc": [49.5, 49.5], "lambda": [0.9, 0.9], "bdur_10_90_deg": [24.0, 24.0],
                        "wiebe_m": [6.4, 6.4]})
    src = tmp_path / "points.csv"
    pts.to_csv(src, index=False)
    out = tmp_path / "res.parquet"
    assert main(["simulate", "--points", str(src), "--out", str(out)]) == 2
    assert "row 1, column 'speed_rpm'" in capsys.readouterr().err
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [src]


def test_mbc_run_quick_pipeline_on_packaged_data(quick_run, run_copy):
    """The whole pipeline (small settings) through real Prefect + a 2-worker Dask cluster.

    Checks the stage outputs the issues name, that the index page links only files that exist,
    and that the run folder is only renamed from ``.partial`` once complete.  ``quick_run`` is the
    session's one quick run (tests/conftest.py); the later-stage part works on a copy of it.
    """
    out = quick_run.out
    for rel in ("index.html", "manifest.json", "calibration/airflow_match.parquet",
                "calibration/combustion_params.parquet", "calibration/calibration.html", "model/model.json",
                "model/learning_curve.png", "virtual_bench/measured.parquet", "maps/ecu_tables.parquet",
                "maps/spark_advance.csv", "maps/injection_time.csv", "maps/lambda_target.csv", "bench.parquet"):
        assert (out / rel).is_file(), rel
    assert list((out / "gap").glob("*.png")), "gap report figures"
    assert not out.with_name(out.name + ".partial").exists()
    man = json.loads((out / "manifest.json").read_text())
    assert man["status"] == "complete" and set(man["timings_s"]) >= {"calibration", "maps", "gap"}
    air = pd.read_parquet(out / "calibration" / "airflow_match.parquet")
    assert len(air) == 7 and air["ga_rel_pct"].notna().all()
    spark = pd.read_csv(out / "maps" / "spark_advance.csv", index_col=0)
    assert spark.shape == (3, 3)
    page = (out / "index.html").read_text()
    assert "(missing)" not in page and "maps/spark_advance.csv" in page
    for ecu_file in ("speeduino.msq", "rusefi.msq", "ecu_tables.dcm", "spark_advance.table"):   # linked ECU files
        assert (out / "maps" / "ecu" / ecu_file).is_file() and f"maps/ecu/{ecu_file}" in page, ecu_file
    assert "index:" in quick_run.stdout
    # the run keeps the bench data it was given (the file itself is gone since)
    assert man["bench"] == str(quick_run.bench) and not quick_run.bench.exists()
    kept = pd.read_parquet(out / "bench.parquet")
    assert kept["point_id"].tolist() == pd.read_csv(packaged_bench_path(), dtype={"point_id": str})["point_id"].tolist()
    # the calibrated engine is in the run folder, with the matched values
    from engine_model.calibrated import CalibratedEngine
    eng = CalibratedEngine.load(out / "engine.toml")
    knock = man["calibration"]["knock"]
    assert eng.overrides == pytest.approx({**man["calibration"]["airflow"]["parameters"],
                                           "knock.delay_multiplier": knock["delay_multiplier_table"]})
    assert eng.spec_hash() == man["calibrated_spec_hash"]
    # a later stage alone, on the finished run: it uses the run's engine and bench copy, and leaves the
    # other stages' outputs
    out = run_copy
    spark_before = (out / "maps" / "spark_advance.csv").read_bytes()
    assert main(["run", "--quick", "--stages", "gap", "--out", str(out)]) == 0
    man2 = json.loads((out / "manifest.json").read_text())
    assert list(man2["timings_s"]) == ["gap"] and man2["stages"] == ["gap"]
    assert man2["calibrated_spec_hash"] == man["calibrated_spec_hash"]
    assert man2["bench"] == man["bench"]
    assert "maps" in man2 and (out / "maps" / "spark_advance.csv").read_bytes() == spark_before
    assert "maps/spark_advance.csv" in (out / "index.html").read_text()


def test_mbc_run_refuses_a_stage_whose_inputs_are_missing(tmp_path, capsys):
    out = tmp_path / "empty"
    assert main(["run", "--quick", "--stages", "maps", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "stage 'maps' needs the 'calibration' stage's output" in err and "engine.toml" in err
    assert not out.exists() and not (tmp_path / "empty.partial").exists()


def test_mbc_run_refuses_a_negative_doe_seed_before_any_work(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--quick", "--doe-seed", "-1", "--out", str(out)]) == 2
    assert "CampaignSettings.doe_seed = -1 must be an integer >= 0" in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "run.partial").exists()
    # the D-optimal part of the design keeps the 6 points a quadratic needs
    assert main(["run", "--quick", "--doe-fill-points", "5", "--out", str(out)]) == 2
    assert "CampaignSettings.doe_fill_points = 5 must be an integer in [0, doe_points - 6 = 4]" \
        in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "run.partial").exists()


def test_mbc_maps_knock_uncertainty_z_reaches_the_settings(tmp_path, capsys):
    """`--knock-uncertainty-z` is passed to MapSettings: a bad value is refused by name before any cluster starts."""
    from engine_model.tables import PriorModel

    model = PriorModel().save(tmp_path / "prior.json")
    out = tmp_path / "maps"
    assert main(["maps", "--model", str(model), "--out", str(out), "--knock-uncertainty-z", "-1"]) == 2
    assert "MapSettings.knock_uncertainty_z = -1.0" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("reach, message", [("-5", "MapSettings.bench_offset_reach_rpm = -5.0"),
                                            ("far", "--bench-offset-reach 'far': expected a distance in rpm")])
def test_mbc_maps_bench_offset_reach_is_checked_before_any_work(tmp_path, capsys, reach, message):
    from engine_model.tables import PriorModel

    model = PriorModel().save(tmp_path / "prior.json")
    out = tmp_path / "maps"
    assert main(["maps", "--model", str(model), "--out", str(out), "--bench-offset-reach", reach]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
