"""Knock calibration: the delay multiplier of the end-gas correlation from what the bench saw.

The knock index of the cycle model scales exactly as 1/m with the delay multiplier m
(``KnockSpec.delay_multiplier``): the multiplier divides the integrand and nothing in the
cycle depends on the index.  So one spark sweep per bench point at the identified burn
gives, for every m at once, the model's knock index at the spark the bench ran and at that
spark plus the fastest cycles' advance (``KnockSpec.cycle_ca50_advance_deg``).

Evidence, per bench point (y = ln of the knock index of the fastest cycles at m = 1):

- ran knock-free (``knock`` 0, e.g. every Table 2 point):  the bench says y < ln m
- knocking or knock-limited (``knock`` 1, the spark at onset): y >= ln m
- an onset sweep is a run of such rows: it brackets ln m from both sides.

Each observation is read through a probit link, P(knock) = Phi((y - ln m)/sigma): sigma is
the scatter between the model's index and the bench's onset (model error and the bench's
knock detection), fitted with ln m when the data carry both sides.  Prior: ln m ~ N(0, ln 2)
(the literature constants taken as right within a factor of 2, 1 sigma: an assumption of this
project) and ln sigma ~ N(ln 0.1, 0.7) (a 10 % knock-index scatter, about 2 deg of spark at the
model's 0.045-0.05 /deg slope, within a factor of 2).  The posterior is evaluated on a grid.

The table uses the ``knock_probability`` (default 2 %) quantile of the predictive distribution of a
cell's multiplier (the posterior of ln m widened by the scatter, the knock-prone side): with
knock-free points only, never below the bound they set, and the report says it is a bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.special import log_ndtr

__all__ = ["KnockCalibration", "bench_sweep_plan", "calibrate_knock", "point_evidence"]

#: Spark offsets of the sweep around each bench point's spark [deg]: +-6 deg covers MBT at the identified burn
#: (its CA50 sits 6.5-11.5 deg ATDC on Table 2, the model's MBT CA50 is 6-11 deg ATDC) and a 1.5 deg step puts
#: the fastest cycles' default 3 deg advance on a sweep point.
SWEEP_OFFSETS_DEG = (-6.0, -4.5, -3.0, -1.5, 0.0, 1.5, 3.0, 4.5, 6.0)
#: Prior of ln(multiplier): N(0, PRIOR_SIGMA_LN) [A] the literature constants right within a factor of 2.
PRIOR_SIGMA_LN = math.log(2.0)
#: Prior of the model-to-bench scatter sigma (in ln knock index): log-normal around 0.1, factor 2 [A].
SCATTER_PRIOR = (math.log(0.10), 0.7)
_LNM_GRID = np.linspace(-3.0, 3.0, 1201)
_LNS_GRID = np.linspace(math.log(0.01), math.log(1.0), 61)
#: Draws from the grid posterior for the predictive quantile (fixed seed: the result is reproducible; the 2 %
#: quantile of 20000 draws moves by < 1 % between seeds).
_PREDICTIVE_DRAWS = 20000


def bench_sweep_plan(identified: pd.DataFrame, overrides: dict | None = None,
                     offsets=SWEEP_OFFSETS_DEG) -> pd.DataFrame:
    """Spark sweeps at the identified burns: one row per (bench point, offset) for the cycle model.

    ``identified``: the identification table (``point_id, speed_rpm, throttle_pct, spark_deg_btdc, lambda,
    bdur_10_90_deg, wiebe_m``); points without a burn are left out.  ``overrides``: ``spec.*`` columns to
    add (the airflow match).  Columns ``knock_point_id`` and ``spark_offset_deg`` link rows to the points.
    """
    ok = identified[np.isfinite(pd.to_numeric(identified["bdur_10_90_deg"], errors="coerce"))]
    rows = []
    for _, r in ok.iterrows():
        for off in offsets:
            rows.append({"point_id": f"{r['point_id']}@{off:+.1f}", "knock_point_id": str(r["point_id"]),
                         "spark_offset_deg": float(off), "speed_rpm": float(r["speed_rpm"]),
                         "throttle_pct": float(r["throttle_pct"]),
                         "spark_deg_btdc": float(r["spark_deg_btdc"]) + float(off), "lambda": float(r["lambda"]),
                         "bdur_10_90_deg": float(r["bdur_10_90_deg"]), "wiebe_m": float(r["wiebe_m"])})
    plan = pd.DataFrame(rows)
    for k, v in (overrides or {}).items():
        plan[k if str(k).startswith("spec.") else f"spec.{k}"] = float(v)
    return plan


def _log_interp(x: np.ndarray, y: np.ndarray, at: float) -> float:
    """ln y at ``at``, linear in ln y through the points (end segments extended); NaN without 2 points."""
    good = np.isfinite(x) & np.isfinite(y) & (y > 0)
    x, ly = x[good], np.log(y[good])
    if x.size < 2:
        return math.nan
    o = np.argsort(x)
    x, ly = x[o], ly[o]
    if at <= x[0]:
        return float(ly[0] + (ly[1] - ly[0]) / (x[1] - x[0]) * (at - x[0]))
    if at >= x[-1]:
        return float(ly[-1] + (ly[-1] - ly[-2]) / (x[-1] - x[-2]) * (at - x[-1]))
    return float(np.interp(at, x, ly))


def _mbt(s: np.ndarray, t: np.ndarray) -> tuple[float, bool]:
    """(spark of maximum torque, inside the sweep): least-squares parabola through the best point's +-3 deg."""
    good = np.isfinite(s) & np.isfinite(t)
    s, t = s[good], t[good]
    if s.size < 3:
        return math.nan, False
    i = int(np.argmax(t))
    near = np.abs(s - s[i]) <= 3.0 + 1e-9
    if near.sum() >= 3:
        a, b, _c = np.polyfit(s[near] - s[i], t[near], 2)
        if a < 0:
            v = s[i] - b / (2 * a)
            inside = 0 < i < s.size - 1
            return float(np.clip(v, s.min(), s.max())), bool(inside)
    return float(s[i]), bool(0 < i < s.size - 1)


