"""Tests of engine_model.thermo: gas properties, product composition and energy release."""
from __future__ import annotations

import math

import numpy as np
import pytest

from engine_model import thermo as th
from engine_model.thermo import (FuelSpec, constant_cp_gas_set, cp_mass, cv_mass, gas_set, h_mass,
                                 mix_coeffs, products_mole_fractions, temperature_from_u, u_mass)

# Independent reference data used by the checks below.
ATOM = {"C": 12.011, "H": 1.008, "O": 15.999, "N": 14.007, "Ar": 39.948}   # IUPAC conventional atomic weights [g/mol]
AIR = {"N2": 0.78084, "O2": 0.209476, "Ar": 0.00934}                         # U.S. Standard Atmosphere 1976, sea level
# NIST-JANAF Thermochemical Tables (Chase 1998): formation enthalpies at 298.15 K [J/mol]
HF_CO2, HF_CO, HF_H2O_GAS = -393522.0, -110527.0, -241826.0
HV_CO = HF_CO - HF_CO2          # CO + 1/2 O2 -> CO2 [J/mol]
HV_H2 = -HF_H2O_GAS             # H2 + 1/2 O2 -> H2O(g) [J/mol]
LAMBDAS = (0.8, 0.9, 1.0, 1.2)


def _unit_mass(fuel):
    """Mass of one C1HyOz unit [kg/mol], computed independently of the module."""
    return 1e-3 * (ATOM["C"] + fuel.h_to_c * ATOM["H"] + fuel.o_to_c * ATOM["O"])


def _q_per_kg_fuel(gs):
    """Heat released per kg of fuel at 298.15 K [J/kg]."""
    return gs.heat_release_j_per_kg_mix * (1.0 + gs.far) / gs.far


def _t_adiabatic(gs):
    """Constant-pressure adiabatic flame temperature from 298.15 K reactants [K] (bisection)."""
    target = h_mass(gs.coeffs[1], 298.15)
    lo, hi = 300.0, 4000.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if h_mass(gs.coeffs[2], mid) > target:
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


# ------------------------------------------------------------------------------------- air
def test_air_cp_and_r_match_tables():
    gs = gas_set(1.0)
    air = gs.coeffs[0]
    # Cengel & Boles, Thermodynamics, Table A-2(b) (from NBS Circular 564, 1955): 1.005 / 1.142 kJ/(kg K);
    # rtol 3e-3: the table is rounded to 1 J/(kg K) and is for slightly different air.
    assert cp_mass(air, 300.0) == pytest.approx(1005.0, rel=3e-3)
    assert cp_mass(air, 1000.0) == pytest.approx(1142.0, rel=3e-3)
    # R_air = 287.05 J/(kg K) for M = 28.9644 g/mol (U.S. Standard Atmosphere); rtol 1e-3: trace gases dropped.
    assert gs.r_specific[0] == pytest.approx(287.05, rel=1e-3)


def test_air_gamma_at_300k():
    gs = gas_set(1.0)
    gamma = cp_mass(gs.coeffs[0], 300.0) / cv_mass(gs.coeffs[0], gs.r_specific[0], 300.0)
    # 1.400 per Cengel Table A-2(b); the brief allows 0.3 %.
    assert gamma == pytest.approx(1.40, rel=3e-3)


# ---------------------------------------------------------------------------- composition
@pytest.mark.parametrize("lam", LAMBDAS)
def test_product_element_balance(lam):
    fuel = FuelSpec()
    x = products_mole_fractions(lam, fuel)
    assert sum(x.values()) == pytest.approx(1.0, abs=1e-14)   # round-off only
    assert min(x.values()) >= 0.0
    c = x["CO2"] + x["CO"]
    h = 2 * x["H2O"] + 2 * x["H2"]
    o = 2 * x["CO2"] + x["CO"] + x["H2O"] + 2 * x["O2"]
    n = 2 * x["N2"]
    ast = 1.0 + fuel.h_to_c / 4.0 - fuel.o_to_c / 2.0
    o2_in = lam * ast
    expect = {"H": fuel.h_to_c, "O": 2.0 * o2_in + fuel.o_to_c, "N": 2.0 * o2_in * AIR["N2"] / AIR["O2"],
              "Ar": o2_in * AIR["Ar"] / AIR["O2"]}
    got = {"H": h / c, "O": o / c, "N": n / c, "Ar": x["Ar"] / c}
    for k in expect:
        # atoms per carbon atom must close to round-off (brief: 1e-12)
        assert got[k] == pytest.approx(expect[k], rel=1e-12, abs=1e-12), k


