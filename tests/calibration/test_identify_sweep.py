"""Spark-sweep identification against the virtual bench's hidden law (engine_model.calibration.sweeps).

Cost: 2 operating points x 4 sparks on the virtual bench plus a 5 x 5 (BDUR10-90, m) grid per runnable
point, all with doe.QUICK_SOLVER (1 deg step): the bench and the identification use the same solver, so
the comparison measures the identification, not solver differences (~170 simulations, ~20 s warm).  The
bench is read with eight noise seeds (the grid is simulated once).
"""

import numpy as np
import pandas as pd
import pytest

from engine_model import doe
from engine_model import priors
from engine_model.bench.burnlaw import BurnLaw
from engine_model.calibration.identify import identification_plan, identify
from engine_model.contracts import SWEEP_COLUMNS
from engine_model.calibration.sweeps import identify_sweeps, measured_mbt, sweep_plan
from engine_model.bench.virtual import VirtualBench

from conftest import SIM_WORKERS

OPS = pd.DataFrame({"throttle_pct": [20.0, 60.0], "speed_rpm": [9000.0, 12000.0]})
OFFSETS = (-15.0, -10.0, -5.0, 0.0)


NOISE_SEEDS = tuple(range(8))


@pytest.fixture(scope="module")
def sweep_data():
    law = BurnLaw()
    plan = sweep_plan(OPS, OFFSETS)
    meas = VirtualBench(law=law, solver=doe.QUICK_SOLVER, seed=0).measure(plan)   # noise on (default)
    ok = meas[meas["status"] == "ok"].reset_index(drop=True)
    res = doe.quick_evaluate(identification_plan(ok, None, 5, 5), workers=SIM_WORKERS)
    res["bench_point_id"] = identification_plan(ok, None, 5, 5)["bench_point_id"].to_numpy()
    return law, plan, meas, ok, res


@pytest.fixture(scope="module")
def seeded_errors(sweep_data):
    """Joint and per-point identification errors against the hidden law, per noise seed of the bench."""
    law, plan, _meas, ok0, res = sweep_data
    rows = []
    engine, runs = VirtualBench(law=law, solver=doe.QUICK_SOLVER), {}

    def simulated_once(pts):
        # the truth engine's rows do not depend on the noise seed: simulate them once, every seed reads them
        key = int(pd.util.hash_pandas_object(pts, index=False).sum())
        if key not in runs:
            runs[key] = engine.default_evaluate(pts)
        return runs[key].copy()

    for seed in NOISE_SEEDS:
        meas = VirtualBench(law=law, solver=doe.QUICK_SOLVER, seed=seed).measure(plan, evaluate=simulated_once)
        ok = meas[meas["status"] == "ok"].reset_index(drop=True)
        assert list(ok["point_id"]) == list(ok0["point_id"])      # noise does not change which points run
        joint = identify_sweeps(meas, res, eta_trans=0.95)
        truth = law.predict(joint[["throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda"]])
        for k in range(len(joint)):
            t = truth["bdur_10_90_deg"].iloc[k]
            rows.append({"seed": seed, "kind": "joint", "eb": joint["bdur_10_90_deg"].iloc[k] - t,
                         "em": joint["wiebe_m"].iloc[k] - truth["wiebe_m"].iloc[k],
                         "covered": bool(joint["bdur_10_90_deg_lo"].iloc[k] - 0.1 <= t
                                         <= joint["bdur_10_90_deg_hi"].iloc[k] + 0.1)})
        per = identify(ok.assign(at_mbt=False), res, eta_trans=0.95, surface="spline").table
        pt = law.predict(per[["throttle_pct", "speed_rpm", "spark_deg_btdc"]].assign(
            **{"lambda": ok["lambda"].to_numpy()}))
        for k in range(len(per)):
            rows.append({"seed": seed, "kind": "per_point", "eb": per["bdur_10_90_deg"].iloc[k]
                         - pt["bdur_10_90_deg"].iloc[k], "em": per["wiebe_m"].iloc[k] - pt["wiebe_m"].iloc[k],
                         "covered": np.nan})
    return pd.DataFrame(rows)


def test_sweep_plan_layout():
    plan = sweep_plan(OPS, OFFSETS)
    assert len(plan) == 8 and set(plan["op_id"]) == {"op01", "op02"}
    # bench order: throttle, speed, spark ascending; run_order 1..n
    assert plan["run_order"].tolist() == list(range(1, 9))
    keys = plan[["throttle_pct", "speed_rpm", "spark_deg_btdc"]].to_numpy()
    assert all(tuple(a) <= tuple(b) for a, b in zip(keys[:-1], keys[1:]))
    for oid, g in plan.groupby("op_id"):
        r = OPS.iloc[int(oid[2:]) - 1]
        s0 = priors.spark_estimate(r.speed_rpm, r.throttle_pct)
        np.testing.assert_allclose(g["spark_deg_btdc"] - s0, OFFSETS)
        assert g["point_id"].tolist() == [f"{oid}-s{k}" for k in range(4)]
        np.testing.assert_allclose(g["lambda"], priors.lambda_target(r.throttle_pct))
    with pytest.raises(ValueError, match="distinct spark offsets"):
        sweep_plan(OPS, (0.0, 5.0))
    with pytest.raises(ValueError, match="row 1, column 'speed_rpm'"):
        sweep_plan(OPS.assign(speed_rpm=[9000.0, np.nan]), OFFSETS)


