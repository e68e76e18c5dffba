"""In-cylinder sub-models: Woschni heat transfer and the knock (Livengood-Wu) rate."""

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
def end_gas_temperature(p, p_ref, t_ref, exponent):
    """Unburned end-gas temperature [K], isentropic from the reference state: T_r*(p/p_r)^((g-1)/g)."""
    return t_ref * math.exp(exponent * math.log(p / p_ref))


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def ignition_delay(p, t_unburned, delay_coeff_s, pressure_exponent, activation_temp_k):
    """Douaud-Eyzat ignition delay [s] = A' * (p/1 atm)^-n * exp(B/T_u).

    ``delay_coeff_s`` is A' = A*(ON/100)^3.402 (Douaud and Eyzat 1978, SAE 780080).
    """
    return delay_coeff_s * math.exp(-pressure_exponent * math.log(p / P_STD_PA) + activation_temp_k / t_unburned)
