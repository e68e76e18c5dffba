"""Quasi-1D gas dynamics in pipes: conservative MUSCL-Hancock finite volumes with the HLLC flux.

State
-----
All pipes of a network share one flat array of cells ``q[ncell, NQ]`` holding cell *totals*:
masses of air, fresh mixture and products [kg] (columns ``Q_A, Q_M, Q_P``, the same indices and
units as ``V_MA, V_MM, V_MP`` of a 0D volume), axial momentum [kg m/s] (``Q_MOM``) and total
energy [J] (``Q_E``) = internal energy including the enthalpies of formation (the energy a 0D volume
holds in ``V_U``) plus kinetic energy.  A cell is therefore bookkept exactly like a 0D volume and
mass and energy move between cells and volumes without conversion.  ``tcell[ncell]`` keeps each
cell's temperature as the warm start of its u -> T Newton inversion (as ``vol[:, V_T]`` does).

The layout (``build_pipes``) is an int table ``pipes[npipe, 2]`` = (first cell, number of cells)
and a cell-geometry table ``geom[NG, ncell]`` (struct of arrays: cell volume, length, face areas,
hydraulic diameter, wall temperature, friction and heat-transfer data; see the ``G_*`` constants).
Cell ``i`` of a pipe spans [x_i-1/2, x_i+1/2]; the *left* end of a pipe is its first cell's left
face (x = 0), the *right* end its last cell's right face (x = L); velocity and momentum are
positive from left to right.

Per step the caller (1) evaluates the primitive state of every cell (``pipe_props``: density,
velocity, pressure, temperature, sound speed, gamma, cp, enthalpy, gas constant, mass fractions into
``prim[NPM, ncell]``), (2) computes the flux across every pipe end with the boundary functions of
:mod:`engine_model.cycle.pipe_bc` into ``bflux[npipe, 2, NQ]``, (3) advances all pipes by dt with
``advance`` and updates its 0D volumes with the same end fluxes.  ``max_stable_dt`` gives the
largest stable step for the current ``prim``.

Scheme
------
Equations: the quasi-1D Euler equations for a pipe of cross-section A(x),
d(rho Y_s A)/dt + d(rho Y_s u A)/dx = 0, d(rho u A)/dt + d((rho u^2 + p) A)/dx = p dA/dx - tau_w P_w,
d(E A)/dt + d(u (E + p) A)/dx = q_w P_w, integrated over each cell (finite volumes on cell totals,
face fluxes times face areas), which makes the update conservative by construction: the
number that leaves one cell through a face enters its neighbour.

* **Reconstruction** (Toro 2009, ch. 14, sec. 14.4, MUSCL-Hancock; ch. 13-14 for TVD slope
  limiters): piecewise-linear in the primitive variables rho, Y_s, u, p with the van Leer (harmonic)
  limiter, 2 a b / (a + b) for a b > 0, else 0.  Van Leer sits between minmod (too diffusive for
  the acoustics the engine model is about) and MC/superbee (compressive, square off smooth waves);
  it is smooth in its arguments, so the order at smooth points is not lost to limiter switching.
  The three mass fractions get one common limiter factor applied to their central slopes (the
  smallest of the per-species van Leer ratios 4 a b / (a + b)^2), so the reconstructed fractions
  still sum to one and stay inside their neighbours' range.  The end cells of a pipe are
  reconstructed piecewise-constant (their outer neighbour is a boundary, not a cell).
* **Hancock predictor**: the face values of each cell are advanced by dt/2 with the primitive,
  non-conservative form of the quasi-1D equations evaluated at the cell (rho_t = -u rho_x - rho u_x
  - rho u A'/A, u_t = -u u_x - p_x / rho, p_t = -u p_x - rho c^2 u_x - rho c^2 u A'/A, Y_t = -u Y_x),
  the "primitive-variable" form of the predictor; it costs no flux evaluations and is well balanced
  by itself (u = 0, p_x = 0 gives no change).
* **Riemann solver**: HLLC (Toro 2009, sec. 10.4) written for a general equation of state: the
  star states follow from p, rho, u and E of each side alone (Rankine-Hugoniot across S_L, S_R and
  the contact S*), species travel as partial densities with the mass flux, each with the mass
  fraction of its side of the contact, so a contact (backflow of burned gas into a port) keeps its
  composition and temperature instead of being smeared into an average.  Wave-speed estimates: the
  pressure-based ones of Toro sec. 10.5 (PVRS guess of p*, shock branch sqrt(1 + (g+1)/(2g)
  (p*/p_K - 1)) with each side's own gamma = cp/(cp - R) at its reconstructed temperature; c^2 =
  gamma R T is exact for a thermally perfect mixture).  They bound the true speeds more tightly than
  Davis' min/max estimates (less dissipation at contacts) and need no Roe average of a
  variable-gamma gas.  The face thermodynamics (T = p/(rho R), e(T) and cp(T) from the NASA
  polynomials of the face's mixture) is evaluated exactly, so every face state is consistent with
  the cell energies it is built from.
* **Area source**: the cell's momentum gets (p_L + p_R)/2 (A_i+1/2 - A_i-1/2) with p_L, p_R the
  cell's own reconstructed-and-predicted face pressures (the integral of a linear p against dA over
  the cell).  For a gas at rest (u = 0, uniform p) the HLLC momentum flux at each face is exactly p
  (S* = 0, star states identical to the side states; the code forms U* - U so that this holds in
  floating point) and the source equals p (A_R - A_L) term for term, so the state stays at rest to
  round-off whatever the area variation (tested).
* **Wall friction and heat transfer**: explicit source terms evaluated with the cell state at the
  start of the step (first order in time; both act on time scales D / (f |u|) of ~10 ms, three
  orders above the step).  Darcy factor from Haaland's explicit formula with the wall roughness
  (turbulent, evaluated at Re >= 2300), 64/Re where larger (laminar, so friction and heat transfer
  stay finite and linear in u as u -> 0), Re = rho |u| D / mu(T) (Sutherland, as in
  ``flow.gas_viscosity``), or a fixed factor per pipe.  Wall shear tau_w = f rho u |u| / 8 acts on
  the wetted perimeter; friction does no work on the gas as a whole (the wall does not move), so the
  total energy gets no friction term: the kinetic energy it removes reappears as internal energy.
  Heat flux by the Chilton-Colburn analogy St Pr^(2/3) = f / 8 with Pr = 0.7: q_w = (f/8) rho |u| cp
  Pr^(-2/3) (T_w - T).
* **Time integration**: the MUSCL-Hancock step is a one-step predictor-corrector, second order in
  time for the homogeneous part; it is stable for Courant numbers max(|u| + c) dt / dx <= 1 (Toro
  ch. 14); ``max_stable_dt`` returns cfl * dx / max(|u| + c) with cfl = 0.9 by default.  The end
  fluxes are supplied by the caller for the whole step (they are computed from the cell states at
  the start of the step: first order in time at the pipe ends).

References
----------
Toro, E.F., Riemann Solvers and Numerical Methods for Fluid Dynamics, 3rd ed., Springer 2009:
ch. 4 (exact Riemann solver, used by the tests), sec. 10.4-10.6 (HLLC, wave-speed estimates),
ch. 13-14 (TVD slope limiters, MUSCL-Hancock).
van Leer, B., "Towards the ultimate conservative difference scheme V", J. Comput. Phys. 32 (1979)
101-136 (MUSCL, the harmonic limiter).
Haaland, S.E., J. Fluids Eng. 105 (1983) 89-90 (friction factor).
Colburn, A.P., Trans. AIChE 29 (1933) 174-210 (heat transfer / friction analogy).
"""

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..thermo import T_MID, mixture_tcphr
from .flow import gas_viscosity
from .layout import FASTMATH

