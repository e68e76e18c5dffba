"""Flow elements against the isentropic-nozzle formulas written out independently here."""

import dataclasses
import math

import numpy as np
import pytest

from engine_model import default_spec, gas_set
from engine_model.cycle import kinematics
from engine_model.cycle.flow import (orifice_flow, restrictor_flow, throttle_open_area, valve_effective_area,
                                     seat_events, valve_lift)
from engine_model.thermo import cp_mass

R_AIR = 287.05          # J/(kg K), dry air (textbook value, independent of thermo.py)
P0, T0 = 101325.0, 298.15


def _gamma_air(T):
    gs = gas_set(1.0)
    cp = cp_mass(gs.coeffs[0], T)
    return cp / (cp - gs.r_specific[0]), gs.r_specific[0]


def _isentropic_choked(A, p0, t0, gamma=1.4, r=R_AIR):
    return A * p0 * math.sqrt(gamma / (r * t0)) * (2 / (gamma + 1)) ** ((gamma + 1) / (2 * (gamma - 1)))


def _isentropic_subsonic(A, p0, t0, p, gamma=1.4, r=R_AIR):
    pr = p / p0
    return A * p0 / math.sqrt(r * t0) * math.sqrt(2 * gamma / (gamma - 1) * (pr ** (2 / gamma) - pr ** ((gamma + 1) / gamma)))


def test_restrictor_choked_flow_matches_isentropic_formula():
    """20 mm throat, Cd 1, no diffuser: 0.5 % of the textbook gamma = 1.4 value.

    The kernel takes gamma and R from the NASA-polynomial air model (gamma = 1.4007
    at 298 K), so agreement within 0.5 % is a real check, not a tautology.
    """
    A = math.pi / 4 * 0.020**2
    g, r = _gamma_air(T0)
    for p_down in (0.0, 10e3, 40e3, 52e3):
        m = restrictor_flow(A, 0.0, P0, T0, r, g, p_down)
        assert m == pytest.approx(_isentropic_choked(A, P0, T0), rel=5e-3)
    # about 0.0745 kg/s = 268 kg/h: the FS restrictor limit at sea level
    assert 0.073 < _isentropic_choked(A, P0, T0) < 0.076


def test_restrictor_subsonic_flow_matches_formula_and_is_continuous_at_choking():
    A = math.pi / 4 * 0.020**2
    g, r = _gamma_air(T0)
    for pr in (0.6, 0.8, 0.95, 0.995):
        m = restrictor_flow(A, 0.0, P0, T0, r, g, pr * P0)
        assert m == pytest.approx(_isentropic_subsonic(A, P0, T0, pr * P0), rel=5e-3)
    prc = (2 / (g + 1)) ** (g / (g - 1))
    below = restrictor_flow(A, 0.0, P0, T0, r, g, prc * P0 * (1 - 1e-6))
    above = restrictor_flow(A, 0.0, P0, T0, r, g, prc * P0 * (1 + 1e-6))
    assert above == pytest.approx(below, rel=1e-5)
    assert restrictor_flow(A, 0.0, P0, T0, r, g, P0) == 0.0


def test_diffuser_recovery_moves_choking_to_a_higher_back_pressure():
    """With recovery k the throat still chokes at p_t/p0 = pr*, reached when p_down/p0 = k + (1-k) pr*."""
    A = math.pi / 4 * 0.020**2
    g, r = _gamma_air(T0)
    k = 0.85
    prc = (2 / (g + 1)) ** (g / (g - 1))
    pr_choke = k + (1 - k) * prc
    m_choked = _isentropic_choked(A, P0, T0, g, r)
    assert restrictor_flow(A, k, P0, T0, r, g, (pr_choke - 0.01) * P0) == pytest.approx(m_choked, rel=1e-9)
    m_sub = restrictor_flow(A, k, P0, T0, r, g, (pr_choke + 0.01) * P0)
    assert 0.5 * m_choked < m_sub < m_choked
    # a plain orifice at the same back pressure passes much less than the venturi
    assert orifice_flow(A, P0, T0, r, g, (pr_choke + 0.01) * P0) < 0.5 * m_sub


def test_throttle_area_limits():
    s = default_spec().intake
    a0 = throttle_open_area(0.0, s.throttle_bore_m, s.throttle_shaft_m, s.throttle_closed_deg)
    assert a0 == pytest.approx(0.0, abs=1e-12)
    pct = np.linspace(0, 100, 101)
    a = throttle_open_area(pct, s.throttle_bore_m, s.throttle_shaft_m, s.throttle_closed_deg)
    assert np.all(np.diff(a) >= -1e-15)
    bore_area = math.pi / 4 * s.throttle_bore_m**2
    # wide open: bore minus the spindle's projection (within the small-a expansion of the formula)
    wot = bore_area - s.throttle_bore_m * s.throttle_shaft_m
    assert a[-1] == pytest.approx(wot, rel=0.02)
    assert a[-1] < bore_area


