"""Ideal-gas thermodynamics of air, fresh mixture and burned gas on a mass basis.

Three *pseudo-species* per operating point: index 0 ``A`` dry air, index 1 ``M`` fresh mixture
(air + fuel vapour at the given lambda), index 2 ``P`` its complete-combustion products (no
dissociation).  Each carries NASA 7-coefficient polynomials already multiplied by its specific gas
constant, in a ``(2, 7)`` block (range 0 below ``T_MID``, range 1 at or above it)::

    cp(T) [J/(kg K)] = c0 + c1 T + c2 T^2 + c3 T^3 + c4 T^4
    h(T)  [J/kg]     = c0 T + c1 T^2/2 + c2 T^3/3 + c3 T^4/4 + c4 T^5/5 + c5
    s0(T) [J/(kg K)] = c0 ln T + c1 T + c2 T^2/2 + c3 T^3/3 + c4 T^4/4 + c6

Enthalpies are absolute (elements at 298.15 K have h = 0), so the heat released when ``M`` turns
into ``P`` follows from the composition change alone.  The fuel's enthalpy of formation is solved
so that lean combustion at 298.15 K releases exactly the LHV of the :class:`FuelSpec`; rich
mixtures release less because CO and H2 remain.  The scalar kernels are ``numba.njit`` functions
over one ``(2, 7)`` block, callable from compiled cycle code.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba
import numpy as np

__all__ = [
    "T_MID", "T_REF", "R_UNIVERSAL", "K_WATER_GAS", "FUEL_CARBON_NUMBER",
    "FuelSpec", "GasSet", "stoich_afr", "products_mole_fractions", "gas_set",
    "constant_cp_gas_set", "cp_mass", "h_mass", "u_mass", "cv_mass", "s0_mass",
    "temperature_from_u", "mix_coeffs", "enthalpy_coeffs", "mixture_state", "PRODUCT_SPECIES",
]

T_MID = 1000.0          # [K] common range split of the GRI-Mech 3.0 polynomials used below
T_REF = 298.15          # [K] standard reference temperature of the NASA enthalpy datum
R_UNIVERSAL = 8.314462618  # [J/(mol K)] CODATA 2018 (exact since the 2019 SI redefinition)
K_WATER_GAS = 3.5       # [-] CO2 + H2 <-> CO + H2O, Heywood 1988, Internal Combustion Engine Fundamentals, sec 4.9.1
FUEL_CARBON_NUMBER = 8.26  # [-] gasoline molecule C8.26H15.5, Heywood 1988, Table 4.8 (fixes the vapour molar mass)
_T_MIN, _T_MAX = 150.0, 4500.0  # [K] clamp of the u -> T inversion (design choice: wider than any cylinder state)

# Standard atomic weights [g/mol], IUPAC/CIAAW conventional values (as used by Cantera).
_ATOM = {"C": 12.011, "H": 1.008, "O": 15.999, "N": 14.007, "Ar": 39.948}

# NASA 7-coefficient data (dimensionless, cp/R ...), [low 200/300-1000 K, high 1000-3500/5000 K],
# copied from GRI-Mech 3.0 as distributed with Cantera: repo Cantera/cantera, data/gri30.yaml
# (commit 638955d640c0b16949e5313de4cdf14f3747b63a).
_NASA = {
    "N2": ([3.298677, 1.4082404e-03, -3.963222e-06, 5.641515e-09, -2.444854e-12, -1020.8999, 3.950372],
           [2.92664, 1.4879768e-03, -5.68476e-07, 1.0097038e-10, -6.753351e-15, -922.7977, 5.980528]),
    "O2": ([3.78245636, -2.99673416e-03, 9.84730201e-06, -9.68129509e-09, 3.24372837e-12, -1063.94356, 3.65767573],
           [3.28253784, 1.48308754e-03, -7.57966669e-07, 2.09470555e-10, -2.16717794e-14, -1088.45772, 5.45323129]),
    "Ar": ([2.5, 0.0, 0.0, 0.0, 0.0, -745.375, 4.366],
           [2.5, 0.0, 0.0, 0.0, 0.0, -745.375, 4.366]),
    "CO2": ([2.35677352, 8.98459677e-03, -7.12356269e-06, 2.45919022e-09, -1.43699548e-13, -4.83719697e+04, 9.90105222],
            [3.85746029, 4.41437026e-03, -2.21481404e-06, 5.23490188e-10, -4.72084164e-14, -4.8759166e+04, 2.27163806]),
    "H2O": ([4.19864056, -2.0364341e-03, 6.52040211e-06, -5.48797062e-09, 1.77197817e-12, -3.02937267e+04, -0.849032208],
            [3.03399249, 2.17691804e-03, -1.64072518e-07, -9.7041987e-11, 1.68200992e-14, -3.00042971e+04, 4.9667701]),
    "CO": ([3.57953347, -6.1035368e-04, 1.01681433e-06, 9.07005884e-10, -9.04424499e-13, -1.4344086e+04, 3.50840928],
           [2.71518561, 2.06252743e-03, -9.98825771e-07, 2.30053008e-10, -2.03647716e-14, -1.41518724e+04, 7.81868772]),
    "H2": ([2.34433112, 7.98052075e-03, -1.9478151e-05, 2.01572094e-08, -7.37611761e-12, -917.935173, 0.683010238],
           [3.3372792, -4.94024731e-05, 4.99456778e-07, -1.79566394e-10, 2.00255376e-14, -950.158922, -3.20502331]),
}
_ELEMENTS = {"N2": {"N": 2}, "O2": {"O": 2}, "Ar": {"Ar": 1}, "CO2": {"C": 1, "O": 2},
             "H2O": {"H": 2, "O": 1}, "CO": {"C": 1, "O": 1}, "H2": {"H": 2}}
PRODUCT_SPECIES = ("CO2", "CO", "H2O", "H2", "O2", "N2", "Ar")

# iso-octane vapour (IC8H18, 7/20/0 THERMC), LLNL iso-octane mechanism v3 (Mehl, Curran, Pitz &
# Westbrook 2009), repo jiweiqi/CollectionOfMechanisms,
# i-Octane_C8H18/llnl_version3/ReducedByTianfengLu/red99/therm.dat; ranges 300-1396 K / 1396-5000 K.
_IC8H18_TMID = 1396.0  # [K] mid temperature of that entry
_IC8H18_LOW = [-4.20868893e+00, 1.11440581e-01, -7.91346582e-05, 2.92406242e-08, -4.43743191e-12,
               -2.99446875e+04, 4.49521701e+01]
_IC8H18_HIGH = [2.71373590e+01, 3.79004890e-02, -1.29437358e-05, 2.00760372e-09, -1.16400580e-13,
                -4.07958177e+04, -1.23277495e+02]
_IC8H18_M = 8 * _ATOM["C"] + 18 * _ATOM["H"]  # [g/mol]

# Dry air, U.S. Standard Atmosphere 1976 sea-level mole fractions of N2, O2, Ar; the remaining
# 0.034 % (CO2, Ne, He, ...) is dropped and the three are renormalised to sum to one.
_AIR_RAW = {"N2": 0.78084, "O2": 0.209476, "Ar": 0.00934}
_AIR_X = {k: v / sum(_AIR_RAW.values()) for k, v in _AIR_RAW.items()}


def _molar_mass(species: str) -> float:
    """Molar mass of a species [kg/mol]."""
    return 1e-3 * sum(n * _ATOM[e] for e, n in _ELEMENTS[species].items())


def poly_h(a, T):
    """h/R [K] of one NASA range ``a`` (length 7) at T [K]."""
    return T * (a[0] + T * (a[1] / 2 + T * (a[2] / 3 + T * (a[3] / 4 + T * a[4] / 5)))) + a[5]


def poly_s(a, T):
    """Dimensionless s0/R of one NASA range ``a``."""
    return a[0] * math.log(T) + T * (a[1] + T * (a[2] / 2 + T * (a[3] / 3 + T * a[4] / 4))) + a[6]


def _make_continuous(low, high) -> np.ndarray:
    """(2,7) molar array with a6, a7 of the high range shifted so h and s0 are exactly continuous at T_MID.

    The published ranges agree at 1000 K only to ~1e-3 K in h/R (< 0.01 J/mol); an exact match keeps
    the Newton inversion of u(T) from hunting across a step.
    """
    a = np.array([low, high], dtype=float)
    a[1, 5] += poly_h(a[0], T_MID) - poly_h(a[1], T_MID)
    a[1, 6] += poly_s(a[0], T_MID) - poly_s(a[1], T_MID)
    return a


#: NASA 7-coefficient blocks per species, made continuous at T_MID (dimensionless, cp/R ...).
SPECIES_NASA = {k: _make_continuous(*v) for k, v in _NASA.items()}


def _refit_isooctane() -> np.ndarray:
    """Iso-octane molar coefficients re-split at T_MID (cp/R, dimensionless).

    The source splits at 1396 K.  Below 1000 K its low-range polynomial is used unchanged (it is the
    exact source curve there).  Above 1000 K a new quartic is fitted by least squares to the source
    cp over 1000-3500 K (to cover the validity range of this module), constrained to equal the low
    range at 1000 K; a6/a7 then make h and s0 continuous.
    """
    lo, hi = np.array(_IC8H18_LOW), np.array(_IC8H18_HIGH)
    T = np.linspace(T_MID, 3500.0, 501)
    src = np.where(T < _IC8H18_TMID, np.polyval(lo[4::-1], T), np.polyval(hi[4::-1], T))
    t = T / 1000.0                                  # scaled variable for a well-conditioned fit
    A = np.vander(t, 5, increasing=True)
    con = np.ones(5)                                # value of the basis at t = 1 (T = T_MID)
    kkt = np.zeros((6, 6))
    kkt[:5, :5] = 2.0 * A.T @ A
    kkt[:5, 5] = kkt[5, :5] = con
    rhs = np.concatenate([2.0 * A.T @ src, [np.polyval(lo[4::-1], T_MID)]])
    b = np.linalg.solve(kkt, rhs)[:5]
    high = np.zeros(7)
    high[:5] = b / 1000.0 ** np.arange(5)
    return _make_continuous(lo, high)


_ISOOCTANE_A = _refit_isooctane()


def _mass_coeffs(moles: dict[str, float]) -> tuple[np.ndarray, float, float]:
    """Mass-based (2,7) coefficients, R [J/(kg K)] and mass [kg] of a species mixture given in moles."""
    mass = sum(n * _molar_mass(s) for s, n in moles.items())
    a = sum(n * SPECIES_NASA[s] for s, n in moles.items())
    ntot = sum(moles.values())
    return R_UNIVERSAL * a / mass, R_UNIVERSAL * ntot / mass, mass


def _h_np(c, T):
    """h [J/kg] of a (2,7) mass-based block, plain Python."""
    return poly_h(c[0] if T < T_MID else c[1], T)


@dataclass(frozen=True)
class FuelSpec:
    """Fuel properties used by the gas model.

    Parameters
    ----------
    lhv_j_per_kg : float
        Lower heating value [J/kg], water as vapour, 298.15 K; allowed [1e7, 1.5e8].
    h_to_c : float
        Hydrogen/carbon atom ratio y of the C1HyOz fuel unit [-]; allowed [0, 4].
    o_to_c : float
        Oxygen/carbon atom ratio z [-]; allowed [0, 1].
    """

    lhv_j_per_kg: float = 44.0e6
    h_to_c: float = 1.87
    o_to_c: float = 0.0

    def __post_init__(self):
        for name, lo, hi in (("lhv_j_per_kg", 1.0e7, 1.5e8), ("h_to_c", 0.0, 4.0), ("o_to_c", 0.0, 1.0)):
            v = getattr(self, name)
            try:
                ok = lo <= float(v) <= hi
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise ValueError(f"fuel.{name} = {v!r} is outside the allowed range [{lo:g}, {hi:g}]")
            object.__setattr__(self, name, float(v))


def _fuel_unit_mass(fuel: FuelSpec) -> float:
    """Mass of one C1HyOz unit [kg/mol]."""
    return 1e-3 * (_ATOM["C"] + fuel.h_to_c * _ATOM["H"] + fuel.o_to_c * _ATOM["O"])


def _o2_stoich(fuel: FuelSpec) -> float:
    """Moles of O2 per C1HyOz unit for complete combustion [-]."""
    return 1.0 + fuel.h_to_c / 4.0 - fuel.o_to_c / 2.0


def stoich_afr(fuel: FuelSpec) -> float:
    """Stoichiometric air/fuel mass ratio [kg air / kg fuel]."""
    m_air = sum(x * _molar_mass(s) for s, x in _AIR_X.items())
    return _o2_stoich(fuel) / _AIR_X["O2"] * m_air / _fuel_unit_mass(fuel)


def _check_lam(lam) -> float:
    try:
        lam_f = float(lam)
    except (TypeError, ValueError):
        raise ValueError(f"lam = {lam!r}: expected a number") from None
    if not (math.isfinite(lam_f) and lam_f > 0.0):
        raise ValueError(f"lam = {lam!r} must be finite and > 0")
    return lam_f


def _product_moles(lam: float, fuel: FuelSpec) -> dict[str, float]:
    """Moles of complete-combustion products per C1HyOz unit at air excess ratio ``lam``."""
    lam = _check_lam(lam)
    y, z, ast = fuel.h_to_c, fuel.o_to_c, _o2_stoich(fuel)
    o2_in = lam * ast
    n = {s: 0.0 for s in PRODUCT_SPECIES}
    n["N2"] = o2_in * _AIR_X["N2"] / _AIR_X["O2"]
    n["Ar"] = o2_in * _AIR_X["Ar"] / _AIR_X["O2"]
    if lam >= 1.0:
        n["CO2"], n["H2O"], n["O2"] = 1.0, y / 2.0, o2_in - ast
        return n
    o_tot = 2.0 * o2_in + z                       # O atoms available per C
    if o_tot <= 1.0:
        lam_min = (1.0 - z) / (2.0 * ast)
        raise ValueError(f"lam = {lam!r} is too rich: no CO2/CO-only products below lam = {lam_min:.4g} (soot)")
    # a = CO2; b = 1 - a (C); c = o_tot - 2a - b (O); d = y/2 - c (H); K a d = b c  ->  quadratic in a
    k = K_WATER_GAS
    bq = k * (y / 2.0 - o_tot + 1.0) + o_tot
    cq = o_tot - 1.0
    disc = math.sqrt(bq * bq + 4.0 * (k - 1.0) * cq)
    a = 2.0 * cq / (bq + disc) if bq >= 0.0 else (disc - bq) / (2.0 * (k - 1.0))
    n["CO2"], n["CO"] = a, 1.0 - a
    n["H2O"] = o_tot - 2.0 * a - n["CO"]
    n["H2"] = y / 2.0 - n["H2O"]
    if min(n.values()) < 0.0:
        raise ValueError(f"lam = {lam!r}: no non-negative water-gas equilibrium composition")
    return n


def products_mole_fractions(lam: float, fuel: FuelSpec = FuelSpec()) -> dict[str, float]:
    """Mole fractions of the burned gas of a fuel/air mixture at air excess ratio ``lam``.

    Lean and stoichiometric: CO2, H2O, O2, N2, Ar.  Rich: CO2, CO, H2O, H2, N2, Ar with the
    water-gas shift fixed at ``K_WATER_GAS``.  No dissociation.  All keys of ``PRODUCT_SPECIES``
    are present (zero where absent).

    Raises
    ------
    ValueError
        If ``lam`` is not finite and positive or so rich that carbon cannot be oxidised to CO.
    """
    n = _product_moles(lam, fuel)
    tot = sum(n.values())
    return {s: v / tot for s, v in n.items()}


@dataclass(frozen=True, eq=False)
class GasSet:
    """Mass-based NASA coefficients of air (0), fresh mixture (1) and products (2).

    Attributes
    ----------
    coeffs : ndarray, shape (3, 2, 7)
        [species][range][c0..c6], range 0 for T < T_MID; units J/(kg K) and J/kg (read-only).
    r_specific : ndarray, shape (3,)
        Specific gas constants [J/(kg K)].
    lam, far, afr_stoich : float
        Air excess ratio, fuel/air and stoichiometric air/fuel mass ratios [-].
    fuel_coeffs : ndarray, shape (2, 7); fuel_r_specific : float
        Mass-based coefficients and gas constant [J/(kg K)] of the fuel vapour.
    heat_release_j_per_kg_mix : float
        h_M(298.15) - h_P(298.15) [J per kg of fresh mixture burned].
    """

    coeffs: np.ndarray
    r_specific: np.ndarray
    lam: float
    far: float
    afr_stoich: float
    fuel_coeffs: np.ndarray
    fuel_r_specific: float
    heat_release_j_per_kg_mix: float


def _frozen(a) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=np.float64)
    a.flags.writeable = False
    return a


@functools.lru_cache(maxsize=32)
def _fuel_coeffs(fuel: FuelSpec) -> tuple[np.ndarray, float]:
    """Fuel-vapour mass coefficients (cp from iso-octane per kg, h_f solved from the LHV) and R."""
    m_fuel = FUEL_CARBON_NUMBER * _fuel_unit_mass(fuel)
    c_f = R_UNIVERSAL * _ISOOCTANE_A / (1e-3 * _IC8H18_M)
    c_air, _, _ = _mass_coeffs(_AIR_X)
    afr = stoich_afr(fuel)
    c_pst, _, _ = _mass_coeffs(_product_moles(1.0, fuel))
    # LHV = h_F + AFR h_A - (1 + AFR) h_P  at 298.15 K  ->  required h_F(298.15)
    hf = fuel.lhv_j_per_kg - afr * _h_np(c_air, T_REF) + (1.0 + afr) * _h_np(c_pst, T_REF)
    c_f[:, 5] += hf - _h_np(c_f, T_REF)
    return _frozen(c_f), float(R_UNIVERSAL / m_fuel)


@functools.lru_cache(maxsize=256)
def _gas_set_cached(lam: float, fuel: FuelSpec) -> GasSet:
    c_a, r_a, _ = _mass_coeffs(_AIR_X)
    c_f, r_f = _fuel_coeffs(fuel)
    afr = stoich_afr(fuel)
    far = 1.0 / (lam * afr)
    c_m = (c_a + far * c_f) / (1.0 + far)
    r_m = (r_a + far * r_f) / (1.0 + far)
    c_p, r_p, _ = _mass_coeffs(_product_moles(lam, fuel))
    q = float(_h_np(c_m, T_REF) - _h_np(c_p, T_REF))
    return GasSet(coeffs=_frozen(np.stack([c_a, c_m, c_p])), r_specific=_frozen([r_a, r_m, r_p]),
                  lam=lam, far=far, afr_stoich=afr, fuel_coeffs=c_f, fuel_r_specific=r_f,
                  heat_release_j_per_kg_mix=q)


def gas_set(lam: float, fuel: FuelSpec = FuelSpec()) -> GasSet:
    """Coefficients of air, fresh mixture and products for air excess ratio ``lam``.

    Results are cached; the arrays are read-only.

    Raises
    ------
    ValueError
        If ``lam`` is not finite and > 0, or too rich for CO/CO2-only products.
    """
    return _gas_set_cached(_check_lam(lam), fuel)


def constant_cp_gas_set(gamma: float, r_specific: float, heat_release_j_per_kg_mix: float,
                        far: float = 0.0) -> GasSet:
    """Constant-cp gas set for ideal-cycle tests.

    All three species (and the fuel) get cp = gamma R / (gamma - 1) and the same R.  A and M have
    h(298.15) = 0; P is offset by ``-heat_release_j_per_kg_mix`` so that M -> P at any fixed T
    releases exactly that heat.  ``lam`` is reported as 1 and ``afr_stoich`` as 1/far (inf if 0).
    """
    for name, v, ok in (("gamma", gamma, lambda x: x > 1.0), ("r_specific", r_specific, lambda x: x > 0.0),
                        ("heat_release_j_per_kg_mix", heat_release_j_per_kg_mix, lambda x: True),
                        ("far", far, lambda x: x >= 0.0)):
        if not (math.isfinite(float(v)) and ok(float(v))):
            raise ValueError(f"{name} = {v!r} is not allowed (gamma > 1, r_specific > 0, far >= 0, all finite)")
    cp = gamma * r_specific / (gamma - 1.0)
    c = np.zeros((2, 7))
    c[:, 0] = cp
    c[:, 5] = -cp * T_REF
    coeffs = np.stack([c, c, c])
    coeffs[2, :, 5] -= heat_release_j_per_kg_mix
    return GasSet(coeffs=_frozen(coeffs), r_specific=_frozen([r_specific] * 3), lam=1.0, far=float(far),
                  afr_stoich=(1.0 / far if far > 0.0 else math.inf), fuel_coeffs=_frozen(c),
                  fuel_r_specific=float(r_specific), heat_release_j_per_kg_mix=float(heat_release_j_per_kg_mix))


# ---------------------------------------------------------------- numba kernels over one (2, 7) block
_jit = numba.njit(cache=True, fastmath=False, _nrt=False)


@_jit
def cp_mass(c, T):
    """Specific heat at constant pressure [J/(kg K)] at temperature T [K]."""
    k = 0 if T < T_MID else 1
    return c[k, 0] + T * (c[k, 1] + T * (c[k, 2] + T * (c[k, 3] + T * c[k, 4])))


@_jit
def h_mass(c, T):
    """Absolute specific enthalpy [J/kg] at T [K]."""
    k = 0 if T < T_MID else 1
    return T * (c[k, 0] + T * (c[k, 1] / 2.0 + T * (c[k, 2] / 3.0 + T * (c[k, 3] / 4.0 + T * c[k, 4] / 5.0)))) + c[k, 5]


@_jit
def s0_mass(c, T):
    """Standard-state specific entropy [J/(kg K)] at T [K] (no mixing or pressure term)."""
    k = 0 if T < T_MID else 1
    return c[k, 0] * math.log(T) + T * (c[k, 1] + T * (c[k, 2] / 2.0 + T * (c[k, 3] / 3.0 + T * c[k, 4] / 4.0))) + c[k, 6]


@_jit
def u_mass(c, r, T):
    """Specific internal energy u = h - R T [J/kg]; r is the gas constant [J/(kg K)]."""
    return h_mass(c, T) - r * T


@_jit
def cv_mass(c, r, T):
    """Specific heat at constant volume [J/(kg K)]."""
    return cp_mass(c, T) - r


@_jit
def temperature_from_u(c, r, u, t_guess):
    """Temperature [K] at which u_mass(c, r, T) equals ``u`` [J/kg].

    Newton iteration from ``t_guess`` [K], stopping when the step is below 1e-9 of T or after 20
    steps; T is clamped to [150, 4500] K (a target outside that range returns the bound).
    """
    T = min(t_guess, _T_MAX) if t_guess >= _T_MIN else (_T_MIN if t_guess < _T_MIN else T_MID)  # NaN -> T_MID
    for _ in range(20):
        k = 0 if T < T_MID else 1
        cv = c[k, 0] - r + T * (c[k, 1] + T * (c[k, 2] + T * (c[k, 3] + T * c[k, 4])))
        uu = T * (c[k, 0] - r + T * (c[k, 1] / 2.0 + T * (c[k, 2] / 3.0 + T * (c[k, 3] / 4.0 + T * c[k, 4] / 5.0)))) + c[k, 5]
        t_new = T - (uu - u) / cv
        if t_new < _T_MIN:
            t_new = _T_MIN
        elif t_new > _T_MAX:
            t_new = _T_MAX
        if abs(t_new - T) <= 1e-9 * t_new:
            return t_new
        T = t_new
    return T


@_jit
def mix_coeffs(coeffs, y_a, y_m, y_p, out):
    """Write the mass-fraction-weighted (2,7) block y_a*A + y_m*M + y_p*P of ``coeffs`` into ``out``."""
    for i in range(2):
        for j in range(7):
            out[i, j] = y_a * coeffs[0, i, j] + y_m * coeffs[1, i, j] + y_p * coeffs[2, i, j]


def enthalpy_coeffs(coeffs) -> np.ndarray:
    """Enthalpy-polynomial form of a (3, 2, 7) block of NASA mass coefficients: (3, 2, 6) [c0, c1/2, c2/3, c3/4, c4/5, c5].

    h(T) = T (e0 + T (e1 + T (e2 + T (e3 + T e4)))) + e5 and
    cp(T) = e0 + T (2 e1 + T (3 e2 + T (4 e3 + T 5 e4))): the form the cycle
    kernel mixes, so that its Newton iteration on u(T) does no division by the
    polynomial's integer constants.  Python face of :func:`enthalpy_coeffs_into`.
    """
    c = np.ascontiguousarray(coeffs, dtype=np.float64)
    if c.shape != (3, 2, 7):
        raise ValueError(f"enthalpy_coeffs: expected (3, 2, 7) coefficients (species A, M, P x 2 ranges), "
                         f"got shape {c.shape}")
    out = np.empty((3, 2, 6))
    enthalpy_coeffs_into(c, out)
    return out


@_jit
def enthalpy_coeffs_into(coeffs, out):
    """Compiled form of :func:`enthalpy_coeffs` for a (3, 2, 7) block into ``out`` (3, 2, 6)."""
    for s in range(3):
        for k in range(2):
            for j in range(5):
                out[s, k, j] = coeffs[s, k, j] / (j + 1.0)
            out[s, k, 5] = coeffs[s, k, 5]


@_jit
def _mix_range(hcoeffs, k, y_a, y_m, y_p):
    """Mass-weighted enthalpy-polynomial coefficients (e0..e5, see ``enthalpy_coeffs``) of temperature range k."""
    return (y_a * hcoeffs[0, k, 0] + y_m * hcoeffs[1, k, 0] + y_p * hcoeffs[2, k, 0],
            y_a * hcoeffs[0, k, 1] + y_m * hcoeffs[1, k, 1] + y_p * hcoeffs[2, k, 1],
            y_a * hcoeffs[0, k, 2] + y_m * hcoeffs[1, k, 2] + y_p * hcoeffs[2, k, 2],
            y_a * hcoeffs[0, k, 3] + y_m * hcoeffs[1, k, 3] + y_p * hcoeffs[2, k, 3],
            y_a * hcoeffs[0, k, 4] + y_m * hcoeffs[1, k, 4] + y_p * hcoeffs[2, k, 4],
            y_a * hcoeffs[0, k, 5] + y_m * hcoeffs[1, k, 5] + y_p * hcoeffs[2, k, 5])


@_jit
def mixture_state(hcoeffs, rsp, y_a, y_m, y_p, u, t_guess, out):
    """Temperature, cp, h and R of a three-species mixture from its specific internal energy, in one pass.

    Mixes only the coefficient range the Newton iteration is in (re-mixing if
    it crosses ``T_MID``), which is what the cycle kernel needs per volume per
    stage.  Same result as ``mix_coeffs`` + ``temperature_from_u`` +
    ``cp_mass`` + ``h_mass``.

    Parameters
    ----------
    hcoeffs : (3, 2, 6) float64
        Enthalpy-polynomial coefficients of A, M, P (``enthalpy_coeffs`` of the mass-based NASA block).
    rsp : (3,) float64
        Specific gas constants [J/(kg K)].
    y_a, y_m, y_p : float
        Mass fractions [-].
    u : float
        Specific internal energy [J/kg].
    t_guess : float
        Starting temperature [K].
    out : (4,) float64
        Receives T [K], cp [J/(kg K)], h [J/kg], R [J/(kg K)].
    """
    t, cp, h, r = mixture_tcphr(hcoeffs, rsp, y_a, y_m, y_p, u, t_guess)
    out[0] = t
    out[1] = cp
    out[2] = h
    out[3] = r


# Newton on u(T) converges quadratically: after a step d the error left is
# ~ (dcv/dT)/(2 cv) * d^2, and (dcv/dT)/(2 cv) < 1e-3 1/K for every gas here
# (largest for CO2 and fuel vapour at low T, NASA polynomials).  Stopping once
# d^2 < 1e-4 K^2 therefore leaves < 1e-7 K, without the confirming extra step
# that a bound on d itself would cost.
_NEWTON_STEP2 = 1e-4   # [K^2]


# inlined into its caller at the numba level (the cycle kernel calls it 30 times
# per step; a call passes each array argument as a 7-word struct on the stack),
# and with fused multiply-adds like the cycle kernels (see cycle/layout.py).
# numba's cache=True does not track this dependency; engine_model/cycle/__init__.py
# drops the cycle kernels' cache when this file changes.
@numba.njit(cache=True, fastmath={"contract"}, _nrt=False, inline="always")
def mixture_tcphr(hcoeffs, rsp, y_a, y_m, y_p, u, t_guess):
    """(T, cp, h, R) of a three-species mixture from its specific internal energy; see ``mixture_state``.

    Scalar-returning form used by the cycle kernel.  Newton from ``t_guess``,
    re-mixing the coefficients if the iterate crosses ``T_MID``; h = u + R T.
    """
    r = y_a * rsp[0] + y_m * rsp[1] + y_p * rsp[2]
    T = t_guess if (t_guess >= _T_MIN and t_guess <= _T_MAX) else T_MID
    k = 0 if T < T_MID else 1
    e0, e1, e2, e3, e4, e5 = _mix_range(hcoeffs, k, y_a, y_m, y_p)
    for _ in range(30):
        # u(T) = T (e0 - r + T (e1 + T (e2 + T (e3 + T e4)))) + e5, cv = du/dT
        cv = e0 - r + T * (2.0 * e1 + T * (3.0 * e2 + T * (4.0 * e3 + T * (5.0 * e4))))
        uu = T * (e0 - r + T * (e1 + T * (e2 + T * (e3 + T * e4)))) + e5
        t_new = T - (uu - u) / cv
        if t_new < _T_MIN:
            t_new = _T_MIN
        elif t_new > _T_MAX:
            t_new = _T_MAX
        k_new = 0 if t_new < T_MID else 1
        if k_new != k:
            k = k_new
            e0, e1, e2, e3, e4, e5 = _mix_range(hcoeffs, k, y_a, y_m, y_p)
            T = t_new
            continue
        d = t_new - T
        done = d * d <= _NEWTON_STEP2
        T = t_new
        if done:
            break
    cp = e0 + T * (2.0 * e1 + T * (3.0 * e2 + T * (4.0 * e3 + T * (5.0 * e4))))
    return T, cp, u + r * T, r
