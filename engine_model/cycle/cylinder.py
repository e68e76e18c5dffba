"""In-cylinder sub-models: Woschni heat transfer, the end-gas temperature and the knock (Livengood-Wu) rate."""

import math

from numba import njit

from engine_model.cycle.layout import FASTMATH

P_STD_PA = 101325.0  # 1 atm, the pressure unit of the Douaud-Eyzat correlation


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def woschni_velocity(c1, c2, mean_piston_speed, vd, t_ref, p_ref, v_ref, p, p_motored):
    """Woschni characteristic gas velocity [m/s].

    w = C1*Sp + C2 * Vd*T_r/(p_r*V_r) * (p - p_mot), reference state at IVC
    (Woschni 1967, SAE 670931; Heywood 1988 eq. 12.19).  The combustion term is
    clipped at zero so w never falls below the motored value.
    """
    w = c1 * mean_piston_speed
    if c2 > 0.0:
        dp = p - p_motored
        if dp > 0.0:
            w += c2 * vd * t_ref / (p_ref * v_ref) * dp
    return w


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def woschni_coefficient(coeff_b, p, t_gas, w):
    """Woschni heat-transfer coefficient [W/(m^2 K)].

    h = coeff_b * p[kPa]^0.8 * T^-0.55 * w^0.8, with coeff_b = 3.26*B^-0.2
    (times any multiplier) precomputed by the caller.
    """
    return coeff_b * math.exp(0.8 * math.log(p * 1e-3 * w) - 0.55 * math.log(t_gas))


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def wall_heat_rate(h, t_gas, a_head, t_head, a_piston, t_piston, a_liner, t_liner):
    """Heat flow from gas to walls [W] = h * sum(A_i (T - T_wall,i))."""
    return h * (a_head * (t_gas - t_head) + a_piston * (t_gas - t_piston) + a_liner * (t_gas - t_liner))


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def end_gas_temperature(c, s_target, t_guess):
    """Unburned end-gas temperature [K] on a variable-cp isentrope.

    Solves s0(T) = ``s_target`` for T by Newton's method from ``t_guess``, where s0 is the
    standard-state entropy of the end-gas mixture (a (2, 7) block of mass NASA coefficients
    ``c``, see :func:`engine_model.thermo.s0_mass`) and ``s_target`` = s0(T_ref) + R ln(p/p_ref)
    carries the pressure: ds = cp dT/T - R dp/p = 0 integrated exactly, so the result does not
    depend on the crank step.
    """
    t = t_guess if t_guess > 200.0 else 700.0
    for _ in range(30):
        k = 0 if t < 1000.0 else 1
        s0 = c[k, 0] * math.log(t) + t * (c[k, 1] + t * (c[k, 2] / 2.0 + t * (c[k, 3] / 3.0 + t * c[k, 4] / 4.0))) \
            + c[k, 6]
        cp = c[k, 0] + t * (c[k, 1] + t * (c[k, 2] + t * (c[k, 3] + t * c[k, 4])))
        t_new = t - (s0 - s_target) * t / cp
        if t_new < 150.0:
            t_new = 150.0
        elif t_new > 3000.0:
            t_new = 3000.0
        if abs(t_new - t) <= 1e-9 * t_new:
            return t_new
        t = t_new
    return t


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def ignition_delay(p, t_unburned, delay_coeff_s, pressure_exponent, activation_temp_k):
    """Douaud-Eyzat ignition delay [s] = A' * (p/1 atm)^-n * exp(B/T_u).

    ``delay_coeff_s`` is A' = A*(ON/100)^3.402 (Douaud and Eyzat 1978, SAE 780080), times
    the delay multiplier calibrated on bench data.  The dilution factor of the end gas is
    applied by the caller (:func:`dilution_factor`).
    """
    return delay_coeff_s * math.exp(-pressure_exponent * math.log(p / P_STD_PA) + activation_temp_k / t_unburned)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def dilution_factor(burned_fraction, exponent):
    """(1 - x_b)^d: the factor on the autoignition rate 1/tau for burned gas (residual, EGR) in the end gas.

    Burned gas takes the place of fuel and oxygen at the same pressure and temperature; with the
    chain-branching rate first order in their concentration the delay grows as 1/(1 - x_b)
    (d = 1).  Sources of the form and the exponent: ``KnockSpec.dilution_exponent``.
    """
    x = burned_fraction if burned_fraction < 0.95 else 0.95
    if x <= 0.0:
        return 1.0
    return math.exp(exponent * math.log(1.0 - x))
