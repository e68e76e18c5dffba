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

When the tables use it (:attr:`KnockSpeedCalibration.supported`): only where the data inform ``b``, i.e. its
posterior standard deviation is at most ``SUPPORT_RATIO`` of the prior's.  Otherwise (e.g. Table 2 alone:
knock-free points between 8000 and 11000 rpm) the one-parameter multiplier stays, because a slope the data
do not see would only widen the table's margin away from ``n_ref`` by the prior's guess.  When used, a cell
at speed n takes :meth:`KnockSpeedCalibration.table_multiplier`: the ``knock_probability`` quantile of the
predictive distribution of ln m(n) (posterior of a and b plus the scatter), as the one-parameter table does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.special import log_ndtr

from engine_model.knock.calibrate import PRIOR_SIGMA_LN, SCATTER_PRIOR

__all__ = ["SLOPE_PRIOR_SD", "REFERENCE_SPEED_RPM", "SUPPORT_RATIO", "KnockSpeedCalibration",
           "calibrate_knock_speed", "multiplier_at", "with_speed_multiplier"]

#: Prior 1-sigma of b = d ln m / d ln n [-]: [A] a factor 1.65 on the multiplier over a speed ratio of e
#: (e.g. 4000 -> 11000 rpm), an assumption of this project, set before any trial.
SLOPE_PRIOR_SD = 0.5
#: Speed at which ``a`` is the multiplier's log [rpm]: mid-range of a 3000-13000 rpm engine.
REFERENCE_SPEED_RPM = 6000.0
#: The tables use the speed term when the posterior sd of b is at most this share of the prior's [A]: the data
#: then carry at least 3 times the prior's information on b (variance ratio 1/4), an assumption of this project.
SUPPORT_RATIO = 0.5
#: Draws of the predictive distribution (fixed seed, as the one-parameter fit: the result is reproducible).
_PREDICTIVE_DRAWS = 20000
_A_GRID = np.linspace(-1.5, 1.0, 251)
_B_GRID = np.linspace(-1.5, 1.5, 121)
_LNS_GRID = np.linspace(math.log(0.01), math.log(1.0), 31)


@dataclass(frozen=True)
class KnockSpeedCalibration:
    """Grid posterior of (a, b, ln sigma) of ``ln m = a + b ln(n / reference_speed_rpm)`` with the probit scatter sigma."""

    posterior_abs: np.ndarray       # (len(_A_GRID), len(_B_GRID), len(_LNS_GRID)) grid posterior, sums to 1
    reference_speed_rpm: float
    n_clean: int
    n_knock: int

    @property
    def posterior_ab(self) -> np.ndarray:
        """Posterior of (a, b), the scatter marginalised."""
        return self.posterior_abs.sum(axis=2)

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

    def slope_sd(self) -> float:
        """Posterior standard deviation of b."""
        pb = self.posterior_ab.sum(axis=0)
        mean = float((pb * _B_GRID).sum())
        return math.sqrt(max(float((pb * (_B_GRID - mean) ** 2).sum()), 0.0))

    @property
    def supported(self) -> bool:
        """Do the data inform b (posterior sd <= SUPPORT_RATIO x prior sd)?  Only then do the tables use it."""
        return self.slope_sd() <= SUPPORT_RATIO * SLOPE_PRIOR_SD

    def table_multiplier(self, speed_rpm, knock_probability: float = 0.02) -> np.ndarray:
        """The ``knock_probability`` quantile of the predictive multiplier at each speed [-] (array)."""
        if not 0 < knock_probability < 0.5:
            raise ValueError(f"knock_probability = {knock_probability!r}: expected (0, 0.5)")
        n = np.atleast_1d(np.asarray(speed_rpm, dtype=float))
        rng = np.random.default_rng(0)
        w = self.posterior_abs.ravel()
        ia, ib, isg = np.unravel_index(rng.choice(w.size, size=_PREDICTIVE_DRAWS, p=w), self.posterior_abs.shape)
        z = rng.standard_normal(_PREDICTIVE_DRAWS)
        x = np.log(n / self.reference_speed_rpm)
        draws = _A_GRID[ia][None, :] + _B_GRID[ib][None, :] * x[:, None] + np.exp(_LNS_GRID[isg])[None, :] * z
        return np.exp(np.quantile(draws, knock_probability, axis=1))

    def summary(self, speeds_rpm, knock_probability: float = 0.02) -> dict:
        """Plain-JSON record: the slope's posterior, whether the tables use it, the table multipliers at
        ``speeds_rpm`` (``[[speed, multiplier], ...]``)."""
        med, lo, hi = self.slope()
        sp = np.asarray(sorted(set(float(v) for v in speeds_rpm)), dtype=float)
        return {"model": "ln m = a + b ln(n / n_ref)", "reference_speed_rpm": self.reference_speed_rpm,
                "slope_median": round(med, 4), "slope_68": [round(lo, 4), round(hi, 4)],
                "slope_sd": round(self.slope_sd(), 4), "slope_prior_sd": SLOPE_PRIOR_SD,
                "used": bool(self.supported), "knock_probability": knock_probability,
                "rule": f"used when the posterior sd of b <= {SUPPORT_RATIO:g} x its prior sd",
                "table_multipliers": [[float(n), round(float(m), 4)]
                                      for n, m in zip(sp, self.table_multiplier(sp, knock_probability))]}


def multiplier_at(table_multipliers, speed_rpm) -> np.ndarray:
    """Multiplier at ``speed_rpm`` from ``[[speed, multiplier], ...]`` (a summary's ``table_multipliers``):
    linear in ln m against ln n between the listed speeds, held beyond them."""
    t = np.asarray(table_multipliers, dtype=float)
    if t.ndim != 2 or t.shape[1] != 2 or not len(t) or (t <= 0).any():
        raise ValueError(f"table_multipliers: expected [[speed_rpm, multiplier], ...] with positive values, got "
                         f"{table_multipliers!r}")
    t = t[np.argsort(t[:, 0])]
    n = np.asarray(speed_rpm, dtype=float)
    return np.exp(np.interp(np.log(n), np.log(t[:, 0]), np.log(t[:, 1])))


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
    p3 = np.exp(logp - logp.max())
    p3 /= p3.sum()
    return KnockSpeedCalibration(posterior_abs=p3, reference_speed_rpm=float(reference_speed_rpm),
                                 n_clean=int((~kn).sum()), n_knock=int(kn.sum()))


#: Plan column that sets the delay multiplier per row (a ``spec.<section>.<field>`` override of the simulator).
MULTIPLIER_COLUMN = "spec.knock.delay_multiplier"


def with_speed_multiplier(plan: pd.DataFrame, table_multipliers) -> pd.DataFrame:
    """``plan`` with :data:`MULTIPLIER_COLUMN` set from its ``speed_rpm`` (:func:`multiplier_at`), rounded to
    4 decimals (the summary's precision; the simulator prepares one spec per distinct value)."""
    m = multiplier_at(table_multipliers, pd.to_numeric(plan["speed_rpm"], errors="coerce").to_numpy(float))
    return plan.assign(**{MULTIPLIER_COLUMN: np.round(m, 4)})
