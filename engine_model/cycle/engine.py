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
of the volumes it joins over a horizon tau, including the known pressure rates
from the piston, wall heat and runner flows (``_solve_chain``; the coupled
groups are [throttle body, plenum], [intake port k, cylinder k, exhaust port k]
and [collector]).  This is smooth (no explicit/implicit switch) and stays
correct where the square-root law is stiff (nearly equal pressures, the small
cylinder volume during valve overlap).  ``par[P_NET] = 0`` restores the former
element-wise explicit/backward-Euler switch.  Each flow leaves one volume and enters another with
the same mass and enthalpy, so mass and energy are conserved by construction;
the cycle-level balances reported in ``out`` therefore measure how periodic the
converged cycle is.
"""

import math

import numpy as np
from numba import njit

from ..thermo import cp_mass, h_mass, mixture_state
from .cylinder import (end_gas_temperature, ignition_delay, wall_heat_rate, woschni_coefficient,
                       woschni_velocity)
from .flow import orifice_flow, orifice_flow_lin, restrictor_throat_pressure
from .layout import *  # noqa: F401,F403  (index constants)

# property columns of the scratch array ``props``
PR_P, PR_T, PR_R, PR_G, PR_H, PR_YA, PR_YM, PR_YP, PR_RHO, PR_S = range(10)
NPR = 10
STIFF_FRACTION = 2.0  # legacy switch (par[P_NET] = 0 / elements outside the network): see _flow_between

# accumulator layout: global entries, then 6 per cylinder
A_AIR, A_HAIR, A_FUEL, A_HFUEL, A_OUT, A_HOUT, A_BURN, A_MIN = range(8)
A_CYL0 = 8
AC_WORK, AC_Q, AC_KNOCK, AC_EXM, AC_EXMT = range(5)
AC_N = 6


def n_volumes(ncyl):
    """Number of gas volumes for ``ncyl`` cylinders (cylinders, 2 ports each, plenum, throttle body, collector)."""
    return 3 * ncyl + 3


def n_accumulators(ncyl):
    return A_CYL0 + AC_N * ncyl


@njit(cache=True, fastmath=FASTMATH)
def _eval_props(vol, vcur, nvol, coeffs, rsp, cbuf, props):
    """Fill ``props`` (p, T, R, gamma, h, y, rho, stiffness) for every volume; return a failure code."""
    for k in range(nvol):
        ma = vol[k, V_MA]
        mm = vol[k, V_MM]
        mp = vol[k, V_MP]
        if ma < -1e-15 or mm < -1e-15 or mp < -1e-15:
            return 200 + k
        m = ma + mm + mp
        if not (m > 0.0):
            return 200 + k
        ya = ma / m
        ym = mm / m
        yp = mp / m
        mixture_state(coeffs, rsp, ya, ym, yp, vol[k, V_U] / m, vol[k, V_T], cbuf)
        t = cbuf[0]
        cp = cbuf[1]
        r = cbuf[3]
        if not (t > 150.0 and t < 4400.0):
            return 100 + k
        vol[k, V_T] = t
        v = vcur[k]
        p = m * r * t / v
        g = cp / (cp - r)
        props[k, PR_P] = p
        props[k, PR_T] = t
        props[k, PR_R] = r
        props[k, PR_G] = g
        props[k, PR_H] = cbuf[2]
        props[k, PR_YA] = ya
        props[k, PR_YM] = ym
        props[k, PR_YP] = yp
        props[k, PR_RHO] = m / v
        props[k, PR_S] = g * r * t / v
    return 0


@njit(cache=True, fastmath=FASTMATH)
def _transfer(i, j, mdot, nvol, props, dvol):
    """Move ``mdot`` [kg/s] from i to j (negative: j to i) with the upstream composition and enthalpy."""
    u = i if mdot >= 0.0 else j
    fa = mdot * props[u, PR_YA]
    fm = mdot * props[u, PR_YM]
    fp = mdot * props[u, PR_YP]
    fh = mdot * props[u, PR_H]
    if i < nvol:
        dvol[i, V_MA] -= fa
        dvol[i, V_MM] -= fm
        dvol[i, V_MP] -= fp
        dvol[i, V_U] -= fh
    if j < nvol:
        dvol[j, V_MA] += fa
        dvol[j, V_MM] += fm
        dvol[j, V_MP] += fp
        dvol[j, V_U] += fh


@njit(cache=True, fastmath=FASTMATH)
def _element_flow(cda, rec, p_up, t_up, r_up, g_up, p_dn):
    """Forward flow of an orifice (rec = 0) or a venturi with diffuser recovery ``rec`` [kg/s]."""
    if rec > 0.0:
        return orifice_flow(cda, p_up, t_up, r_up, g_up, restrictor_throat_pressure(p_up, p_dn, rec))
    return orifice_flow(cda, p_up, t_up, r_up, g_up, p_dn)


@njit(cache=True, fastmath=FASTMATH)
def _implicit_flow(cda, rec, p_up, t_up, r_up, g_up, p_dn, s_up, s_dn, dt, m0):
    """Orifice flow evaluated with end-of-step pressures (backward Euler), solved for mdot.

    Solves m = f(p_up - s_up*dt*m, p_dn + s_dn*dt*m) on [0, min(m0, m_eq)] by
    Illinois regula falsi, where s = gamma*R*T/V is the pressure change per kg
    of an adiabatic volume and m_eq the flow that equalises the two pressures
    in one step.  Near equal pressures the square-root orifice law makes the
    explicit flow stiff; this form relaxes smoothly to the quasi-equilibrium.
    """
    c = (s_up + s_dn) * dt
    lo = 0.0
    hi = (p_up - p_dn) / c
    if m0 < hi:
        hi = m0
    g_lo = -m0
    g_hi = hi - _element_flow(cda, rec, p_up - s_up * dt * hi, t_up, r_up, g_up, p_dn + s_dn * dt * hi)
    if g_hi <= 0.0:
        return hi
    side = 0
    m = hi
    for _ in range(30):
        m = (lo * g_hi - hi * g_lo) / (g_hi - g_lo)
        g = m - _element_flow(cda, rec, p_up - s_up * dt * m, t_up, r_up, g_up, p_dn + s_dn * dt * m)
        if abs(g) <= 1e-9 * m0:
            break
        if g > 0.0:
            hi = m
            g_hi = g
            if side == 1:
                g_lo *= 0.5
            side = 1
        else:
            lo = m
            g_lo = g
            if side == -1:
                g_hi *= 0.5
            side = -1
    return m


@njit(cache=True, fastmath=FASTMATH)
def _flow_between(i, j, cda, rec_fwd, props, dt, stiff=STIFF_FRACTION):
    """Signed flow i -> j [kg/s] through an orifice, or a venturi (recovery ``rec_fwd`` for i -> j only).

    Implicit in the two pressures where the explicit flow is stiff (see ``_implicit_flow``).
    """
    pi = props[i, PR_P]
    pj = props[j, PR_P]
    if pi >= pj:
        u, d, sgn, rec = i, j, 1.0, rec_fwd
    else:
        u, d, sgn, rec = j, i, -1.0, 0.0
    pu = props[u, PR_P]
    pd = props[d, PR_P]
    m0 = _element_flow(cda, rec, pu, props[u, PR_T], props[u, PR_R], props[u, PR_G], pd)
    su = props[u, PR_S]
    sd = props[d, PR_S]
    if m0 > 0.0 and (su + sd) * dt * m0 > stiff * (pu - pd):
        m0 = _implicit_flow(cda, rec, pu, props[u, PR_T], props[u, PR_R], props[u, PR_G], pd, su, sd, dt, m0)
    return sgn * m0


@njit(cache=True, fastmath=FASTMATH)
def _orifice_between(i, j, cda, props, dt, stiff=STIFF_FRACTION):
    """Signed orifice flow i -> j [kg/s]."""
    return _flow_between(i, j, cda, 0.0, props, dt, stiff)


@njit(cache=True, fastmath=FASTMATH)
def _coef(n, u, props, vcur):
    """Pressure change of volume n per kg of gas from volume u entering it [Pa/kg] (gamma_n R_u T_u / V_n)."""
    return props[n, PR_G] * props[u, PR_R] * props[u, PR_T] / vcur[n]


@njit(cache=True, fastmath=FASTMATH)
def _add_rate(i, j, m, nvol, props, vcur, rate):
    """Pressure rates [Pa/s] of i and j caused by a flow m [kg/s] from i to j."""
    u = i if m >= 0.0 else j
    if i < nvol:
        rate[i] -= _coef(i, u, props, vcur) * m
    if j < nvol:
        rate[j] += _coef(j, u, props, vcur) * m


@njit(cache=True, fastmath=FASTMATH)
def _lin_between(i, j, cda, rec_fwd, props, eps, E, e):
    """Signed flow i -> j and its linearisation, stored in row e of E (i, j, m0, dm/dp_i, -dm/dp_j, upstream)."""
    pi = props[i, PR_P]
    pj = props[j, PR_P]
    if pi >= pj:
        if rec_fwd > 0.0:
            pt = restrictor_throat_pressure(pi, pj, rec_fwd)
            f, fu, ft = orifice_flow_lin(cda, pi, props[i, PR_T], props[i, PR_R], props[i, PR_G], pt, eps)
            if pt <= 0.0:
                ft = 0.0
            a = fu - ft * rec_fwd / (1.0 - rec_fwd)
            b = -ft / (1.0 - rec_fwd)
        else:
            f, a, ft = orifice_flow_lin(cda, pi, props[i, PR_T], props[i, PR_R], props[i, PR_G], pj, eps)
            b = -ft
        m, u = f, i
    else:
        f, fu, ft = orifice_flow_lin(cda, pj, props[j, PR_T], props[j, PR_R], props[j, PR_G], pi, eps)
        m, u = -f, j
        a = -ft
        b = fu
    E[e, 0] = i
    E[e, 1] = j
    E[e, 2] = m
    E[e, 3] = a
    E[e, 4] = b
    E[e, 5] = u
    E[e, 6] = m


@njit(cache=True, fastmath=FASTMATH)
def _solve_chain(nodes, nn, elist, nel, E, props, vcur, rate, dt, wmode, M, rhs, tau):
    """Linearly implicit flows of the elements ``elist`` joining the volumes ``nodes`` (n <= 3).

    Each element's flow is linearised about the current pressures,
    m_e = m0_e + a_e dP_i - b_e dP_j, and the pressure changes over the horizon
    tau_n of each volume n are solved together with those flows,
    dP_n = tau_n (rate_n + sum_e c_ne m_e), where rate_n holds every other
    contribution (piston, wall heat, runner flows).  tau = dt*z/(1+z) with z the
    volume's own stiffness dt*sum(c*conductance) (``wmode`` 1), or tau = dt
    (``wmode`` 0, the default: measured to converge faster in the step).  Where
    the flows are stiff the flow follows the demand of the rest of the network
    (piston, runners) with no artificial pressure drop and no oscillation; where
    they are slow it is the explicit flow plus an O(tau) look-ahead.  Result in E[e, 6].
    """
    for a in range(nn):
        n = nodes[a]
        z = 0.0
        for q in range(nel):
            e = elist[q]
            u = int(E[e, 5])
            if int(E[e, 0]) == n:
                z += _coef(n, u, props, vcur) * E[e, 3]
            elif int(E[e, 1]) == n:
                z += _coef(n, u, props, vcur) * E[e, 4]
        z *= dt
        tau[a] = dt if wmode < 0.5 else dt * z / (1.0 + z)
        for b in range(nn):
            M[a, b] = 0.0
        M[a, a] = 1.0
        rhs[a] = tau[a] * rate[n]
    for q in range(nel):
        e = elist[q]
        i = int(E[e, 0])
        j = int(E[e, 1])
        u = int(E[e, 5])
        ia = -1
        ja = -1
        for a in range(nn):
            if nodes[a] == i:
                ia = a
            if nodes[a] == j:
                ja = a
        m0 = E[e, 2]
        al = E[e, 3]
        be = E[e, 4]
        if ia >= 0:
            c = -tau[ia] * _coef(i, u, props, vcur)
            rhs[ia] += c * m0
            M[ia, ia] -= c * al
            if ja >= 0:
                M[ia, ja] += c * be
        if ja >= 0:
            c = tau[ja] * _coef(j, u, props, vcur)
            rhs[ja] += c * m0
            M[ja, ja] += c * be
            if ia >= 0:
                M[ja, ia] -= c * al
    # Gaussian elimination with partial pivoting (n <= 3)
    for a in range(nn):
        piv = a
        for b in range(a + 1, nn):
            if abs(M[b, a]) > abs(M[piv, a]):
                piv = b
        if piv != a:
            for c2 in range(nn):
                tmp = M[a, c2]
                M[a, c2] = M[piv, c2]
                M[piv, c2] = tmp
            tmp = rhs[a]
            rhs[a] = rhs[piv]
            rhs[piv] = tmp
        for b in range(a + 1, nn):
            f = M[b, a] / M[a, a]
            for c2 in range(a, nn):
                M[b, c2] -= f * M[a, c2]
            rhs[b] -= f * rhs[a]
    for a in range(nn - 1, -1, -1):
        acc = rhs[a]
        for b in range(a + 1, nn):
            acc -= M[a, b] * rhs[b]
        rhs[a] = acc / M[a, a]
    for q in range(nel):
        e = elist[q]
        i = int(E[e, 0])
        j = int(E[e, 1])
        m = E[e, 2]
        for a in range(nn):
            if nodes[a] == i:
                m += E[e, 3] * rhs[a]
            if nodes[a] == j:
                m -= E[e, 4] * rhs[a]
        E[e, 6] = m


@njit(cache=True, fastmath=FASTMATH)
def _iv_transfer(ip, k, m, far, fuel_c, nvol, props, dvol, acc):
    """Intake-valve flow port ip -> cylinder k; forward flow carries the injected fuel with its air."""
    if m >= 0.0:
        ya = props[ip, PR_YA]
        mf = m * ya * far
        hf = h_mass(fuel_c, props[ip, PR_T])
        dvol[ip, V_MA] -= m * ya
        dvol[ip, V_MM] -= m * props[ip, PR_YM]
        dvol[ip, V_MP] -= m * props[ip, PR_YP]
        dvol[ip, V_U] -= m * props[ip, PR_H]
        dvol[k, V_MM] += m * (ya + props[ip, PR_YM]) + mf
        dvol[k, V_MP] += m * props[ip, PR_YP]
        dvol[k, V_U] += m * props[ip, PR_H] + mf * hf
        acc[A_FUEL] += mf
        acc[A_HFUEL] += mf * hf
    else:
        _transfer(ip, k, m, nvol, props, dvol)


@njit(cache=True, fastmath=FASTMATH)
def _derivs(vol, mr, s_step, stage, par, tab, offs, coeffs, rsp, fuel_c, ref, nvol, cbuf, props,
            vcur, dvol, dmr, acc, rate, E, M, rhs, tau, nodes, elist):
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
    net = par[P_NET] > 0.5
    mask = int(par[P_NET_MASK]) if net else 0
    eps = par[P_NET_EPS]
    wmode = par[P_NET_W]
    stiff = par[P_STIFF]

    # current volumes of the cylinders
    for k in range(ncyl):
        li = (s_step + stage - offs[k]) % nstep
        vcur[k] = tab[T_V, li]
    code = _eval_props(vol, vcur, nvol, coeffs, rsp, cbuf, props)
    if code != 0:
        return code
    dvol[:, :] = 0.0
    acc[:] = 0.0
    rate[:] = 0.0

    # ---- runners (intake k: plenum -> port k; exhaust k: port k -> collector)
    for side in range(2):
        if side == 0:
            a_r = par[P_IR_A]
            l_r = par[P_IR_L]
            k_r = par[P_IR_K]
            inertia = par[P_IR_INERTIA] > 0.5
        else:
            a_r = par[P_ER_A]
            l_r = par[P_ER_L]
            k_r = par[P_ER_K]
            inertia = par[P_ER_INERTIA] > 0.5
        for k in range(ncyl):
            if side == 0:
                up = ipl
                dn = ncyl + k
            else:
                up = 2 * ncyl + k
                dn = icol
            idx = side * ncyl + k
            if inertia:
                m = mr[idx]
                rho = props[up, PR_RHO] if m >= 0.0 else props[dn, PR_RHO]
                dmr[idx] = a_r / l_r * (props[up, PR_P] - props[dn, PR_P]) \
                    - k_r / (2.0 * rho * a_r * l_r) * m * abs(m)
            else:
                m = _orifice_between(up, dn, a_r / math.sqrt(k_r), props, dt, stiff)
                dmr[idx] = 0.0
            _transfer(up, dn, m, nvol, props, dvol)
            _add_rate(up, dn, m, nvol, props, vcur, rate)

    # ---- exhaust collector -> ambient.  The tailpipe beyond the collector is
    # full of exhaust gas, so gas drawn back in has the collector's composition
    # and temperature (pseudo-volume ``tpipe`` at ambient pressure), not fresh air.
    tpipe = nvol + 1
    for c in range(NPR):
        props[tpipe, c] = props[icol, c]
    props[tpipe, PR_P] = par[P_PAMB]
    props[tpipe, PR_RHO] = par[P_PAMB] / (props[icol, PR_R] * props[icol, PR_T])
    props[tpipe, PR_S] = 0.0

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
    if mask & 1:
        _lin_between(amb, itb, par[P_THR_CDA], 0.0, props, eps, E, 0)
    else:
        E[0, 6] = _orifice_between(amb, itb, par[P_THR_CDA], props, dt, stiff)
        _add_rate(amb, itb, E[0, 6], nvol, props, vcur, rate)
    if mask & 2:
        _lin_between(itb, ipl, par[P_RES_CDA], par[P_RES_REC], props, eps, E, 1)
    else:
        E[1, 6] = _flow_between(itb, ipl, par[P_RES_CDA], par[P_RES_REC], props, dt, stiff)
        _add_rate(itb, ipl, E[1, 6], nvol, props, vcur, rate)
    if mask & 16:
        _lin_between(icol, tpipe, par[P_TP_CDA], 0.0, props, eps, E, 2)
    else:
        E[2, 6] = _orifice_between(icol, tpipe, par[P_TP_CDA], props, dt, stiff)
        _add_rate(icol, tpipe, E[2, 6], nvol, props, vcur, rate)
    for k in range(ncyl):
        le = (s_step + stage - offs[k]) % nstep
        aiv = tab[T_AIV, le]
        aev = tab[T_AEV, le]
        e = 3 + 2 * k
        if aiv > 0.0:
            if mask & 4:
                _lin_between(ncyl + k, k, aiv, 0.0, props, eps, E, e)
            else:
                E[e, 6] = _orifice_between(ncyl + k, k, aiv, props, dt, stiff)
                _add_rate(ncyl + k, k, E[e, 6], nvol, props, vcur, rate)
        else:
            E[e, 6] = 0.0
        if aev > 0.0:
            if mask & 8:
                _lin_between(k, 2 * ncyl + k, aev, 0.0, props, eps, E, e + 1)
            else:
                E[e + 1, 6] = _orifice_between(k, 2 * ncyl + k, aev, props, dt, stiff)
                _add_rate(k, 2 * ncyl + k, E[e + 1, 6], nvol, props, vcur, rate)
        else:
            E[e + 1, 6] = 0.0
    # network solves: [throttle body, plenum], [collector], [port, cylinder, port] per cylinder
    nel = 0
    if mask & 1:
        elist[nel] = 0
        nel += 1
    if mask & 2:
        elist[nel] = 1
        nel += 1
    if nel > 0:
        nodes[0] = itb
        nodes[1] = ipl
        _solve_chain(nodes, 2, elist, nel, E, props, vcur, rate, dt, wmode, M, rhs, tau)
    if mask & 16:
        nodes[0] = icol
        elist[0] = 2
        _solve_chain(nodes, 1, elist, 1, E, props, vcur, rate, dt, wmode, M, rhs, tau)
    for k in range(ncyl):
        le = (s_step + stage - offs[k]) % nstep
        e = 3 + 2 * k
        nel = 0
        if (mask & 4) and tab[T_AIV, le] > 0.0:
            elist[nel] = e
            nel += 1
        if (mask & 8) and tab[T_AEV, le] > 0.0:
            elist[nel] = e + 1
            nel += 1
        if nel > 0:
            nodes[0] = ncyl + k
            nodes[1] = k
            nodes[2] = 2 * ncyl + k
            _solve_chain(nodes, 3, elist, nel, E, props, vcur, rate, dt, wmode, M, rhs, tau)

    # ---- apply the flows (each leaves one volume and enters another, same mass and enthalpy)
    mth = E[0, 6]
    _transfer(amb, itb, mth, nvol, props, dvol)
    acc[A_AIR] += mth * (1.0 if mth >= 0.0 else props[itb, PR_YA])   # air only: what an airflow meter sees
    acc[A_MIN] += mth                                                 # all species: for the mass balance
    acc[A_HAIR] += mth * (props[amb, PR_H] if mth >= 0.0 else props[itb, PR_H])
    _transfer(itb, ipl, E[1, 6], nvol, props, dvol)
    mtp = E[2, 6]
    _transfer(icol, tpipe, mtp, nvol, props, dvol)
    acc[A_OUT] += mtp
    acc[A_HOUT] += mtp * props[icol, PR_H]
    for k in range(ncyl):
        base = A_CYL0 + AC_N * k
        e = 3 + 2 * k
        m = E[e, 6]
        if m != 0.0:
            _iv_transfer(ncyl + k, k, m, far, fuel_c, nvol, props, dvol, acc)
        m = E[e + 1, 6]
        if m != 0.0:
            _transfer(k, 2 * ncyl + k, m, nvol, props, dvol)
            if m > 0.0:
                acc[base + AC_EXM] += m
                acc[base + AC_EXMT] += m * props[k, PR_T]
    return 0


@njit(cache=True, fastmath=FASTMATH)
def _set_ambient(props, amb, par, coeffs, rsp):
    t = par[P_TAMB]
    c = coeffs[SP_A]
    cp = cp_mass(c, t)
    props[amb, PR_P] = par[P_PAMB]
    props[amb, PR_T] = t
    props[amb, PR_R] = rsp[SP_A]
    props[amb, PR_G] = cp / (cp - rsp[SP_A])
    props[amb, PR_H] = h_mass(c, t)
    props[amb, PR_YA] = 1.0
    props[amb, PR_YM] = 0.0
    props[amb, PR_YP] = 0.0
    props[amb, PR_RHO] = par[P_PAMB] / (rsp[SP_A] * t)
    props[amb, PR_S] = 0.0


@njit(cache=True, fastmath=FASTMATH)
def run_engine(par, tab, offs, coeffs, rsp, fuel_c, vol, mr, vfix, out, trace):
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
    mr : (2*ncyl,) float64
        Initial runner mass flows [kg/s]; overwritten.
    vfix : (nvol,) float64
        Volumes [m^3] (cylinder entries ignored).
    out : (NOUT,) float64
        Cycle results of the last cycle (``O_*``).
    trace : (2*ncyl + 5, nstep) float64
        Last-cycle traces: cylinder pressures, cylinder temperatures, plenum,
        collector, throttle-body, intake-port-1 and exhaust-port-1 pressures [Pa, K].
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
    props = np.zeros((nvol + 2, NPR))   # + ambient, + tailpipe pseudo-volume
    _set_ambient(props, nvol, par, coeffs, rsp)
    vcur = vfix.copy()
    vol1 = np.empty_like(vol)
    d0 = np.empty_like(vol)
    d1 = np.empty_like(vol)
    mr1 = np.empty_like(mr)
    dm0 = np.zeros_like(mr)
    dm1 = np.zeros_like(mr)
    rate = np.zeros(nvol)
    E = np.zeros((3 + 2 * ncyl, 7))
    Mx = np.zeros((3, 3))
    rhs = np.zeros(3)
    tau = np.zeros(3)
    nodes = np.zeros(3, dtype=np.int64)
    elist = np.zeros(3, dtype=np.int64)
    a0 = np.zeros(nacc)
    a1 = np.zeros(nacc)
    cyc_acc = np.zeros(nacc)
    # per-cylinder reference state: p_ivc, T_ivc, V_ivc, isentropic exponent, mixture mass at SOC
    ref = np.zeros((ncyl, 5))
    for k in range(ncyl):
        ref[k, 0] = par[P_PAMB]
        ref[k, 1] = 330.0
        ref[k, 2] = tab[T_V, idx_ivc]
        ref[k, 3] = 0.4 / 1.4
        ref[k, 4] = 0.0
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
    # Aitken (one-mode vector) extrapolation of the slow cycle-to-cycle mode
    # (mostly burned gas washing out of the plenum): states at cycle ends.
    hist_vol = np.zeros((2, nvol, NVCOL))
    hist_mr = np.zeros((2, mr.shape[0]))
    hist_m = np.zeros(4)
    n_hist = 0
    since_jump = 0
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
            fail = _derivs(vol, mr, s, 0, par, tab, offs, coeffs, rsp, fuel_c, ref, nvol, cbuf, props,
                           vcur, d0, dm0, a0, rate, E, Mx, rhs, tau, nodes, elist)
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
            for i in range(nvol):
                for c in range(NVCOL - 1):
                    vol1[i, c] = vol[i, c] + dt * d0[i, c]
                vol1[i, V_T] = vol[i, V_T]
            for i in range(mr.shape[0]):
                mr1[i] = mr[i] + dt * dm0[i]
            fail = _derivs(vol1, mr1, s, 1, par, tab, offs, coeffs, rsp, fuel_c, ref, nvol, cbuf, props,
                           vcur, d1, dm1, a1, rate, E, Mx, rhs, tau, nodes, elist)
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
        if prev_trap > 0.0:
            dtrap = abs(mtrap - prev_trap) / mtrap
            dwork = abs(wnet - prev_work) / max(abs(wnet), 0.01 * pref)
            if cyc >= mincyc and dtrap < tol and dwork < tol and mbal < tol:
                converged = 1
        prev_trap = mtrap
        prev_work = wnet
        if converged == 1:
            break
        # shift the history (4 scalars, 2 states) and try an extrapolation
        for j in range(3):
            hist_m[j] = hist_m[j + 1]
        hist_vol[0] = hist_vol[1]
        hist_mr[0] = hist_mr[1]
        hist_vol[1] = vol
        hist_mr[1] = mr
        # the slow mode lives in the manifolds: track the gas stored outside the cylinders
        m_store = 0.0
        for i in range(ncyl, nvol):
            m_store += vol[i, V_MA] + vol[i, V_MM] + vol[i, V_MP]
        hist_m[3] = m_store
        n_hist = min(n_hist + 1, 4)
        since_jump += 1
        if par[P_AITKEN] > 0.5 and n_hist == 4 and since_jump >= 4 and cyc >= 4:
            s1 = hist_m[1] - hist_m[0]
            s2 = hist_m[2] - hist_m[1]
            s3 = hist_m[3] - hist_m[2]
            if s1 != 0.0 and s2 != 0.0:
                q1 = s2 / s1
                q = s3 / s2
                # a clean geometric mode (two ratio estimates agree) that still matters
                # against the tolerance; near convergence plain cycles finish the job
                if 0.3 < q < 0.95 and abs(q - q1) < 0.1 and abs(s3) > max(0.05 * tol, 1e-5) * m_store:
                    f = q / (1.0 - q)
                    ok = True
                    # species masses may be exactly zero; refuse only a clearly negative one
                    for i in range(nvol):
                        mi = vol[i, V_MA] + vol[i, V_MM] + vol[i, V_MP]
                        for c in range(V_U):
                            x = vol[i, c] + f * (vol[i, c] - hist_vol[0, i, c])
                            if x < -1e-6 * mi:
                                ok = False
                    if ok:
                        for i in range(nvol):
                            for c in range(NVCOL - 1):
                                vol[i, c] += f * (vol[i, c] - hist_vol[0, i, c])
                                if c < V_U and vol[i, c] < 0.0:
                                    vol[i, c] = 0.0
                        for i in range(mr.shape[0]):
                            mr[i] += f * (mr[i] - hist_mr[0, i])
                        since_jump = 0
                        n_hist = 0
                        prev_trap = -1.0   # the next cycle starts a fresh comparison

    out[:] = 0.0
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
