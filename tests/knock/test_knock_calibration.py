"""Knock calibration: the posterior of the delay multiplier, the evidence per bench point, the onset-sweep plan,
and the table honouring the bench's clean MBT sparks."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from engine_model import default_spec, knock
from engine_model.tables import EcuGrid, MapSettings, PriorModel, build_maps


def _evidence(y: np.ndarray, flags: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame({"point_id": [f"p{i}" for i in range(len(y))], "ln_ki_cycle_m1": y, "knock": flags,
                         "ki_cycle_m1": np.exp(y)})


@pytest.mark.parametrize("seed", [11, 12, 13, 14, 15])
def test_two_sided_evidence_recovers_the_multiplier(seed):
    """30 onset observations around a true multiplier 1.3 with a 5 % scatter: median within 10 %, the 68 % band
    holds the truth, and the table value sits on the knock-prone side of the median."""
    rng = np.random.default_rng(seed)
    y = rng.uniform(-0.6, 0.9, 30)
    flags = y + rng.normal(0.0, 0.05, 30) > math.log(1.3)
    kc = knock.calibrate_knock(_evidence(y, flags))
    assert kc.kind == "two-sided"
    assert abs(math.log(kc.multiplier_median / 1.3)) < 0.1
    assert kc.multiplier_lo68 <= 1.3 * 1.05 and kc.multiplier_hi68 >= 1.3 / 1.05
    assert kc.multiplier_table < kc.multiplier_median


def test_knock_free_points_give_a_bound_and_the_table_respects_it():
    y = np.log(np.array([0.89, 0.82, 0.79, 0.74, 0.70, 0.66, 0.66]))     # Table 2 at m = 1 (fastest cycles)
    kc = knock.calibrate_knock(_evidence(y, np.zeros(7, bool)))
    assert kc.kind == "lower bound" and kc.lower_bound == pytest.approx(0.89)
    assert np.all(np.exp(y) / kc.multiplier_table < 1.0)
    assert "lower bound" in kc.text() and "knock-sweeps" in kc.text()
    # a bound far above the prior's bulk still holds
    kc2 = knock.calibrate_knock(_evidence(np.log(np.array([3.0, 2.0])), np.zeros(2, bool)))
    assert kc2.multiplier_table > 3.0


def test_point_evidence_reads_the_sweep():
    """Knock index exp(0.05 (s - 60)) and a torque parabola peaking 1.2 deg after the bench spark: the evidence
    has the exact knock index with the 3 deg advance (log-linear) and the MBT."""
    ident = pd.DataFrame({"point_id": ["a", "b"], "speed_rpm": [8000.0, 10000.0], "throttle_pct": 100.0,
                          "spark_deg_btdc": [49.4, 49.5], "lambda": 0.9, "bdur_10_90_deg": [50.0, 44.6],
                          "wiebe_m": [2.4, 2.8]})
    plan = knock.bench_sweep_plan(ident, overrides={"exhaust.runner_length_m": 0.216})
    assert len(plan) == 2 * len(knock.calibrate.SWEEP_OFFSETS_DEG)
    assert (plan["spec.exhaust.runner_length_m"] == 0.216).all()
    s = plan["spark_deg_btdc"].to_numpy(float)
    s0 = plan["knock_point_id"].map({"a": 49.4, "b": 49.5}).to_numpy(float)
    res = pd.DataFrame({"knock_index": np.exp(0.05 * (s - 60.0)) / 2.0,           # ran with multiplier 2
                        "brake_torque_nm": 45.0 - 0.01 * (s - s0 - 1.2) ** 2})
    bench = ident.assign(knock=False, at_mbt=True)
    ev = knock.point_evidence(bench, plan, res, multiplier_used=2.0, advance_deg=3.0)
    assert ev["ki_cycle_m1"].to_numpy() == pytest.approx(np.exp(0.05 * (np.array([49.4, 49.5]) + 3.0 - 60.0)))
    assert ev["mbt_minus_bench_deg"].to_numpy() == pytest.approx([1.2, 1.2], abs=1e-6)
    assert ev["knock_slope_per_deg"].to_numpy() == pytest.approx([0.05, 0.05])


def test_knock_sweep_plan_spreads_sweeps_and_steps_in_the_advance_direction():
    plan = knock.knock_sweep_plan(lambda n, t: 20.0 + n / 500.0, speeds=np.arange(3000, 13001, 1000),
                                  throttles=[60, 80, 100], max_points=40)
    assert len(plan) <= 40
    sweeps = plan.groupby("sweep_id")
    assert sweeps.ngroups == 5
    first = plan[plan["sweep_id"] == "ks01"]
    assert (first["speed_rpm"].iloc[0], first["throttle_pct"].iloc[0]) == (3000, 100)   # most knock-prone first
    for _, g in sweeps:
        s = g.sort_values("step")["spark_deg_btdc"].to_numpy()
        assert np.allclose(np.diff(s), 3.0)
        n = g["speed_rpm"].iloc[0]
        assert s[0] == pytest.approx(20.0 + n / 500.0 - 12.0)
    sites = plan.drop_duplicates("sweep_id")[["speed_rpm", "throttle_pct"]]
    assert sites["speed_rpm"].min() == 3000 and sites["speed_rpm"].max() == 13000
    assert plan["knock"].isna().all()
    with pytest.raises(ValueError, match="do not hold one sweep"):
        knock.knock_sweep_plan(lambda n, t: 30.0, [5000], [100], max_points=3)


def _engine(plan):
    """Torque parabola peaking at 30 deg; knock index exp(0.08 (s - 33)): knock-limited at every cell."""
    s = plan["spark_deg_btdc"].to_numpy(float)
    out = plan.copy()
    out["brake_torque_nm"] = 40.0 - 0.02 * (s - 30.0) ** 2
    out["knock_index"] = np.exp(0.08 * (s - 33.0))
    out["bmep_bar"] = 8.0
    out["air_mass_flow_kg_h"] = 100.0
    out["status"] = "ok"
    return out


def test_table_honours_the_bench_clean_mbt_spark():
    """A cell the bench ran clean at MBT takes the bench's spark, though the model puts the border 3 deg lower;
    the other cells stay knock-limited; the consistency table reports the cell exactly."""
    grid = EcuGrid((50, 100), (6000, 9000, 12000))
    bench = pd.DataFrame({"point_id": ["b1", "b2"], "speed_rpm": [9000.0, 10500.0], "throttle_pct": [100.0, 100.0],
                          "spark_deg_btdc": [33.5, 33.0], "at_mbt": True, "knock": False})
    st = MapSettings(max_second_diff_deg=100.0, cycle_advance_deg=3.0, knock_uncertainty_z=0.0)
    res = build_maps(default_spec(), PriorModel(), grid=grid, evaluate=_engine, settings=st, bench=bench)
    c = res.cells.set_index(["throttle_pct", "speed_rpm"])
    assert c.loc[(100, 9000), "spark_deg_btdc"] == pytest.approx(33.5)
    assert c.loc[(100, 9000), "spark_source"] == "bench" and c.loc[(100, 9000), "limited_by"] == "bench"
    for n in (6000, 12000):                              # border 33 - 3 (fastest cycles) = 30: knock-limited
        assert c.loc[(100, n), "spark_deg_btdc"] <= 30.0 + 1e-9 and c.loc[(100, n), "limited_by"] == "knock"
    ev = pd.DataFrame({"point_id": ["b1"], "speed_rpm": [9000.0], "throttle_pct": [100.0],
                       "spark_deg_btdc": [33.5], "at_mbt": [True], "knock": [False], "ki_m1": [0.5],
                       "ki_cycle_m1": [0.6], "mbt_model_deg_btdc": [32.0]})
    tab = knock.bench_consistency(ev, res.cells, multiplier=1.2)
    assert tab["table_minus_bench_deg"].iloc[0] == pytest.approx(0.0)
    assert tab["knock_index_fastest_cycles"].iloc[0] == pytest.approx(0.5)
    summ = knock.consistency_summary(tab)
    assert summ["mbt_within_2deg"] == "1 of 1" and summ["table_within_3deg"] == "1 of 1"


def test_trend_reference_at_a_pinned_wot_cell_carries_the_bench_offset():
    """10000 rpm: the bench pinned WOT at 49.5 deg where the model's MBT is 53.3.  Part load at 50.4 deg is a drop
    against the model's WOT MBT when the table carried no offset, and none when it carried the bench's -3.8."""
    cells = pd.DataFrame({"speed_rpm": 10000.0, "throttle_pct": [60.0, 100.0], "spark_deg_btdc": [50.4, 49.5],
                          "spark_mbt_deg_btdc": [54.2, 53.3], "limited_by": ["mbt", "bench"],
                          "infeasible_reason": ["", ""], "plenum_pressure_bar": [0.9, 0.98]})
    drops = knock.table_trends(cells)["part_load_drops"]
    assert [d["throttle_pct"] for d in drops] == [60.0] and drops[0]["wot_reference"] == pytest.approx(53.3)
    carried = cells.assign(bench_mbt_offset_deg=[-3.8, -3.8])
    assert knock.table_trends(carried)["part_load_drops"] == []
    low = cells.assign(spark_deg_btdc=[47.0, 49.5], bench_mbt_offset_deg=[-3.8, -3.8])    # 2.5 deg below 49.5
    assert [d["throttle_pct"] for d in knock.table_trends(low)["part_load_drops"]] == [60.0]


def test_light_load_knock_is_read_on_the_charge_not_the_throttle():
    """A knock-limited cell at 10 % throttle is light-load knock when it holds under half of WOT's charge at its
    speed, not when the butterfly already passes most of it; without a WOT cell to compare, it counts as light."""
    cells = pd.DataFrame({"speed_rpm": [2000.0, 2000.0, 3000.0, 3000.0, 4000.0],
                          "throttle_pct": [10.0, 100.0, 10.0, 100.0, 20.0],
                          "vol_eff": [0.30, 0.75, 0.60, 0.74, 0.70], "plenum_pressure_bar": [0.6, 1.0, 0.9, 1.0, 0.95],
                          "spark_deg_btdc": [10.0, 5.0, 12.0, 15.0, 20.0],
                          "spark_mbt_deg_btdc": [14.0, 9.0, 16.0, 15.0, 24.0],
                          "limited_by": ["knock", "knock", "knock", "mbt", "knock"], "infeasible_reason": ""})
    t = knock.table_trends(cells)
    assert [(d["speed_rpm"], d["throttle_pct"]) for d in t["small_throttle_knock"]] == \
        [(2000.0, 10.0), (3000.0, 10.0), (4000.0, 20.0)]
    assert t["small_throttle_knock"][0]["charge_vs_wot"] == pytest.approx(0.4)
    assert [(d["speed_rpm"], d["charge_vs_wot"]) for d in t["light_load_knock"]] == [(2000.0, 0.4), (4000.0, None)]
    assert "knock_evidence" not in t
    bench = pd.DataFrame({"speed_rpm": [2500.0, 3000.0], "throttle_pct": [100.0, 60.0]})
    ev = knock.table_trends(cells, bench=bench)["knock_evidence"]
    assert ev == {"points": 2, "speed_rpm": [2500.0, 3000.0], "throttle_pct": [60.0, 100.0], "knock_cells": 4,
                  "knock_cells_outside_speeds": 3, "outside_speeds_rpm": [2000.0, 4000.0]}


def test_knock_at_full_charge_on_a_leaner_lambda_than_wot_is_flagged():
    """3000 rpm: the 50 % cell holds 0.95 of WOT's charge and is knock-limited at lambda 1.0 where WOT runs 0.9:
    flagged.  Not flagged: the same cell at WOT's lambda, at 0.8 of the charge, or limited by MBT; nor the WOT
    cell itself; nor anything when the cells carry no lambda."""
    def cells(lam50=1.0, ve50=0.76, limit50="knock"):
        return pd.DataFrame({"speed_rpm": 3000.0, "throttle_pct": [20.0, 50.0, 100.0],
                             "vol_eff": [0.40, ve50, 0.80], "plenum_pressure_bar": [0.5, 0.99, 1.0],
                             "spark_deg_btdc": [20.0, 9.0, 15.0], "spark_mbt_deg_btdc": [20.0, 18.0, 15.0],
                             "limited_by": ["mbt", limit50, "knock"], "infeasible_reason": "",
                             "lambda": [1.0, lam50, 0.9]})
    flagged = knock.table_trends(cells())["full_charge_lean_knock"]
    assert [(d["speed_rpm"], d["throttle_pct"]) for d in flagged] == [(3000.0, 50.0)]
    assert flagged[0]["lambda"] == 1.0 and flagged[0]["wot_lambda"] == 0.9
    assert flagged[0]["charge_vs_wot"] == pytest.approx(0.95)
    assert knock.table_trends(cells(lam50=0.9))["full_charge_lean_knock"] == []
    assert knock.table_trends(cells(ve50=0.64))["full_charge_lean_knock"] == []     # 0.8 of WOT's charge
    assert knock.table_trends(cells(limit50="mbt"))["full_charge_lean_knock"] == []
    assert knock.table_trends(cells().drop(columns="lambda"))["full_charge_lean_knock"] == []
