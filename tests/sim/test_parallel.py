"""Rows shared among processes give the same table as one process, row for row."""

from __future__ import annotations

import pandas as pd

from engine_model import SolverSettings, default_spec
from engine_model.bench.knock_truth import KnockTruth, simulate_with_truth
from engine_model.sim import simulate
from engine_model.sim.simulate import MIN_ROWS_TO_SPLIT, chain_starts

SOLVER = SolverSettings(step_deg=1.0)


def _plan() -> pd.DataFrame:
    # 4 operating points x 4 sparks, one with a spec override: 4 warm-start chains of 4 rows
    rows, cd0 = [], default_spec().intake.restrictor_cd
    for n, t, cd in ((7000.0, 100.0, cd0), (9000.0, 100.0, cd0), (9000.0, 100.0, 0.9 * cd0), (11000.0, 60.0, cd0)):
        for s in (30.0, 36.0, 42.0, 48.0):
            rows.append({"point_id": f"{n:g}-{t:g}-{cd:.3f}-{s:g}", "speed_rpm": n, "throttle_pct": t,
                         "spark_deg_btdc": s, "lambda": 0.9, "bdur_10_90_deg": 26.0, "wiebe_m": 3.0,
                         "spec.intake.restrictor_cd": cd})
    return pd.DataFrame(rows)


def test_chains_start_where_the_gas_state_changes():
    assert chain_starts(_plan().assign(p_amb_pa=101325.0, t_amb_k=298.0, wiebe_a=5.0)) == [0, 4, 8, 12]


def test_two_processes_give_the_one_process_table():
    spec, plan = default_spec(), _plan()
    assert len(plan) >= MIN_ROWS_TO_SPLIT
    done = []
    one = simulate(spec, plan, SOLVER)
    two = simulate(spec, plan, SOLVER, workers=2, progress=lambda d, n: done.append(d))
    cols = [c for c in one.columns if c != "sim_time_s"]
    pd.testing.assert_frame_equal(one[cols], two[cols])
    # it was shared: progress comes per chain of 4 rows, not per row
    assert sorted(done) == [4, 8, 12, 16], done


def test_knock_truth_rows_in_two_processes_are_the_same():
    spec, plan = default_spec(), _plan().drop(columns=["spec.intake.restrictor_cd"])
    one = simulate_with_truth(spec, plan, KnockTruth(), SOLVER)
    two = simulate_with_truth(spec, plan, KnockTruth(), SOLVER, workers=2)
    cols = [c for c in one.columns if c != "sim_time_s"]
    pd.testing.assert_frame_equal(one[cols], two[cols])
