"""The airflow parameter screen: linear algebra on known Jacobians, the data floor on known curves.

No simulation here (the screen's simulations are a plain batch through ``match_airflow``'s
problem class, tested in test_calibrate_airflow.py).
"""

import itertools

import numpy as np
import pandas as pd
import pytest

from engine_model.calibration.airflow import Parameter
from engine_model.calibration.screen import CANDIDATES, Sensitivity, rank_subsets, sensitivities, smooth_floor

PARAMS = tuple(Parameter(f"sec.p{j}", -1.0, 1.0, 0.01) for j in range(5))
SPEEDS = np.linspace(8000, 11000, 7)


def _sens(r0, J):
    return Sensitivity(np.asarray(r0, float), np.asarray(J, float), tuple(p.name for p in PARAMS),
                       {p.name: 0.0 for p in PARAMS}, SPEEDS, 0)


def test_exact_triple_is_found_and_ranked_first():
    rng = np.random.default_rng(3)
    J = rng.normal(size=(7, 5))
    x_true = np.array([0.2, -0.1, 0.15])
    r0 = -J[:, [0, 2, 4]] @ x_true
    rk = rank_subsets(_sens(r0, J), PARAMS, 3, trust=1.0)
    assert len(rk) == 10
    best = rk.iloc[0]
    assert best["parameters"] == "sec.p0 + sec.p2 + sec.p4"
    assert best["max_abs_minimax_pct"] == pytest.approx(0.0, abs=1e-7)
    assert best["rms_ls_pct"] == pytest.approx(0.0, abs=1e-7)
    assert [best[f"d:sec.p{j}"] for j in (0, 2, 4)] == pytest.approx(list(x_true), abs=1e-6)
    # random 7 x 3 columns cannot zero a generic residual: every other triple is left with a misfit
    assert (rk["max_abs_minimax_pct"].iloc[1:] > 1e-3).all()
    # minimax never exceeds the least-squares solution's max |residual|
    assert (rk["max_abs_minimax_pct"] <= rk["max_abs_ls_pct"] + 1e-9).all()


def test_trust_region_limits_the_move():
    J = np.zeros((7, 5))
    J[:, 0] = 1.0                       # p0 shifts every point by 1 % per unit
    r0 = np.full(7, 1.0)                # needs p0 = -1 (the bound) to reach zero
    wide = rank_subsets(_sens(r0, J), PARAMS, 1, trust=0.5)        # |move| <= 0.5 * 2 = 1
    narrow = rank_subsets(_sens(r0, J), PARAMS, 1, trust=0.1)      # |move| <= 0.2
    assert wide.set_index("parameters").loc["sec.p0", "max_abs_minimax_pct"] == pytest.approx(0.0, abs=1e-9)
    assert narrow.set_index("parameters").loc["sec.p0", "max_abs_minimax_pct"] == pytest.approx(0.8, abs=1e-9)


def test_left_out_parameter_returns_to_its_spec_value():
    J = np.zeros((7, 5))
    J[:, 0] = 1.0
    J[:, 1] = np.linspace(-1, 1, 7)     # a tilt
    r0 = np.zeros(7)                    # perfect at the base ...
    rk = rank_subsets(_sens(r0, J), PARAMS, 1, spec_values={"sec.p1": 0.5}, trust=1.0).set_index("parameters")
    # ... but without p1 in the subset it goes back to 0.5: a +-0.5 % tilt that p0 (a level) cannot remove
    assert rk.loc["sec.p0", "max_abs_minimax_pct"] == pytest.approx(0.5, abs=1e-9)
    assert rk.loc["sec.p1", "max_abs_minimax_pct"] == pytest.approx(0.0, abs=1e-9)


def test_correlated_pair_is_reported():
    J = np.zeros((7, 5))
    J[:, 0] = np.linspace(1, 2, 7)
    J[:, 1] = 2 * np.linspace(1, 2, 7) + 1e-3 * np.arange(7) ** 2
    J[:, 2] = np.sin(np.arange(7))
    rk = rank_subsets(_sens(np.zeros(7), J), PARAMS, 2).set_index("parameters")
    assert rk.loc["sec.p0 + sec.p1", "max_abs_corr"] > 0.99
    assert rk.loc["sec.p0 + sec.p2", "max_abs_corr"] < 0.9


def test_smooth_floor_known_cases():
    n = SPEEDS
    # airflow exactly N x quadratic VE: a degree-2 curve fits it, a constant VE does not
    v = 0.018 * (1 + 0.05 * ((n - 9500) / 1500) - 0.04 * ((n - 9500) / 1500) ** 2)
    f2, r2 = smooth_floor(n, n * v, 2)
    assert f2 == pytest.approx(0.0, abs=1e-6) and np.abs(r2).max() < 1e-5
    # two-level VE, constant curve: p = (1 + 1.1) / 2 and max |Ga_REL| = 0.05 / 1.05
    v2 = np.where(np.arange(7) % 2 == 0, 1.0, 1.1)
    f0, r0 = smooth_floor(n, n * v2, 0)
    # 1e-4 %: the LP's feasibility tolerance (~1e-7 relative) limits the bisection, not the method
    assert f0 == pytest.approx(100 * 0.05 / 1.05, abs=1e-4)
    assert np.abs(r0).max() == pytest.approx(f0, abs=1e-4)
    # more freedom never raises the floor
    fl = [smooth_floor(n, n * v2, d)[0] for d in range(4)]
    assert all(b <= a + 1e-4 for a, b in itertools.pairwise(fl)), fl   # 1e-4: LP tolerance as above


def test_sensitivities_central_differences_on_a_linear_model():
    """A fake evaluate whose airflow is linear in two spec values: the screen returns the exact derivative."""
    from engine_model.bench import load_bench
    from engine_model.calibration.airflow import ga_rel_pct

    meas = load_bench()
    params = (Parameter("intake.restrictor_cd", 0.85, 0.99, 0.01), Parameter("intake.runner_length_m", 0.1, 0.35, 0.01))

    def ev(plan):
        ga = plan["speed_rpm"] / 50.0 * (1 + 0.5 * (plan["spec.intake.restrictor_cd"] - 0.9)
                                         - 0.2 * (plan["spec.intake.runner_length_m"] - 0.2))
        return plan.assign(air_mass_flow_kg_h=ga, converged=True, vol_eff=0.9, status="ok")

    s = sensitivities(meas, ev, {"intake.restrictor_cd": 0.9, "intake.runner_length_m": 0.2}, params)
    g = lambda cd, L: ga_rel_pct(meas["speed_rpm"] / 50 * (1 + 0.5 * (cd - 0.9) - 0.2 * (L - 0.2)),  # noqa: E731
                                 meas["air_mass_flow_kg_h"])
    assert np.allclose(s.r0, g(0.9, 0.2))
    fd = (g(0.91, 0.2) - g(0.89, 0.2)) / 0.02
    assert np.allclose(s.jac[:, 0], fd)
    assert s.simulations == 5 * len(meas)
    assert isinstance(s.table(), pd.DataFrame)
    with pytest.raises(ValueError, match="no value for"):
        sensitivities(meas, ev, {"intake.restrictor_cd": 0.9}, params)


def test_candidate_ranges_are_valid_spec_values():
    from engine_model import default_spec

    spec = default_spec()
    for p in CANDIDATES:
        spec.with_values({p.name: p.low})      # raises if a bound is outside the spec's validated range
        spec.with_values({p.name: p.high})
