"""The hidden knock truth of the virtual knock bench: a structure the calibrated model does not share.

The calibration (:mod:`engine_model.knock`) fits one delay multiplier to the Douaud-Eyzat
integral of the cycle model.  To test it on something it cannot reproduce by construction,
the virtual knock bench decides knock with its own model, evaluated in plain NumPy on the
cycle's pressure and temperature traces:

* two parallel Arrhenius branches (rates add), a low-activation branch with a strong
  pressure dependence and a high-activation branch that takes over in hot end gas: the
  two-slope shape of measured gasoline ignition delays in ln(tau) against 1/T (the single
  Arrhenius line of Douaud-Eyzat has one slope);
* end gas compressed on a polytropic line from the spark (exponent below the isentropic
  one: heat loss to the walls), not an isentrope;
* a weaker dilution term (1 - x_r)^0.5 and the integral to 95 % burned;
* knock heard when the mean cycle's index reaches 0.8 (cycle-to-cycle spread expressed as
  a lower threshold, not as an advance of the burn), with a log-normal detection scatter.

The constants are not a published correlation: they only have to be a plausible engine that
knocks at high load and low speed and runs Table 2's WOT sparks clean.  They were set once,
before the calibration was run against them, and are not changed to make it pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from engine_model import wiebe
from engine_model.sim.prepare import OperatingPoint, SolverSettings
from engine_model.sim.simulate import CHUNKS_PER_WORKER, MIN_ROWS_TO_SPLIT, map_in_processes, simulate_point
from engine_model.spec import EngineSpec

__all__ = ["KnockTruth", "truth_knock_index", "simulate_with_truth"]

P_ATM = 101325.0


@dataclass(frozen=True)
class KnockTruth:
    """Constants of the hidden knock truth (delays in s, pressures in atm, temperatures in K)."""

    a1_s: float = 2.0e-3
    n1: float = 1.3
    b1_k: float = 4200.0
    a2_s: float = 2.0e-9
    n2: float = 0.6
    b2_k: float = 18000.0
    polytropic_n: float = 1.30
    dilution_exponent: float = 0.5
    end_burn_fraction: float = 0.95
    onset_index: float = 0.8
    detect_sigma_ln: float = 0.05

    def rate(self, p_pa: np.ndarray, t_u: np.ndarray) -> np.ndarray:
        """1/tau [1/s] of the two branches together."""
        pa = np.asarray(p_pa, float) / P_ATM
        tau1 = self.a1_s * pa ** -self.n1 * np.exp(self.b1_k / t_u)
        tau2 = self.a2_s * pa ** -self.n2 * np.exp(self.b2_k / t_u)
        return 1.0 / tau1 + 1.0 / tau2


def truth_knock_index(truth: KnockTruth, trace: np.ndarray, ncyl: int, speed_rpm: float, spark_deg_btdc: float,
                      bdur_10_90_deg: float, wiebe_m: float, residual_fraction: float, ivc_deg: float) -> float:
    """The truth's knock index of cylinder 1 from a cycle's traces (``simulate_point(..., return_traces=True)``)."""
    p_all, t_all = trace[0], trace[ncyl]
    nstep = p_all.size
    ang = np.arange(nstep) * 720.0 / nstep
    ang = np.where(ang < 360.0, ang, ang - 720.0)
    o = np.argsort(ang)
    ang, p, t = ang[o], p_all[o], t_all[o]
    bdur = wiebe.bdur_10_90_to_bdur(bdur_10_90_deg, wiebe_m)
    a_end = float(wiebe.angle_at_fraction(truth.end_burn_fraction, spark_deg_btdc, bdur, wiebe_m))
    a_ivc = ivc_deg - 720.0 if ivc_deg > 360.0 else ivc_deg - 360.0 if ivc_deg > 0 else ivc_deg
    sel = (ang >= a_ivc) & (ang <= a_end)
    ang, p, t = ang[sel], p[sel], t[sel]
    before = ang < -spark_deg_btdc
    if before.all() or not before.any():
        return math.nan
    i_s = int(np.flatnonzero(before)[-1])
    ex = (truth.polytropic_n - 1.0) / truth.polytropic_n
    t_u = np.where(before, t, t[i_s] * (p / p[i_s]) ** ex)
    dil = (1.0 - min(max(residual_fraction, 0.0), 0.95)) ** truth.dilution_exponent
    dt = np.diff(ang) / (6.0 * speed_rpm)
    r = truth.rate(p, t_u) * dil
    return float(np.sum(0.5 * (r[1:] + r[:-1]) * dt))


def simulate_with_truth(spec: EngineSpec, plan: pd.DataFrame, truth: KnockTruth,
                        solver: SolverSettings = SolverSettings(), workers: int = 1) -> pd.DataFrame:
    """Simulate every plan row (each from a cold start); add ``knock_index_truth`` (the truth's index).

    ``workers > 1`` (and at least :data:`~engine_model.sim.simulate.MIN_ROWS_TO_SPLIT` rows): the rows are
    shared among that many spawned processes
    (:func:`engine_model.sim.simulate.map_in_processes`); every row is independent, so the result is the same.
    """
    if workers > 1 and len(plan) >= MIN_ROWS_TO_SPLIT:
        k = workers * CHUNKS_PER_WORKER
        frames = [plan.iloc[ix[0]:ix[-1] + 1] for ix in np.array_split(np.arange(len(plan)), k) if len(ix)]
        parts = map_in_processes(simulate_with_truth, frames, workers, (spec,), (truth, solver))
        return pd.concat(parts, ignore_index=True)
    ivc = spec.intake_valves.open_deg + spec.intake_valves.duration_deg
    rows = []
    for _, r in plan.iterrows():
        op = OperatingPoint(speed_rpm=float(r["speed_rpm"]), throttle_pct=float(r["throttle_pct"]),
                            spark_deg_btdc=float(r["spark_deg_btdc"]), lam=float(r["lambda"]),
                            bdur_10_90_deg=float(r["bdur_10_90_deg"]), wiebe_m=float(r["wiebe_m"]))
        row, _, tr = simulate_point(spec, op, solver, return_traces=True)
        row = dict(row)
        row["knock_index_truth"] = truth_knock_index(
            truth, tr, spec.geometry.n_cylinders, op.speed_rpm, op.spark_deg_btdc, op.bdur_10_90_deg,
            op.wiebe_m, float(row["residual_fraction"]), ivc)
        rows.append(row)
    out = pd.DataFrame(rows)
    out.insert(0, "point_id", plan["point_id"].astype(str).to_numpy())
    return out
