"""Converged-cycle driver of the multi-cylinder engine (numba).

The engine is a network of 0D volumes joined by flow elements:

    ambient -throttle-> throttle body -restrictor-> plenum =runner k=> intake port k
    -intake valve k-> cylinder k -exhaust valve k-> exhaust port k =runner k=> collector
    -tailpipe-> ambient

``=runner=>`` elements carry a mass-flow state with a lumped momentum equation
(gas inertia, so Helmholtz/ram tuning with speed exists) or, with inertia off,
act as quasi-steady resistances.  Every volume holds the masses of three
pseudo-species (air A, fresh mixture M = air + fuel vapour, products P) and its
total internal energy including enthalpies of formation; temperature follows
from that energy, so the heat released by combustion is the change of
composition M -> P, not a separate source term.

Integration: fixed crank-angle step, Heun's method (explicit trapezoidal RK2)
on all states.  The orifice elements (throttle, restrictor, valves, tailpipe)
are evaluated, in each Heun stage, linearly implicitly: every flow is
linearised in the two pressures and solved together with the pressure changes
of the volumes it joins over one step, including the known pressure rates
from the piston, wall heat and runner flows (``network.solve_one`` and
``solve_two``, closed forms; the coupled groups are [throttle body, plenum],
[intake port k, cylinder k, exhaust port k] and [collector]).  This is smooth (no explicit/implicit switch) and stays
correct where the square-root law is stiff (nearly equal pressures, the small
cylinder volume during valve overlap).  Quasi-steady runners (inertia off) use
a single-element flow, implicit where stiff (``network.flow_between``).  Each
flow leaves one volume and enters another with
the same mass and enthalpy, so mass and energy are conserved by construction;
the cycle-level balances reported in ``out`` therefore measure how periodic the
converged cycle is.
"""

import math

import numpy as np
from numba import njit

from engine_model.thermo import enthalpy_coeffs_into
from engine_model.cycle.accel import mpe, pack_state, state_weights, unpack_state
from engine_model.cycle.cylinder import (end_gas_temperature, ignition_delay, wall_heat_rate, woschni_coefficient,
                       woschni_velocity)
from engine_model.cycle.layout import *  # noqa: F401,F403  (index constants)
from engine_model.cycle.network import add_rate, lin_between, orifice_between, solve_one, solve_two
from engine_model.cycle.volumes import *  # noqa: F401,F403  (props columns, accumulator layout, volume kernels)
from engine_model.cycle.volumes import eval_props, iv_transfer, set_ambient, transfer, transfer_as

RHO_MIN = 0.5    # [-] smallest contraction ratio assumed by the convergence estimate
# [-] slowest cycle-to-cycle ratio assumed until an extrapolation has measured one:
# the plenum-composition mode of the R6 decays by 0.86-0.92 per cycle over the map
# (measured on 12 points, 250-cycle runs); a larger value only costs cycles.
RHO_START = 0.92
RHO_MAX = 0.97   # [-] ratios above this count as not contracting
SLUG_EMPTY = 1e-12  # [-] a backflow slug below this share of its room counts as empty
PHI_DT = 0.5        # [-] slug share of a forward draw m_s / (m_s + PHI_DT m dt)
MBAL_SHARE = 0.25   # [-] the cycle's mass imbalance must be below this share of the tolerance (floor seen ~1.5e-4)


def n_volumes(ncyl, nseg_in=1, nseg_ex=1):
    """Number of gas volumes for ``ncyl`` cylinders.

    Cylinders, 2 ports each, plenum, throttle body, collector, then the inner
    joints of the segmented runners (``nseg - 1`` per runner; intake runners
    first, runner by runner, then exhaust).
    """
    return 3 * ncyl + 3 + ncyl * (nseg_in - 1) + ncyl * (nseg_ex - 1)



@njit(cache=True, fastmath=FASTMATH, _nrt=False, inline="always")
def _plenum_bulk(vol, mr, props, ipl, nflow, ncyl):
    """Mass fractions and specific enthalpy [J/kg] of the plenum's bulk: the plenum node minus the slugs.

    The slugs hold their gas at the enthalpy it came in with, so the bulk's
    enthalpy is what the node's enthalpy leaves for it.  Falls back to the node's
    own properties should the slugs ever hold more than three quarters of it.
    """
    sa = 0.0
    sm = 0.0
    sp = 0.0
    sh = 0.0
    for k in range(ncyl):
        b = nflow + NSLUG * k
        sa += max(mr[b + SL_A], 0.0)
        sm += max(mr[b + SL_M], 0.0)
        sp += max(mr[b + SL_P], 0.0)
        sh += mr[b + SL_H]
    ba = max(vol[ipl, V_MA] - sa, 0.0)
    bm = max(vol[ipl, V_MM] - sm, 0.0)
    bp = max(vol[ipl, V_MP] - sp, 0.0)
    mb = ba + bm + bp
    mpl = vol[ipl, V_MA] + vol[ipl, V_MM] + vol[ipl, V_MP]
    if mb > 0.25 * mpl:
        return ba / mb, bm / mb, bp / mb, (mpl * props[ipl, PR_H] - sh) / mb
    return props[ipl, PR_YA], props[ipl, PR_YM], props[ipl, PR_YP], props[ipl, PR_H]