# ------------------------------------------------------------------ cell state columns q[i, :]
Q_A = 0      # mass of air [kg]            (= V_MA of a 0D volume)
Q_M = 1      # mass of fresh mixture [kg]  (= V_MM)
Q_P = 2      # mass of products [kg]       (= V_MP)
Q_MOM = 3    # axial momentum [kg m/s], positive from the pipe's left end to its right end
Q_E = 4      # total energy [J]: internal incl. formation enthalpies (as V_U) + kinetic
NQ = 5

# ------------------------------------------------------------------ primitive rows prim[k, i]
PM_RHO = 0   # density [kg/m3]
PM_U = 1     # velocity [m/s]
PM_P = 2     # pressure [Pa]
PM_T = 3     # temperature [K]
PM_C = 4     # sound speed [m/s]
PM_G = 5     # gamma = cp / (cp - R) [-]
PM_CP = 6    # cp [J/(kg K)]
PM_H = 7     # absolute specific enthalpy [J/kg]
PM_R = 8     # gas constant [J/(kg K)]
PM_YA = 9    # mass fractions [-]
PM_YM = 10
PM_YP = 11
NPM = 12

# ------------------------------------------------------------------ cell geometry rows geom[k, i]
G_V = 0      # cell volume [m3]
G_INVV = 1   # 1 / volume [1/m3]
G_DX = 2     # cell length [m]
G_INVDX = 3  # 1 / length [1/m]
G_AL = 4     # area of the left face [m2]
G_AR = 5     # area of the right face [m2]
G_DLNA = 6   # (A_R - A_L) / V = (dA/dx) / A [1/m]
G_D = 7      # hydraulic diameter at the cell centre [m]
G_TW = 8     # wall temperature [K]
G_FFIX = 9   # fixed Darcy friction factor [-]; 0 = Haaland from Re and roughness
G_RGH = 10   # (eps/D / 3.7)^1.11, the roughness term of Haaland's formula [-]
G_KF = 11    # friction multiplier * V / (2 D) [m2]: momentum source = -f rho u |u| * G_KF
G_KH = 12    # heat-transfer multiplier * V / (2 D Pr^(2/3)) [m2]: heat = f rho |u| cp (Tw - T) * G_KH
NG = 13

