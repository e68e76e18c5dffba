"""`mbc plan` runs the plan flow through Prefect and writes a plan that `mbc sweep` accepts."""

from __future__ import annotations

import json

import pandas as pd

from engine_model import doe
from flows.cli import main
from flows.store import read_results


def test_mbc_plan_then_sweep(prefect_api, tmp_path, capsys):
    out_dir = tmp_path / "plans"
    assert main(["plan", "lhs", "--name", "lhs8", "--n", "8", "--seed", "3", "--out-dir", str(out_dir),
                 "--bound", "speed_rpm=6000:11000", "--bound", "throttle_pct=40:100", "--feasibility", "off"]) == 0
    meta = json.loads((out_dir / "lhs8.meta.json").read_text())
    assert meta["generator"] == "lhs" and meta["seed"] == 3 and meta["n_points"] == 8
    assert meta["bounds"]["speed_rpm"] == [6000.0, 11000.0]
    plan = doe.load_plan(out_dir / "lhs8.parquet")
    assert plan["speed_rpm"].between(6000, 11000).all() and plan["throttle_pct"].between(40, 100).all()
    # bench run order: throttle ascending, then speed
    assert list(plan.sort_values(["throttle_pct", "speed_rpm"])["point_id"]) == list(plan["point_id"])
    csv = pd.read_csv(out_dir / "lhs8.csv")
    assert len(csv) == 8 and {"bdur_10_90_deg", "wiebe_m"} <= set(csv.columns)
    # the same seed gives the same plan through the CLI
    assert main(["plan", "lhs", "--name", "lhs8b", "--n", "8", "--seed", "3", "--out-dir", str(out_dir),
                 "--bound", "speed_rpm=6000:11000", "--bound", "throttle_pct=40:100", "--feasibility", "off"]) == 0
    assert doe.plan_hash(doe.load_plan(out_dir / "lhs8b.parquet")) == doe.plan_hash(plan)

    out = tmp_path / "sweep"
    assert main(["sweep", "--plan", str(out_dir / "lhs8.csv"), "--out", str(out), "--workers", "2",
                 "--step-deg", "1", "--tolerance", "0.01"]) == 0
    res = read_results(out)
    assert list(res["point_id"]) == list(plan["point_id"])
    assert "8/8 points" in capsys.readouterr().out


def test_mbc_plan_bad_option_is_refused(tmp_path, capsys):
    assert main(["plan", "sobol", "--name", "x", "--out-dir", str(tmp_path), "--bound", "speed_rpm=9000"]) == 2
    assert "--bound 'speed_rpm=9000'" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