@njit(cache=True, fastmath=FASTMATH, _nrt=False, inline="always")
def _slug_flow(ipl, dn, m, mr, dmr, b, slug_v, yb_a, yb_m, yb_p, hb, dt, props, dvol):
    """Flow ``m`` [kg/s] plenum node -> runner (negative: back into the plenum node) through a backflow slug.

    Backflow enters the slug ``mr[b:b + NSLUG]`` with the composition and
    enthalpy of the gas it comes from.  Forward flow takes the share
    phi = m_s / (m_s + PHI_DT m dt) from the slug and the rest from the plenum's
    bulk (composition ``yb_*``, specific enthalpy ``hb`` [J/kg]).  With PHI_DT =
    1/2 that is the step's discretisation of "all from the slug until it is
    empty": phi is 1 to within PHI_DT dt m / m_s, and in the step where the slug
    runs out the Heun predictor overshoots below zero, the second stage draws
    nothing and the slug ends the step exactly empty.  (A wider transition,
    PHI_DT = 1 or 2, left a tail of slug that never emptied and a
    cycle-to-cycle noise floor of ~3e-5 at low load.)

    The slug has room for ``slug_v`` [m^3] times the node's density: as it fills
    the last fifth of that room, backflow pushes a growing share g (a
    smoothstep from 0 at 80 % to 1 at 100 % full) of its own mass out of the
    slug's far end into the bulk, so a full slug passes on what it takes in (a
    ramp, not a switch, keeps the right-hand side continuous).  Mass, species
    and energy of the plenum node and of the runner's downstream volume change
    exactly as for any other flow; the slug is a ledger inside the node.
    """
    room = slug_v * props[ipl, PR_RHO]          # [kg]
    s_a = max(mr[b + SL_A], 0.0)
    s_m = max(mr[b + SL_M], 0.0)
    s_p = max(mr[b + SL_P], 0.0)
    ms = s_a + s_m + s_p
    live = ms > SLUG_EMPTY * room               # below: counts as empty (no 1/ms of denormal masses)
    inv = 1.0 / ms if live else 0.0
    hs = mr[b + SL_H] * inv if live else hb
    if m >= 0.0:
        phi = ms / (ms + PHI_DT * m * dt) if live else 0.0
        w = m * phi * inv                       # [1/s]: share of the slug leaving per second
        dmr[b + SL_A] = -w * s_a
        dmr[b + SL_M] = -w * s_m
        dmr[b + SL_P] = -w * s_p
        dmr[b + SL_H] = -m * phi * hs
        # what the runner receives: the slug's share plus the bulk's
        ya = phi * s_a * inv + (1.0 - phi) * yb_a
        ym = phi * s_m * inv + (1.0 - phi) * yb_m
        yp = phi * s_p * inv + (1.0 - phi) * yb_p
        transfer_as(ipl, dn, m, ya, ym, yp, phi * hs + (1.0 - phi) * hb, dvol)
    else:
        dmr[b + SL_A] = -m * props[dn, PR_YA]
        dmr[b + SL_M] = -m * props[dn, PR_YM]
        dmr[b + SL_P] = -m * props[dn, PR_YP]
        dmr[b + SL_H] = -m * props[dn, PR_H]
        x = (ms / room - 0.8) * 5.0             # 0 at 80 %, 1 at 100 % of the room
        if x > 0.0 and live:
            g = 1.0 if x >= 1.0 else x * x * (3.0 - 2.0 * x)
            r = -m * g * inv                    # [1/s]: share of the slug pushed on into the bulk
            dmr[b + SL_A] -= r * s_a
            dmr[b + SL_M] -= r * s_m
            dmr[b + SL_P] -= r * s_p
            dmr[b + SL_H] -= r * ms * hs
        transfer_as(ipl, dn, m, props[dn, PR_YA], props[dn, PR_YM], props[dn, PR_YP], props[dn, PR_H], dvol)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _consistent_slugs(vol, mr, ipl, nflow, ncyl):
    """Keep the slug ledgers inside the plenum node after an extrapolated (or supplied) state.

    No slug species below zero, and together no more of a species than the node
    holds (scaled down, with its enthalpy content, where they would).
    """
    for c in range(3):
        tot = 0.0
        for k in range(ncyl):
            b = nflow + NSLUG * k
            if mr[b + c] < 0.0:
                mr[b + c] = 0.0
            tot += mr[b + c]
        have = max(vol[ipl, c], 0.0)
        if tot > have:
            f = have / tot
            for k in range(ncyl):
                b = nflow + NSLUG * k
                ms = mr[b + SL_A] + mr[b + SL_M] + mr[b + SL_P]
                cut = mr[b + c] * (1.0 - f)
                if ms > 0.0:
                    mr[b + SL_H] *= (ms - cut) / ms
                mr[b + c] -= cut


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _derivs(vol, mr, s_step, stage, par, tab, offs, hcoeffs, rsp, fuel_c, ref, nvol, cbuf, props,
            vcur, dvol, dmr, acc, rate, E):
    """Time derivatives of all states at the start (stage 0) or end (stage 1) of step ``s_step``.

    Returns a failure code (0 = ok).  ``acc`` receives the rates of the cycle integrals.
    """
    ncyl = int(par[P_NCYL])
    nstep = int(par[P_NSTEP])
    dt = par[P_DT]
    far = par[P_FAR]
    ipl = 3 * ncyl
    itb = ipl + 1
    icol = ipl + 2
    amb = nvol
    eps = par[P_NET_EPS]
    # current volumes of the cylinders
    for k in range(ncyl):
        li = (s_step + stage - offs[k]) % nstep
        vcur[k] = tab[T_V, li]
    code = eval_props(vol, vcur, nvol, hcoeffs, rsp, cbuf, props)
    if code != 0:
        return code
    dvol[:, :] = 0.0
    acc[:] = 0.0
    rate[:] = 0.0

    # ---- runners (intake k: plenum -> port k; exhaust k: port k -> collector).
    # Each runner is ``nseg`` lumped segments in series, a mass-flow state with
    # its momentum equation per segment; the joints between segments are gas
    # volumes (indices from icol + 1 on, see ``n_volumes``).  The loss factor k_r
    # (exit dump, minor losses and wall friction, see ``prepare``) is spread evenly
    # over the segments, so in steady flow the runner's pressure drop is
    # k_r * m^2 / (2 rho A^2) whatever ``nseg``.
    jnt = icol + 1
    # Backflow slugs of the intake runners (``P_IR_SLUG_V`` > 0): gas pushed back out
    # of a port is held, in the runner's plenum-side share of the plenum node, as a
    # slug of its own composition and enthalpy, and is the first gas that runner
    # draws again; only what overflows that share joins the plenum's bulk.  The
    # plenum node's pressure and temperature stay those of all its gas; the bulk,
    # which every runner draws once its slug is used up, is the node minus the slugs.
    slug_v = par[P_IR_SLUG_V]
    slug_on = slug_v > 0.0 and par[P_IR_INERTIA] > 0.5
    nflow = ncyl * (int(par[P_IR_NSEG]) + int(par[P_ER_NSEG]))
    if slug_on:
        yb_a, yb_m, yb_p, hb = _plenum_bulk(vol, mr, props, ipl, nflow, ncyl)
    else:
        yb_a, yb_m, yb_p, hb = props[ipl, PR_YA], props[ipl, PR_YM], props[ipl, PR_YP], props[ipl, PR_H]
    for side in range(2):
        if side == 0:
            a_r = par[P_IR_A]
            l_r = par[P_IR_L]
            k_r = par[P_IR_K]
            inertia = par[P_IR_INERTIA] > 0.5
            nseg = int(par[P_IR_NSEG])
            m_first = 0
        else:
            a_r = par[P_ER_A]
            l_r = par[P_ER_L]
            k_r = par[P_ER_K]
            inertia = par[P_ER_INERTIA] > 0.5
            nseg = int(par[P_ER_NSEG])
            m_first = ncyl * int(par[P_IR_NSEG])
        l_s = l_r / nseg
        c_dp = a_r / l_s                       # [m]: d(mdot)/dt per unit pressure difference
        c_loss = k_r / (2.0 * a_r * l_r)       # [1/m^3]: loss term is c_loss * m|m| / rho
        for k in range(ncyl):
            if side == 0:
                up_end = ipl
                dn_end = ncyl + k
            else:
                up_end = 2 * ncyl + k
                dn_end = icol
            for j in range(nseg):
                up = up_end if j == 0 else jnt + j - 1
                dn = dn_end if j == nseg - 1 else jnt + j
                idx = m_first + k * nseg + j
                if inertia:
                    m = mr[idx]
                    rho = props[up, PR_RHO] if m >= 0.0 else props[dn, PR_RHO]
                    dmr[idx] = c_dp * (props[up, PR_P] - props[dn, PR_P]) - c_loss * m * abs(m) / rho
                else:
                    m = orifice_between(up, dn, a_r / math.sqrt(k_r), props, dt)
                    dmr[idx] = 0.0
                if slug_on and side == 0 and j == 0:
                    _slug_flow(up, dn, m, mr, dmr, nflow + NSLUG * k, slug_v, yb_a, yb_m, yb_p, hb, dt, props, dvol)
                else:
                    transfer(up, dn, m, nvol, props, dvol)
                add_rate(up, dn, m, nvol, props, vcur, rate)
            jnt += nseg - 1

    # ---- exhaust collector -> ambient.  The tailpipe beyond the collector is
    # full of exhaust gas, so gas drawn back in has the collector's composition
    # and temperature (pseudo-volume ``tpipe`` at ambient pressure), not fresh air.
    tpipe = nvol + 1
    for c in range(NPR):
        props[tpipe, c] = props[icol, c]
    props[tpipe, PR_P] = par[P_PAMB]
    props[tpipe, PR_RHO] = par[P_PAMB] / (props[icol, PR_R] * props[icol, PR_T])
    props[tpipe, PR_S] = 0.0
    props[tpipe, PR_GV] = 0.0

    # ---- cylinders: combustion, wall heat, piston work, knock
    for k in range(ncyl):
        ls = (s_step - offs[k]) % nstep          # start of the step (burn increment, dV)
        ls1 = (ls + 1) % nstep
        le = ls1 if stage == 1 else ls           # evaluation point of this stage
        base = A_CYL0 + AC_N * k
        p = props[k, PR_P]
        t = props[k, PR_T]
        dvdt = (tab[T_V, ls1] - tab[T_V, ls]) / dt

        # combustion: the exact Wiebe increment of this step, spread evenly over it
        if par[P_COMBUSTION] > 0.5:
            dxb = tab[T_XB, ls1] - tab[T_XB, ls]
            if dxb > 0.0:
                mb = ref[k, 4] * dxb / dt
                cap = vol[k, V_MM] / dt
                if mb > cap:
                    mb = cap if cap > 0.0 else 0.0
                dvol[k, V_MM] -= mb
                dvol[k, V_MP] += mb
                acc[A_BURN] += mb * far / (1.0 + far)

        # Woschni wall heat transfer, phase-dependent constants
        phase = tab[T_PHASE, le]
        if phase < 0.5:
            c1 = par[P_C1_GE]
            c2 = 0.0
        elif phase < 1.5:
            c1 = par[P_C1_CL]
            c2 = 0.0
        else:
            c1 = par[P_C1_CL]
            c2 = par[P_C2]
        pmot = ref[k, 0] * tab[T_VMOT, le]
        w = woschni_velocity(c1, c2, par[P_SP], par[P_VD], ref[k, 1], ref[k, 0], ref[k, 2], p, pmot)
        h = woschni_coefficient(par[P_WOSCHNI], p, t, w)
        q = wall_heat_rate(h, t, par[P_A_HEAD], par[P_TW_HEAD], par[P_A_PISTON], par[P_TW_PISTON],
                           tab[T_ALINER, le], par[P_TW_LINER])
        dvol[k, V_U] -= q + p * dvdt
        acc[base + AC_WORK] += p * dvdt
        acc[base + AC_Q] += q
        g = props[k, PR_G]
        rate[k] -= (g * p * dvdt + (g - 1.0) * q) / vcur[k]

        # end-gas autoignition (Livengood-Wu integrand 1/tau)
        if tab[T_KWIN, le] > 0.5:
            tu = end_gas_temperature(p, ref[k, 0], ref[k, 1], ref[k, 3])
            acc[base + AC_KNOCK] += 1.0 / ignition_delay(p, tu, par[P_KN_A], par[P_KN_N], par[P_KN_B])

    # ---- orifice elements.  Those outside the network (legacy treatment) first,
    # so that their flows enter the network solve as known pressure rates.
    # element rows: 0 throttle, 1 restrictor, 2 tailpipe, 3+2k intake valve k, 4+2k exhaust valve k
    lin_between(amb, itb, par[P_THR_CDA], 0.0, props, eps, E, 0)
    lin_between(itb, ipl, par[P_RES_CDA], par[P_RES_REC], props, eps, E, 1)
    lin_between(icol, tpipe, par[P_TP_CDA], 0.0, props, eps, E, 2)
    # network solves: [throttle body, plenum], [collector], [intake port, cylinder, exhaust port] per cylinder
    solve_two(0, 1, E, props, rate, nvol, dt)
    solve_one(2, E, props, rate, nvol, dt)
    for k in range(ncyl):
        le = (s_step + stage - offs[k]) % nstep
        e = 3 + 2 * k
        E[e, 6] = 0.0
        E[e + 1, 6] = 0.0
        aiv = tab[T_AIV, le]
        aev = tab[T_AEV, le]
        if aiv > 0.0:
            lin_between(ncyl + k, k, aiv, 0.0, props, eps, E, e)
        if aev > 0.0:
            lin_between(k, 2 * ncyl + k, aev, 0.0, props, eps, E, e + 1)
        if aiv > 0.0 and aev > 0.0:
            solve_two(e, e + 1, E, props, rate, nvol, dt)
        elif aiv > 0.0:
            solve_one(e, E, props, rate, nvol, dt)
        elif aev > 0.0:
            solve_one(e + 1, E, props, rate, nvol, dt)

    # ---- apply the flows (each leaves one volume and enters another, same mass and enthalpy)
    mth = E[0, 6]
    transfer(amb, itb, mth, nvol, props, dvol)
    acc[A_AIR] += mth * (1.0 if mth >= 0.0 else props[itb, PR_YA])   # air only: what an airflow meter sees
    acc[A_MIN] += mth                                                 # all species: for the mass balance
    acc[A_HAIR] += mth * (props[amb, PR_H] if mth >= 0.0 else props[itb, PR_H])
    mres = E[1, 6]
    if mres < 0.0 and slug_on:
        # gas pushed back through the restrictor comes from the plenum's bulk, not from the runners' slugs
        transfer_as(itb, ipl, mres, yb_a, yb_m, yb_p, hb, dvol)
    else:
        transfer(itb, ipl, mres, nvol, props, dvol)
    mtp = E[2, 6]
    transfer(icol, tpipe, mtp, nvol, props, dvol)
    acc[A_OUT] += mtp
    acc[A_HOUT] += mtp * props[icol, PR_H]
    for k in range(ncyl):
        base = A_CYL0 + AC_N * k
        e = 3 + 2 * k
        m = E[e, 6]
        if m != 0.0:
            iv_transfer(ncyl + k, k, m, far, fuel_c, nvol, props, dvol, acc)
        m = E[e + 1, 6]
        if m != 0.0:
            transfer(k, 2 * ncyl + k, m, nvol, props, dvol)
            if m > 0.0:
                acc[base + AC_EXM] += m
                acc[base + AC_EXMT] += m * props[k, PR_T]
    return 0


