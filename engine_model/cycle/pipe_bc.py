"""Fluxes across pipe ends: closed end, orifice to a 0D volume, open end into a volume, constant pressure.

Every function here writes ``bflux[ip, side, :]``, the flux across one end of pipe ``ip`` in the
pipe's +x direction (left to right), integrated over the end face: species masses A, M, P [kg/s],
momentum [N] (= (rho u^2 + p) A, the momentum flux including the pressure force) and energy [W].
``side`` 0 is the pipe's left end (its first cell; a positive flux enters the pipe), 1 its right
end (its last cell; a positive flux leaves the pipe).  :func:`pipes.advance` applies it to the
end cell; the caller applies the *same numbers* to the 0D volume on the other side, e.g. with
:func:`apply_end_flux`, so mass, every species and energy are conserved exactly: whatever leaves
the volume enters the pipe.  The energy flux is the mass flow times the donor's stagnation
enthalpy: the volume's specific enthalpy ``props[kv, PR_H]`` (a volume's gas is at rest) for flow
out of the volume, h + w^2/2 of the pipe-end state for flow out of the pipe; species go with the
donor's mass fractions.  The kinetic energy that enters a volume becomes internal energy there
(the volume has no momentum), which is the dump loss.

The volume side is described by a row ``props[kv]`` laid out as in :mod:`volumes`
(``PR_P, PR_T, PR_R, PR_G, PR_H, PR_YA, PR_YM, PR_YP``): ``eval_props`` output can be passed as is.

Method (Benson 1982; the same structure as the boundary conditions of 1D engine codes such as
OpenWAM): the end cell's state and the characteristic that reaches the end from inside the pipe
fix a one-parameter family of possible end states, and the boundary's own law (no flow at a wall,
the quasi-steady orifice, a given pressure) picks one.  Here that family is the isentropic wave
(the two-rarefaction approximation of Toro 2009, ch. 9, used for compressions as well):
with z = c_b / c_c the sound-speed ratio across the wave and w the velocity *out of* the pipe,

    w = w_c - 2 c_c (z - 1) / (gamma_c - 1),   p_b = p_c z^(2 gamma_c/(gamma_c - 1)),

the Riemann invariant w + 2c/(gamma - 1) carried unchanged from the cell to the end (the cell's
gamma, c and entropy).  The end cell's state is the start-of-step cell average (first order at the
end).  For each law the end state solves one scalar equation in z by Newton's method, safeguarded
by bisection inside a bracket that is known to hold the single root.  The residuals are the
squared continuity equations, smooth through zero flow (where the orifice law has a square-root
singularity) and through the choke point.  The warm start is the end velocity of the last two
calls, extrapolated linearly in time (``wb[ip, side, :]``): 1.8 iterations per open end on
average in the engine-like benchmark (two logarithm/exponential pairs each); a closed end costs
one pair.

* Outflow from the pipe through an orifice (throat area Cd A = ``cda_out``): the gas expands
  isentropically from the cell through the end state to the throat, where its pressure is the
  volume's (or sonic if that is below the critical pressure); continuity end -> throat closes the
  system.  Flow from the pipe end into the volume leaves as a jet and its kinetic energy is lost in
  the volume.
* Inflow from the volume through the orifice (``cda_in``): isentropic from the volume's stagnation
  state (p, T of the volume) to the throat at the pipe-end pressure (or choked), then the jet
  spreads to the pipe area at constant pressure with the volume's stagnation enthalpy (energy
  conserved, entropy produced: the Borda-Carnot loss); continuity throat -> pipe end.
* Cd A is clipped to the end area: an opening larger than the pipe behaves as the pipe end.  Cd A = 0
  is a wall.  With Cd A equal to the end area the outflow is a jet at the volume pressure (sonic
  if choked) and the inflow is isentropic (the open end of :func:`bc_open`).
* Within the boundary solve the gas is treated as calorically perfect with the gamma of the cell
  (wave side) and of the volume (orifice side); the energy fluxes use the absolute enthalpies.

References
----------
Benson, R.S., The Thermodynamics and Gas Dynamics of Internal-Combustion Engines, vol. 1,
Clarendon Press, 1982 (boundary conditions of the method of characteristics: pipe to cylinder,
open ends).
Toro, E.F., Riemann Solvers and Numerical Methods for Fluid Dynamics, 3rd ed., Springer 2009,
ch. 4 (wave curves of the exact Riemann problem) and ch. 9 (two-rarefaction approximation).
Heywood, J.B., Internal Combustion Engine Fundamentals, 1988, app. C (orifice flow).
"""

