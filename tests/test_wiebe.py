"""Tests for engine_model.wiebe (Wiebe law, paper MVM2012-024 eqs 2-5)."""
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from engine_model import wiebe as w

M_GRID = np.linspace(0.5, 10.0, 12)
DUR_GRID = np.linspace(10.0, 90.0, 9)


def test_completeness_constant():
    # pure closed-form arithmetic: only float rounding separates the two
    assert w.WIEBE_A_999 == pytest.approx(-math.log(0.001), abs=1e-12)
    assert w.completeness_constant(0.999) == pytest.approx(w.WIEBE_A_999, abs=1e-12)
    assert w.completeness_constant() == pytest.approx(6.9078, abs=1e-4)  # paper eq 3 value
    assert isinstance(w.completeness_constant(0.99), float)


def test_bdur_round_trip_grid():
    m, d = np.meshgrid(M_GRID, DUR_GRID)
    back = w.bdur_10_90_to_bdur(w.bdur_to_bdur_10_90(d, m), m)
    # a multiply then divide by the same ratio: only rounding error
    np.testing.assert_allclose(back, d, rtol=1e-12)
    back2 = w.bdur_to_bdur_10_90(w.bdur_10_90_to_bdur(d, m), m)
    np.testing.assert_allclose(back2, d, rtol=1e-12)


def test_soc_ca50_round_trip_grid():
    m, d = np.meshgrid(M_GRID, DUR_GRID)
    soc = np.linspace(5.0, 60.0, m.size).reshape(m.shape)
    ca50 = w.ca50_deg_atdc(soc, d, m)
    # add then subtract the same offset: rounding only (values are O(10-100) deg)
    np.testing.assert_allclose(w.soc_for_ca50(ca50, d, m), soc, rtol=1e-12)


@pytest.mark.parametrize("m", [0.5, 2.0, 6.4, 10.0])
@pytest.mark.parametrize("x", [0.1, 0.5, 0.9])
def test_angle_at_fraction_matches_numerical_root(x, m):
    soc, bdur = 30.0, 60.0
    root = brentq(lambda th: w.burn_fraction(th, soc, bdur, m) - x,
                  -soc, -soc + bdur, xtol=1e-13, rtol=1e-14)
    # brentq is converged to ~1e-13 deg; 1e-9 deg leaves margin for slope effects
    assert w.angle_at_fraction(x, soc, bdur, m) == pytest.approx(root, abs=1e-9)


def test_eq4_matches_angle_difference():
    m, d = np.meshgrid(M_GRID, DUR_GRID)
    diff = w.angle_at_fraction(0.9, 20.0, d, m) - w.angle_at_fraction(0.1, 20.0, d, m)
    # same closed form computed two ways; differences are rounding after cancelling SOC
    np.testing.assert_allclose(w.bdur_to_bdur_10_90(d, m), diff, rtol=1e-10)


@pytest.mark.parametrize("bdur_10_90, m", [(24.0, 6.4), (25.0, 6.1)])
def test_paper_wot_9000_case_ca50_in_mbt_window(bdur_10_90, m):
    res = w.burn_angles(50.0, bdur_10_90, m)
    # paper sec. 4: identified parameters give CA50 within 8-10 deg ATDC (Bargende MBT rule)
    assert 8.0 <= res["ca50_deg_atdc"] <= 10.0
    assert res["ca10_deg_atdc"] < res["ca50_deg_atdc"] < res["ca90_deg_atdc"]
    # CA90 - CA10 must reproduce the requested 10-90 duration; rounding only
    assert res["ca90_deg_atdc"] - res["ca10_deg_atdc"] == pytest.approx(bdur_10_90, rel=1e-12)
    assert res["bdur_deg"] > bdur_10_90


@pytest.mark.parametrize("m", [0.5, 2.0, 6.4, 10.0])
def test_burn_rate_integrates_to_burn_fraction(m):
    soc, bdur = 40.0, 70.0
    theta = np.linspace(-60.0, 40.0, 200_001)  # 0.0005 deg step
    rate = w.burn_rate(theta, soc, bdur, m)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(theta))])
    # trapezoid error ~ h^2 * max|x'''| * span / 12, well below 1e-6 at this step
    np.testing.assert_allclose(cum, w.burn_fraction(theta, soc, bdur, m), atol=1e-6)


