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
velocity, pressure, temperature, sound speed, gamma, cp, enthalpy, gas constant, mass fractions and
the linearised equation of state into ``prim[NPM, ncell]``), every few steps also the friction
factors (``friction_factors`` into ``fric[NF, ncell]``), (2) computes the flux across every pipe
end with the boundary functions of :mod:`engine_model.cycle.pipe_bc` into ``bflux[npipe, 2, NQ]``,
(3) advances all pipes by dt with ``advance`` and updates its 0D volumes with the same end fluxes.
``max_stable_dt`` gives the largest stable step for the current ``prim``.

Scheme
------
Equations: the quasi-1D Euler equations for a pipe of cross-section A(x),
d(rho Y_s A)/dt + d(rho Y_s u A)/dx = 0, d(rho u A)/dt + d((rho u^2 + p) A)/dx = p dA/dx - tau_w P_w,
d(E A)/dt + d(u (E + p) A)/dx = q_w P_w, integrated over each cell (finite volumes on cell totals,
face fluxes times face areas), which makes the update conservative by construction: the
number that leaves one cell through a face enters its neighbour.

* **Reconstruction** (Toro 2009, ch. 14, the MUSCL-Hancock scheme; ch. 13-14 for TVD slope
  limiters): piecewise-linear in the primitive variables rho, Y_s, u, p with the monotonised-central
  (MC) limiter minmod(2a, 2b, (a + b)/2) of van Leer (1977).  Among the TVD limiters it clips
  smooth extrema least (the engine model is about acoustics: minmod would damp the tuning waves)
  without the squaring-off of superbee, and it needs no division, so it compiles branch-free.
  The mass fractions of A and M are limited on their own and P gets the negative of their sum,
  so the slopes sum to zero and the face fractions to one without a division; where that slope
  exceeds the limit of P (only where all three species vary) the three are scaled down together.
  Face fractions pushed below zero by the predictor are clipped and renormalised.  The end cells of a pipe are reconstructed piecewise-constant
  (their outer neighbour is a boundary, not a cell).
* **Hancock predictor**: the face values of each cell are advanced by dt/2 with the primitive,
  non-conservative form of the quasi-1D equations evaluated at the cell (rho_t = -u rho_x - rho u_x
  - rho u A'/A, u_t = -u u_x - p_x / rho, p_t = -u p_x - rho c^2 u_x - rho c^2 u A'/A, Y_t = -u Y_x),
  the "primitive-variable" form of the predictor; it costs no flux evaluations and is well balanced
  by itself (u = 0, p_x = 0 gives no change).
* **Face energy**: the total energy of a face state needs e(rho, p, Y) of the face.  Instead of a
  temperature inversion per face, each cell's equation of state is linearised about the cell
  state (``pipe_props`` provides d(rho e)/dp = 1/(gamma - 1), d(rho e)/d rho and d(rho e)/d(rho Y_s)
  from the species energies): exact for gases of equal gamma (the constant-cp test gases, with any
  formation enthalpies), and for the NASA-polynomial gases an error second order in the face-cell
  differences, i.e. of the order of the scheme's own truncation error.  It replaces a division,
  a square root and two polynomials per face state by a few multiply-adds.