# ------------------------------------------------------------------ face-state work rows work[k, i]
# the predicted state of cell i at its left face (W_*) and right face (W_* + NWS)
W_RHO = 0
W_YA = 1
W_YM = 2
W_YP = 3
W_U = 4
W_P = 5
W_E = 6      # total energy per volume [J/m3]
W_C = 7      # sound speed [m/s]
W_G = 8      # gamma [-]
NWS = 9
NWK = 2 * NWS

# Haaland's formula is evaluated at Re >= RE_TURB (below it is meaningless, and at Re ~ 7 it is
# singular); the laminar 64/Re is taken where larger, so f(Re) is continuous: 64/Re up to Re ~ 1300,
# then a plateau at Haaland's value for 2300 through the transition, then Haaland.
RE_TURB = 2300.0
PRANDTL = 0.7            # [-] Prandtl number of air and burned gas, 300-1500 K (design value)
_PR23 = PRANDTL ** (2.0 / 3.0)
T_MIN_OK, T_MAX_OK = 150.0, 4400.0   # [K] a cell outside this range counts as failed (as volumes.py)


# ================================================================== Python-side builder
@dataclass(frozen=True)
class PipeSpec:
    """Geometry and wall data of one pipe.

    Parameters
    ----------
    length : float
        Length [m].
    n_cells : int
        Number of finite volumes (>= 1).
    d_left, d_right : float
        Inner diameter at the left (x = 0) and right (x = L) end [m]; linear taper in between.
        ``d_right`` defaults to ``d_left``.
    d_faces : sequence of float, optional
        Diameters at all ``n_cells + 1`` faces [m] (overrides d_left/d_right); cells are conical frusta.
    wall_temperature : float
        Wall temperature [K] for the heat transfer.
    roughness : float
        Absolute wall roughness [m] for Haaland's friction factor (0 = smooth).
    darcy_f : float
        Fixed Darcy friction factor [-]; 0 (default) computes it from Re and roughness.
    friction : float
        Multiplier on the wall shear [-] (0 = frictionless).
    heat_transfer : float
        Multiplier on the wall heat flux [-] (0 = adiabatic).
    """

    length: float
    n_cells: int
    d_left: float
    d_right: float | None = None
    d_faces: tuple | None = None
    wall_temperature: float = 300.0
    roughness: float = 0.0
    darcy_f: float = 0.0
    friction: float = 1.0
    heat_transfer: float = 1.0


