"""Learning curve: plans, cheap identification, feasibility lookup, the curve itself and its plot.

The curve test uses the polynomial family only and two sizes, so it runs in a
few seconds; the full measurement (both families, five designs, seven sizes,
five seeds, feasibility from the virtual bench) is benchmarks/learning_curve.py.
"""

import numpy as np
import pandas as pd
import pytest

from engine_model import priors
from engine_model.globalmodel import learning as L
from engine_model.bench.burnlaw import BurnLaw

LAW = BurnLaw()


@pytest.mark.parametrize("design", ["grid", "d_optimal", "sobol", "lhs"])
def test_design_plans_cover_the_space_around_mbt(design):
    p = L.design_plan(design, 24, seed=0)
    assert p["point_id"].is_unique
    off = p["spark_offset_deg"]
    assert off.between(-20, 5).all() and off.max() - off.min() > 15
    assert p["throttle_pct"].between(5, 100).all() and p["speed_rpm"].between(*L.BOUNDS["speed_rpm"]).all()
    est = priors.spark_estimate(p["speed_rpm"].to_numpy(), p["throttle_pct"].to_numpy())
    np.testing.assert_allclose(p["spark_deg_btdc"] - est, off)
    np.testing.assert_allclose(p["lambda"], priors.lambda_target(p["throttle_pct"].to_numpy()))
    if design == "grid":
        kt, kn, ks = L.grid_levels(24)
        assert len(p) == kt * kn * ks and p["throttle_pct"].nunique() == kt
    else:
        assert len(p) == 24


def test_grid_levels_and_unknown_design():
    assert np.prod(L.grid_levels(64)) in range(48, 81)
    with pytest.raises(ValueError, match="unknown design"):
        L.design_plan("taguchi", 16)
    with pytest.raises(ValueError, match="needs a feasible"):
        L.design_plan("d_optimal_feasible", 16)


def test_noisy_truth_statistics_and_masking():
    p = L.design_plan("sobol", 1024, seed=3)
    ident = L.noisy_truth(LAW, 1.5, 0.4, seed=1)(p)
    y = LAW.predict(p)
    eb, em = ident["bdur_10_90_deg"] - y["bdur_10_90_deg"], ident["wiebe_m"] - y["wiebe_m"]
    # 1024 draws: a sample std is within +-9 % (4 sigma) of the true one
    assert abs(eb.std() / 1.5 - 1) < 0.09 and abs(em.std() / 0.4 - 1) < 0.09
    pd.testing.assert_frame_equal(ident, L.noisy_truth(LAW, 1.5, 0.4, seed=1)(p))
    feas = lambda pts: pts["throttle_pct"].to_numpy() > 30  # noqa: E731
    masked = L.noisy_truth(LAW, 1.5, 0.4, seed=1, feasible=feas)(p)
    assert masked.loc[p["throttle_pct"] <= 30, "bdur_10_90_deg"].isna().all()
    assert masked.loc[p["throttle_pct"] > 30, "bdur_10_90_deg"].notna().all()


def test_phasing_noisy_truth_has_the_measured_error_structure():
    from engine_model.globalmodel.mapmodel import ca50_offset_deg
    p = L.design_plan("sobol", 1024, seed=3)
    ident = L.phasing_noisy_truth(LAW, seed=1)(p)
    y = LAW.predict(p)
    off = ca50_offset_deg(y["bdur_10_90_deg"].to_numpy(), y["wiebe_m"].to_numpy())
    eo, em = ident["ca50_offset_deg"] - off, ident["wiebe_m"] - y["wiebe_m"]
    eb = ident["bdur_10_90_deg"] - y["bdur_10_90_deg"]
    # the drawn noise: the measured sigmas within +-9 % (4 sigma of a 1024-draw std) and correlation within 0.05
    assert abs(eo.std() / L.IDENT_SIGMA_CA50_OFFSET_DEG - 1) < 0.09 and abs(em.std() / L.IDENT_SIGMA_M - 1) < 0.09
    assert abs(np.corrcoef(eo, em)[0, 1] - L.IDENT_RHO_CA50_OFFSET_M) < 0.05
    # BDUR10-90 is the burn of the noisy (offset, m): the reported columns are one consistent Wiebe burn
    np.testing.assert_allclose(ca50_offset_deg(ident["bdur_10_90_deg"].to_numpy(), ident["wiebe_m"].to_numpy()),
                               ident["ca50_offset_deg"], rtol=1e-9)
    # and the structure the identification showed follows: BDUR10-90 and m errors strongly anti-correlated,
    # BDUR10-90 off by ~2.8 deg (measured 2.81 RMS over 16 sweeps, -0.99 correlation; here 1024 draws give
    # 3.1 / -0.97, the law's sensitivity varying over the map)
    assert np.corrcoef(eb, em)[0, 1] < -0.9 and 2.0 < eb.std() < 4.0
    pd.testing.assert_frame_equal(ident, L.phasing_noisy_truth(LAW, seed=1)(p))
    masked = L.phasing_noisy_truth(LAW, seed=1, feasible=lambda pts: pts["throttle_pct"].to_numpy() > 30)(p)
    assert masked.loc[p["throttle_pct"] <= 30, ["bdur_10_90_deg", "wiebe_m"]].isna().all().all()
    with pytest.raises(ValueError, match="rho in"):
        L.phasing_noisy_truth(LAW, rho=1.5)