def point_evidence(bench: pd.DataFrame, plan: pd.DataFrame, results: pd.DataFrame, multiplier_used: float,
                   advance_deg: float) -> pd.DataFrame:
    """Per bench point: the model's knock index (at m = 1) at the bench spark and with the fastest cycles'
    advance, the model's MBT at the identified burn, and what the bench saw.

    ``multiplier_used``: the delay multiplier the sweep ran with (its knock indices are multiplied by it).
    Columns: ``point_id, speed_rpm, throttle_pct, spark_deg_btdc, at_mbt, knock, ki_m1, ki_cycle_m1,
    ln_ki_cycle_m1, mbt_model_deg_btdc, mbt_inside_sweep, mbt_minus_bench_deg, knock_slope_per_deg``.
    """
    res = results.reset_index(drop=True)
    pl = plan.reset_index(drop=True)
    if len(res) != len(pl):
        raise ValueError(f"knock sweep: {len(res)} results for {len(pl)} planned points")
    ki = pd.to_numeric(res["knock_index"], errors="coerce").to_numpy(float) * float(multiplier_used)
    tq = pd.to_numeric(res["brake_torque_nm"], errors="coerce").to_numpy(float)
    b = bench.set_index("point_id")
    rows = []
    for pid, idx in pl.groupby("knock_point_id", sort=False).indices.items():
        s = pl["spark_deg_btdc"].to_numpy(float)[idx]
        s0 = float(b.at[pid, "spark_deg_btdc"])
        lk0 = _log_interp(s, ki[idx], s0)
        lkc = _log_interp(s, ki[idx], s0 + advance_deg)
        mbt, inside = _mbt(s, tq[idx])
        knock = bool(b.at[pid, "knock"]) if "knock" in b.columns and pd.notna(b.at[pid, "knock"]) else False
        at_mbt = bool(b.at[pid, "at_mbt"]) if "at_mbt" in b.columns else not knock
        rows.append({"point_id": pid, "speed_rpm": float(b.at[pid, "speed_rpm"]),
                     "throttle_pct": float(b.at[pid, "throttle_pct"]), "spark_deg_btdc": s0, "at_mbt": at_mbt,
                     "knock": knock, "ki_m1": math.exp(lk0) if math.isfinite(lk0) else math.nan,
                     "ki_cycle_m1": math.exp(lkc) if math.isfinite(lkc) else math.nan, "ln_ki_cycle_m1": lkc,
                     "knock_slope_per_deg": (lkc - lk0) / advance_deg if advance_deg > 0 else math.nan,
                     "mbt_model_deg_btdc": mbt, "mbt_inside_sweep": inside, "mbt_minus_bench_deg": mbt - s0})
    return pd.DataFrame(rows)