@dataclass(frozen=True, eq=False)
class PipeNet:
    """Flat arrays of a set of pipes (see the module docstring).

    Attributes
    ----------
    pipes : ndarray int64 (npipe, 2)
        First cell and number of cells of each pipe.
    geom : ndarray float64 (NG, ncell)
        Cell geometry, rows ``G_*``.
    ncell, npipe : int
    specs : tuple of PipeSpec
    """

    pipes: np.ndarray
    geom: np.ndarray
    ncell: int
    npipe: int
    specs: tuple

    def first_cell(self, ip):
        """Index of the first (left-end) cell of pipe ``ip``."""
        return int(self.pipes[ip, 0])

    def last_cell(self, ip):
        """Index of the last (right-end) cell of pipe ``ip``."""
        return int(self.pipes[ip, 0] + self.pipes[ip, 1] - 1)

    def x_centres(self, ip):
        """Cell-centre positions of pipe ``ip`` from its left end [m]."""
        n = int(self.pipes[ip, 1])
        dx = self.specs[ip].length / n
        return (np.arange(n) + 0.5) * dx

    def new_arrays(self):
        """Fresh work arrays: (q, tcell, prim, work, bflux, wb), zeros except tcell = 300 K."""
        return (np.zeros((self.ncell, NQ)), np.full(self.ncell, 300.0), np.zeros((NPM, self.ncell)),
                np.zeros((NWK, self.ncell)), np.zeros((self.npipe, 2, NQ)), np.zeros((self.npipe, 2)))


def build_pipes(specs) -> PipeNet:
    """Flat layout of a list of :class:`PipeSpec` (cells numbered pipe after pipe).

    Raises
    ------
    ValueError
        For a non-positive length, cell count or diameter.
    """
    specs = tuple(specs)
    if not specs:
        raise ValueError("build_pipes: no pipes")
    rows = []
    pipes = np.zeros((len(specs), 2), dtype=np.int64)
    first = 0
    for ip, s in enumerate(specs):
        n = int(s.n_cells)
        if n < 1 or not (s.length > 0.0):
            raise ValueError(f"pipe {ip}: length {s.length!r} and n_cells {s.n_cells!r} must be positive")
        if s.d_faces is not None:
            d = np.asarray(s.d_faces, dtype=float)
            if d.shape != (n + 1,):
                raise ValueError(f"pipe {ip}: d_faces needs n_cells + 1 = {n + 1} values, got {d.shape}")
        else:
            d_r = s.d_left if s.d_right is None else s.d_right
            d = np.linspace(s.d_left, d_r, n + 1)
        if not np.all(d > 0.0):
            raise ValueError(f"pipe {ip}: diameters must be positive")
        if s.darcy_f < 0.0 or s.roughness < 0.0 or s.friction < 0.0 or s.heat_transfer < 0.0:
            raise ValueError(f"pipe {ip}: darcy_f, roughness and the multipliers must be >= 0")
        dx = s.length / n
        af = 0.25 * np.pi * d * d
        dl, dr = d[:-1], d[1:]
        vol = np.pi * dx / 12.0 * (dl * dl + dl * dr + dr * dr)   # conical frustum
        dh = np.sqrt(4.0 * vol / (dx * np.pi))                    # diameter of the mean section
        g = np.zeros((NG, n))
        g[G_V] = vol
        g[G_INVV] = 1.0 / vol
        g[G_DX] = dx
        g[G_INVDX] = 1.0 / dx
        g[G_AL] = af[:-1]
        g[G_AR] = af[1:]
        g[G_DLNA] = (af[1:] - af[:-1]) / vol
        g[G_D] = dh
        g[G_TW] = s.wall_temperature
        g[G_FFIX] = s.darcy_f
        g[G_RGH] = (s.roughness / dh / 3.7) ** 1.11
        g[G_KF] = s.friction * vol / (2.0 * dh)
        g[G_KH] = s.heat_transfer * vol / (2.0 * dh * _PR23)
        rows.append(g)
        pipes[ip] = first, n
        first += n
    geom = np.ascontiguousarray(np.concatenate(rows, axis=1))
    return PipeNet(pipes=pipes, geom=geom, ncell=first, npipe=len(specs), specs=specs)