* **Riemann solver**: HLLC (Toro 2009, sec. 10.4) written for a general equation of state: the
  star states follow from p, rho, u and E of each side alone (Rankine-Hugoniot across S_L, S_R and
  the contact S*), species travel as partial densities with the mass flux, each with the mass
  fraction of its side of the contact, so a contact (backflow of burned gas into a port) keeps its
  composition and temperature instead of being smeared into an average.  Wave-speed estimates:
  the pressure-based ones of Toro sec. 10.5 (PVRS guess of p*, S_K = u_K -/+ c_K q_K with the
  shock factor q_K = sqrt(1 + (g+1)/(2g) (p*/p_K - 1)) where p* > p_K), with the sound speed
  c^2 = gamma R T and the local gamma = cp/(cp - R) of the cell on each side (exact for a thermally
  perfect mixture).  Against Davis' min/max estimates they lower the Sod L1 error by ~20 % at no
  measurable cost.  The supersonic cases are the same formula with S_K clipped at 0 and the
  shock factor is max(1, ...) under the root, so the solver has no branch to mispredict.
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
  ``flow.gas_viscosity``), or a fixed factor per pipe; ``friction_factors`` computes them into an
  array that the caller refreshes every few steps (the logarithm and the viscosity cost as much
  as the rest of a cell's step, and f varies as Re^-0.2).  Wall shear tau_w = f rho u |u| / 8 acts
  on the wetted perimeter; friction does no work on the gas as a whole (the wall does not move),
  so the total energy gets no friction term: the kinetic energy it removes reappears as internal
  energy.  Heat flux by the Chilton-Colburn analogy St Pr^(2/3) = f / 8 with Pr = 0.7: q_w = (f/8)
  rho |u| cp Pr^(-2/3) (T_w - T).
* **Time integration**: the MUSCL-Hancock step is a one-step predictor-corrector, second order in
  time for the homogeneous part; it is stable for Courant numbers max(|u| + c) dt / dx <= 1 (Toro
  ch. 14); ``max_stable_dt`` returns cfl * dx / max(|u| + c) with cfl = 0.9 recommended.  The end
  fluxes are supplied by the caller for the whole step (they are computed from the cell states at
  the start of the step: first order in time at the pipe ends).
* **Temperature**: ``pipe_props`` takes one Newton step on u(T) from the previous temperature
  (iterating only if the correction exceeds 5 K).  Its error is below 1e-3 dT^2 K for a change dT
  since the last step; measured in the engine-like benchmark: < 1e-3 K.  It does not accumulate
  (the energy is exact; the next step starts again from it) and does not touch conservation.

Coupling to a crank-angle driver
--------------------------------
* One pipe step: ``pipe_props`` (every cell), ``friction_factors`` (every few steps; before the
  first step), one boundary function per pipe end (volume side from the volumes' property rows at
  the start of the step), ``advance``, then ``pipe_bc.apply_end_flux`` with the same dt for each
  end.  Mass, every species and energy of pipes plus volumes are then conserved to round-off
  whatever else the driver does (tested over 144000 steps: drift ~1e-14).  With a two-stage
  (Heun) volume integration, use the end fluxes as a constant rate over the pipe step in both
  stages (they are not re-evaluated in the second stage), otherwise pipe and volume see different
  numbers.
* Stability: dt <= ``max_stable_dt(prim, geom, ncell, 0.9)``.  With ~25 mm cells the Courant
  number of a 0.5 deg step is ~0.4 at 9000 rpm (measured, benchmark) and below that at higher
  speed (dt shrinks as 1/rpm), but 2.5-3.5 at 1000 rpm (dt = 8.3e-5 s): there the driver splits
  its step into ceil(dt / max_stable_dt) pipe sub-steps, each with fresh properties and end
  fluxes, and gives each sub-step's end fluxes to the volumes.  Conversely, at 9000 rpm a pipe step every 1 deg (Courant ~0.8) is stable and
  halves the cost (benchmarks/pipe_kernel.py --deg 1).
* The end fluxes are explicit in the volume state: the volume's pressure must not move much in
  one step, i.e. dt A c / V < ~1 for the smallest volume attached (end area A, sound speed c);
  an R6 cylinder at TDC (12.5 cm3, port 1e-3 m2) gives ~0.4 at 9000 rpm.
* Persistent arrays: ``tcell`` (Newton warm start), ``fric``, ``wb`` (end-velocity warm start of
  the boundary solves); ``prim``, ``work`` and ``bflux`` are rewritten every step.

References
----------
Toro, E.F., Riemann Solvers and Numerical Methods for Fluid Dynamics, 3rd ed., Springer 2009:
ch. 4 (exact Riemann solver, used by the tests), sec. 10.4-10.6 (HLLC, wave-speed estimates),
ch. 13-14 (TVD slope limiters, MUSCL-Hancock).
van Leer, B., "Towards the ultimate conservative difference scheme IV", J. Comput. Phys. 23 (1977)
276-299 (the monotonised-central slope); "... V", J. Comput. Phys. 32 (1979) 101-136 (MUSCL).
Haaland, S.E., J. Fluids Eng. 105 (1983) 89-90 (friction factor).
Colburn, A.P., Trans. AIChE 29 (1933) 174-210 (heat transfer / friction analogy).
"""

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..thermo import T_MID
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
# the cell's equation of state linearised about its state: the internal energy per volume of a
# nearby state (rho', p', Y') is rho e + K1 (p' - p) + K2 (rho' - rho) + rho' sum_s K_s (Y'_s - Y_s)
PM_K1 = 12   # d(rho e)/dp at rho, Y = cv / R = 1 / (gamma - 1) [-]
PM_K2 = 13   # d(rho e)/d rho at p, Y = e - cv T [J/kg]
PM_KA = 14   # d(rho e)/d(rho Y_s) at rho, p = e_s - cv T R_s / R [J/kg], species A, M, P
PM_KM = 15
PM_KP = 16
PM_V = 17    # specific volume 1 / rho [m3/kg]
PM_GP = 18   # (gamma + 1) / (2 gamma p) [1/Pa]: the shock factor of the wave-speed estimate
NPM = 19

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
W_U = 1
W_P = 2
W_E = 3      # total energy per volume [J/m3]
W_YA = 4
W_YM = 5
W_YP = 6
NWS = 7
NWK = 2 * NWS

# ------------------------------------------------------------------ friction rows fric[k, i] (friction_factors)
F_TURB = 0   # Darcy factor of the turbulent branch at the cell's Re (or the pipe's fixed factor) [-]
F_LAM = 1    # laminar branch as f rho |u| = 64 mu / D [kg/(m2 s)] (0 with a fixed factor)
NF = 2

# Haaland's formula is evaluated at Re >= RE_TURB (below it is meaningless, and at Re ~ 7 it is
# singular); the laminar 64/Re is taken where larger, so f(Re) is continuous: 64/Re up to Re ~ 1300,
# then a plateau at Haaland's value for 2300 through the transition, then Haaland.
RE_TURB = 2300.0
NEWTON_ONE_STEP = 5.0    # [K] a larger first Newton correction of T is iterated to convergence
# Decorators of the kernels: the cycle package's style (cache, FASTMATH, no reference counting,
# see layout.py), plus error_model="numpy": a float division follows IEEE (x/0 -> inf or NaN)
# instead of numba's default check-and-raise ZeroDivisionError on every division.  The check is a
# compare and branch per division that also keeps LLVM from scheduling the divisions freely;
# dropping it halved the time of the Riemann solver measured alone (25 -> 12.5 ns per face), a
# few % of a whole step.  A state that would have raised becomes non-finite, which
# ``pipe_props`` reports as a failed cell.
kernel = njit(cache=True, fastmath=FASTMATH, _nrt=False, error_model="numpy")
kernel_inline = njit(cache=True, fastmath=FASTMATH, _nrt=False, error_model="numpy", inline="always")

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
        """Fresh arrays (q, tcell, prim, fric, work, bflux, wb): zeros, except tcell = 300 K and fric = NaN.

        ``fric`` is NaN until ``friction_factors`` fills it, so a step taken without friction data
        fails loudly (``pipe_props`` reports the cells) instead of running frictionless.
        """
        return (np.zeros((self.ncell, NQ)), np.full(self.ncell, 300.0), np.zeros((NPM, self.ncell)),
                np.full((NF, self.ncell), np.nan), np.zeros((NWK, self.ncell)),
                np.zeros((self.npipe, 2, NQ)), np.zeros((self.npipe, 2, 2)))


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
@kernel
def fill_cells(q, tcell, geom, i_start, i_end, p, t, u, ya, ym, yp, hcoeffs, rsp):
    """Set cells [i_start, i_end) to pressure p [Pa], temperature t [K], velocity u [m/s], mass fractions."""
    r = ya * rsp[0] + ym * rsp[1] + yp * rsp[2]
    rho = p / (r * t)
    k = 0 if t < T_MID else 1
    h = 0.0
    for s in range(3):
        y = ya if s == 0 else (ym if s == 1 else yp)
        h += y * (t * (hcoeffs[s, k, 0] + t * (hcoeffs[s, k, 1] + t * (hcoeffs[s, k, 2] + t * (
            hcoeffs[s, k, 3] + t * hcoeffs[s, k, 4])))) + hcoeffs[s, k, 5])
    e = h - r * t
    for i in range(i_start, i_end):
        m = rho * geom[G_V, i]
        q[i, Q_A] = m * ya
        q[i, Q_M] = m * ym
        q[i, Q_P] = m * yp
        q[i, Q_MOM] = m * u
        q[i, Q_E] = m * (e + 0.5 * u * u)
        tcell[i] = t


@kernel
def inventory(q, i_start, i_end, out):
    """Sums over cells [i_start, i_end): out = (air, mixture, products [kg], momentum [kg m/s], energy [J])."""
    for j in range(NQ):
        out[j] = 0.0
    for i in range(i_start, i_end):
        for j in range(NQ):
            out[j] += q[i, j]


# ================================================================== primitive state of every cell
@kernel_inline
def _species_eu(hcoeffs, rsp, s, k, t):
    """Internal energy [J/kg] and cv [J/(kg K)] of species s at t [K] from range k of the enthalpy coefficients."""
    c0 = hcoeffs[s, k, 0]
    c1 = hcoeffs[s, k, 1]
    c2 = hcoeffs[s, k, 2]
    c3 = hcoeffs[s, k, 3]
    c4 = hcoeffs[s, k, 4]
    r = rsp[s]
    e = t * (c0 - r + t * (c1 + t * (c2 + t * (c3 + t * c4)))) + hcoeffs[s, k, 5]
    cv = c0 - r + t * (2.0 * c1 + t * (3.0 * c2 + t * (4.0 * c3 + t * (5.0 * c4))))
    return e, cv


@kernel
def pipe_props(q, tcell, geom, ncell, hcoeffs, rsp, prim):
    """Fill ``prim[:, :ncell]`` from the cell totals; temperature by Newton from the warm start ``tcell`` (updated).

    One Newton step on u(T) from the previous temperature: its error is (dcv/dT) / (2 cv) dT^2
    < 1e-3 dT^2 K for a change dT [K] since the last call (over a time step dT is a few K at
    most, so the error is a few mK and does not accumulate: the energy itself is exact and the next
    call starts from it again).  A correction above NEWTON_ONE_STEP iterates to convergence.  The
    species energies of the last Newton point, moved to the new temperature with their cv, give
    the linearised equation of state (rows PM_K*) used for the face states.

    Returns 0, or 1 + the index of the first cell with non-positive or non-finite mass or a
    temperature outside [150, 4400] K (``prim`` is then incomplete).
    """
    r_a = rsp[0]
    r_m = rsp[1]
    r_p = rsp[2]
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
        t0 = tcell[i]
        if not (t0 > T_MIN_OK and t0 < T_MAX_OK):
            t0 = T_MID
        for _ in range(30):
            k = 0 if t0 < T_MID else 1
            ea, cva = _species_eu(hcoeffs, rsp, 0, k, t0)
            em, cvm = _species_eu(hcoeffs, rsp, 1, k, t0)
            ep, cvp = _species_eu(hcoeffs, rsp, 2, k, t0)
            cv = ya * cva + ym * cvm + yp * cvp
            inv_cv = 1.0 / cv
            dt = (e - (ya * ea + ym * em + yp * ep)) * inv_cv
            if abs(dt) <= NEWTON_ONE_STEP or not (abs(dt) < 1e4):
                break
            t0 += dt
        t = t0 + dt
        if not (t > T_MIN_OK and t < T_MAX_OK):
            return 1 + i
        tcell[i] = t
        r = ya * r_a + ym * r_m + yp * r_p
        inv_r = 1.0 / r
        rho = m * geom[G_INVV, i]
        g = 1.0 + r * inv_cv
        cvt = cv * t
        prim[PM_RHO, i] = rho
        prim[PM_U, i] = u
        prim[PM_P, i] = rho * r * t
        prim[PM_T, i] = t
        prim[PM_C, i] = math.sqrt(g * r * t)
        prim[PM_G, i] = g
        prim[PM_CP, i] = cv + r
        prim[PM_H, i] = e + r * t
        prim[PM_R, i] = r
        prim[PM_YA, i] = ya
        prim[PM_YM, i] = ym
        prim[PM_YP, i] = yp
        prim[PM_K1, i] = cv * inv_r
        prim[PM_K2, i] = e - cvt
        cvt *= inv_r
        prim[PM_KA, i] = ea + cva * dt - cvt * r_a
        prim[PM_KM, i] = em + cvm * dt - cvt * r_m
        prim[PM_KP, i] = ep + cvp * dt - cvt * r_p
        prim[PM_V, i] = inv_m * geom[G_V, i]
        prim[PM_GP, i] = 0.5 * (g + 1.0) / (g * rho * r * t)
    return 0


@kernel
def friction_factors(prim, geom, ncell, fric):
    """Darcy friction data of every cell from ``prim`` into ``fric[NF, ncell]`` (input of ``advance``).

    Turbulent: Haaland's formula at Re = rho |u| D / mu(T) (Sutherland), evaluated at Re >= 2300;
    laminar: f rho |u| = 64 mu / D; ``advance`` takes the larger.  A pipe with a fixed factor gets
    it unchanged.  The factor varies as Re^-0.2 or less, so refreshing it every few steps is enough
    (the log and the viscosity cost about as much as the rest of a cell's step).
    """
    for i in range(ncell):
        ffix = geom[G_FFIX, i]
        if ffix > 0.0:
            fric[F_TURB, i] = ffix
            fric[F_LAM, i] = 0.0
            continue
        d = geom[G_D, i]
        mu = gas_viscosity(prim[PM_T, i])
        re = prim[PM_RHO, i] * abs(prim[PM_U, i]) * d / mu
        if re < RE_TURB:
            re = RE_TURB
        x = -1.8 * math.log10(geom[G_RGH, i] + 6.9 / re)
        fric[F_TURB, i] = 1.0 / (x * x)
        fric[F_LAM, i] = 64.0 * mu / d


@kernel
def max_stable_dt(prim, geom, ncell, cfl):
    """Largest stable time step [s]: cfl * min over cells of dx / (|u| + c); cfl <= 1 (0.9 recommended)."""
    smax = 0.0
    for i in range(ncell):
        s = (abs(prim[PM_U, i]) + prim[PM_C, i]) * geom[G_INVDX, i]
        if s > smax:
            smax = s
    return cfl / smax if smax > 0.0 else math.inf


# ================================================================== limiter and HLLC
@kernel_inline
def _mc(a, b):
    """Monotonised-central limited slope of the one-sided differences a, b: minmod(2a, 2b, (a+b)/2), branch-free."""
    c = 0.5 * (a + b)
    m = min(abs(c), 2.0 * min(abs(a), abs(b)))
    return math.copysign(m, c) * (1.0 if a * b > 0.0 else 0.0)


@kernel_inline
def _hllc(rl, ul, pl, el, yal, yml, ypl, cl, gpl, rr, ur, pr, er, yar, ymr, ypr, cr, gpr):
    """HLLC flux per unit area (mass A, M, P [kg/(m2 s)], momentum [Pa], energy [W/m2]); e = total energy per volume.

    Wave speeds: pressure-based (PVRS p*, shock factor sqrt(1 + (g+1)/(2g) (p*/p - 1)) where
    p* > p) with the sound speeds cl, cr and the factors gpl, gpr = (g+1)/(2 g p) of the two cells.
    Flux in the star region in the form F*_K = (S* (S_K U_K - F_K) + S_K p* D*) / (S_K - S*),
    D* = (0, 1, S*), p* the mean of the two sides' star pressures (one of the equivalent forms of
    Toro 2009, sec. 10.4; equal to the U*-form when both star pressures agree, as they do by S*): two
    divisions per face.  The side K follows from the sign of S*; the supersonic cases select F_L or
    F_R.  No branches: every case is computed and selected.
    """
    pm = max(0.5 * (pl + pr) - 0.125 * (ur - ul) * (rl + rr) * (cl + cr), 0.0)
    sl = ul - cl * math.sqrt(max(1.0, 1.0 + gpl * (pm - pl)))
    sr = ur + cr * math.sqrt(max(1.0, 1.0 + gpr * (pm - pr)))
    dl = rl * (sl - ul)
    dr = rr * (sr - ur)
    ss = (pr - pl + ul * dl - ur * dr) / (dl - dr)
    ps = 0.5 * (pl + pr + dl * (ss - ul) + dr * (ss - ur))
    sup = sl >= 0.0 or sr <= 0.0                  # supersonic: the flux is F_L or F_R itself
    left = sl >= 0.0 if sup else ss >= 0.0
    rk = rl if left else rr
    uk = ul if left else ur
    pk = pl if left else pr
    ek = el if left else er
    sk = sl if left else sr
    mk = rk * uk                                  # F_K: mass, momentum, energy
    fmk = mk * uk + pk
    fek = uk * (ek + pk)
    inv = 1.0 / (sk - ss)
    m = ss * (sk * rk - mk) * inv
    mom = (ss * (sk * mk - fmk) + sk * ps) * inv
    en = ss * (sk * ek - fek + sk * ps) * inv
    if sup:
        m = mk
        mom = fmk
        en = fek
    ya = yal if left else yar
    ym = yml if left else ymr
    yp = ypl if left else ypr
    return m * ya, m * ym, m * yp, mom, en


# ================================================================== the step
@kernel_inline
def _clip_fractions(fa, fm, fq):
    """Mass fractions clipped at zero and renormalised to sum to one."""
    fa = max(fa, 0.0)
    fm = max(fm, 0.0)
    fq = max(fq, 0.0)
    inv = 1.0 / (fa + fm + fq)
    return fa * inv, fm * inv, fq * inv


@kernel_inline
def _face_states(prim, geom, i0, n, dt, work):
    """Reconstruct, predict by dt/2 and store the left/right face states of the cells of one pipe."""
    hdt = 0.5 * dt
    for i in range(i0, i0 + n):
        rho = prim[PM_RHO, i]
        u = prim[PM_U, i]
        p = prim[PM_P, i]
        ya = prim[PM_YA, i]
        ym = prim[PM_YM, i]
        yp = prim[PM_YP, i]
        if i == i0 or i == i0 + n - 1:
            drho = 0.0
            du = 0.0
            dp = 0.0
            dya = 0.0
            dym = 0.0
            dyp = 0.0
        else:
            drho = _mc(rho - prim[PM_RHO, i - 1], prim[PM_RHO, i + 1] - rho)
            du = _mc(u - prim[PM_U, i - 1], prim[PM_U, i + 1] - u)
            dp = _mc(p - prim[PM_P, i - 1], prim[PM_P, i + 1] - p)
            # species: A and M limited, P their complement so that the slopes sum to zero; scaled
            # down together if that exceeds the limit of P (only where all three vary)
            dya = _mc(ya - prim[PM_YA, i - 1], prim[PM_YA, i + 1] - ya)
            dym = _mc(ym - prim[PM_YM, i - 1], prim[PM_YM, i + 1] - ym)
            dyp = -(dya + dym)
            a = yp - prim[PM_YP, i - 1]
            b = prim[PM_YP, i + 1] - yp
            lim = min(abs(0.5 * (a + b)), 2.0 * min(abs(a), abs(b))) if a * b > 0.0 else 0.0
            if abs(dyp) > lim:
                f = lim / abs(dyp)
                dya *= f
                dym *= f
                dyp *= f
        # Hancock predictor: dt/2 of the primitive quasi-1D equations at the cell
        nu = hdt * geom[G_INVDX, i]
        rc2 = prim[PM_G, i] * p                   # rho c^2
        dla = hdt * u * geom[G_DLNA, i]           # dt/2 u A'/A
        r1 = rho - nu * (u * drho + rho * du) - dla * rho
        u1 = u - nu * (u * du + dp * prim[PM_V, i])
        p1 = p - nu * (u * dp + rc2 * du) - dla * rc2
        nuu = nu * u
        rl = r1 - 0.5 * drho
        rr = r1 + 0.5 * drho
        pl = p1 - 0.5 * dp
        pr = p1 + 0.5 * dp
        if not (rl > 0.0 and rr > 0.0 and pl > 0.0 and pr > 0.0):
            # a limited slope too steep for positivity: first order in this cell
            drho = 0.0
            du = 0.0
            dp = 0.0
            dya = 0.0
            dym = 0.0
            dyp = 0.0
            rl = rho
            rr = rho
            pl = p
            pr = p
            u1 = u
        re = rho * prim[PM_H, i] - p              # rho e of the cell
        k1 = prim[PM_K1, i]
        k2 = prim[PM_K2, i]
        ka = prim[PM_KA, i]
        km = prim[PM_KM, i]
        kp = prim[PM_KP, i]
        # left face (the fractions sum to one unless a clip at zero needs a renormalisation)
        fa = ya - nuu * dya - 0.5 * dya
        fm = ym - nuu * dym - 0.5 * dym
        fq = yp - nuu * dyp - 0.5 * dyp
        if fa < 0.0 or fm < 0.0 or fq < 0.0:
            fa, fm, fq = _clip_fractions(fa, fm, fq)
        fu = u1 - 0.5 * du
        work[W_RHO, i] = rl
        work[W_U, i] = fu
        work[W_P, i] = pl
        work[W_E, i] = (re + k1 * (pl - p) + k2 * (rl - rho)
                        + rl * (ka * (fa - ya) + km * (fm - ym) + kp * (fq - yp)) + 0.5 * rl * fu * fu)
        work[W_YA, i] = fa
        work[W_YM, i] = fm
        work[W_YP, i] = fq
        # right face
        fa = ya - nuu * dya + 0.5 * dya
        fm = ym - nuu * dym + 0.5 * dym
        fq = yp - nuu * dyp + 0.5 * dyp
        if fa < 0.0 or fm < 0.0 or fq < 0.0:
            fa, fm, fq = _clip_fractions(fa, fm, fq)
        fu = u1 + 0.5 * du
        work[NWS + W_RHO, i] = rr
        work[NWS + W_U, i] = fu
        work[NWS + W_P, i] = pr
        work[NWS + W_E, i] = (re + k1 * (pr - p) + k2 * (rr - rho)
                              + rr * (ka * (fa - ya) + km * (fm - ym) + kp * (fq - yp)) + 0.5 * rr * fu * fu)
        work[NWS + W_YA, i] = fa
        work[NWS + W_YM, i] = fm
        work[NWS + W_YP, i] = fq


@kernel
def advance(q, prim, geom, pipes, bflux, fric, dt, work):
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
    fric : (NF, ncell) float64
        Friction data (``friction_factors``, refreshed every few steps).
    dt : float
        Time step [s], at most ``max_stable_dt(prim, ...)``.
    work : (NWK, ncell) float64
        Scratch.
    """
    npipe = pipes.shape[0]
    for ip in range(npipe):
        i0 = pipes[ip, 0]
        n = pipes[ip, 1]
        _face_states(prim, geom, i0, n, dt, work)
        # interior faces: face between cell i - 1 (its right state) and cell i (its left state)
        for i in range(i0 + 1, i0 + n):
            fa, fm, fp, fmom, fe = _hllc(
                work[NWS + W_RHO, i - 1], work[NWS + W_U, i - 1], work[NWS + W_P, i - 1],
                work[NWS + W_E, i - 1], work[NWS + W_YA, i - 1], work[NWS + W_YM, i - 1],
                work[NWS + W_YP, i - 1], prim[PM_C, i - 1], prim[PM_GP, i - 1],
                work[W_RHO, i], work[W_U, i], work[W_P, i], work[W_E, i], work[W_YA, i], work[W_YM, i],
                work[W_YP, i], prim[PM_C, i], prim[PM_GP, i])
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
            smom = 0.5 * (work[W_P, i] + work[NWS + W_P, i]) * (geom[G_AR, i] - geom[G_AL, i])
            u = prim[PM_U, i]
            frho = max(fric[F_LAM, i], fric[F_TURB, i] * prim[PM_RHO, i] * abs(u))   # f rho |u|
            q[i, Q_MOM] += dt * (smom - frho * u * geom[G_KF, i])
            q[i, Q_E] += dt * frho * prim[PM_CP, i] * (geom[G_TW, i] - prim[PM_T, i]) * geom[G_KH, i]
