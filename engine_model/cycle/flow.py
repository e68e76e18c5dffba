"""Compressible flow through orifices, the restrictor venturi and valve curtains.

References
----------
Heywood, J.B., Internal Combustion Engine Fundamentals, 1988, app. C
(isentropic flow through a flow restriction, eqs C.8-C.9).
Haaland, S.E., "Simple and explicit formulas for the friction factor in
turbulent pipe flow", J. Fluids Eng. 105 (1983) 89-90 (pipe friction).
White, F.M., Viscous Fluid Flow, 3rd ed., 2006, eq. 1-36 (Sutherland's law).
"""

import math

import numpy as np
from numba import njit

from engine_model.cycle.layout import FASTMATH


# Every gas here has gamma >= 1.05, whose critical pressure ratio is <= 0.595:
# above this ratio the flow is subsonic without evaluating the critical ratio.
SUBSONIC_ABOVE = 0.6


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def critical_pressure_ratio(gamma):
    """Throat-to-stagnation pressure ratio at sonic flow, (2/(g+1))^(g/(g-1)) [-]."""
    return (2.0 / (gamma + 1.0)) ** (gamma / (gamma - 1.0))


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def orifice_flow(cda, p_up, t_up, r_up, gamma, p_throat):
    """Isentropic mass flow through an orifice, choked below the critical ratio.

    Parameters
    ----------
    cda : float
        Effective area Cd*A [m^2].
    p_up, t_up : float
        Upstream stagnation pressure [Pa] and temperature [K].
    r_up, gamma : float
        Upstream specific gas constant [J/(kg K)] and ratio of specific heats [-].
    p_throat : float
        Static pressure at the throat (= downstream pressure for a plain orifice) [Pa].

    Returns
    -------
    float
        Mass flow [kg/s], >= 0 (flow from up to down; caller handles reverse flow).

    Notes
    -----
    mdot = Cd A p0/sqrt(R T0) * sqrt(2g/(g-1) * (pr^(2/g) - pr^((g+1)/g))), with
    pr = max(p_throat/p0, pr_crit) so that choking emerges at high flow.
    """
    if cda <= 0.0 or p_up <= 0.0:
        return 0.0
    pr = p_throat / p_up
    if pr >= 1.0:
        return 0.0
    prc = critical_pressure_ratio(gamma)
    if pr < prc:
        pr = prc
    t = pr ** (1.0 / gamma)
    psi2 = 2.0 * gamma / (gamma - 1.0) * (t * t - pr * t)
    if psi2 <= 0.0:
        return 0.0
    return cda * p_up / math.sqrt(r_up * t_up) * math.sqrt(psi2)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def restrictor_throat_pressure(p_up, p_down, recovery):
    """Throat static pressure of a venturi whose diffuser recovers a fraction of the throat dynamic head.

    p_down = p_t + recovery * (p_up - p_t)  ->  p_t = (p_down - recovery*p_up) / (1 - recovery)  [Pa]
    """
    pt = (p_down - recovery * p_up) / (1.0 - recovery)
    return pt if pt > 0.0 else 0.0


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def restrictor_flow(cda, recovery, p_up, t_up, r_up, gamma, p_down):
    """Forward mass flow through the restrictor venturi [kg/s] (0 if p_down >= p_up); recovery 0 is a plain orifice.

    The throat pressure follows from the downstream (plenum) pressure and the
    diffuser recovery; the flow chokes when the throat reaches the critical
    ratio, i.e. when p_down/p_up <= recovery + (1 - recovery)*pr_crit.
    """
    if p_down >= p_up:
        return 0.0
    return orifice_flow(cda, p_up, t_up, r_up, gamma, restrictor_throat_pressure(p_up, p_down, recovery))


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def steady_plenum_pressure(thr_cda, res_cda, res_rec, p_amb, t_amb, r, gamma, ve, vd_tot, speed_rpm):
    """Plenum pressure [Pa] at which throttle + restrictor in series pass what the cylinders draw.

    Steady, isothermal estimate used only to start the cycle iteration close to
    the answer (bisection on the plenum pressure; inside it, bisection on the
    throttle-body pressure at which throttle and restrictor pass the same flow).

    Parameters
    ----------
    thr_cda, res_cda : float
        Effective areas of throttle and restrictor throat [m^2].
    res_rec : float
        Diffuser pressure recovery of the restrictor [-].
    p_amb, t_amb : float
        Ambient pressure [Pa] and temperature [K].
    r, gamma : float
        Gas constant [J/(kg K)] and isentropic exponent [-] of the air.
    ve : float
        Volumetric efficiency assumed for the cylinders' draw [-], at plenum density.
    vd_tot : float
        Total displacement [m^3].
    speed_rpm : float
        Engine speed [rpm].
    """
    lo, hi = 0.02 * p_amb, p_amb * 0.9999
    for _ in range(60):
        p_pl = 0.5 * (lo + hi)
        a, b = p_pl, p_amb
        for _ in range(50):
            p_tb = 0.5 * (a + b)
            m1 = orifice_flow(thr_cda, p_amb, t_amb, r, gamma, p_tb)
            m2 = restrictor_flow(res_cda, res_rec, p_tb, t_amb, r, gamma, p_pl)
            if m1 > m2:
                a = p_tb
            else:
                b = p_tb
        supply = orifice_flow(thr_cda, p_amb, t_amb, r, gamma, 0.5 * (a + b))
        draw = ve * p_pl / (r * t_amb) * vd_tot * speed_rpm / 120.0
        if supply - draw > 0.0:
            lo = p_pl
        else:
            hi = p_pl
    return 0.5 * (lo + hi)