# ================================================================== state set-up and inventory
@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def fill_cells(q, tcell, geom, i_start, i_end, p, t, u, ya, ym, yp, hcoeffs, rsp):
    """Set cells [i_start, i_end) to pressure p [Pa], temperature t [K], velocity u [m/s], mass fractions."""
    r = ya * rsp[0] + ym * rsp[1] + yp * rsp[2]
    rho = p / (r * t)
    k = 0 if t < T_MID else 1
    h = 0.0
    for s, y in ((0, ya), (1, ym), (2, yp)):
        c = hcoeffs[s, k]
        h += y * (t * (c[0] + t * (c[1] + t * (c[2] + t * (c[3] + t * c[4])))) + c[5])
    e = h - r * t
    for i in range(i_start, i_end):
        m = rho * geom[G_V, i]
        q[i, Q_A] = m * ya
        q[i, Q_M] = m * ym
        q[i, Q_P] = m * yp
        q[i, Q_MOM] = m * u
        q[i, Q_E] = m * (e + 0.5 * u * u)
        tcell[i] = t


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def inventory(q, i_start, i_end, out):
    """Sums over cells [i_start, i_end): out = (air, mixture, products [kg], momentum [kg m/s], energy [J])."""
    for j in range(NQ):
        out[j] = 0.0
    for i in range(i_start, i_end):
        for j in range(NQ):
            out[j] += q[i, j]


# ================================================================== primitive state of every cell
@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def pipe_props(q, tcell, geom, ncell, hcoeffs, rsp, prim):
    """Fill ``prim[:, :ncell]`` from the cell totals; Newton for T from the warm start ``tcell`` (updated).

    Returns 0, or 1 + the index of the first cell with non-positive or non-finite mass or a
    temperature outside [150, 4400] K (``prim`` is then incomplete).
    """
    for i in range(ncell):
        ma = q[i, Q_A]
        mm = q[i, Q_M]
        mp = q[i, Q_P]
        m = ma + mm + mp
        if not (m > 0.0) or ma < 0.0 or mm < 0.0 or mp < 0.0:
            return 1 + i
        inv_m = 1.0 / m
        ya = ma * inv_m
        ym = mm * inv_m
        yp = mp * inv_m
        u = q[i, Q_MOM] * inv_m
        e = q[i, Q_E] * inv_m - 0.5 * u * u
        t, cp, h, r = mixture_tcphr(hcoeffs, rsp, ya, ym, yp, e, tcell[i])
        if not (t > T_MIN_OK and t < T_MAX_OK):
            return 1 + i
        tcell[i] = t
        rho = m * geom[G_INVV, i]
        g = cp / (cp - r)
        prim[PM_RHO, i] = rho
        prim[PM_U, i] = u
        prim[PM_P, i] = rho * r * t
        prim[PM_T, i] = t
        prim[PM_C, i] = math.sqrt(g * r * t)
        prim[PM_G, i] = g
        prim[PM_CP, i] = cp
        prim[PM_H, i] = h
        prim[PM_R, i] = r
        prim[PM_YA, i] = ya
        prim[PM_YM, i] = ym
        prim[PM_YP, i] = yp
    return 0


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def max_stable_dt(prim, geom, ncell, cfl):
    """Largest stable time step [s]: cfl * min over cells of dx / (|u| + c); cfl <= 1 (0.9 recommended)."""
    smax = 0.0
    for i in range(ncell):
        s = (abs(prim[PM_U, i]) + prim[PM_C, i]) * geom[G_INVDX, i]
        if s > smax:
            smax = s
    return cfl / smax if smax > 0.0 else math.inf