import math

from .layout import V_MA, V_MM, V_MP, V_U
from .pipes import kernel, kernel_inline  # the kernels' decorators (see pipes.py)
from .pipes import (G_AL, G_AR, NQ, PM_C, PM_CP, PM_G, PM_H, PM_P, PM_RHO, PM_T, PM_U, PM_YA, PM_YM,
                    PM_YP, Q_A, Q_E, Q_M, Q_MOM, Q_P)
from .volumes import PR_G, PR_H, PR_P, PR_R, PR_T, PR_YA, PR_YM, PR_YP

Z_MIN = 1e-3        # [-] floor of the sound-speed ratio across the wave (vacuum guard)
Z_TOL = 1e-7        # [-] Newton stops when its step in z is below this (error left < 1e-10)
MAX_IT = 50         # Newton/bisection iterations at most (bisection alone needs ~25 for Z_TOL)
THETA_MIN = 0.02    # [-] smallest T_b / T_0 accepted for the inflow jet (beyond: outside the bracket)


@kernel_inline
def _end(pipes, geom, ip, side):
    """(end cell, end face area [m2], s) with s = +1 at the right end and -1 at the left end."""
    i0 = pipes[ip, 0]
    if side == 0:
        return i0, geom[G_AL, i0], -1.0
    i = i0 + pipes[ip, 1] - 1
    return i, geom[G_AR, i], 1.0


@kernel_inline
def _put(bflux, ip, side, fx, ya, ym, yp, fmom, h0):
    """Store a flux: ``fx`` mass flow in +x [kg/s], composition, momentum flux [N], specific energy h0 [J/kg]."""
    bflux[ip, side, Q_A] = fx * ya
    bflux[ip, side, Q_M] = fx * ym
    bflux[ip, side, Q_P] = fx * yp
    bflux[ip, side, Q_MOM] = fmom
    bflux[ip, side, Q_E] = fx * h0


@kernel_inline
def _wall_flux(bflux, ip, side, p_w, area):
    for j in range(NQ):
        bflux[ip, side, j] = 0.0
    bflux[ip, side, Q_MOM] = p_w * area


@kernel
def bc_wall(prim, pipes, geom, ip, side, bflux):
    """Closed end: no mass or energy flux, momentum flux = wall pressure * area.  Returns the wall pressure [Pa].

    The wall pressure is where the isentropic wave from the end cell brings the gas to rest:
    p_w = p_c (1 + (gamma - 1) w_c / (2 c_c))^(2 gamma / (gamma - 1)), w_c the cell velocity towards the wall.
    """
    i, area, s = _end(pipes, geom, ip, side)
    c = prim[PM_C, i]
    g = prim[PM_G, i]
    k = 2.0 / (g - 1.0)
    z = max(1.0 + s * prim[PM_U, i] / (k * c), Z_MIN)
    p_w = prim[PM_P, i] * math.exp((k + 2.0) * math.log(z))
    _wall_flux(bflux, ip, side, p_w, area)
    return p_w


