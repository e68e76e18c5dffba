"""Chen-Flynn friction model (Chen & Flynn 1965, SAE 650733)."""

from numba import njit

from engine_model.cycle.layout import FASTMATH


@njit(cache=True, fastmath=FASTMATH)
def chen_flynn_fmep(a_pa, b, c_pa_s_per_m, d_pa_s2_per_m2, pmax_pa, mean_piston_speed_m_s):
    """Friction mean effective pressure [Pa] = A + B*p_max + C*Sp + D*Sp^2.

    Parameters
    ----------
    a_pa : float
        Constant term [Pa].
    b : float
        Peak-pressure coefficient [-].
    c_pa_s_per_m, d_pa_s2_per_m2 : float
        Linear and quadratic piston-speed coefficients [Pa s/m], [Pa s^2/m^2].
    pmax_pa : float
        Peak cylinder pressure [Pa].
    mean_piston_speed_m_s : float
        Mean piston speed [m/s].
    """
    sp = mean_piston_speed_m_s
    return a_pa + b * pmax_pa + c_pa_s_per_m * sp + d_pa_s2_per_m2 * sp * sp