def test_holdout_grid_scores_the_whole_design_space():
    # the hold-out grid must reach the DOE's lowest and highest speed: a band the DOE covers but the grid
    # leaves out is never scored (the 2000-3000 rpm band was, while both started at 3000 rpm)
    g = L.holdout_grid()
    lo, hi = L.BOUNDS["speed_rpm"]
    assert g["speed_rpm"].min() == lo and g["speed_rpm"].max() == hi
    tl, th = L.BOUNDS["throttle_pct"]
    assert g["throttle_pct"].min() == tl and g["throttle_pct"].max() == th


def test_nearest_feasible_lookup():
    grid = L.holdout_grid()
    ok = (grid["throttle_pct"] >= 20).to_numpy()
    feas = L.nearest_feasible(grid, ok)
    q = pd.DataFrame({"throttle_pct": [6.0, 90.0], "speed_rpm": [5000.0, 5000.0], "spark_offset_deg": [0.0, -3.0]})
    assert list(feas(q)) == [False, True]
    cand = L.design_plan("d_optimal_feasible", 16, feasible=feas)
    assert (cand["throttle_pct"] >= 20 - 1e-9).all()  # picked from feasible candidates only


@pytest.mark.slow
def test_learning_curve_improves_with_points_and_compares_designs(tmp_path):
    curve = L.learning_curve(None, LAW, sizes=(16, 64), designs=("grid", "d_optimal", "sobol"), seeds=(0, 1),
                             families=("poly",), identify_seeded=lambda s: L.noisy_truth(LAW, 1.0, 0.3, seed=s))
    assert len(curve) == 3 * 2 * 2 and curve.attrs["n_test"] == len(L.holdout_grid())
    s = L.summarise(curve)
    for design, g in s.groupby("design"):
        g = g.sort_values("n_target")
        # four times the points: the error must fall for every design (noise 1 deg, 16 -> ~60 points)
        assert g["rmse_bdur_10_90_deg_mean"].iloc[1] < g["rmse_bdur_10_90_deg_mean"].iloc[0], design
    reach = L.points_to_reach(curve, {"bdur_10_90_deg": 2.0, "wiebe_m": 0.5})
    assert set(reach["design"]) == {"grid", "d_optimal", "sobol"}
    assert reach["n_points"].notna().any()
    png = L.plot_learning_curve(curve, tmp_path / "lc.png", target={"bdur_10_90_deg": 1.0, "wiebe_m": 0.3})
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_learning_curve_reports_failed_fits():
    # everything infeasible except a sliver: too few identified points -> NaN errors with a note, not a crash
    feas = lambda pts: pts["throttle_pct"].to_numpy() > 99  # noqa: E731
    curve = L.learning_curve(None, LAW, sizes=(16,), designs=("sobol",), seeds=(0,), families=("poly",),
                             identify_seeded=lambda s: L.noisy_truth(LAW, seed=s, feasible=feas))
    assert np.isnan(curve["rmse_bdur_10_90_deg"].iloc[0]) and "need >= 6" in curve["note"].iloc[0]


@pytest.mark.slow
def test_bench_identify_chain_on_two_points():
    # the real chain (virtual bench -> Wiebe identification) on one runnable and one knock-aborted point, with a
    # coarse 5 x 5 identification grid and the quick solver to keep it to ~30 simulations: the test checks the
    # wiring (columns, NaN for the aborted point, statuses), not the identification's accuracy.
    from engine_model.bench import NoiseModel, VirtualBench
    from engine_model.doe import QUICK_SOLVER

    bench = VirtualBench(noise=NoiseModel.none(), solver=QUICK_SOLVER)
    plan = pd.DataFrame({"point_id": ["wot9k", "wot4k"], "throttle_pct": 100.0, "speed_rpm": [9000.0, 4000.0],
                         "spark_deg_btdc": [45.0, 40.0], "lambda": 0.9})
    out = L.bench_identify(bench, n_bdur=5, n_m=5)(plan)
    assert list(out["point_id"]) == ["wot9k", "wot4k"]
    assert list(out["bench_status"]) == ["ok", "knock_abort"]
    assert np.isnan(out["bdur_10_90_deg"].iloc[1]) and out["identify_status"].iloc[1] == "not run: knock_abort"
    assert out["identify_status"].iloc[0] != ""
    if np.isfinite(out["bdur_10_90_deg"].iloc[0]):
        assert 20 <= out["bdur_10_90_deg"].iloc[0] <= 50 and out["bdur_10_90_deg_std"].iloc[0] > 0


def test_bench_feasibility_runs_each_point_once():
    calls = []

    def ev(points):
        calls.append(len(points))
        out = points.copy()
        for col, v in (("brake_torque_nm", 40.0), ("air_mass_flow_kg_h", 100.0), ("fuel_mass_flow_kg_h", 8.0),
                       ("exhaust_temp_k", 1100.0), ("converged", True), ("status", "ok"), ("bmep_bar", 8.0)):
            out[col] = v
        out["knock_index"] = np.where(out["speed_rpm"] < 5000, 1.5, 0.3)  # knock below 5000 rpm
        return out

    from engine_model.bench import VirtualBench

    feas = L.bench_feasibility(VirtualBench(), evaluate=ev)
    p = pd.DataFrame({"throttle_pct": [50.0, 50.0], "speed_rpm": [4000.0, 9000.0], "spark_deg_btdc": 30.0,
                      "lambda": 1.0})
    assert list(feas(p)) == [False, True]
    assert list(feas(pd.concat([p, p.iloc[:1]]))) == [False, True, False]
    assert calls == [2]  # the second call was served from the cache
