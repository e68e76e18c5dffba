"""Physical first guesses used by plans, screening and tables: burn, MBT spark, lambda, bench limits.

References
----------
.. [P] Mrda, Miljic, Kitanovic, Popovic, Tomic, "Model based approach in
   Yamaha R6 Formula Student engine control parameters optimisation",
   MVM2012-024 (Figure 1, Table 2, eqs 2-5, bench procedure).
.. [H] J.B. Heywood, Internal Combustion Engine Fundamentals, McGraw-Hill
   1988, sec. 9.3 (burn angles vs speed, load and residual gas).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from engine_model import wiebe

__all__ = ["MIN_BMEP_BAR", "CA50_TARGET_DEG_ATDC", "MBT_CA50_DEG_ATDC", "WIEBE_M_REF", "combustion_estimate",
           "spark_estimate", "lambda_target", "with_combustion"]

#: Lowest BMEP a manually controlled brake can hold as a steady point [bar]:
#: 1 bar is 4.8 N m on 599 cc; below it the brake's torque resolution and the
#: cycle-to-cycle torque scatter exceed the load, and torque barely responds to
#: spark, so no MBT can be found (the paper's Figure 1 'zone 2').
MIN_BMEP_BAR = 1.0


# Combustion prior (see combustion_estimate).
BDUR_REF_DEG = 24.0         # [P] BDUR10-90 at WOT 9000 rpm


SPEED_REF_RPM = 9000.0      # [P]


WIEBE_M_REF = 6.25          # [P] mid of m = 6.1-6.4


SPEED_EXPONENT = 1.0 / 3.0  # [H] burn angles ~ (mean piston speed)^(1/3), Hires et al. SAE 780232


LOAD_FACTOR = 0.3           # [A] +30 % burn angle at closed throttle (residual dilution), see Notes


BDUR_RANGE_DEG = (20.0, 50.0)  # [P] the paper's BDUR10-90 sweep range


CA50_TARGET_DEG_ATDC = 9.0  # [P] MBT criterion CA50 = 8-10 deg ATDC (Bargende 1995)


MBT_CA50_DEG_ATDC = 8.0     # [P] lower end: CA50 at or before this = at/after MBT


def combustion_estimate(speed_rpm, throttle_pct):
    """Prior Wiebe parameters (BDUR10-90, m) of an operating point.

    Parameters
    ----------
    speed_rpm : float or array_like
        Engine speed [rpm], > 0.
    throttle_pct : float or array_like
        Throttle opening [%], 0-100.  Broadcast against ``speed_rpm``.

    Returns
    -------
    bdur_10_90_deg : float or ndarray
        10-90 % burn duration [deg CA].
    wiebe_m : float or ndarray
        Wiebe shape factor [-] (the constant 6.25).

    Notes
    -----
    ``BDUR10-90 = 24 * (N / 9000)^(1/3) * (1 + 0.3 (1 - throttle/100)^3)``,
    clipped to 20-50 deg.

    * 24 deg at m = 6.25 is the paper's identification at WOT 9000 rpm
      (24-25 deg at m = 6.1-6.4) [P].
    * Turbulence intensity scales with mean piston speed, so the burn *time*
      falls roughly as 1/N and the burn *angle* changes only weakly; Hires et
      al. (SAE 780232, quoted in [H] sec. 9.3) correlate it with (mean piston
      speed)^(1/3).  With the CA50 = 9 deg rule this exponent reproduces the
      WOT spark advances of the paper's Table 2 (8000-11000 rpm) within 3.2
      deg.  Note the angle therefore *shortens* at low speed; the clip at 20
      deg (the bottom of the paper's sweep) keeps it plausible there.
    * At part load the residual-gas fraction rises and the laminar flame slows
      ([H] sec. 9.3); the cube keeps the effect at small throttle openings,
      where the restricted engine actually runs at low load.  The +30 % at a
      closed throttle is an engineering assumption of this project.
    * m is held at the paper's 6.25: the paper identifies it at one point only.
    """
    n = np.asarray(speed_rpm, dtype=float)
    t = np.asarray(throttle_pct, dtype=float)
    if np.any(~(n > 0)) or np.any(~((t >= 0) & (t <= 100))):
        raise ValueError("combustion_estimate: need speed_rpm > 0 and 0 <= throttle_pct <= 100; "
                         f"got speed {n.ravel()[:3]}..., throttle {t.ravel()[:3]}...")
    load = 1.0 + LOAD_FACTOR * (1.0 - t / 100.0) ** 3
    bdur = np.clip(BDUR_REF_DEG * (n / SPEED_REF_RPM) ** SPEED_EXPONENT * load, *BDUR_RANGE_DEG)
    m = np.full_like(bdur, WIEBE_M_REF)
    if bdur.ndim == 0:
        return float(bdur), float(m)
    return bdur, m


def spark_estimate(speed_rpm, throttle_pct):
    """Prior MBT spark advance [deg BTDC]: the SOC that puts CA50 at 9 deg ATDC.

    Parameters
    ----------
    speed_rpm : float or array_like
        Engine speed [rpm].
    throttle_pct : float or array_like
        Throttle opening [%].

    Returns
    -------
    float or ndarray
        Spark advance = start of combustion [deg BTDC] (the paper takes the
        spark timing as SOC [P]).

    Notes
    -----
    ``SOC = BDUR * (ln 2 / a)^(1/(m+1)) - 9`` (paper eq 5 inverted,
    :func:`engine_model.wiebe.soc_for_ca50`) with BDUR and m from
    :func:`combustion_estimate`; 9 deg ATDC is the middle of the MBT window
    8-10 deg ATDC (Bargende 1995, in [P]).  WOT 9000 rpm gives 49.7 deg
    against 50.0 deg measured (Table 2).
    """
    bdur_10_90, m = combustion_estimate(speed_rpm, throttle_pct)
    bdur = wiebe.bdur_10_90_to_bdur(bdur_10_90, m)
    return wiebe.soc_for_ca50(CA50_TARGET_DEG_ATDC, bdur, m)


def lambda_target(throttle_pct):
    """Target excess-air ratio [-]: 1.0 at part load, 0.9 near WOT.

    ``lambda = 1.0`` up to 60 % throttle, falling linearly to 0.9 at 90 % and
    above.  0.9 is the paper's WOT setting (Table 2, power enrichment); 1.0 is
    the usual stoichiometric part-load target.  The ramp (an assumption of this
    project) keeps the target continuous for space-filling designs.

    Parameters
    ----------
    throttle_pct : float or array_like
        Throttle opening [%].

    Returns
    -------
    float or ndarray
        Excess-air ratio [-].
    """
    lam = np.interp(np.asarray(throttle_pct, dtype=float), [0.0, 60.0, 90.0, 100.0], [1.0, 1.0, 0.9, 0.9])
    return float(lam) if lam.ndim == 0 else lam


def with_combustion(plan: pd.DataFrame, bdur=None, m=None) -> pd.DataFrame:
    """Add the Wiebe columns ``bdur_10_90_deg, wiebe_m`` so a plan can be simulated.

    Parameters
    ----------
    plan : DataFrame
        Any plan (needs ``speed_rpm, throttle_pct``).
    bdur : float, optional
        Constant BDUR10-90 [deg]; None keeps an existing column, else uses
        :func:`combustion_estimate`.
    m : float, optional
        Constant Wiebe shape factor [-]; None as for ``bdur``.

    Returns
    -------
    DataFrame
        A copy with both columns.
    """
    out = plan.copy()
    est_b, est_m = combustion_estimate(out["speed_rpm"].to_numpy(float), out["throttle_pct"].to_numpy(float))
    for col, val, est in (("bdur_10_90_deg", bdur, est_b), ("wiebe_m", m, est_m)):
        if val is not None:
            out[col] = float(val)
        elif col not in out.columns:
            out[col] = est
    return out
