"""A second knock parameter: the delay multiplier's dependence on engine speed.

:func:`engine_model.knock.calibrate_knock` fits one multiplier m of the Douaud-Eyzat delay.  A real end gas
need not follow one Arrhenius line: where the engine's delay has another temperature or pressure dependence
(two-stage ignition, heat loss), the multiplier that puts the model's border on the engine's drifts across
the map, and with it the fitted one between the sweeps that bracket an onset.  Here

    ln m(n) = a + b ln(n / n_ref)

with the same probit link and priors as the one-parameter fit (``a`` as ln m there; ln sigma as there) and
``b ~ N(0, SLOPE_PRIOR_SD)``.  Where the evidence has no onset at more than one speed, ``b`` stays at its prior
and the fit is the one-parameter fit with a wider spread away from ``n_ref``; the report states the
posterior of ``b`` so a user sees whether the data moved it.

Status: evaluated on the virtual knock bench (:mod:`engine_model.knock.recovery`, field
``within_tol_pct_speed_term``); the spark tables still use the one-parameter multiplier.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.special import log_ndtr

from engine_model.knock.calibrate import PRIOR_SIGMA_LN, SCATTER_PRIOR

__all__ = ["SLOPE_PRIOR_SD", "REFERENCE_SPEED_RPM", "KnockSpeedCalibration", "calibrate_knock_speed"]

#: Prior 1-sigma of b = d ln m / d ln n [-]: [A] a factor 1.65 on the multiplier over a speed ratio of e
#: (e.g. 4000 -> 11000 rpm), an assumption of this project, set before any trial.
SLOPE_PRIOR_SD = 0.5
#: Speed at which ``a`` is the multiplier's log [rpm]: mid-range of a 3000-13000 rpm engine.
REFERENCE_SPEED_RPM = 6000.0
_A_GRID = np.linspace(-1.5, 1.0, 251)
_B_GRID = np.linspace(-1.5, 1.5, 121)
_LNS_GRID = np.linspace(math.log(0.01), math.log(1.0), 31)


@dataclass(frozen=True)
class KnockSpeedCalibration:
    """Grid posterior of (a, b) of ``ln m = a + b ln(n / reference_speed_rpm)`` (scatter marginalised)."""

    posterior_ab: np.ndarray        # (len(_A_GRID), len(_B_GRID)), sums to 1
    reference_speed_rpm: float
    n_clean: int
    n_knock: int

    def _quantile(self, values: np.ndarray, u: float) -> float:
        w = self.posterior_ab.ravel()
        o = np.argsort(values)
        return float(values[o][min(np.searchsorted(np.cumsum(w[o]), u), w.size - 1)])

    def multiplier_median(self, speed_rpm: float) -> float:
        """Posterior median of the multiplier at ``speed_rpm``."""
        x = math.log(float(speed_rpm) / self.reference_speed_rpm)
        return math.exp(self._quantile((_A_GRID[:, None] + _B_GRID[None, :] * x).ravel(), 0.5))

    def slope(self) -> tuple[float, float, float]:
        """(median, 16 %, 84 % quantiles) of b."""
        vals = np.broadcast_to(_B_GRID[None, :], self.posterior_ab.shape).ravel()
        return tuple(self._quantile(vals, u) for u in (0.5, 0.1587, 0.8413))


def calibrate_knock_speed(evidence: pd.DataFrame,
                          reference_speed_rpm: float = REFERENCE_SPEED_RPM) -> KnockSpeedCalibration:
    """Fit ``ln m = a + b ln(n / n_ref)`` to :func:`engine_model.knock.point_evidence` rows (finite index)."""
    ev = evidence[np.isfinite(evidence["ln_ki_cycle_m1"].to_numpy(float))]
    if not len(ev):
        raise ValueError("calibrate_knock_speed: no evidence row with a finite knock index")
    y = ev["ln_ki_cycle_m1"].to_numpy(float)
    kn = ev["knock"].to_numpy(bool)
    x = np.log(ev["speed_rpm"].to_numpy(float) / float(reference_speed_rpm))
    a, b, ls = _A_GRID[:, None, None], _B_GRID[None, :, None], _LNS_GRID[None, None, :]
    sg = np.exp(ls)
    logp = (-0.5 * (a / PRIOR_SIGMA_LN) ** 2 - 0.5 * (b / SLOPE_PRIOR_SD) ** 2
            - 0.5 * ((ls - SCATTER_PRIOR[0]) / SCATTER_PRIOR[1]) ** 2)
    for yi, ki, xi in zip(y, kn, x):
        arg = (yi - (a + b * xi)) / sg
        logp = logp + (log_ndtr(arg) if ki else log_ndtr(-arg))
    p = np.exp(logp - logp.max()).sum(axis=2)
    return KnockSpeedCalibration(posterior_ab=p / p.sum(), reference_speed_rpm=float(reference_speed_rpm),
                                 n_clean=int((~kn).sum()), n_knock=int(kn.sum()))