@kernel_inline
def _z_out(wc, k, g, a, zv, zw, z):
    """Outflow: root in [zv, zw] of H(z) = (a z^k W)^2 - (z_t^k W_t)^2, the squared continuity end -> throat.

    Velocities are in units of the cell's sound speed: W = wc - k (z - 1) at the end, z_t, W_t at the
    throat, isentropic from the end at the volume pressure (z_t = zv, W_t^2 = W^2 + k (z^2 - zv^2)) or
    sonic (W_t = z_t, z_t^2 = 2/(g+1) (z^2 + W^2/k)).  Squared, the residual is smooth through zero
    flow and through the choke point; it decreases in z, H(zv) >= 0 >= H(zw) for a = A/CdA >= 1.
    Returns (z, z^k).
    """
    lo = zv
    hi = zw
    if not (z > lo and z < hi):
        z = hi
    zv2 = zv * zv
    zvk2 = math.exp(2.0 * k * math.log(zv))
    cs = 2.0 / (g + 1.0)
    zk = 1.0
    for _ in range(MAX_IT):
        w = wc - k * (z - 1.0)
        zk = math.exp(k * math.log(z))
        m = a * zk * w
        zt2 = cs * (z * z + w * w / k)
        if zt2 > zv2:                              # sonic throat
            ztk1 = math.exp((k + 1.0) * math.log(zt2))
            h = m * m - ztk1
            dh = -2.0 * (z - w) * (a * k * zk * m / z + (k + 1.0) * cs * ztk1 / zt2)
        else:
            h = m * m - zvk2 * (w * w + k * (z * z - zv2))
            dh = -2.0 * k * (z - w) * (a * zk * m / z + zvk2)
        if h > 0.0:
            lo = z
        else:
            hi = z
        if dh < 0.0:
            step = h / dh
            if abs(step) <= Z_TOL:
                zn = z - step
                return zn, zk * (1.0 - k * step / z)
            zn = z - step
        else:
            zn = lo - 1.0
        if not (zn > lo and zn < hi):
            zn = 0.5 * (lo + hi)
            if hi - lo <= Z_TOL:
                return zn, zk * (1.0 + k * (zn - z) / z)
        z = zn
    return z, math.exp(k * math.log(z))


@kernel_inline
def _z_in(wc, k, lpc, gv, alpha, sig, bet, zw, zv, z):
    """Inflow: root in [zw, zv] of H(z) = (pr (-W) sig / theta)^2 - alpha^2 psi(pr)^2, squared continuity
    throat -> end.

    pr = p_b / p_v = exp((k + 2) ln z + lpc), W = wc - k (z - 1) < 0 the end velocity / c_c,
    theta = T_b / T_v = 1 - bet W^2, sig = c_c / sqrt(R_v T_v), alpha = CdA / A and psi^2 =
    2g/(g-1) (pr^(2/g) - pr^((g+1)/g)) of the volume gas, constant below the critical ratio (smooth
    there: its slope vanishes at the critical ratio).  H increases in z, H(zw) < 0 < H(zv).
    Returns (z, pr).
    """
    kk = k + 2.0
    lo = zw
    hi = zv
    if not (z > lo and z < hi):
        z = lo
    gm1 = gv - 1.0
    c2g = 2.0 * gv / gm1
    prc = -1.0                                     # critical ratio, computed when first needed
    psic2 = 0.0
    for _ in range(MAX_IT):
        w = wc - k * (z - 1.0)
        lpr = kk * math.log(z) + lpc
        pr = math.exp(lpr)
        th = 1.0 - bet * w * w
        if th < THETA_MIN:                         # beyond the fastest possible jet: above the root
            hi = z
            z = 0.5 * (lo + hi)
            if hi - lo <= Z_TOL:
                return z, math.exp(kk * math.log(z) + lpc)
            continue
        if pr < 0.6 and prc < 0.0:
            cc = math.exp(math.log(2.0 / (gv + 1.0)) / gm1)
            prc = 2.0 * cc / (gv + 1.0)
            psic2 = cc * cc * 2.0 * gv / (gv + 1.0)
        if pr <= prc:
            psi2 = psic2
            dpsi2 = 0.0
        else:
            t = math.exp(lpr / gv)
            psi2 = c2g * t * (t - pr)
            dpsi2 = c2g * t * (2.0 * t / (gv * pr) - (gv + 1.0) / gv)
        phi = sig * pr * (-w) / th
        h = phi * phi - alpha * alpha * psi2
        if h > 0.0:
            hi = z
        else:
            lo = z
        dpr = pr * kk / z
        dphi = sig * (dpr * (-w) + pr * k - pr * (-w) * 2.0 * bet * w * k / th) / th
        dh = 2.0 * phi * dphi - alpha * alpha * dpsi2 * dpr
        if dh > 0.0:
            step = h / dh
            if abs(step) <= Z_TOL:
                return z - step, pr * (1.0 - kk * step / z)
            zn = z - step
        else:
            zn = lo - 1.0
        if not (zn > lo and zn < hi):
            zn = 0.5 * (lo + hi)
            if hi - lo <= Z_TOL:
                return zn, math.exp(kk * math.log(zn) + lpc)
        z = zn
    return z, math.exp(kk * math.log(z) + lpc)