# ----------------------------------------------------------------- Python-side geometry helpers

def throttle_open_area(throttle_pct, bore_m, shaft_m, closed_deg, leak_area_m2=0.0):
    """Geometric open area of a butterfly throttle [m^2].

    Parameters
    ----------
    throttle_pct : float or array
        Pedal position 0..100 [%], mapped linearly to plate angle closed_deg..90 deg.
    bore_m, shaft_m : float
        Throttle bore and spindle diameter [m].
    closed_deg : float
        Plate angle from the bore normal when closed [deg].
    leak_area_m2 : float
        Leakage area past the closed plate [m^2], added.

    Notes
    -----
    Area of an inclined plate with a spindle (Harrington and Bolt, as given in
    Heywood 1988 sec. 7.3): with a = d/D and psi the plate angle,
    A/(pi D^2/4) = 1 - cos(psi)/cos(psi0) + 2/pi [ a/cos(psi) sqrt(cos^2 psi - a^2 cos^2 psi0)
    + cos(psi)/cos(psi0) asin(a cos(psi0)/cos(psi)) - a sqrt(1-a^2) - asin(a) ],
    valid until the plate is edge-on to the spindle (cos psi = a cos psi0); beyond,
    the area stays at that value (bore minus spindle blockage).
    """
    pct = np.clip(np.asarray(throttle_pct, dtype=float), 0.0, 100.0)
    psi0 = np.radians(closed_deg)
    psi = psi0 + (np.pi / 2 - psi0) * pct / 100.0
    a = shaft_m / bore_m
    cos_edge = a * np.cos(psi0)
    c = np.maximum(np.cos(psi), cos_edge)
    frac = (1.0 - c / np.cos(psi0)
            + 2.0 / np.pi * (a / c * np.sqrt(np.maximum(c * c - cos_edge**2, 0.0))
                             + c / np.cos(psi0) * np.arcsin(np.minimum(cos_edge / c, 1.0))
                             - a * np.sqrt(1.0 - a * a) - np.arcsin(a)))
    return np.pi / 4 * bore_m**2 * np.maximum(frac, 0.0) + leak_area_m2


def _flank(x, s):
    """Quintic rise from 0 to 1 over x in [0, 1] with slope ``s`` and zero curvature at x = 0 (where the ramp
    ends) and zero slope and curvature at x = 1 (the nose): s x + (10 - 6 s) x^3 + (8 s - 15) x^4 + (6 - 3 s) x^5.
    With s = 0 it is the 3-4-5 polynomial; monotonic for 0 <= s <= 1."""
    x = np.clip(x, 0.0, 1.0)
    return x * (s + x * x * ((10.0 - 6.0 * s) + x * ((8.0 * s - 15.0) + x * (6.0 - 3.0 * s))))


