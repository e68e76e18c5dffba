"""The command line: `mbc simulate` and `mbc run` write complete results, or nothing."""

import json

import pandas as pd

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


def test_mbc_run_on_packaged_data(prefect_api, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--out", str(out)]) == 0
    files = {p.name for p in out.iterdir()}
    assert {"simulated.parquet", "comparison.csv", "wot_comparison.png", "manifest.json", "bench_sweep"} <= files
    cmp_ = pd.read_csv(out / "comparison.csv")
    assert len(cmp_) == 7 and cmp_["air_kg_h_sim"].notna().all()
    man = json.loads((out / "manifest.json").read_text())
    assert man["points"] == 7 and man["wiebe_m"] == 6.4 and man["status"] == "complete"
    assert man["sweeps"]["bench_sweep"]["counts"]["points"] == 7
    sweep_man = json.loads((out / "bench_sweep" / "manifest.json").read_text())
    assert sweep_man["status"] == "complete" and sweep_man["dask"]["workers"] == 2
    assert "wot_9000" in capsys.readouterr().out
    assert not (tmp_path / "run.partial").exists()