@kernel
def bc_orifice(prim, pipes, geom, ip, side, cda_out, cda_in, props, kv, wb, bflux):
    """Pipe end joined to 0D volume ``kv`` through an orifice (valve, throttle), either direction.

    Parameters
    ----------
    prim, pipes, geom
        Primitive state (``pipes.pipe_props``) and layout.
    ip, side : int
        Pipe and end (0 left, 1 right).
    cda_out, cda_in : float
        Effective area Cd*A [m2] for flow pipe -> volume and volume -> pipe (0 = closed); clipped
        to the end face area.
    props : (nvol, >= 8) float64; kv : int
        Volume properties in the layout of ``volumes.eval_props`` (p, T, R, gamma, h, y).
    wb : (npipe, 2, 2) float64
        End velocity out of the pipe [m/s] of the last two calls (this one's on return, then the
        previous one): the warm start of the solve (linear extrapolation in time).  Zeros are a
        valid start; the values only affect how many iterations the solve takes.
    bflux : (npipe, 2, NQ) float64
        Receives the end flux (+x direction; see the module docstring).

    Returns
    -------
    float
        Static pressure at the pipe end [Pa].
    """
    i, area, s = _end(pipes, geom, ip, side)
    p = prim[PM_P, i]
    c = prim[PM_C, i]
    g = prim[PM_G, i]
    k = 2.0 / (g - 1.0)
    kk = k + 2.0
    wc = s * prim[PM_U, i] / c                    # end cell velocity out of the pipe / c
    zw = max(1.0 + wc / k, Z_MIN)                 # the wave that brings the gas to rest
    w1 = wb[ip, side, 0]
    w0 = wb[ip, side, 1]
    wb[ip, side, 1] = w1
    if cda_out > 0.0 or cda_in > 0.0:
        pv = props[kv, PR_P]
        lpc = math.log(p / pv)
        zv = math.exp(-lpc / kk)                  # the wave that brings the gas to the volume pressure
        z0 = 1.0 + (wc - (2.0 * w1 - w0) / c) / k
        if zw > zv and cda_out > 0.0:
            # ------------------------------------------------------------ pipe -> volume
            if cda_out < area:
                z, zk = _z_out(wc, k, g, area / cda_out, zv, zw, z0)
            else:
                z = zv
                if wc - k * (z - 1.0) > z:        # faster than sound at the volume pressure: sonic exit
                    z = (wc + k) / (1.0 + k)
                zk = math.exp(k * math.log(z))
            w = wc - k * (z - 1.0)
            z2 = z * z
            p_b = p * zk * z2
            wv = w * c
            mdot = prim[PM_RHO, i] * zk * wv * area   # out of the pipe [kg/s]
            h0 = prim[PM_H, i] + prim[PM_CP, i] * prim[PM_T, i] * (z2 - 1.0) + 0.5 * wv * wv
            _put(bflux, ip, side, s * mdot, prim[PM_YA, i], prim[PM_YM, i], prim[PM_YP, i],
                 mdot * wv + p_b * area, h0)
            wb[ip, side, 0] = wv
            return p_b
        if zw < zv and cda_in > 0.0:
            # ------------------------------------------------------------ volume -> pipe
            tv = props[kv, PR_T]
            rv = props[kv, PR_R]
            gv = props[kv, PR_G]
            cpv = gv * rv / (gv - 1.0)
            alpha = cda_in / area if cda_in < area else 1.0
            sig = c / math.sqrt(rv * tv)
            bet = c * c / (2.0 * cpv * tv)
            z, pr = _z_in(wc, k, lpc, gv, alpha, sig, bet, zw, zv, z0)
            w = wc - k * (z - 1.0)
            wv = w * c                            # < 0: into the pipe
            p_b = pv * pr
            t_b = tv * (1.0 - bet * w * w)
            mdot = p_b / (rv * t_b) * (-wv) * area    # into the pipe [kg/s]
            _put(bflux, ip, side, -s * mdot, props[kv, PR_YA], props[kv, PR_YM], props[kv, PR_YP],
                 mdot * (-wv) + p_b * area, props[kv, PR_H])
            wb[ip, side, 0] = wv
            return p_b
    # closed, or no pressure difference
    p_w = p * math.exp(kk * math.log(zw))
    _wall_flux(bflux, ip, side, p_w, area)
    wb[ip, side, 0] = 0.0
    return p_w