# ================================================================== face thermodynamics and HLLC
@njit(cache=True, fastmath=FASTMATH, _nrt=False, inline="always")
def _face_eos(hcoeffs, rsp, ya, ym, yp, rho, p):
    """(rho e [J/m3], c [m/s], gamma) of a mixture at density rho and pressure p (exact polynomials)."""
    r = ya * rsp[0] + ym * rsp[1] + yp * rsp[2]
    t = p / (rho * r)
    k = 0 if t < T_MID else 1
    e0 = ya * hcoeffs[0, k, 0] + ym * hcoeffs[1, k, 0] + yp * hcoeffs[2, k, 0]
    e1 = ya * hcoeffs[0, k, 1] + ym * hcoeffs[1, k, 1] + yp * hcoeffs[2, k, 1]
    e2 = ya * hcoeffs[0, k, 2] + ym * hcoeffs[1, k, 2] + yp * hcoeffs[2, k, 2]
    e3 = ya * hcoeffs[0, k, 3] + ym * hcoeffs[1, k, 3] + yp * hcoeffs[2, k, 3]
    e4 = ya * hcoeffs[0, k, 4] + ym * hcoeffs[1, k, 4] + yp * hcoeffs[2, k, 4]
    e5 = ya * hcoeffs[0, k, 5] + ym * hcoeffs[1, k, 5] + yp * hcoeffs[2, k, 5]
    h = t * (e0 + t * (e1 + t * (e2 + t * (e3 + t * e4)))) + e5
    cp = e0 + t * (2.0 * e1 + t * (3.0 * e2 + t * (4.0 * e3 + t * (5.0 * e4))))
    g = cp / (cp - r)
    return rho * h - p, math.sqrt(g * p / rho), g


@njit(cache=True, fastmath=FASTMATH, _nrt=False, inline="always")
def _hllc(rl, yal, yml, ypl, ul, pl, el, cl, gl, rr, yar, ymr, ypr, ur, pr, er, cr, gr):
    """HLLC flux per unit area (mass A, M, P [kg/(m2 s)], momentum [Pa], energy [W/m2]); e* = total energy per volume."""
    # pressure-based wave-speed estimates (Toro sec. 10.5): PVRS p*, then each side's own gamma
    pm = 0.5 * (pl + pr) - 0.125 * (ur - ul) * (rl + rr) * (cl + cr)
    if pm < 0.0:
        pm = 0.0
    ql = 1.0
    if pm > pl:
        ql = math.sqrt(1.0 + (gl + 1.0) / (2.0 * gl) * (pm / pl - 1.0))
    qr = 1.0
    if pm > pr:
        qr = math.sqrt(1.0 + (gr + 1.0) / (2.0 * gr) * (pm / pr - 1.0))
    sl = ul - cl * ql
    sr = ur + cr * qr
    if sl >= 0.0:
        m = rl * ul
        return m * yal, m * yml, m * ypl, m * ul + pl, ul * (el + pl)
    if sr <= 0.0:
        m = rr * ur
        return m * yar, m * ymr, m * ypr, m * ur + pr, ur * (er + pr)
    dl = rl * (sl - ul)          # mass flux through the left wave, seen from it
    dr = rr * (sr - ur)
    ss = (pr - pl + ul * dl - ur * dr) / (dl - dr)
    if ss >= 0.0:
        # star state minus left state: (chi - 1) U_L + chi (0, rho (S* - u), E-term), chi = (S_L - u_L)/(S_L - S*)
        chi1 = (ss - ul) / (sl - ss)                 # chi - 1, exactly 0 when S* = u_L
        chi = chi1 + 1.0
        m = rl * ul + sl * rl * chi1                 # = rho*_L S*
        mom = rl * ul * ul + pl + sl * (m - rl * ul)
        de = chi1 * el + chi * (ss - ul) * (rl * ss + pl / (sl - ul))
        en = ul * (el + pl) + sl * de
        return m * yal, m * yml, m * ypl, mom, en
    chi1 = (ss - ur) / (sr - ss)
    chi = chi1 + 1.0
    m = rr * ur + sr * rr * chi1
    mom = rr * ur * ur + pr + sr * (m - rr * ur)
    de = chi1 * er + chi * (ss - ur) * (rr * ss + pr / (sr - ur))
    en = ur * (er + pr) + sr * de
    return m * yar, m * ymr, m * ypr, mom, en


@njit(cache=True, fastmath=FASTMATH, _nrt=False, inline="always")
def _vl(a, b):
    """Van Leer (harmonic) limited slope of the one-sided differences a, b."""
    ab = a * b
    return 2.0 * ab / (a + b) if ab > 0.0 else 0.0


@njit(cache=True, fastmath=FASTMATH, _nrt=False, inline="always")
def _phi(a, b):
    """Van Leer slope / central slope, in [0, 1] (1 where both differences vanish)."""
    ab = a * b
    if ab > 0.0:
        s = a + b
        return 4.0 * ab / (s * s)
    if a == 0.0 and b == 0.0:
        return 1.0
    return 0.0


