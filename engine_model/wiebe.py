"""Wiebe mass-fraction-burned law and the burn-angle conversions built on it.

The cumulative burned fraction follows the Wiebe (1970) exponential law
(Heywood 1988, sec. 9.2.1; reference paper MVM2012-024, eqs 2-5)::

    x_b(theta) = 1 - exp(-a * ((theta - theta_soc) / BDUR) ** (m + 1))

for ``theta >= theta_soc`` and zero before it. ``BDUR`` is the *total*
duration, i.e. the angle over which ``x_b`` climbs from 0 to the completeness
level ``x_eoc`` that fixes ``a = -ln(1 - x_eoc)`` (eq 3).

Sign conventions: crank angles are in degrees with 0 at firing TDC and
positive after it (ATDC). Start of combustion is passed as an ECU shows a
spark advance, i.e. positive degrees BTDC, so ``theta_soc = -soc_deg_btdc``.
Every function broadcasts over numpy arrays and returns a Python float when
all inputs are scalars.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = [
    "WIEBE_A_999", "completeness_constant", "burn_fraction", "burn_rate",
    "angle_at_fraction", "bdur_to_bdur_10_90", "bdur_10_90_to_bdur",
    "ca50_deg_atdc", "soc_for_ca50", "burn_angles",
]

#: Wiebe efficiency constant for 99.9 % completeness, -ln(0.001) ~ 6.9078 [-].
WIEBE_A_999: float = -math.log(0.001)


def _out(v):
    """Return a Python float for 0-d results, otherwise the ndarray."""
    v = np.asarray(v, dtype=float)
    return float(v) if v.ndim == 0 else v


def _check(name, value, low=None, high=None, finite=True):
    """Float array of ``value``; ValueError naming ``name`` if NaN or outside (low, high)."""
    arr = np.asarray(value, dtype=float)
    bad = np.isnan(arr)
    if finite:
        bad |= ~np.isfinite(arr)
    if low is not None:
        bad |= arr <= low
    if high is not None:
        bad |= arr >= high
    if np.any(bad):
        first = float(arr[bad].flat[0])
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        raise ValueError(f"{name} must lie in ({lo}, {hi}) and be finite; got {first!r}")
    return arr


def _shape(m, a, bdur_deg=None):
    """Validate the Wiebe shape arguments (and optionally the total duration)."""
    m = _check("m", m, low=-1.0)
    a = _check("a", a, low=0.0)
    if bdur_deg is None:
        return m, a
    return m, a, _check("bdur_deg", bdur_deg, low=0.0)


def _unit_angle(x, m, a):
    """Normalised angle (theta - theta_soc)/BDUR at which x_b = x [-] (inverse of eq 2)."""
    return (-np.log1p(-x) / a) ** (1.0 / (m + 1.0))


def completeness_constant(x_end: float = 0.999) -> float:
    """Wiebe constant ``a = -ln(1 - x_end)`` (paper eq 3).

    ``x_end`` [-] in (0, 1) is the burned fraction taken as end of combustion;
    returns ``a`` [-] (6.9078 for the default 99.9 %).
    """
    x = _check("x_end", x_end, low=0.0, high=1.0)
    return _out(-np.log1p(-x))


def burn_fraction(theta_deg_atdc, soc_deg_btdc, bdur_deg, m, a=WIEBE_A_999):
    """Cumulative mass fraction burned ``x_b(theta)`` (Wiebe 1970; paper eq 2).

    Parameters
    ----------
    theta_deg_atdc : float or array_like
        Crank angle [deg ATDC].
    soc_deg_btdc : float or array_like
        Start of combustion [deg BTDC]; positive means before TDC.
    bdur_deg : float or array_like
        Total (0 to x_eoc) burn duration [deg], > 0.
    m : float or array_like
        Wiebe shape (form) factor [-], > -1.
    a : float or array_like
        Efficiency constant [-], > 0.

    Returns
    -------
    float or ndarray
        Burned fraction [-]; 0 before SOC, rising monotonically towards 1.
    """
    m, a, bdur = _shape(m, a, bdur_deg)
    theta = _check("theta_deg_atdc", theta_deg_atdc, finite=False)
    soc = _check("soc_deg_btdc", soc_deg_btdc)
    tau = np.maximum((theta + soc) / bdur, 0.0)
    return _out(-np.expm1(-a * tau ** (m + 1.0)))


def burn_rate(theta_deg_atdc, soc_deg_btdc, bdur_deg, m, a=WIEBE_A_999):
    """Burn rate ``dx_b/dtheta`` [1/deg], the analytic derivative of eq 2.

    ``dx_b/dtheta = a (m+1)/BDUR * tau**m * exp(-a tau**(m+1))`` with
    ``tau = (theta - theta_soc)/BDUR``; zero before SOC. Parameters as in
    :func:`burn_fraction`. For -1 < m < 0 the rate is singular at SOC itself.

    Returns
    -------
    float or ndarray
        Burn rate [1/deg].
    """
    m, a, bdur = _shape(m, a, bdur_deg)
    theta = _check("theta_deg_atdc", theta_deg_atdc, finite=False)
    soc = _check("soc_deg_btdc", soc_deg_btdc)
    tau = (theta + soc) / bdur
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.maximum(tau, 0.0)
        rate = a * (m + 1.0) / bdur * t ** m * np.exp(-a * t ** (m + 1.0))
    return _out(np.where((tau > 0.0) & (tau < np.inf), rate, 0.0))  # 0 at theta=+inf


def angle_at_fraction(x, soc_deg_btdc, bdur_deg, m, a=WIEBE_A_999):
    """Crank angle at which a burned fraction ``x`` is reached (inverse of eq 2).

    ``CA_x = -SOC + BDUR * (-ln(1 - x)/a)**(1/(m+1))``.

    Parameters
    ----------
    x : float or array_like
        Burned fraction [-], in (0, 1) (0.5 gives CA50).
    soc_deg_btdc, bdur_deg, m, a
        As in :func:`burn_fraction`.

    Returns
    -------
    float or ndarray
        Angle ``CA_x`` [deg ATDC].
    """
    m, a, bdur = _shape(m, a, bdur_deg)
    x = _check("x", x, low=0.0, high=1.0)
    soc = _check("soc_deg_btdc", soc_deg_btdc)
    return _out(-soc + bdur * _unit_angle(x, m, a))


def _span_10_90(m, a):
    """BDUR10-90 / BDUR ratio [-] (paper eq 4, positive-log form)."""
    return _unit_angle(0.9, m, a) - _unit_angle(0.1, m, a)


def bdur_to_bdur_10_90(bdur_deg, m, a=WIEBE_A_999):
    """10-90 % burn duration from total duration (paper eq 4).

    ``BDUR10-90 = BDUR * ((-ln 0.1/a)**(1/(m+1)) - (-ln 0.9/a)**(1/(m+1)))``.

    ``bdur_deg`` [deg] > 0, ``m`` [-] > -1, ``a`` [-] > 0; returns BDUR10-90 [deg].
    """
    m, a, bdur = _shape(m, a, bdur_deg)
    return _out(bdur * _span_10_90(m, a))


def bdur_10_90_to_bdur(bdur_10_90_deg, m, a=WIEBE_A_999):
    """Total burn duration from the 10-90 % duration (eq 4 solved for BDUR).

    ``bdur_10_90_deg`` [deg] > 0; ``m``, ``a`` as in :func:`bdur_to_bdur_10_90`.
    Returns the total (0 to x_eoc) burn duration [deg].
    """
    m, a = _shape(m, a)
    d = _check("bdur_10_90_deg", bdur_10_90_deg, low=0.0)
    return _out(d / _span_10_90(m, a))


def ca50_deg_atdc(soc_deg_btdc, bdur_deg, m, a=WIEBE_A_999):
    """50 % burn angle ``CA50 = -SOC + BDUR*(ln 2/a)**(1/(m+1))`` [deg ATDC] (eq 5).

    Parameters as in :func:`burn_fraction`.
    """
    return angle_at_fraction(0.5, soc_deg_btdc, bdur_deg, m, a)


def soc_for_ca50(ca50_deg_atdc, bdur_deg, m, a=WIEBE_A_999):
    """Start of combustion [deg BTDC] that places CA50 at ``ca50_deg_atdc`` (eq 5 inverted).

    ``ca50_deg_atdc`` is the target 50 % angle [deg ATDC]; ``bdur_deg``, ``m``,
    ``a`` as in :func:`burn_fraction`. Returns SOC [deg BTDC], positive before TDC.
    """
    m, a, bdur = _shape(m, a, bdur_deg)
    ca50 = _check("ca50_deg_atdc", ca50_deg_atdc)
    return _out(bdur * _unit_angle(0.5, m, a) - ca50)


def burn_angles(soc_deg_btdc, bdur_10_90_deg, m, a=WIEBE_A_999) -> dict:
    """Total duration and CA10/CA50/CA90 from the (SOC, BDUR10-90, m) set.

    This is the input set the reference paper gives its 1D model, with the
    measured spark advance taken as SOC. Outputs share the broadcast shape.

    ``soc_deg_btdc`` [deg BTDC], ``bdur_10_90_deg`` [deg] > 0, ``m`` [-], ``a`` [-].
    Returns a dict with ``bdur_deg`` [deg] and ``ca10_deg_atdc``,
    ``ca50_deg_atdc``, ``ca90_deg_atdc`` [deg ATDC].
    """
    bdur = bdur_10_90_to_bdur(bdur_10_90_deg, m, a)
    cas = [angle_at_fraction(p / 100.0, soc_deg_btdc, bdur, m, a) for p in (10, 50, 90)]
    vals = np.broadcast_arrays(bdur, *cas)  # give every entry the common shape
    keys = ("bdur_deg", "ca10_deg_atdc", "ca50_deg_atdc", "ca90_deg_atdc")
    return {k: _out(np.array(v)) for k, v in zip(keys, vals)}
