"""The linearised orifice law used by the network solve agrees with the plain law and its own derivatives."""

import numpy as np
import pytest

from engine_model.cycle.flow import orifice_flow, orifice_flow_lin

EPS = 1e-4   # linear band of the kernel (prepare: P_NET_EPS)


@pytest.mark.parametrize("gamma", [1.22, 1.3, 1.4])
def test_linearised_law_equals_orifice_law_outside_the_linear_band(gamma):
    """Choked and subsonic branches (including the pow-free choked form) give the isentropic flow."""
    for pr in np.linspace(0.05, 1.0 - 2 * EPS, 300):
        plain = orifice_flow(1e-4, 1e5, 320.0, 287.0, gamma, pr * 1e5)
        lin = orifice_flow_lin(1e-4, 1e5, 320.0, 287.0, gamma, pr * 1e5, EPS)[0]
        assert lin == pytest.approx(plain, rel=1e-13)


@pytest.mark.parametrize("pr", [0.3, 0.52, 0.7, 0.95, 0.99995])
def test_partial_derivatives_match_finite_differences(pr):
    gamma, p_up, h = 1.33, 1.2e5, 1e-3
    f, dfu, dft = orifice_flow_lin(1e-4, p_up, 900.0, 290.0, gamma, pr * p_up, EPS)
    fu = lambda p: orifice_flow_lin(1e-4, p, 900.0, 290.0, gamma, pr * p_up, EPS)[0]  # noqa: E731
    ft = lambda p: orifice_flow_lin(1e-4, p_up, 900.0, 290.0, gamma, p, EPS)[0]  # noqa: E731
    assert dfu == pytest.approx((fu(p_up + h) - fu(p_up - h)) / (2 * h), rel=1e-5, abs=1e-12)
    assert dft == pytest.approx((ft(pr * p_up + h) - ft(pr * p_up - h)) / (2 * h), rel=1e-5, abs=1e-12)