@pytest.mark.parametrize("lam", (0.7, 0.8, 0.9, 0.99))
def test_rich_products_obey_water_gas_equilibrium(lam):
    x = products_mole_fractions(lam)
    assert x["O2"] == 0.0 and x["CO"] > 0.0 and x["H2"] > 0.0
    # K = x_CO x_H2O / (x_CO2 x_H2) = 3.5 (Heywood 1988 sec 4.9.1); rtol 1e-10: closed-form root
    assert x["CO"] * x["H2O"] / (x["CO2"] * x["H2"]) == pytest.approx(3.5, rel=1e-10)


def test_water_gas_constant_is_plausible_freeze_point():
    # K = 3.5 should be the GRI-Mech 3.0 equilibrium constant of CO2 + H2 <-> CO + H2O somewhere in
    # 1650-1800 K, the range where the shift reaction freezes during expansion (Heywood 1988 sec 4.9.1).
    def g(species, T):
        a = th.SPECIES_NASA[species][0 if T < th.T_MID else 1]
        return th.R_UNIVERSAL * (th.poly_h(a, T) - T * th.poly_s(a, T))

    def k_eq(T):
        return math.exp(-(g("CO", T) + g("H2O", T) - g("CO2", T) - g("H2", T)) / (th.R_UNIVERSAL * T))

    assert k_eq(1650.0) < th.K_WATER_GAS < k_eq(1800.0)


def test_lean_products_have_no_co_or_h2():
    x = products_mole_fractions(1.2)
    assert x["CO"] == 0.0 and x["H2"] == 0.0 and x["O2"] > 0.0


def test_gas_constants_consistent_with_composition():
    fuel = FuelSpec()
    for lam in LAMBDAS:
        gs = gas_set(lam, fuel)
        x = products_mole_fractions(lam, fuel)
        m = {"CO2": ATOM["C"] + 2 * ATOM["O"], "CO": ATOM["C"] + ATOM["O"], "H2O": 2 * ATOM["H"] + ATOM["O"],
             "H2": 2 * ATOM["H"], "O2": 2 * ATOM["O"], "N2": 2 * ATOM["N"], "Ar": ATOM["Ar"]}
        m_mix = 1e-3 * sum(x[s] * m[s] for s in x)
        # R_P = R_u / M_mix: same physics, different code path; rtol 1e-12 round-off
        assert gs.r_specific[2] == pytest.approx(th.R_UNIVERSAL / m_mix, rel=1e-12)
        assert gs.far == pytest.approx(1.0 / (lam * gs.afr_stoich), rel=1e-15)
    # AFR of CH1.87 gasoline ~14.6 (Heywood 1988, Table D.4 ~14.6); rtol 5e-3 for air-composition differences
    assert th.stoich_afr(fuel) == pytest.approx(14.6, rel=5e-3)


# ------------------------------------------------------------------------------- energy
@pytest.mark.parametrize("fuel", [FuelSpec(), FuelSpec(lhv_j_per_kg=43.0e6, h_to_c=2.0, o_to_c=0.05)])
@pytest.mark.parametrize("lam", (1.0, 1.1, 1.2, 1.5))
def test_lhv_recovered_for_lean_mixtures(fuel, lam):
    gs = gas_set(lam, fuel)
    # exact by construction of the fuel's formation enthalpy; rtol 1e-9 allows float round-off
    assert _q_per_kg_fuel(gs) == pytest.approx(fuel.lhv_j_per_kg, rel=1e-9)


