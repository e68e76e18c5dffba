"""The engine's pipes coupled to its 0D volumes: one crank step of the pipe network (numba).

The pipes of the 1D gas exchange (intake runners, exhaust primaries, collector, tailpipe) are advanced by
:func:`pipes.advance` in sub-steps that keep the Courant number at ``cfl``; every sub-step's end fluxes
(:mod:`pipe_bc`) are computed from the pipe ends and the volumes' state at the start of the crank step,
and the same numbers are summed into ``xfer``, the mass and energy every volume gains from the pipes over
the crank step.  The engine driver adds ``xfer / dt`` to the volumes' rates in both stages of its
Heun step, so pipes plus volumes conserve mass, every species and energy exactly.

The end table ``ends[ip, side, :]`` says what is at each pipe end (``E_KIND``: ``BC_OPEN`` or
``BC_ORIFICE``; ``E_VOL``: the volume, ``nvol`` = the ambient) and ``endp[ip, side, :]`` its parameters
(entry loss [-], or the effective areas out of and into the pipe [m2]).
"""

import math

from numba import njit

from engine_model.cycle.layout import (BC_OPEN, E_KIND, E_VOL, FASTMATH, V_MA, V_MM, V_MP, V_U)
from engine_model.cycle.pipe_bc import bc_open, bc_orifice
from engine_model.cycle.pipe_scheme import advance
from engine_model.cycle.pipes import (PM_R, PM_T, Q_A, Q_E, Q_M, Q_P, friction_factors,
                                      max_stable_dt, pipe_props)
from engine_model.cycle.volumes import PR_GV, PR_RT

__all__ = ["pipe_step", "pipe_energy"]


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def pipe_energy(q):
    """Total energy of all pipe cells [J]."""
    e = 0.0
    for i in range(q.shape[0]):
        e += q[i, Q_E]
    return e


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def pipe_step(q, tcell, geom, pipes, prim, fric, work, bflux, wb, ends, endp, props, nvol, hcoeffs, rsp, dt,
              cfl, fric_every, counter, xfer, xrate):
    """Advance every pipe by the crank step ``dt`` [s] in Courant-limited sub-steps.

    Parameters
    ----------
    q, tcell, geom, pipes, prim, fric, work, bflux, wb
        Pipe state and work arrays (see :mod:`pipes`).
    ends, endp
        What is at each pipe end, and its parameters (module docstring).
    props : (nvol + 1, NPR) float64
        Volume properties at the start of the step; row ``nvol`` is the ambient.
    hcoeffs, rsp
        Gas properties (enthalpy coefficients, gas constants).
    dt : float
        Crank step [s].
    cfl : float
        Courant number of the sub-steps [-].
    fric_every : int
        Friction factors are refreshed at the first sub-step of every this many crank steps (at fixed crank
        angles, so that a periodic state stays periodic whatever the number of sub-steps).
    counter : (1,) int64
        Crank steps taken so far (for the friction refresh); updated.
    xfer : (nvol + 1, >= 4) float64
        Zeroed here, then the species masses [kg] and energy [J] each volume gains from the pipes over the
        step (``V_MA, V_MM, V_MP, V_U`` columns); row ``nvol`` is what leaves into the ambient.
    xrate : (nvol + 1,) float64
        Zeroed here, then the pressure change [Pa] of each volume those gains cause at constant volume
        (gamma_v R T_donor / V per kg), the known part of its pressure change for the implicit orifice
        solves.

    Returns
    -------
    (int, int, float, float)
        Failure code (0 ok, 300 + cell index of a failed cell), the number of sub-steps, the energy that
        entered the pipes through their ends over the step [J], and the Courant number of the whole crank
        step at its start (max over cells of dt (|u| + c) / dx).
    """
    ncell = q.shape[0]
    npipe = pipes.shape[0]
    for i in range(xfer.shape[0]):
        for c in range(xfer.shape[1]):
            xfer[i, c] = 0.0
        xrate[i] = 0.0
    e_in = 0.0
    code = pipe_props(q, tcell, geom, ncell, hcoeffs, rsp, prim)
    if code != 0:
        return 300 + code - 1, 0, 0.0, 0.0
    dts = max_stable_dt(prim, geom, ncell, cfl)
    courant = cfl * dt / dts
    nsub = int(math.ceil(dt / dts - 1e-9)) if dts > 0.0 else 1
    if nsub < 1:
        nsub = 1
    h = dt / nsub
    for j in range(nsub):
        if j > 0:
            code = pipe_props(q, tcell, geom, ncell, hcoeffs, rsp, prim)
            if code != 0:
                return 300 + code - 1, nsub, e_in, courant
        if j == 0 and counter[0] % fric_every == 0:
            friction_factors(prim, geom, ncell, fric)
        for ip in range(npipe):
            for side in range(2):
                kv = ends[ip, side, E_VOL]
                if ends[ip, side, E_KIND] == BC_OPEN:
                    bc_open(prim, pipes, geom, ip, side, endp[ip, side, 0], props, kv, wb, bflux)
                else:
                    bc_orifice(prim, pipes, geom, ip, side, endp[ip, side, 0], endp[ip, side, 1], props, kv, wb,
                               bflux)
        advance(q, prim, geom, pipes, bflux, fric, h, work)
        for ip in range(npipe):
            for side in range(2):
                kv = ends[ip, side, E_VOL]
                sg = h if side == 1 else -h          # the volume gains what leaves the pipe at its end
                dma = sg * bflux[ip, side, Q_A]
                dmm = sg * bflux[ip, side, Q_M]
                dmp = sg * bflux[ip, side, Q_P]
                de = sg * bflux[ip, side, Q_E]
                xfer[kv, V_MA] += dma
                xfer[kv, V_MM] += dmm
                xfer[kv, V_MP] += dmp
                xfer[kv, V_U] += de
                e_in -= de
                dm = dma + dmm + dmp
                if kv < nvol:
                    # donor R T: the pipe end cell's for flow into the volume, the volume's own for flow out
                    i_end = pipes[ip, 0] + (pipes[ip, 1] - 1 if side == 1 else 0)
                    rt = prim[PM_R, i_end] * prim[PM_T, i_end] if dm > 0.0 else props[kv, PR_RT]
                    xrate[kv] += props[kv, PR_GV] * rt * dm
    counter[0] += 1
    return 0, nsub, e_in, courant