def _seat_profile(theta, seat_duration, max_lift, ramp_height, ramp_deg):
    """Lift [m] at ``theta`` crank degrees after the valve leaves its seat, for a seat-to-seat event of
    ``seat_duration`` degrees (0 outside): a constant-velocity ramp to ``ramp_height`` over ``ramp_deg``,
    then a quintic flank (:func:`_flank`) that starts with the ramp's velocity and no acceleration and reaches
    ``max_lift`` with zero velocity and acceleration at the middle of the event; mirrored for the closing."""
    t = np.asarray(theta, dtype=float)
    half = 0.5 * seat_duration
    d = np.where(t <= half, t, seat_duration - t)                    # distance from the nearer seat event
    flank = max(half - ramp_deg, 1e-9)
    rise = max(max_lift - ramp_height, 1e-12)
    if ramp_deg > 0.0:
        ramp = ramp_height * d / ramp_deg
        slope = min(ramp_height / ramp_deg * flank / rise, 1.0)      # ramp velocity in flank units
    else:
        ramp = np.full_like(d, ramp_height)
        slope = 0.0
    lift = np.where(d < ramp_deg, ramp, ramp_height + rise * _flank((d - ramp_deg) / flank, slope))
    return np.where((t >= 0.0) & (t <= seat_duration), np.maximum(lift, 0.0), 0.0)


def seat_events(valves) -> tuple[float, float]:
    """(seat opening angle [cycle deg], seat-to-seat duration [deg]) of a valve set.

    ``valves.open_deg`` and ``close_deg`` are where the lift is ``timing_lift_m``; with a timing lift above
    the ramp the seat events lie ``delta`` degrees outside them, found so that the profile of the longer
    seat-to-seat event reaches the timing lift exactly ``delta`` after the seat.
    """
    dur, h = valves.duration_deg, valves.timing_lift_m
    if h <= 0.0:
        return valves.open_deg, dur
    lo, hi = 0.0, 0.5 * dur
    for _ in range(60):   # bisection: the lift at delta grows with delta
        mid = 0.5 * (lo + hi)
        lift = float(_seat_profile(mid, dur + 2.0 * mid, valves.max_lift_m, valves.ramp_height_m,
                                   valves.ramp_duration_deg))
        lo, hi = (mid, hi) if lift < h else (lo, mid)
    delta = 0.5 * (lo + hi)
    return (valves.open_deg - delta) % 720.0, dur + 2.0 * delta


def valve_lift(theta_deg, valves):
    """Valve lift [m] at cycle angles ``theta_deg`` [deg] of a :class:`~engine_model.spec.ValveSet`.

    Notes
    -----
    Seat to seat, the lift rises on a constant-velocity ramp of ``ramp_height_m`` over
    ``ramp_duration_deg`` (the cam's clearance ramp, the part after the clearance is taken up), then on a
    quintic polynomial flank to ``max_lift_m`` at the middle of the event, and back the same way.  The flank
    continues the ramp's velocity with zero acceleration and arrives at the nose with zero velocity and
    acceleration (the 3-4-5 polynomial of cam design with a starting slope; polynomial cam functions as in
    Norton, *Cam Design and Manufacturing Handbook*, 2nd ed. 2009), so the lift has no velocity jump except
    the ramp's own at the seat.  The timing events are where the lift
    equals ``timing_lift_m`` (:func:`seat_events`).  Against a half-sine over the same events the flanks
    are steeper near the nose and lower near the seats: at gas-exchange TDC the R6's intake lift is ~0.9 mm
    instead of ~3.8 mm.
    """
    open_deg, seat_dur = seat_events(valves)
    t = np.mod(np.asarray(theta_deg, dtype=float) - open_deg, 720.0)
    return _seat_profile(t, seat_dur, valves.max_lift_m, valves.ramp_height_m, valves.ramp_duration_deg)


def valve_effective_area(theta_deg, valves):
    """Effective flow area Cd(L/D) * pi*D*L * n_valves [m^2] of one cylinder's valve set."""
    lift = valve_lift(theta_deg, valves)
    cd = np.interp(lift / valves.diameter_m, valves.cd_ld, valves.cd)
    return valves.n_valves * cd * np.pi * valves.diameter_m * lift