@pytest.mark.parametrize("lam", (0.9, 0.8))
def test_rich_shortfall_equals_heating_value_of_co_and_h2(lam):
    fuel = FuelSpec()
    gs = gas_set(lam, fuel)
    q = _q_per_kg_fuel(gs)
    assert q < fuel.lhv_j_per_kg
    x = products_mole_fractions(lam, fuel)
    per_c = 1.0 / (x["CO2"] + x["CO"])            # product moles per mole of fuel carbon
    expected = (x["CO"] * per_c * HV_CO + x["H2"] * per_c * HV_H2) / _unit_mass(fuel)
    # JANAF vs GRI-Mech polynomial formation enthalpies differ by < 1e-4; rtol 5e-4
    assert fuel.lhv_j_per_kg - q == pytest.approx(expected, rel=5e-4)


def test_adiabatic_flame_temperature():
    t_stoich = _t_adiabatic(gas_set(1.0))
    # Complete combustion without dissociation: Turns 2012 (An Introduction to Combustion, 3rd ed.,
    # Table B.1) gives ~2270 K *with* dissociation for C3-C8 alkanes/air; frozen products run
    # ~100-200 K hotter.  Default fuel (LHV 44 MJ/kg at H/C 1.87, AFR 14.6) -> band 2300-2500 K.
    assert 2300.0 <= t_stoich <= 2500.0
    iso = FuelSpec(lhv_j_per_kg=44.3e6, h_to_c=2.25)   # iso-octane, LHV per Heywood 1988 Table D.4
    assert 2300.0 <= _t_adiabatic(gas_set(1.0, iso)) <= 2450.0
    # Without dissociation the peak is at stoichiometric: rich loses CO/H2 energy, lean dilutes.
    assert _t_adiabatic(gas_set(0.9)) < t_stoich - 50.0
    assert _t_adiabatic(gas_set(1.1)) < t_stoich - 50.0


# ---------------------------------------------------------------------------- kernels
def _blocks():
    gs = gas_set(0.9)
    blocks = [(gs.coeffs[i], gs.r_specific[i]) for i in range(3)]
    out = np.empty((2, 7))
    for ya, ym, yp in ((0.2, 0.7, 0.1), (0.0, 0.05, 0.95), (1 / 3, 1 / 3, 1 / 3)):
        mix_coeffs(gs.coeffs, ya, ym, yp, out)
        r = ya * gs.r_specific[0] + ym * gs.r_specific[1] + yp * gs.r_specific[2]
        blocks.append((out.copy(), r))
    return blocks


def test_mix_coeffs_is_mass_weighted_sum():
    gs = gas_set(1.1)
    out = np.empty((2, 7))
    mix_coeffs(gs.coeffs, 0.1, 0.3, 0.6, out)
    ref = 0.1 * gs.coeffs[0] + 0.3 * gs.coeffs[1] + 0.6 * gs.coeffs[2]
    np.testing.assert_allclose(out, ref, rtol=1e-15, atol=0.0)   # same arithmetic, round-off only


def test_temperature_from_u_inverts_u_mass():
    temps = np.concatenate([np.linspace(200.0, 3500.0, 67), [999.999999, 1000.0, 1000.000001]])
    worst = 0.0
    for c, r in _blocks():
        for T in temps:
            u = u_mass(c, r, T)
            for guess in (T * 1.05, T - 40.0, 1500.0, 300.0):
                worst = max(worst, abs(temperature_from_u(c, r, u, guess) - T))
    assert worst < 1e-8   # brief: invert to 1e-8 K


def test_temperature_from_u_clamps_out_of_range():
    c, r = gas_set(1.0).coeffs[2], gas_set(1.0).r_specific[2]
    assert temperature_from_u(c, r, u_mass(c, r, 6000.0), 2000.0) == 4500.0
    assert temperature_from_u(c, r, u_mass(c, r, 100.0), 300.0) == 150.0


def test_cv_positive_over_clamp_range():
    # Newton divides by cv: it must stay positive over the whole clamp range 150-4500 K.
    gs = gas_set(0.8)
    for c, r in [(gs.coeffs[i], gs.r_specific[i]) for i in range(3)] + [(gs.fuel_coeffs, gs.fuel_r_specific)]:
        assert min(cv_mass(c, r, T) for T in np.linspace(150.0, 4500.0, 200)) > 0.0


