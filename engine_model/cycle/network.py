"""Orifice elements between volumes: explicit/implicit single-element flows and the linearly implicit network solve."""

from numba import njit

from .flow import orifice_flow_lin, restrictor_flow, restrictor_throat_pressure
from .layout import *  # noqa: F401,F403  (index constants)
from .volumes import PR_G, PR_P, PR_R, PR_S, PR_T

STIFF_FRACTION = 2.0  # single-element flows: solved implicitly when the explicit flow would move > 2x the equalising mass per step


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
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
    g_hi = hi - restrictor_flow(cda, rec, p_up - s_up * dt * hi, t_up, r_up, g_up, p_dn + s_dn * dt * hi)
    if g_hi <= 0.0:
        return hi
    side = 0
    m = hi
    for _ in range(30):
        m = (lo * g_hi - hi * g_lo) / (g_hi - g_lo)
        g = m - restrictor_flow(cda, rec, p_up - s_up * dt * m, t_up, r_up, g_up, p_dn + s_dn * dt * m)
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


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _flow_between(i, j, cda, rec_fwd, props, dt):
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
    m0 = restrictor_flow(cda, rec, pu, props[u, PR_T], props[u, PR_R], props[u, PR_G], pd)
    su = props[u, PR_S]
    sd = props[d, PR_S]
    if m0 > 0.0 and (su + sd) * dt * m0 > STIFF_FRACTION * (pu - pd):
        m0 = _implicit_flow(cda, rec, pu, props[u, PR_T], props[u, PR_R], props[u, PR_G], pd, su, sd, dt, m0)
    return sgn * m0


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _orifice_between(i, j, cda, props, dt):
    """Signed orifice flow i -> j [kg/s]."""
    return _flow_between(i, j, cda, 0.0, props, dt)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _coef(n, u, props, vcur):
    """Pressure change of volume n per kg of gas from volume u entering it [Pa/kg] (gamma_n R_u T_u / V_n)."""
    return props[n, PR_G] * props[u, PR_R] * props[u, PR_T] / vcur[n]


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _add_rate(i, j, m, nvol, props, vcur, rate):
    """Pressure rates [Pa/s] of i and j caused by a flow m [kg/s] from i to j."""
    u = i if m >= 0.0 else j
    if i < nvol:
        rate[i] -= _coef(i, u, props, vcur) * m
    if j < nvol:
        rate[j] += _coef(j, u, props, vcur) * m


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
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


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _solve_chain(nodes, nn, elist, nel, E, props, vcur, rate, dt, M, rhs):
    """Linearly implicit flows of the elements ``elist`` joining the volumes ``nodes`` (n <= 3).

    Each element's flow is linearised about the current pressures,
    m_e = m0_e + a_e dP_i - b_e dP_j, and the pressure changes of the volumes
    over one step, dP_n = dt (rate_n + sum_e c_ne m_e), are solved together
    with those flows; rate_n holds every other contribution (piston, wall heat,
    runner flows).  Where the flows are stiff the flow follows the demand of the
    rest of the network (piston, runners) with no artificial pressure drop and no
    oscillation; where they are slow it is the explicit flow plus an O(dt)
    look-ahead.  Result in E[e, 6].
    """
    for a in range(nn):
        for b in range(nn):
            M[a, b] = 0.0
        M[a, a] = 1.0
        rhs[a] = dt * rate[nodes[a]]
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
            c = -dt * _coef(i, u, props, vcur)
            rhs[ia] += c * m0
            M[ia, ia] -= c * al
            if ja >= 0:
                M[ia, ja] += c * be
        if ja >= 0:
            c = dt * _coef(j, u, props, vcur)
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