def test_measured_mbt_bracketing():
    s = pd.DataFrame({"spark_deg_btdc": [20.0, 25.0, 30.0, 35.0], "status": ["ok"] * 4,
                      "brake_torque_nm": [40.0, 44.0, 45.0, 44.0]})
    mbt, why = measured_mbt(s)
    # parabola through (25, 44), (30, 45), (35, 44): vertex at 30
    assert why == "ok" and mbt == pytest.approx(30.0)
    s2 = s.assign(status=["ok", "ok", "ok", "knock_abort"], brake_torque_nm=[40.0, 44.0, 45.0, np.nan])
    mbt, why = measured_mbt(s2)
    assert np.isnan(mbt) and why.startswith("knock-limited")


@pytest.mark.slow   # the virtual-bench sweep fixture (~35 s with the 1D gas exchange)
def test_joint_result_table(sweep_data):
    law, plan, meas, ok, res = sweep_data
    assert (meas.groupby("op_id")["status"].apply(lambda s: (s == "ok").sum()) >= 3).all(), \
        "test points chosen to run >= 3 sparks each on the virtual bench"
    joint = identify_sweeps(meas, res, eta_trans=0.95)
    assert list(joint.columns[:len(SWEEP_COLUMNS)]) == list(SWEEP_COLUMNS) and len(joint) == 2
    assert (joint["bdur_10_90_deg_lo"] <= joint["bdur_10_90_deg"]).all()
    assert (joint["bdur_10_90_deg"] <= joint["bdur_10_90_deg_hi"]).all()


@pytest.mark.slow
def test_joint_beats_per_point_against_hidden_law(seeded_errors):
    """Pooled over 8 noise seeds (16 sweeps).  Lumped gas exchange (20 seeds measured, host and generic builds
    identical): joint RMSE 2.65-2.71 deg / 0.87-0.89 per 8-seed block against per-point 3.4-5.3 deg / 0.98-1.24.
    1D gas exchange (seeds 0-7): joint 3.29 deg against per-point 4.11 deg; the joint error is now mostly a
    bias per sweep (-3 deg at 20 %/9000 rpm, +3 to +6 deg at 60 %/12000 rpm) that the noise seeds do not
    average away, so the joint's advantage is asserted as 10 %, not the 20 % of the lumped model.

    The 95 % regions cover the truth in 78 % of 40 sweeps, not 95 %: they are optimistic (the law moves the
    burn along the sweep by more than the spark-slope profile captures on a 5 x 5 grid).  Asserted: at least
    half covered (with 16 sweeps at 78 %, fewer has a probability of ~0.3 %).
    """
    d = seeded_errors
    rmse = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    j, p = d[d["kind"] == "joint"], d[d["kind"] == "per_point"]
    assert rmse(j["eb"]) < 0.9 * rmse(p["eb"]), (rmse(j["eb"]), rmse(p["eb"]))
    assert rmse(j["em"]) <= rmse(p["em"]) + 0.1, (rmse(j["em"]), rmse(p["em"]))
    assert rmse(j["eb"]) <= 3.5 and rmse(j["em"]) <= 1.1, (rmse(j["eb"]), rmse(j["em"]))
    assert j["covered"].astype(bool).mean() >= 0.5, j


@pytest.mark.slow   # the virtual-bench sweep fixture (~35 s with the 1D gas exchange)
def test_plan_rows_mismatch_is_a_clear_error(sweep_data):
    law, plan, meas, ok, res = sweep_data
    missing = str(ok["point_id"].iloc[0])
    with pytest.raises(ValueError, match=rf"plan/rows mismatch.*{missing}"):
        identify_sweeps(meas, res[res["bench_point_id"] != missing])
    with pytest.raises(ValueError, match="lack column.*op_id"):
        identify_sweeps(meas.drop(columns=["op_id"]), res)


def test_choose_operating_points_respects_bounds_and_screen():
    from engine_model.calibration.sweeps import choose_operating_points
    b = {"throttle_pct": (20.0, 100.0), "speed_rpm": (6000.0, 12000.0)}
    ops = choose_operating_points(6, bounds=b)
    assert len(ops) == 6 and not ops.duplicated().any()
    assert ops["throttle_pct"].between(*b["throttle_pct"]).all() and ops["speed_rpm"].between(*b["speed_rpm"]).all()
    seen = []

    def screen(p):
        seen.append(set(p.columns))
        return (p["throttle_pct"] >= 40.0).to_numpy()

    ops = choose_operating_points(6, feasible=screen, bounds=b)
    assert (ops["throttle_pct"] >= 40.0).all()
    assert {"speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda"} <= seen[0]
    with pytest.raises(ValueError, match=">= 6"):
        choose_operating_points(4)