def test_valve_lift_and_area():
    """Seat to seat: ramp to the ramp height, polynomial flank to the peak, symmetric closing; Cd < 1."""
    spec = default_spec()
    iv = spec.intake_valves
    th = np.arange(0, 720, 0.05)
    lift = valve_lift(th, iv)
    assert lift.max() == pytest.approx(iv.max_lift_m, rel=1e-4)
    open_ = th[lift > 0]
    assert open_.min() == pytest.approx(iv.open_deg, abs=0.051)   # one grid step
    assert open_.max() == pytest.approx(iv.open_deg + iv.duration_deg, abs=0.051)
    # the ramp: constant velocity up to the ramp height, reached ramp_duration after the seat
    end_ramp = float(valve_lift(iv.open_deg + iv.ramp_duration_deg, iv))
    half_ramp = float(valve_lift(iv.open_deg + 0.5 * iv.ramp_duration_deg, iv))
    assert end_ramp == pytest.approx(iv.ramp_height_m, rel=1e-9)
    assert half_ramp == pytest.approx(0.5 * iv.ramp_height_m, rel=1e-9)
    # no jump in velocity where the ramp meets the flank: one-sided slopes agree
    e, h = iv.open_deg + iv.ramp_duration_deg, 1e-4
    left = (end_ramp - float(valve_lift(e - h, iv))) / h
    right = (float(valve_lift(e + h, iv)) - end_ramp) / h
    assert right == pytest.approx(left, rel=1e-3)
    # and nowhere else off the seat: the lift is smooth between the seat events
    inner = (th > iv.open_deg + 0.2) & (th < iv.open_deg + iv.duration_deg - 0.2)
    v = np.gradient(lift, th)
    assert np.abs(np.diff(v[inner])).max() < 0.01 * np.abs(v).max()
    # symmetric about the middle of the event
    mid = iv.open_deg + 0.5 * iv.duration_deg
    assert np.allclose(valve_lift(mid - th[:400], iv), valve_lift(mid + th[:400], iv), atol=1e-12)
    area = valve_effective_area(th, iv)
    assert area.max() < iv.n_valves * math.pi * iv.diameter_m * iv.max_lift_m   # Cd < 1


def test_valve_timing_read_at_a_lift():
    """With a timing lift, the events are where the lift equals it and the seat events lie outside them."""
    iv = default_spec().intake_valves
    iv1 = dataclasses.replace(iv, timing_lift_m=0.001)
    open_seat, dur_seat = seat_events(iv1)
    assert dur_seat > iv1.duration_deg
    assert float(valve_lift(iv1.open_deg, iv1)) == pytest.approx(0.001, rel=1e-6)
    assert float(valve_lift(iv1.open_deg + iv1.duration_deg, iv1)) == pytest.approx(0.001, rel=1e-6)
    assert float(valve_lift(open_seat + 0.01, iv1)) > 0.0
    assert float(valve_lift(open_seat - 0.01, iv1)) == 0.0


def test_slider_crank_volumes():
    g = default_spec().geometry
    v = lambda th: kinematics.cylinder_volume(th, g.bore_m, g.stroke_m, g.conrod_m, g.compression_ratio)
    assert v(0.0) == pytest.approx(g.clearance_m3, rel=1e-12)
    assert v(180.0) == pytest.approx(g.clearance_m3 + g.displacement_m3, rel=1e-12)
    assert v(180.0) / v(0.0) == pytest.approx(g.compression_ratio, rel=1e-12)
    # finite rod: piston is past half stroke before 90 deg
    assert v(90.0) - v(0.0) > 0.5 * g.displacement_m3


def _colebrook(re, rel_rough):
    """Darcy friction factor from the implicit Colebrook-White equation, by fixed-point iteration."""
    x = 8.0
    for _ in range(100):
        x = -2.0 * math.log10(rel_rough / 3.7 + 2.51 * x / re)
    return 1.0 / x**2


@pytest.mark.parametrize("re", [5e3, 2e4, 1e5, 1e6, 1e7])
@pytest.mark.parametrize("rel_rough", [0.0, 1e-4, 1.5e-3, 1e-2])
def test_friction_factor_matches_colebrook(re, rel_rough):
    """Haaland's explicit form stays within 2 % of Colebrook-White over the turbulent range."""
    from engine_model.cycle.flow import darcy_friction_factor
    assert darcy_friction_factor(re, rel_rough) == pytest.approx(_colebrook(re, rel_rough), rel=0.02)


def test_friction_factor_is_laminar_at_low_reynolds_number():
    from engine_model.cycle.flow import darcy_friction_factor
    assert darcy_friction_factor(500.0, 1e-3) == pytest.approx(64.0 / 500.0)


def test_runner_loss_factor_is_minor_losses_plus_dump_plus_darcy_friction():
    """The runner's steady-flow loss in dynamic heads: 1 (exit dump) + k_minor + f(Re) L/D.

    Re of the cycle-mean runner flow, viscosity of air from Sutherland's law
    written out here; f from Colebrook (independent of the Haaland form used).
    """
    from engine_model import OperatingPoint
    from engine_model.cycle import layout as L
    from engine_model.sim.prepare import FRICTION_VE_REF, kernel_inputs
    spec = default_spec()
    it = spec.intake
    op = OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4)
    ki = kernel_inputs(spec, op)
    rho = P0 / (R_AIR * T0)
    mdot = FRICTION_VE_REF * rho * spec.geometry.displacement_m3 * 9000.0 / 120.0
    mu = 1.458e-6 * T0**1.5 / (T0 + 110.4)
    d = it.runner_diameter_m
    re = 4.0 * mdot / (math.pi * d * mu)
    f = _colebrook(re, it.runner_roughness_m / d)
    k_expected = 1.0 + it.runner_loss_k + f * it.runner_length_m / d
    assert ki.par[L.P_IR_K] == pytest.approx(k_expected, rel=0.01)
    assert 0.1 < f * it.runner_length_m / d < 0.3     # friction is a small part of the runner loss