@dataclass(frozen=True)
class KnockCalibration:
    """Result of :func:`calibrate_knock` (multipliers of the Douaud-Eyzat delay, dimensionless)."""

    multiplier_median: float
    multiplier_table: float
    multiplier_lo68: float
    multiplier_hi68: float
    scatter_median: float
    knock_probability: float
    table_rule: str
    n_clean: int
    n_knock: int
    lower_bound: float
    upper_bound: float
    evidence: pd.DataFrame = field(repr=False)

    @property
    def kind(self) -> str:
        """'two-sided' (knock-free and knocking points), 'lower bound' (knock-free only), 'upper bound', 'prior'."""
        if self.n_clean and self.n_knock:
            return "two-sided"
        return "lower bound" if self.n_clean else ("upper bound" if self.n_knock else "prior")

    def summary(self) -> dict:
        return {"delay_multiplier_table": round(self.multiplier_table, 4),
                "delay_multiplier_median": round(self.multiplier_median, 4),
                "delay_multiplier_68": [round(self.multiplier_lo68, 4), round(self.multiplier_hi68, 4)],
                "scatter_ln_ki": round(self.scatter_median, 4), "knock_probability": self.knock_probability,
                "evidence": self.kind,
                "points_knock_free": self.n_clean, "points_knocking": self.n_knock,
                "bound_from_knock_free": round(self.lower_bound, 4) if math.isfinite(self.lower_bound) else None,
                "bound_from_knocking": round(self.upper_bound, 4) if math.isfinite(self.upper_bound) else None}

    def text(self) -> str:
        s = self.summary()
        head = (f"knock calibration ({self.kind}: {self.n_clean} knock-free, {self.n_knock} knocking points): "
                f"delay multiplier {self.multiplier_median:.3g} (68 % {self.multiplier_lo68:.3g}-"
                f"{self.multiplier_hi68:.3g}), model-to-bench scatter {self.scatter_median:.2g} in ln(knock index); "
                f"the table uses {self.multiplier_table:.3g}, {self.table_rule}")
        if self.kind == "lower bound":
            head += (f".  Knock-free points only: the data say multiplier > {s['bound_from_knock_free']} "
                     "(the model must not knock where the bench ran clean); above that the literature prior "
                     "decides.  Knock-onset sweeps (mbc plan knock-sweeps) would bound it from the other side.")
        return head


def calibrate_knock(evidence: pd.DataFrame, knock_probability: float = 0.02) -> KnockCalibration:
    """Posterior of the delay multiplier from :func:`point_evidence` (rows with a finite knock index).

    The table's multiplier is the ``knock_probability`` quantile of the predictive distribution of a cell's
    multiplier (posterior of ln m plus the model-to-bench scatter): a cell the calibrated model calls
    knock-free at its border knocks on the engine with about that probability.
    """
    if not 0 < knock_probability < 0.5:
        raise ValueError(f"knock_probability = {knock_probability!r}: expected (0, 0.5)")
    ev = evidence[np.isfinite(evidence["ln_ki_cycle_m1"].to_numpy(float))]
    y = ev["ln_ki_cycle_m1"].to_numpy(float)
    kn = ev["knock"].to_numpy(bool)
    lm = _LNM_GRID[:, None]
    lsg = _LNS_GRID[None, :]
    sg = np.exp(lsg)
    logp = -0.5 * (lm / PRIOR_SIGMA_LN) ** 2 - 0.5 * ((lsg - SCATTER_PRIOR[0]) / SCATTER_PRIOR[1]) ** 2
    for yi, ki in zip(y, kn):
        arg = (yi - lm) / sg
        logp = logp + (log_ndtr(arg) if ki else log_ndtr(-arg))
    p = np.exp(logp - logp.max())
    pm = p.sum(axis=1)
    pm /= pm.sum()
    cdf = np.cumsum(pm)

    def q(u):
        return float(math.exp(np.interp(u, cdf, _LNM_GRID)))
    ps = p.sum(axis=0)
    ps /= ps.sum()
    scatter = float(math.exp(np.interp(0.5, np.cumsum(ps), _LNS_GRID)))
    lo_b = float(np.exp(y[~kn].max())) if (~kn).any() else math.nan
    hi_b = float(np.exp(y[kn].min())) if kn.any() else math.nan
    # predictive: the knock border of a cell not measured carries the multiplier's uncertainty and the scatter
    rng = np.random.default_rng(0)
    flat = p.ravel() / p.sum()
    pick = rng.choice(flat.size, size=_PREDICTIVE_DRAWS, p=flat)
    i_m, i_s = np.unravel_index(pick, p.shape)
    draws = _LNM_GRID[i_m] + np.exp(_LNS_GRID[i_s]) * rng.standard_normal(_PREDICTIVE_DRAWS)
    table = float(math.exp(np.quantile(draws, knock_probability)))
    rule = f"the predictive {100 * knock_probability:g} % quantile (a cell called knock-free knocks with about " \
           "that probability)"
    if (~kn).any() and not kn.any() and table < lo_b * math.exp(scatter):
        # knock-free evidence only: the model must not knock where the bench ran clean (strictly, with the
        # scatter's median as the margin), whatever the prior says
        table = lo_b * math.exp(scatter)
        rule = (f"the knock-free bound times exp(scatter) (the predictive {100 * knock_probability:g} % quantile, "
                f"{math.exp(np.quantile(draws, knock_probability)):.3g}, would make the model knock where the bench "
                "ran clean)")
    return KnockCalibration(multiplier_median=q(0.5), multiplier_table=table,
                            multiplier_lo68=q(0.1587), multiplier_hi68=q(0.8413), scatter_median=scatter,
                            knock_probability=float(knock_probability), table_rule=rule,
                            n_clean=int((~kn).sum()), n_knock=int(kn.sum()), lower_bound=lo_b, upper_bound=hi_b,
                            evidence=evidence.reset_index(drop=True))
