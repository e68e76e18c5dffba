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

The numerical scheme (MUSCL-Hancock reconstruction, HLLC flux, area, friction and heat sources) is
described with its code in :mod:`engine_model.cycle.pipe_scheme`.

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
Haaland, S.E., J. Fluids Eng. 105 (1983) 89-90 (friction factor, ``friction_factors``).
Colburn, A.P., Trans. AIChE 29 (1933) 174-210 (heat transfer / friction analogy).
The scheme's references (Toro 2009, van Leer 1977/1979) are in :mod:`engine_model.cycle.pipe_scheme`.
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