@kernel
def bc_open(prim, pipes, geom, ip, side, k_in, props, kv, wb, bflux):
    """Pipe end opening into 0D volume ``kv`` without an orifice (plenum -> runner, primary -> collector).

    Outflow leaves as a jet at the volume pressure (sonic if the pressure ratio is supercritical);
    its kinetic energy is dissipated in the volume (dump loss).  Inflow is isentropic from the
    volume's stagnation state for ``k_in`` = 0 (bellmouth); with an entry loss coefficient
    ``k_in`` [-] (~0.5 sharp-edged, ~1 re-entrant) the stagnation pressure drops by k_in pipe
    dynamic heads, p_v - p = (1 + k_in) rho u^2 / 2 at low Mach.  It is realised with the orifice
    model of :func:`bc_orifice`: a jet of area A / sqrt(1 + k_in) at the pipe pressure that spreads
    to the pipe area, its excess kinetic energy dissipated (enthalpy conserved).  Arguments and
    return as :func:`bc_orifice`.
    """
    i, area, s = _end(pipes, geom, ip, side)
    return bc_orifice(prim, pipes, geom, ip, side, area, area / math.sqrt(1.0 + k_in), props, kv, wb, bflux)


@kernel
def bc_pressure(prim, pipes, geom, ip, side, props, kv, bflux):
    """Constant-pressure open end (for tests): static pressure at the end = ``props[kv, PR_P]``.

    Outflow: the pipe gas expands isentropically to that pressure (sonic exit if it cannot).
    Inflow: gas of the reservoir's composition at its static temperature ``props[kv, PR_T]`` enters
    with the velocity the interior wave gives; energy flux mdot (h + w^2/2).  A pressure-release
    end reflects acoustic waves with coefficient -1 and has no end correction (the pressure node is
    at the end face).  Returns the end pressure [Pa].
    """
    i, area, s = _end(pipes, geom, ip, side)
    p = prim[PM_P, i]
    c = prim[PM_C, i]
    g = prim[PM_G, i]
    k = 2.0 / (g - 1.0)
    kk = k + 2.0
    wc = s * prim[PM_U, i] / c
    pa = props[kv, PR_P]
    z = math.exp(math.log(pa / p) / kk)
    w = wc - k * (z - 1.0)
    if w >= 0.0:
        if w > z:
            z = (wc + k) / (1.0 + k)
            w = z
        zk = math.exp(k * math.log(z))
        z2 = z * z
        p_b = p * zk * z2
        wv = w * c
        mdot = prim[PM_RHO, i] * zk * wv * area
        h0 = prim[PM_H, i] + prim[PM_CP, i] * prim[PM_T, i] * (z2 - 1.0) + 0.5 * wv * wv
        _put(bflux, ip, side, s * mdot, prim[PM_YA, i], prim[PM_YM, i], prim[PM_YP, i],
             mdot * wv + p_b * area, h0)
        return p_b
    wv = w * c
    mdot = pa / (props[kv, PR_R] * props[kv, PR_T]) * (-wv) * area
    _put(bflux, ip, side, -s * mdot, props[kv, PR_YA], props[kv, PR_YM], props[kv, PR_YP],
         mdot * (-wv) + pa * area, props[kv, PR_H] + 0.5 * wv * wv)
    return pa


@kernel
def apply_end_flux(bflux, ip, side, dt, vol, kv):
    """Apply the end flux of pipe ``ip`` to the 0D volume on that end: ``vol[kv, V_MA..V_U] += -/+ dt * flux``.

    The volume at a left end (side 0) loses what enters the pipe, the volume at a right end gains
    what leaves it; ``vol`` in the layout of a volume state (V_MA, V_MM, V_MP masses [kg], V_U
    energy [J]), or a rate array with dt = 1.  The energy flux goes into V_U whole (the kinetic
    energy of a jet becomes internal energy of the volume).
    """
    sg = dt if side == 1 else -dt
    vol[kv, V_MA] += sg * bflux[ip, side, Q_A]
    vol[kv, V_MM] += sg * bflux[ip, side, Q_M]
    vol[kv, V_MP] += sg * bflux[ip, side, Q_P]
    vol[kv, V_U] += sg * bflux[ip, side, Q_E]
