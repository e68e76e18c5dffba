"""``mbc calibrate`` end to end on a reduced problem through real Prefect + a 2-worker Dask cluster.

Reduced: two Table 2 points, a 2 x 2 airflow grid with 2 least-squares iterations,
a 4 x 4 identification grid, 1 deg crank step.  Checks the files and their columns,
not the physics (the other calibration tests do that).
"""

import json

import pandas as pd
import pytest

from engine_model.bench import load_bench
from flows.cli import main

AIRFLOW_COLUMNS = ["point_id", "speed_rpm", "air_mass_flow_kg_h_meas", "air_mass_flow_kg_h_sim", "ga_rel_pct"]
PARAM_COLUMNS = ["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "bdur_10_90_deg", "wiebe_m",
                 "ca50_deg_atdc", "brake_power_kw_sim", "brake_power_kw_meas", "eta_trans",
                 "bdur_10_90_deg_lo", "bdur_10_90_deg_hi", "wiebe_m_lo", "wiebe_m_hi", "brake_power_err_pct", "status"]


def test_mbc_calibrate_reduced(prefect_api, tmp_path, capsys):
    bench = load_bench().iloc[[2, 5]]
    src = tmp_path / "bench.csv"
    bench.drop(columns=["at_mbt", "bench_ok", "bench_flags"]).to_csv(src, index=False)
    out = tmp_path / "cal"
    rc = main(["calibrate", "--bench", str(src), "--out", str(out), "--n-bdur", "4", "--n-m", "4",
               "--airflow-grid", "2x2x1", "--airflow-max-nfev", "2", "--step-deg", "1.0", "--workers", "2"])
    assert rc == 0
    cal = out / "calibration"
    air = pd.read_parquet(cal / "airflow_match.parquet")
    assert list(air.columns[:5]) == AIRFLOW_COLUMNS and list(air["point_id"]) == ["wot_9000", "wot_10500"]
    assert air["ga_rel_pct"].abs().max() < 15
    par = pd.read_parquet(cal / "combustion_params.parquet")
    assert set(PARAM_COLUMNS) <= set(par.columns) and len(par) == 2
    assert par["bdur_10_90_deg"].between(20, 50).all() and par["wiebe_m"].between(2, 8).all()
    assert (par["eta_trans"] == 0.95).all()
    summary = json.loads((cal / "summary.json").read_text())
    assert summary["identification"]["simulations"] == 2 * 16
    assert set(summary["airflow"]["parameters"]) == {"exhaust.runner_length_m", "intake.runner_length_m",
                                                     "intake.restrictor_recovery"}
    # identification at the default eta and at the jointly fitted shared eta, per point with pass flags
    idn, je = summary["identification"], summary["joint_eta"]
    assert idn["eta_trans"] == 0.95 and [r["point_id"] for r in idn["per_point"]] == ["wot_9000", "wot_10500"]
    assert all({"power_ok", "ca50_ok", "fit_ok", "bdur_10_90_deg_lo", "wiebe_m_hi"} <= set(r) for r in idn["per_point"])
    assert idn["fit_ok"] == sum(r["fit_ok"] for r in idn["per_point"])
    g = je["groups"][0]
    assert g["throttle_pct"] == 100 and g["ci95"][0] <= g["eta_trans"] <= g["ci95"][1]
    joint_par = pd.read_parquet(cal / "combustion_params_joint_eta.parquet")
    assert set(PARAM_COLUMNS) <= set(joint_par.columns) and (joint_par["eta_trans"] == g["eta_trans"]).all()
    text = capsys.readouterr().out
    assert "Identification at eta_trans = 0.95 (default)" in text and "shared eta_trans" in text
    assert "wot_10500" in text
    for f in ("calibration.md", "calibration.html", "eta_sensitivity.parquet", "eta_relation.parquet",
              "figures/ga_rel_vs_speed.png", "figures/plane_wot_9000.png", "figures/eta_relation.png"):
        assert (cal / f).is_file(), f
    md = (cal / "calibration.md").read_text()
    assert "](figures/plane_wot_9000.png)" in md and "](figures/ga_rel_vs_speed.png)" in md
    # the calibrated engine is written as a spec file that reads back with the matched values
    from engine_model.calibrated import CalibratedEngine
    eng = CalibratedEngine.load(out / "engine.toml")
    knock = summary["knock"]      # knock calibration on the two clean WOT points: a lower bound
    assert knock["evidence"] == "lower bound" and knock["points_knock_free"] == 2
    assert eng.overrides == pytest.approx({**summary["airflow"]["parameters"],
                                           "knock.delay_multiplier": knock["delay_multiplier_table"]})
    assert (cal / "knock_evidence.parquet").is_file() and "knock calibration (lower bound" in text
    for key, val in summary["airflow"]["parameters"].items():
        section, field = key.split(".")
        assert getattr(getattr(eng.spec, section), field) == val
    # every simulation went through the sweep pipeline (resumable parts on disk)
    assert sorted(p.name for p in (out / "sweeps").iterdir())[0] == "airflow-000"
    assert any((out / "sweeps" / "identification-000" / "sweep").glob("part-*.parquet"))


def test_mbc_calibrate_bad_bench_fails_before_work(tmp_path, capsys):
    src = tmp_path / "bench.csv"
    load_bench().drop(columns=["brake_torque_nm"]).to_csv(src, index=False)
    out = tmp_path / "cal"
    assert main(["calibrate", "--bench", str(src), "--out", str(out)]) == 2
    assert "brake_torque_nm" in capsys.readouterr().err and not out.exists()