def test_continuity_at_t_mid():
    gs = gas_set(0.9)
    eps = 1e-9
    for c in list(gs.coeffs) + [gs.fuel_coeffs]:
        cp_lo, cp_hi = cp_mass(c, th.T_MID - eps), cp_mass(c, th.T_MID)
        h_lo, h_hi = h_mass(c, th.T_MID - eps), h_mass(c, th.T_MID)
        assert abs(cp_hi - cp_lo) / cp_hi < 1e-3                       # brief: cp jump < 0.1 %
        assert abs(h_hi - h_lo) / max(abs(h_hi), cp_hi * th.T_MID) < 1e-6  # brief: h jump < 1e-6


def test_gas_set_layout():
    gs = gas_set(1.0)
    assert gs.coeffs.shape == (3, 2, 7) and gs.coeffs.dtype == np.float64 and gs.coeffs.flags.c_contiguous
    assert gs.r_specific.shape == (3,) and gs.fuel_coeffs.shape == (2, 7)
    assert gas_set(1.0) is gs            # cached
    with pytest.raises(ValueError):
        gs.coeffs[0, 0, 0] = 1.0         # read-only, so the cache cannot be corrupted


# ------------------------------------------------------------------------- constant cp
def test_constant_cp_gas_set():
    gamma, r, q = 1.35, 287.0, 2.7e6
    gs = constant_cp_gas_set(gamma, r, q, far=0.068)
    for i in range(3):
        for T in (250.0, 999.0, 1000.0, 2500.0):
            # cp/cv == gamma to round-off
            assert cp_mass(gs.coeffs[i], T) / cv_mass(gs.coeffs[i], gs.r_specific[i], T) == pytest.approx(gamma, rel=1e-14)
    assert h_mass(gs.coeffs[0], 298.15) == pytest.approx(0.0, abs=1e-9)
    for T in (298.15, 800.0, 2400.0):
        # M -> P at fixed T releases exactly q (rtol 1e-12: subtraction of ~1e6 J/kg numbers)
        assert h_mass(gs.coeffs[1], T) - h_mass(gs.coeffs[2], T) == pytest.approx(q, rel=1e-12)
        assert u_mass(gs.coeffs[1], r, T) - u_mass(gs.coeffs[2], r, T) == pytest.approx(q, rel=1e-12)
    assert gs.heat_release_j_per_kg_mix == q and gs.far == 0.068
    with pytest.raises(ValueError, match="gamma"):
        constant_cp_gas_set(1.0, r, q)


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("lam", [0.0, -1.0, float("nan"), float("inf")])
def test_gas_set_rejects_bad_lambda(lam):
    with pytest.raises(ValueError, match="lam"):
        gas_set(lam)


def test_gas_set_rejects_too_rich():
    with pytest.raises(ValueError, match="too rich"):
        gas_set(0.2)


@pytest.mark.parametrize("field,value", [("h_to_c", -1.0), ("lhv_j_per_kg", 0.0), ("o_to_c", float("nan"))])
def test_fuelspec_validation_names_field_and_value(field, value):
    with pytest.raises(ValueError) as err:
        FuelSpec(**{field: value})
    assert field in str(err.value) and repr(value) in str(err.value)


def test_mixture_state_equals_the_separate_functions():
    """The fused kernel helper must agree with mix_coeffs + temperature_from_u + cp_mass + h_mass."""
    thermo = th
    gs = thermo.gas_set(0.9)
    out = np.empty(4)
    buf = np.empty((2, 7))
    hc = thermo.enthalpy_coeffs(gs.coeffs)
    rng = np.random.default_rng(7)
    for _ in range(200):
        y = rng.dirichlet([1.0, 1.0, 1.0])
        T_true = rng.uniform(250.0, 3200.0)
        thermo.mix_coeffs(gs.coeffs, y[0], y[1], y[2], buf)
        r = float(y @ gs.r_specific)
        u = thermo.u_mass(buf, r, T_true)
        guess = rng.uniform(300.0, 2500.0)
        thermo.mixture_state(hc, gs.r_specific, y[0], y[1], y[2], u, guess, out)
        assert out[0] == pytest.approx(T_true, abs=1e-6)
        assert out[1] == pytest.approx(thermo.cp_mass(buf, T_true), rel=1e-10)
        assert out[2] == pytest.approx(thermo.h_mass(buf, T_true), rel=1e-9, abs=1e-3)
        assert out[3] == pytest.approx(r, rel=1e-14)