# ================================================================== the step
@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _face_states(prim, geom, i0, n, dt, hcoeffs, rsp, work):
    """Reconstruct, predict by dt/2 and store the left/right face states of the cells of one pipe."""
    hdt = 0.5 * dt
    for i in range(i0, i0 + n):
        rho = prim[PM_RHO, i]
        u = prim[PM_U, i]
        p = prim[PM_P, i]
        ya = prim[PM_YA, i]
        ym = prim[PM_YM, i]
        yp = prim[PM_YP, i]
        rc2 = prim[PM_G, i] * p                   # rho c^2
        nu = hdt * geom[G_INVDX, i]
        dla = hdt * u * geom[G_DLNA, i]           # dt/2 u A'/A
        if i == i0 or i == i0 + n - 1:
            drho = 0.0
            du = 0.0
            dp = 0.0
            dya = 0.0
            dym = 0.0
            dyp = 0.0
        else:
            drho = _vl(rho - prim[PM_RHO, i - 1], prim[PM_RHO, i + 1] - rho)
            du = _vl(u - prim[PM_U, i - 1], prim[PM_U, i + 1] - u)
            dp = _vl(p - prim[PM_P, i - 1], prim[PM_P, i + 1] - p)
            aa = ya - prim[PM_YA, i - 1]
            ba = prim[PM_YA, i + 1] - ya
            am = ym - prim[PM_YM, i - 1]
            bm = prim[PM_YM, i + 1] - ym
            ap = yp - prim[PM_YP, i - 1]
            bp = prim[PM_YP, i + 1] - yp
            phi = min(_phi(aa, ba), _phi(am, bm), _phi(ap, bp))
            dya = 0.5 * phi * (aa + ba)           # common factor on the central slopes: sum stays 0
            dym = 0.5 * phi * (am + bm)
            dyp = 0.5 * phi * (ap + bp)
        # Hancock predictor: dt/2 of the primitive quasi-1D equations at the cell
        prho = -nu * (u * drho + rho * du) - dla * rho
        pu = -nu * (u * du + dp / rho)
        pp = -nu * (u * dp + rc2 * du) - dla * rc2
        pya = -nu * u * dya
        pym = -nu * u * dym
        pyp = -nu * u * dyp
        rl = rho + prho - 0.5 * drho
        rr = rho + prho + 0.5 * drho
        pl = p + pp - 0.5 * dp
        pr = p + pp + 0.5 * dp
        if not (rl > 0.0 and rr > 0.0 and pl > 0.0 and pr > 0.0):
            # a limited slope too steep for positivity: first order in this cell
            drho = 0.0
            du = 0.0
            dp = 0.0
            dya = 0.0
            dym = 0.0
            dyp = 0.0
            prho = 0.0
            pu = 0.0
            pp = 0.0
            pya = 0.0
            pym = 0.0
            pyp = 0.0
            rl = rho
            rr = rho
            pl = p
            pr = p
        for side in range(2):
            sg = -0.5 if side == 0 else 0.5
            o = side * NWS
            fr = rl if side == 0 else rr
            fp = pl if side == 0 else pr
            fa = max(ya + pya + sg * dya, 0.0)
            fm = max(ym + pym + sg * dym, 0.0)
            fq = max(yp + pyp + sg * dyp, 0.0)
            inv = 1.0 / (fa + fm + fq)
            fa *= inv
            fm *= inv
            fq *= inv
            fu = u + pu + sg * du
            rhoe, c, g = _face_eos(hcoeffs, rsp, fa, fm, fq, fr, fp)
            work[o + W_RHO, i] = fr
            work[o + W_YA, i] = fa
            work[o + W_YM, i] = fm
            work[o + W_YP, i] = fq
            work[o + W_U, i] = fu
            work[o + W_P, i] = fp
            work[o + W_E, i] = rhoe + 0.5 * fr * fu * fu
            work[o + W_C, i] = c
            work[o + W_G, i] = g


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def advance(q, prim, geom, pipes, bflux, dt, hcoeffs, rsp, work):
    """Advance all pipes by ``dt`` [s] (MUSCL-Hancock + HLLC, area, friction and heat sources).

    Parameters
    ----------
    q : (ncell, NQ) float64
        Cell totals, updated in place.
    prim : (NPM, ncell) float64
        Primitive state of ``q`` at the start of the step (``pipe_props``).
    geom : (NG, ncell) float64; pipes : (npipe, 2) int64
        Layout (``build_pipes``).
    bflux : (npipe, 2, NQ) float64
        Flux across each pipe end in the +x direction (left to right), integrated over the end
        face: species mass [kg/s], momentum [N], energy [W].  ``bflux[ip, 0]`` enters the pipe's
        first cell, ``bflux[ip, 1]`` leaves its last cell; the cells change by +dt*bflux[ip, 0] and
        -dt*bflux[ip, 1].
    dt : float
        Time step [s], at most ``max_stable_dt(prim, ...)``.
    hcoeffs, rsp : float64 (3, 2, 6), (3,)
        Enthalpy coefficients (``thermo.enthalpy_coeffs``) and gas constants of A, M, P.
    work : (NWK, ncell) float64
        Scratch.
    """
    npipe = pipes.shape[0]
    for ip in range(npipe):
        i0 = pipes[ip, 0]
        n = pipes[ip, 1]
        _face_states(prim, geom, i0, n, dt, hcoeffs, rsp, work)
        # interior faces: face between cell i - 1 (its right state) and cell i (its left state)
        for i in range(i0 + 1, i0 + n):
            fa, fm, fp, fmom, fe = _hllc(
                work[NWS + W_RHO, i - 1], work[NWS + W_YA, i - 1], work[NWS + W_YM, i - 1],
                work[NWS + W_YP, i - 1], work[NWS + W_U, i - 1], work[NWS + W_P, i - 1],
                work[NWS + W_E, i - 1], work[NWS + W_C, i - 1], work[NWS + W_G, i - 1],
                work[W_RHO, i], work[W_YA, i], work[W_YM, i], work[W_YP, i], work[W_U, i],
                work[W_P, i], work[W_E, i], work[W_C, i], work[W_G, i])
            a = dt * geom[G_AL, i]
            fa *= a
            fm *= a
            fp *= a
            fmom *= a
            fe *= a
            q[i - 1, Q_A] -= fa
            q[i - 1, Q_M] -= fm
            q[i - 1, Q_P] -= fp
            q[i - 1, Q_MOM] -= fmom
            q[i - 1, Q_E] -= fe
            q[i, Q_A] += fa
            q[i, Q_M] += fm
            q[i, Q_P] += fp
            q[i, Q_MOM] += fmom
            q[i, Q_E] += fe
        # pipe ends
        il = i0
        ir = i0 + n - 1
        for j in range(NQ):
            q[il, j] += dt * bflux[ip, 0, j]
            q[ir, j] -= dt * bflux[ip, 1, j]
        # sources: area (predicted face pressures), friction and wall heat (start-of-step state)
        for i in range(i0, i0 + n):
            pavg = 0.5 * (work[W_P, i] + work[NWS + W_P, i])
            smom = pavg * (geom[G_AR, i] - geom[G_AL, i])
            rho = prim[PM_RHO, i]
            u = prim[PM_U, i]
            t = prim[PM_T, i]
            au = abs(u)
            kf = geom[G_KF, i]
            kh = geom[G_KH, i]
            sen = 0.0
            if kf > 0.0 or kh > 0.0:
                ffix = geom[G_FFIX, i]
                if ffix > 0.0:
                    frho = ffix * rho * au                       # f rho |u| [kg/(m3 s)]
                else:
                    d = geom[G_D, i]
                    mu = gas_viscosity(t)
                    re = rho * au * d / mu
                    if re < RE_TURB:
                        re = RE_TURB
                    x = -1.8 * math.log10(geom[G_RGH, i] + 6.9 / re)
                    frho = max(64.0 * mu / d, rho * au / (x * x))
                smom -= frho * u * kf
                sen = frho * prim[PM_CP, i] * (geom[G_TW, i] - t) * kh
            q[i, Q_MOM] += dt * smom
            q[i, Q_E] += dt * sen
