"""Gas volumes of the network: state -> properties, and mass/enthalpy transfer between volumes."""

from numba import njit

from engine_model.thermo import cp_mass, h_mass, mixture_tcphr
from engine_model.cycle.layout import *  # noqa: F401,F403  (index constants)

# property columns of the scratch array ``props``
# PR_S = gamma R T / V is the pressure change per kg of the volume's own gas
# [Pa/kg]; PR_GV = gamma / V and PR_RT = R T split it, so that the pressure
# change of volume n per kg of gas from volume u is props[n, PR_GV] * props[u, PR_RT]
# (no division in the flow solves).
PR_P, PR_T, PR_R, PR_G, PR_H, PR_YA, PR_YM, PR_YP, PR_RHO, PR_S, PR_GV, PR_RT = range(12)
NPR = 12

# accumulator layout: global entries, then 6 per cylinder
A_AIR, A_HAIR, A_FUEL, A_HFUEL, A_OUT, A_HOUT, A_BURN, A_MIN, A_QPORT = range(9)
A_CYL0 = 9
AC_WORK, AC_Q, AC_KNOCK, AC_EXM, AC_EXMT = range(5)
AC_N = 6



@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def eval_props(vol, vcur, nvol, hcoeffs, rsp, cbuf, props):
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
        inv_m = 1.0 / m
        ya = ma * inv_m
        ym = mm * inv_m
        yp = mp * inv_m
        t, cp, h, r = mixture_tcphr(hcoeffs, rsp, ya, ym, yp, vol[k, V_U] * inv_m, vol[k, V_T])
        if not (t > 150.0 and t < 4400.0):
            return 100 + k
        vol[k, V_T] = t
        inv_v = 1.0 / vcur[k]
        rt = r * t
        g = cp / (cp - r)
        props[k, PR_P] = m * rt * inv_v
        props[k, PR_T] = t
        props[k, PR_R] = r
        props[k, PR_G] = g
        props[k, PR_H] = h
        props[k, PR_YA] = ya
        props[k, PR_YM] = ym
        props[k, PR_YP] = yp
        props[k, PR_RHO] = m * inv_v
        props[k, PR_S] = g * rt * inv_v
        props[k, PR_GV] = g * inv_v
        props[k, PR_RT] = rt
    return 0


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def transfer(i, j, mdot, nvol, props, dvol):
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


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def transfer_as(i, j, mdot, ya, ym, yp, h, dvol):
    """Move ``mdot`` [kg/s] from volume i to volume j with the given mass fractions and specific enthalpy [J/kg]."""
    fa = mdot * ya
    fm = mdot * ym
    fp = mdot * yp
    fh = mdot * h
    dvol[i, V_MA] -= fa
    dvol[i, V_MM] -= fm
    dvol[i, V_MP] -= fp
    dvol[i, V_U] -= fh
    dvol[j, V_MA] += fa
    dvol[j, V_MM] += fm
    dvol[j, V_MP] += fp
    dvol[j, V_U] += fh


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def iv_transfer(ip, k, m, far, fuel_c, evap, nvol, props, dvol, acc):
    """Intake-valve flow port ip -> cylinder k; forward flow carries the injected fuel with its air.

    The fuel enters the cylinder as vapour at the port temperature; the part ``evap`` [J per kg of fuel] of
    its latent heat that it took from the charge while evaporating is taken from the port's gas (charge
    cooling), the rest came from the walls.  The fuel's energy input is therefore m_f (h_vap - evap).
    """
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
        dvol[ip, V_U] -= mf * evap
        dvol[k, V_U] += m * props[ip, PR_H] + mf * hf
        acc[A_FUEL] += mf
        acc[A_HFUEL] += mf * (hf - evap)
    else:
        transfer(ip, k, m, nvol, props, dvol)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def set_ambient(props, amb, par, coeffs, rsp):
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
    props[amb, PR_GV] = 0.0
    props[amb, PR_RT] = rsp[SP_A] * t
