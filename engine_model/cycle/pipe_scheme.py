"""One time step of the pipes: MUSCL-Hancock finite volumes with the HLLC flux (:func:`advance`).

The state layout, the property evaluation and the coupling to the crank-angle driver are in
:mod:`engine_model.cycle.pipes`.

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

References
----------
Toro, E.F., Riemann Solvers and Numerical Methods for Fluid Dynamics, 3rd ed., Springer 2009:
ch. 4 (exact Riemann solver, used by the tests), sec. 10.4-10.6 (HLLC, wave-speed estimates),
ch. 13-14 (TVD slope limiters, MUSCL-Hancock).
van Leer, B., "Towards the ultimate conservative difference scheme IV", J. Comput. Phys. 23 (1977)
276-299 (the monotonised-central slope); "... V", J. Comput. Phys. 32 (1979) 101-136 (MUSCL).
Haaland (1983) and Colburn (1933) for the friction and heat-transfer factors: :mod:`engine_model.cycle.pipes`.
"""

import math

from .pipes import kernel, kernel_inline  # the kernels' decorators (see pipes.py)
from .pipes import (G_AL, G_AR, G_DLNA, G_INVDX, G_KF, G_KH, G_TW, NQ, NWS, PM_C, PM_CP, PM_G, PM_GP,
                    PM_H, PM_K1, PM_K2, PM_KA, PM_KM, PM_KP, PM_P, PM_RHO, PM_T, PM_U, PM_V, PM_YA,
                    PM_YM, PM_YP, Q_A, Q_E, Q_M, Q_MOM, Q_P, W_E, W_P, W_RHO, W_U, W_YA, W_YM, W_YP,
                    F_LAM, F_TURB)


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
