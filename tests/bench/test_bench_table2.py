"""The uncalibrated model against the real bench data (paper Table 2, WOT, lambda 0.9).

Simulated at the measured spark with the paper's combustion answer
(BDUR10-90 = 24 deg, m = 6.4); measured torque is behind the gearbox, so it is
compared at the crank as measured / eta_trans with eta_trans = 0.95 (paper).
"""

import pytest

from engine_model import default_spec

from engine_model.sim import simulate
from engine_model.bench import load_bench

ETA_TRANS = 0.95


@pytest.fixture(scope="module")
def table2():
    bench = load_bench()
    pts = bench[["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda"]].copy()
    pts["bdur_10_90_deg"] = 24.0
    pts["wiebe_m"] = 6.4
    return bench, simulate(default_spec(), pts)


def test_all_points_converge(table2):
    _, sim = table2
    assert sim["converged"].all(), sim.loc[~sim["converged"], ["point_id", "status"]]


@pytest.mark.parametrize("col,lo,hi,why", [
    ("vol_eff", 0.5, 1.15, "restricted NA 4-valve engine at WOT: 0.5 (badly tuned) .. 1.15 (strong ram)"),
    ("bmep_bar", 6.0, 14.5, "NA gasoline WOT: 6 .. 14.5 bar"),
    ("bsfc_g_kwh", 220.0, 420.0, "rich (lambda 0.9) SI engine at the crank: 220 .. 420 g/kWh"),
    ("exhaust_temp_k", 1000.0, 1350.0, "port exhaust gas at WOT, high speed: 1000 .. 1350 K"),
    ("pmax_bar", 45.0, 110.0, "CR 12.8 at WOT near MBT: 45 .. 110 bar"),
    ("pmax_deg_atdc", 8.0, 25.0, "peak pressure 8 .. 25 deg ATDC with CA50 near 9 deg"),
    ("residual_fraction", 0.01, 0.18, "4-valve engine with 63 deg overlap at WOT: 1 .. 18 %"),
    ("heat_loss_fraction", 0.05, 0.25, "wall heat at high speed WOT: 5 .. 25 % of fuel energy"),
    ("fmep_bar", 1.0, 3.5, "high-revving 600 cc four: 1 .. 3.5 bar"),
])
def test_outputs_in_physically_plausible_ranges(table2, col, lo, hi, why):
    _, sim = table2
    vals = sim[col]
    assert ((vals >= lo) & (vals <= hi)).all(), f"{col} outside [{lo}, {hi}] ({why}): {vals.round(3).tolist()}"


def test_ca50_of_papers_answer_is_in_the_mbt_window(table2):
    _, sim = table2
    row = sim.loc[sim["speed_rpm"] == 9000].iloc[0]
    assert 8.0 <= row["ca50_deg_atdc"] <= 10.0


@pytest.mark.xfail(strict=True, reason=(
    "Known gap: before calibration (runner lengths and diffuser recovery assumed, the paper does not give the "
    "manifolds) the 1D model breathes up to 17 % more than the bench at 9500-11000 rpm (+1 % at 8000 rpm): "
    "the assumed 0.45 m primaries and 0.22 m intake runners tune the engine near 10000 rpm where the bench "
    "is flat near VE 0.85.  The airflow match removes it (docs/sections/calibration.md).  Strict: passing "
    "would fail this mark and force it to be removed."))
def test_airflow_and_torque_close_to_bench_before_calibration(table2):
    bench, sim = table2
    air_err = (sim["air_mass_flow_kg_h"] / bench["air_mass_flow_kg_h"] - 1).abs()
    tq_err = (sim["brake_torque_nm"] / (bench["brake_torque_nm"] / ETA_TRANS) - 1).abs()
    assert (air_err <= 0.10).all(), air_err.round(3).tolist()
    assert (tq_err <= 0.15).all(), tq_err.round(3).tolist()