def test_burn_fraction_shape():
    soc, bdur, m = 30.0, 60.0, 2.0
    theta = np.linspace(-90.0, 90.0, 3601)
    xb = w.burn_fraction(theta, soc, bdur, m)
    assert np.all(xb[theta <= -soc] == 0.0)  # exactly zero before SOC
    assert np.all(w.burn_rate(theta[theta < -soc], soc, bdur, m) == 0.0)
    assert np.all(np.diff(xb) >= 0.0)
    assert np.all((xb >= 0.0) & (xb <= 1.0))  # saturates to 1.0 in float far past EOC
    # definition of BDUR: 99.9 % reached at SOC + BDUR; rounding only
    assert w.burn_fraction(-soc + bdur, soc, bdur, m) == pytest.approx(0.999, abs=1e-12)
    assert w.burn_fraction(-soc + bdur, soc, bdur, m, a=w.completeness_constant(0.99)) == \
        pytest.approx(0.99, abs=1e-12)


def test_broadcasting_and_return_types():
    theta = np.linspace(-40.0, 40.0, 5)[:, None]
    m = np.array([1.0, 2.0, 6.4])[None, :]
    assert w.burn_fraction(theta, 30.0, 60.0, m).shape == (5, 3)
    assert w.burn_rate(theta, 30.0, 60.0, m).shape == (5, 3)
    assert w.angle_at_fraction(np.array([0.1, 0.5, 0.9]), 30.0, 60.0, 2.0).shape == (3,)
    res = w.burn_angles(np.array([40.0, 50.0]), 24.0, np.array([[6.0], [6.4]]))
    assert all(v.shape == (2, 2) for v in res.values())
    assert isinstance(w.burn_fraction(0.0, 30.0, 60.0, 2.0), float)
    assert isinstance(w.ca50_deg_atdc(30.0, 60.0, 2.0), float)
    # elementwise array result must equal the scalar call; identical arithmetic
    ca = w.ca50_deg_atdc(30.0, 60.0, np.array([1.0, 2.0]))
    assert ca[1] == pytest.approx(w.ca50_deg_atdc(30.0, 60.0, 2.0), abs=1e-12)


@pytest.mark.parametrize("call, name", [
    (lambda: w.burn_fraction(0.0, 30.0, 60.0, -1.0), "m"),
    (lambda: w.burn_fraction(0.0, 30.0, 60.0, np.array([2.0, -1.5])), "m"),
    (lambda: w.burn_rate(0.0, 30.0, 0.0, 2.0), "bdur_deg"),
    (lambda: w.burn_fraction(0.0, 30.0, -5.0, 2.0), "bdur_deg"),
    (lambda: w.burn_fraction(0.0, 30.0, 60.0, 2.0, a=0.0), "a"),
    (lambda: w.burn_fraction(float("nan"), 30.0, 60.0, 2.0), "theta_deg_atdc"),
    (lambda: w.burn_fraction(0.0, float("nan"), 60.0, 2.0), "soc_deg_btdc"),
    (lambda: w.angle_at_fraction(0.0, 30.0, 60.0, 2.0), "x"),
    (lambda: w.angle_at_fraction(1.0, 30.0, 60.0, 2.0), "x"),
    (lambda: w.angle_at_fraction(float("nan"), 30.0, 60.0, 2.0), "x"),
    (lambda: w.completeness_constant(1.0), "x_end"),
    (lambda: w.bdur_10_90_to_bdur(-24.0, 6.4), "bdur_10_90_deg"),
    (lambda: w.bdur_to_bdur_10_90(60.0, float("nan")), "m"),
    (lambda: w.soc_for_ca50(float("nan"), 60.0, 2.0), "ca50_deg_atdc"),
    (lambda: w.burn_angles(50.0, 0.0, 6.4), "bdur_10_90_deg"),
])
def test_bad_inputs_raise_naming_argument(call, name):
    with pytest.raises(ValueError, match=rf"^{name} must"):
        call()