@njit(cache=True, fastmath=FASTMATH)
def run_engine(par, tab, offs, coeffs, rsp, fuel_c, vol, mr, ref, vfix, out, trace, hist):
    """Integrate whole cycles until the engine repeats itself.

    Parameters
    ----------
    par : (NPAR,) float64
        Scalar parameters, see :mod:`.layout` (``P_*``).
    tab : (NTAB, nstep) float64
        Per-local-angle tables (``T_*``), index 0 = firing TDC, step ``par[P_DT]`` in time.
    offs : (ncyl,) int64
        Firing-TDC step index of each cylinder in engine steps.
    coeffs : (3, 2, 7) float64
        Mass-based NASA coefficients of air, mixture, products (:mod:`engine_model.thermo`).
    rsp : (3,) float64
        Specific gas constants of the three species [J/(kg K)].
    fuel_c : (2, 7) float64
        Fuel-vapour coefficients.
    vol : (nvol, NVCOL) float64
        Initial state of every volume; overwritten with the final state.
    mr : (ncyl * (nseg_in + nseg_ex + NSLUG),) float64
        Runner state: segment mass flows [kg/s] (intake runners, then exhaust,
        each runner's segments from its upstream end), then each intake runner's
        backflow slug (air, mixture, products [kg], enthalpy content [J]; used
        when ``par[P_IR_SLUG_V] > 0``, zeros otherwise); overwritten.
    ref : (ncyl, 5) float64
        Per-cylinder reference state of the closed period: pressure [Pa],
        temperature [K] and volume [m^3] at IVC, isentropic exponent
        (gamma-1)/gamma [-] and mixture mass at SOC [kg]; overwritten with the
        values at the end.  Rows with ``ref[k, 1] <= 0`` are unknown (cold
        start) and get defaults.  The mixture mass at SOC of a cylinder that is
        burning at the start is always re-derived from its state, so that the
        burn that straddles the start completes whatever the previous run's
        burn law (the remaining mixture over the remaining Wiebe fraction).
    vfix : (nvol,) float64
        Volumes [m^3] (cylinder entries ignored).
    out : (NOUT,) float64
        Cycle results of the last cycle (``O_*``).
    trace : (2*ncyl + 5, nstep) float64
        Last-cycle traces: cylinder pressures, cylinder temperatures, plenum,
        collector, throttle-body, intake-port-1 and exhaust-port-1 pressures [Pa, K].
    hist : (nh, H_N0 + nvol*(NVCOL-1) + len(mr)) float64
        Per-cycle record (row = cycle - 1, up to ``nh`` cycles; ``nh`` may be 0):
        trapped mass [kg], net work [J], mass imbalance [-], then the end-of-cycle
        state (volume masses and energies, runner flows).
    """
    ncyl = int(par[P_NCYL])
    nstep = int(par[P_NSTEP])
    dt = par[P_DT]
    nvol = vol.shape[0]
    ipl = 3 * ncyl
    itb = ipl + 1
    icol = ipl + 2
    nacc = A_CYL0 + AC_N * ncyl
    idx_ivc = int(par[P_IDX_IVC])
    idx_soc = int(par[P_IDX_SOC])
    maxcyc = int(par[P_MAXCYC])
    mincyc = int(par[P_MINCYC])
    tol = par[P_TOL]

    cbuf = np.empty(4)
    t_start = np.zeros(nvol)            # start-of-step temperature of the previous step [K] (0 = none yet)
    hcoeffs = np.empty((3, 2, 6))      # enthalpy-polynomial form of ``coeffs`` for the property evaluation
    enthalpy_coeffs_into(coeffs, hcoeffs)
    props = np.zeros((nvol + 2, NPR))   # + ambient, + tailpipe pseudo-volume
    set_ambient(props, nvol, par, coeffs, rsp)
    vcur = vfix.copy()
    vol1 = np.empty_like(vol)
    d0 = np.empty_like(vol)
    d1 = np.empty_like(vol)
    mr1 = np.empty_like(mr)
    dm0 = np.zeros_like(mr)
    dm1 = np.zeros_like(mr)
    rate = np.zeros(nvol)
    E = np.zeros((3 + 2 * ncyl, 7))
    a0 = np.zeros(nacc)
    a1 = np.zeros(nacc)
    cyc_acc = np.zeros(nacc)
    # per-cylinder reference state: p_ivc, T_ivc, V_ivc, isentropic exponent, mixture mass at SOC
    for k in range(ncyl):
        if not (ref[k, 1] > 0.0):
            ref[k, 0] = par[P_PAMB]
            ref[k, 1] = 330.0
            ref[k, 2] = tab[T_V, idx_ivc]
            ref[k, 3] = 0.4 / 1.4
        ref[k, 4] = 0.0
        li0 = (nstep - offs[k]) % nstep
        if tab[T_PHASE, li0] > 1.5 and li0 != idx_soc:
            xb0 = tab[T_XB, li0]
            ref[k, 4] = vol[k, V_MM] / (1.0 - xb0) if xb0 < 1.0 - 1e-9 else vol[k, V_MM]
    nflow = ncyl * (int(par[P_IR_NSEG]) + int(par[P_ER_NSEG]))
    slug_on = par[P_IR_SLUG_V] > 0.0 and par[P_IR_INERTIA] > 0.5   # same test as ``_derivs`` (mr's shape: simulate_point)
    if slug_on:
        _consistent_slugs(vol, mr, ipl, nflow, ncyl)
    knock_run = np.zeros(ncyl)       # running Livengood-Wu integral since IVC
    knock_cyc = np.zeros(ncyl)       # value reached in this cycle
    trapped = np.zeros(ncyl)
    trapped_fresh = np.zeros(ncyl)
    resid = np.zeros(ncyl)
    pmax = np.zeros(ncyl)
    pmax_ang = np.zeros(ncyl)
    wgross = np.zeros(ncyl)
    wpump = np.zeros(ncyl)
    ppl_sum = 0.0

    prev_trap = -1.0
    prev_work = 0.0
    # MPE acceleration of the slow cycle-to-cycle modes (see ``accel``)
    acc_k = int(par[P_ACCEL_K])
    acc_warm = int(par[P_ACCEL_WARM])
    nx = nvol * (NVCOL - 1) + mr.shape[0]
    xs = np.zeros((max(acc_k, 1) + 2, nx))
    xw = np.zeros(nx)
    xe = np.zeros(nx)
    G = np.zeros((max(acc_k, 1), max(acc_k, 1)))
    grhs = np.zeros(max(acc_k, 1))
    n_x = 0
    d_prev = -1.0
    rho_slow = RHO_START   # contraction ratio of the slowest mode: assumed, then from the last MPE fit
    converged = 0
    fail = 0
    cyc = 0
    pref = par[P_PAMB] * par[P_VD] * ncyl   # work scale for the convergence floor [J]
    dtrap = 1.0
    dwork = 1.0
    for cyc in range(1, maxcyc + 1):
        cyc_acc[:] = 0.0
        pmax[:] = 0.0
        wgross[:] = 0.0
        wpump[:] = 0.0
        knock_cyc[:] = 0.0
        ppl_sum = 0.0
        for s in range(nstep):
            # crank-angle events at the start of the step
            for k in range(ncyl):
                li = (s - offs[k]) % nstep
                if li == idx_ivc:
                    m = vol[k, V_MA] + vol[k, V_MM] + vol[k, V_MP]
                    trapped[k] = m
                    trapped_fresh[k] = vol[k, V_MA] + vol[k, V_MM]
                    resid[k] = vol[k, V_MP] / m
                    knock_cyc[k] = max(knock_cyc[k], knock_run[k])
                    knock_run[k] = 0.0
                if li == idx_soc:
                    ref[k, 4] = vol[k, V_MM]
            # stage 1
            fail = _derivs(vol, mr, s, 0, par, tab, offs, hcoeffs, rsp, fuel_c, ref, nvol, cbuf, props,
                           vcur, d0, dm0, a0, rate, E)
            if fail != 0:
                break
            # record the state at the start of the step
            for k in range(ncyl):
                li = (s - offs[k]) % nstep
                p = props[k, PR_P]
                trace[k, s] = p
                trace[ncyl + k, s] = props[k, PR_T]
                if p > pmax[k]:
                    pmax[k] = p
                    ang = li * (720.0 / nstep)
                    pmax_ang[k] = ang if ang < 360.0 else ang - 720.0
                if li == idx_ivc:
                    ref[k, 0] = p
                    ref[k, 1] = props[k, PR_T]
                    ref[k, 2] = vcur[k]
                    g = props[k, PR_G]
                    ref[k, 3] = (g - 1.0) / g
            trace[2 * ncyl, s] = props[ipl, PR_P]
            trace[2 * ncyl + 1, s] = props[icol, PR_P]
            trace[2 * ncyl + 2, s] = props[itb, PR_P]
            trace[2 * ncyl + 3, s] = props[ncyl, PR_P]
            trace[2 * ncyl + 4, s] = props[2 * ncyl, PR_P]
            ppl_sum += props[ipl, PR_P]
            # stage 2 (predictor state at the end of the step)
            # Newton start for the end-of-step temperatures: linear extrapolation in
            # time from the last two start-of-step temperatures (leaves ~T'' dt^2
            # to iterate instead of ~T' dt; the answer does not depend on it)
            for i in range(nvol):
                for c in range(NVCOL - 1):
                    vol1[i, c] = vol[i, c] + dt * d0[i, c]
                t0 = vol[i, V_T]
                vol1[i, V_T] = 2.0 * t0 - t_start[i] if t_start[i] > 0.0 else t0
                t_start[i] = t0
            for i in range(mr.shape[0]):
                mr1[i] = mr[i] + dt * dm0[i]
            if slug_on:
                # a slug that runs out within the step overshoots below zero in the predictor (its second
                # stage then draws nothing and the step ends with it empty, see ``_slug_flow``); where the
                # plenum's bulk holds none of a species, the node's predicted mass of it overshoots with it
                for c in range(V_U):
                    if vol1[ipl, c] < 0.0:
                        vol1[ipl, c] = 0.0
            fail = _derivs(vol1, mr1, s, 1, par, tab, offs, hcoeffs, rsp, fuel_c, ref, nvol, cbuf, props,
                           vcur, d1, dm1, a1, rate, E)
            if fail != 0:
                break
            h2 = 0.5 * dt
            for i in range(nvol):
                for c in range(NVCOL - 1):
                    vol[i, c] += h2 * (d0[i, c] + d1[i, c])
                vol[i, V_T] = vol1[i, V_T]
            for i in range(mr.shape[0]):
                mr[i] += h2 * (dm0[i] + dm1[i])
            for i in range(nacc):
                cyc_acc[i] += h2 * (a0[i] + a1[i])
            for k in range(ncyl):
                base = A_CYL0 + AC_N * k
                wk = h2 * (a0[base + AC_WORK] + a1[base + AC_WORK])
                li = (s - offs[k]) % nstep
                if li < nstep // 4 or li >= 3 * nstep // 4:
                    wgross[k] += wk
                else:
                    wpump[k] += wk
                knock_run[k] += h2 * (a0[base + AC_KNOCK] + a1[base + AC_KNOCK])
        if fail != 0:
            break
        # ---- end of cycle: convergence on trapped mass, net work and mass balance
        mtrap = trapped.sum()
        wnet = wgross.sum() + wpump.sum()
        min_ = cyc_acc[A_MIN] + cyc_acc[A_FUEL]
        mbal = abs(min_ - cyc_acc[A_OUT]) / min_ if min_ > 0.0 else 1.0
        # Distance to the periodic solution, estimated from the change per cycle d
        # and the contraction ratio rho: the remaining geometric tail is
        # d*rho/(1 - rho).  rho is the larger of the ratio of the last two changes
        # and the slowest ratio known (RHO_START, then the last MPE fit), so a
        # slow mode hiding under a fast transient is not mistaken for convergence;
        # a growing change never converges.
        est = 1.0
        have_est = False
        if prev_trap > 0.0:
            dtrap = abs(mtrap - prev_trap) / mtrap
            dwork = abs(wnet - prev_work) / max(abs(wnet), 0.01 * pref)
            # the cycle's mass imbalance is a level with a floor set by the integration error, not a
            # change that decays geometrically: it is required below the tolerance on its own and kept out
            # of the tail estimate (inside it, a floor near 1e-4 blocked convergence at some points)
            dn = max(dtrap, dwork)
            rho = max(dn / d_prev, rho_slow) if d_prev > 0.0 else rho_slow
            est = dn * rho / (1.0 - rho) if rho < RHO_MAX else 1.0
            have_est = True
            if cyc >= mincyc and est < tol and dn < tol and mbal < MBAL_SHARE * tol:
                converged = 1
            d_prev = dn
        else:
            d_prev = -1.0
        out[O_EST] = est
        if cyc <= hist.shape[0]:
            hrow = cyc - 1
            hist[hrow, H_MTRAP] = mtrap
            hist[hrow, H_WNET] = wnet
            hist[hrow, H_MBAL] = mbal
            j = H_N0
            for i in range(nvol):
                for c in range(NVCOL - 1):
                    hist[hrow, j] = vol[i, c]
                    j += 1
            for i in range(mr.shape[0]):
                hist[hrow, j] = mr[i]
                j += 1
        prev_trap = mtrap
        prev_work = wnet
        if converged == 1:
            break
        # ---- acceleration: MPE over the last acc_k + 2 end-of-cycle states
        if acc_k > 0 and cyc >= acc_warm:
            pack_state(vol, mr, xs[n_x])
            n_x += 1
            if n_x == acc_k + 2:
                jumped = False
                if have_est and est > tol and cyc + 3 <= maxcyc:
                    state_weights(vol, mr, xw, ncyl)
                    ratio = mpe(xs, n_x, xw, xe, G, grhs)
                    if ratio >= 0.0:
                        # a species mass that the extrapolation would drive below zero
                        # (mixture left in the exhaust from the start, decaying to 0)
                        # drops to a tenth instead
                        xl = xs[n_x - 1]
                        for j in range(nvol * (NVCOL - 1)):
                            if j % (NVCOL - 1) < V_U and xe[j] < 0.1 * xl[j]:
                                xe[j] = 0.1 * xl[j]
                        unpack_state(xe, vol, mr)
                        if slug_on:
                            _consistent_slugs(vol, mr, ipl, nflow, ncyl)
                        jumped = True
                        rho_slow = min(max(ratio, RHO_START), RHO_MAX)
                        prev_trap = -1.0   # the next cycle starts a fresh comparison
                if jumped:
                    pack_state(vol, mr, xs[0])
                    n_x = 1
                else:
                    for r in range(n_x - 1):
                        xs[r, :] = xs[r + 1, :]
                    n_x -= 1

    est = out[O_EST]
    out[:] = 0.0
    out[O_EST] = est
    out[O_CYCLES] = cyc
    out[O_CONVERGED] = converged
    out[O_FAIL] = fail
    if fail != 0:
        out[O_CONVERGED] = 0
        return
    out[O_AIR] = cyc_acc[A_AIR]
    out[O_FUEL] = cyc_acc[A_FUEL]
    out[O_EXH] = cyc_acc[A_OUT]
    out[O_HAIR] = cyc_acc[A_HAIR]
    out[O_HFUEL] = cyc_acc[A_HFUEL]
    out[O_HOUT] = cyc_acc[A_HOUT]
    out[O_FUEL_BURNED] = cyc_acc[A_BURN]
    out[O_WGROSS] = wgross.sum()
    out[O_WPUMP] = wpump.sum()
    exm = 0.0
    exmt = 0.0
    for k in range(ncyl):
        base = A_CYL0 + AC_N * k
        out[O_QWALL] += cyc_acc[base + AC_Q]
        exm += cyc_acc[base + AC_EXM]
        exmt += cyc_acc[base + AC_EXMT]
        out[O_PMAX] += pmax[k] / ncyl
        out[O_PMAX_ANG] += pmax_ang[k] / ncyl
        out[O_RES] += resid[k] / ncyl
        out[O_KNOCK] = max(out[O_KNOCK], knock_cyc[k])
    out[O_TEXH] = exmt / exm if exm > 0.0 else 0.0
    out[O_MTRAP] = trapped.sum()
    out[O_MAIR_TRAP] = trapped_fresh.sum()
    min_ = cyc_acc[A_MIN] + cyc_acc[A_FUEL]
    out[O_MBAL] = abs(min_ - cyc_acc[A_OUT]) / min_ if min_ > 0.0 else 1.0
    out[O_PPLENUM] = ppl_sum / nstep
    out[O_DTRAP] = dtrap
    out[O_DIMEP] = dwork