@njit(cache=True, fastmath=FASTMATH)
def gas_viscosity(t):
    """Dynamic viscosity [Pa s] of air at temperature ``t`` [K], Sutherland's law (White eq. 1-36).

    Used for burned gas too: at equal temperature its viscosity is within ~10 %
    of air's, which moves the friction factor by ~2 % (f ~ Re^-0.2).
    """
    return 1.716e-5 * (273.15 + 110.4) / 273.15**1.5 * t * math.sqrt(t) / (t + 110.4)


@njit(cache=True, fastmath=FASTMATH)
def darcy_friction_factor(re, rel_roughness):
    """Darcy friction factor [-] of fully developed pipe flow.

    Turbulent: Haaland's explicit form of the Colebrook equation,
    1/sqrt(f) = -1.8 log10[(eps/D / 3.7)^1.11 + 6.9/Re] (within 1.5 % of
    Colebrook for 4e3 < Re < 1e8); laminar 64/Re where that is larger, which
    joins the two branches continuously near Re ~ 1.3e3.

    Parameters
    ----------
    re : float
        Reynolds number rho*u*D/mu [-].
    rel_roughness : float
        Wall roughness over diameter eps/D [-].
    """
    re = max(re, 1.0)
    x = -1.8 * math.log10((rel_roughness / 3.7) ** 1.11 + 6.9 / re)
    return max(64.0 / re, 1.0 / (x * x))


def pipe_loss_factor(mdot, t, area, dia, length, k_minor, rel_roughness):
    """Total-pressure loss factor of a pipe segment in dynamic heads [-]: k_minor + f L/D.

    The steady-flow pressure drop is this factor times m|m| / (2 rho A^2).

    Parameters
    ----------
    mdot : float
        Mass flow [kg/s] (either sign).
    t : float
        Gas temperature [K] (for the viscosity).
    area, dia, length : float
        Cross-section [m^2], diameter [m] and length [m] of the segment.
    k_minor : float
        Minor (local) losses of the segment: entry, bends, exit [-].
    rel_roughness : float
        Wall roughness over diameter eps/D [-].
    """
    re = abs(mdot) * dia / (area * gas_viscosity(t))
    return k_minor + darcy_friction_factor(re, rel_roughness) * length / dia


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def orifice_flow_lin(cda, p_up, t_up, r_up, gamma, p_throat, eps):
    """Orifice flow and its partial derivatives: (mdot, dmdot/dp_up, dmdot/dp_throat).

    Same law as :func:`orifice_flow`, except that for 1 - p_throat/p_up < eps the
    flow is continued linearly in (p_up - p_throat) from its value at 1 - eps, so
    the conductance stays finite at equal pressures (the square-root law has an
    infinite slope there).  For p_throat >= p_up the flow is 0 and the derivatives
    are those of the linear branch (the caller's signed law is linear through 0).
    """
    if cda <= 0.0 or p_up <= 0.0:
        return 0.0, 0.0, 0.0
    k = cda / math.sqrt(r_up * t_up)
    pr = p_throat / p_up
    xl = 1.0 - eps
    if pr > xl:
        tl = xl ** (1.0 / gamma)
        psil = math.sqrt(2.0 * gamma / (gamma - 1.0) * (tl * tl - xl * tl))
        g = k * psil / eps                     # d mdot / d(p_up - p_throat)
        if pr >= 1.0:
            return 0.0, g, -g
        return g * (p_up - p_throat), g, -g
    if pr <= SUBSONIC_ABOVE:
        # choked flow needs one power: with c = (2/(g+1))^(1/(g-1)), the critical
        # ratio is 2c/(g+1) and psi* = c*sqrt(2g/(g+1)) (same law, fewer pow calls)
        c = (2.0 / (gamma + 1.0)) ** (1.0 / (gamma - 1.0))
        prc = 2.0 * c / (gamma + 1.0)
        if pr <= prc:
            psi = c * math.sqrt(2.0 * gamma / (gamma + 1.0))
            return k * p_up * psi, k * psi, 0.0
    t = pr ** (1.0 / gamma)
    psi = math.sqrt(2.0 * gamma / (gamma - 1.0) * (t * t - pr * t))
    dpsi = (2.0 * t * t / pr - (gamma + 1.0) * t) / ((gamma - 1.0) * psi)
    return k * p_up * psi, k * (psi - pr * dpsi), k * dpsi
