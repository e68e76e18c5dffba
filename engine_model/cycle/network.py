"""Orifice elements between volumes: explicit/implicit single-element flows and the linearly implicit network solve."""

from numba import njit

from engine_model.cycle.flow import orifice_flow_lin, restrictor_flow, restrictor_throat_pressure
from engine_model.cycle.layout import *  # noqa: F401,F403  (index constants)
from engine_model.cycle.volumes import PR_G, PR_GV, PR_P, PR_R, PR_RT, PR_S, PR_T

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
def flow_between(i, j, cda, rec_fwd, props, dt):
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
def orifice_between(i, j, cda, props, dt):
    """Signed orifice flow i -> j [kg/s]."""
    return flow_between(i, j, cda, 0.0, props, dt)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _coef(n, u, props, vcur):
    """Pressure change of volume n per kg of gas from volume u entering it [Pa/kg] (gamma_n R_u T_u / V_n)."""
    return props[n, PR_GV] * props[u, PR_RT]


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def add_rate(i, j, m, nvol, props, vcur, rate):
    """Pressure rates [Pa/s] of i and j caused by a flow m [kg/s] from i to j."""
    u = i if m >= 0.0 else j
    if i < nvol:
        rate[i] -= _coef(i, u, props, vcur) * m
    if j < nvol:
        rate[j] += _coef(j, u, props, vcur) * m


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def lin_between(i, j, cda, rec_fwd, props, eps, E, e):
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
def _lin_terms(e, E, props, rate, nvol, dt):
    """Terms of element e's linearised flow with the pressure changes of its end volumes substituted.

    With m = m0 + a dP_i - b dP_j and dP_n = dt (rate_n + sum of c_n,u m over the
    flows into n), where c_n,u = gamma_n R_u T_u / V_n and an end at or beyond
    ``nvol`` (ambient, tailpipe) has a fixed pressure, this returns
    (m0 + dt (a rate_i - b rate_j), dt a c_i, dt b c_j, dt a, dt b) with
    c_i, c_j the coefficients of the ends for this element's upstream gas
    (0 for fixed ends).
    """
    i = int(E[e, 0])
    j = int(E[e, 1])
    u = int(E[e, 5])
    ta = dt * E[e, 3]
    tb = dt * E[e, 4]
    rhs = E[e, 2]
    ci = 0.0
    cj = 0.0
    rtu = props[u, PR_RT]
    if i < nvol:
        rhs += ta * rate[i]
        ci = props[i, PR_GV] * rtu
    if j < nvol:
        rhs -= tb * rate[j]
        cj = props[j, PR_GV] * rtu
    return rhs, ta * ci, tb * cj, ta, tb


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def solve_one(e, E, props, rate, nvol, dt):
    """Linearly implicit flow of a single element e; result in E[e, 6].

    The flow is linearised about the current pressures, m = m0 + a dP_i - b dP_j,
    and solved together with the pressure changes of its end volumes over one
    step, dP_n = dt (rate_n +- c_n m); rate_n holds every other contribution
    (piston, wall heat, runner flows).  Where the flow is stiff it follows the
    demand of the rest of the network with no artificial pressure drop and no
    oscillation; where it is slow it is the explicit flow plus an O(dt)
    look-ahead.  Closed form: m (1 + dt (a c_i + b c_j)) = m0 + dt (a rate_i - b rate_j).
    """
    rhs, ai, bj, _, _ = _lin_terms(e, E, props, rate, nvol, dt)
    E[e, 6] = rhs / (1.0 + ai + bj)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def solve_two(e1, e2, E, props, rate, nvol, dt):
    """Linearly implicit flows of two elements in series, e1: i -> s and e2: s -> j (results in E[e, 6]).

    The shared volume s sees both flows: dP_s = dt (rate_s + c_s1 m1 - c_s2 m2),
    with c_s1, c_s2 its coefficients for the upstream gas of e1 and e2.  The two
    linearised flow laws are then a 2 x 2 system in (m1, m2),

        [1 + dt (a1 c_i + b1 c_s1)     -dt b1 c_s2           ] [m1]   [m01 + dt (a1 rate_i - b1 rate_s)]
        [-dt a2 c_s1                   1 + dt (a2 c_s2 + b2 c_j)] [m2] = [m02 + dt (a2 rate_s - b2 rate_j)]

    whose determinant is >= 1 (the cross terms cancel), solved by Cramer's
    rule.  The same linear system as a joint solve for the three pressure changes,
    eliminated in the flows instead.
    """
    s = int(E[e1, 1])
    b1, a1ci, b1cs1, _, tb1 = _lin_terms(e1, E, props, rate, nvol, dt)
    b2, a2cs2, b2cj, ta2, _ = _lin_terms(e2, E, props, rate, nvol, dt)
    gs = props[s, PR_GV]
    a = 1.0 + a1ci + b1cs1
    d = 1.0 + a2cs2 + b2cj
    bb = tb1 * gs * props[int(E[e2, 5]), PR_RT]     # dt b1 c_s2
    cc = ta2 * gs * props[int(E[e1, 5]), PR_RT]     # dt a2 c_s1
    # a d - bb cc expanded: the dt^2 b1 c_s1 a2 c_s2 terms cancel exactly, and
    # what remains is a sum of non-negative terms (no cancellation when stiff)
    x1 = a1ci
    y1 = b1cs1
    x2 = a2cs2
    y2 = b2cj
    inv = 1.0 / (1.0 + x1 + y1 + x2 + y2 + x1 * x2 + x1 * y2 + y1 * y2)
    E[e1, 6] = (d * b1 + bb * b2) * inv
    E[e2, 6] = (a * b2 + cc * b1) * inv
