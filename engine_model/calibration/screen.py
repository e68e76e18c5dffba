"""Screening which global parameters can shape the airflow match, before paying for a full match.

A full airflow match (coarse grid + bounded least squares) costs ~1000
simulations.  Which three global parameters are worth it is decided cheaply:

1. :func:`sensitivities`: Ga_REL [%] at every bench point at a base parameter
   set and central finite differences of it with respect to every candidate
   parameter (``2 k + 1`` parameter sets, one batch).
2. :func:`rank_subsets`: for every subset of ``size`` candidates, the
   linearised best fit within the physical bounds (and a trust region around
   the base, where the linearisation is meant to hold): bounded linear least
   squares (rms and max |Ga_REL| of that solution) and the bounded minimax
   solution (the smallest max |Ga_REL| any combination can reach), plus the
   conditioning of the subset (largest parameter correlation, condition
   number of the column-scaled Jacobian).  Candidates left out of a subset go
   back to their spec values; their move from the base is extrapolated
   linearly too.

The linear screen ranks; only the real, nonlinear match
(:func:`engine_model.calibration.airflow.match_airflow`) decides.

:func:`smooth_floor` gives the data's own floor: the smallest max |Ga_REL|
that *any* polynomial volumetric-efficiency curve of a given degree in speed
can reach on the measured points (a linear programme).  A model whose VE
varies smoothly with speed cannot beat the floor of a low degree.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pandas as pd

from engine_model.calibration.airflow import Evaluate, Parameter, AirflowProblem

# Candidate global parameters with defensible ranges (the spec TOML gives the base value and its source).
CANDIDATES = (
    Parameter("exhaust.runner_length_m", 0.20, 0.70, 0.006, "m",
              "exhaust primary length (scavenging tuning); sport-bike 4-2-1 primaries 0.3-0.6 m [A]"),
    Parameter("intake.runner_length_m", 0.10, 0.35, 0.004, "m",
              "plenum-to-valve length incl. head port (ram tuning); FS manifolds 0.1-0.35 m [A]"),
    Parameter("intake.restrictor_cd", 0.85, 0.99, 0.006, "-",
              "restrictor throat Cd; machined venturis 0.95-0.995 (ISO 5167-4), 0.85 allows a poor inlet"),
    Parameter("intake.restrictor_recovery", 0.30, 0.95, 0.02, "-",
              "diffuser pressure recovery; conical diffusers 0.5 (short/separated) to 0.9 (White, sec. 6.11)"),
    Parameter("intake.runner_diameter_m", 0.030, 0.044, 0.0008, "m",
              "runner/port diameter (inertance L/A, damping); FS runners and R6 ports 30-44 mm [A]"),
    Parameter("exhaust.runner_diameter_m", 0.028, 0.040, 0.0008, "m",
              "primary pipe inner diameter; sport-bike headers 28-40 mm [A]"),
    Parameter("intake.runner_loss_k", 0.1, 1.5, 0.08, "-",
              "runner minor-loss factor (damping of the ram wave); Idelchik entries/bends 0.1-1.5"),
    Parameter("exhaust.runner_loss_k", 0.1, 1.5, 0.08, "-",
              "primary minor-loss factor (damping of the exhaust wave); Idelchik bends 0.1-1.5"),
    Parameter("intake.plenum_volume_m3", 0.0015, 0.0060, 0.0003, "m3",
              "plenum volume; FS restricted 600 cc intakes 1.5-6 L [A]"),
    Parameter("exhaust.collector_volume_m3", 0.0005, 0.0040, 0.0002, "m3",
              "merge collector + silencer inlet volume [A]"),
    Parameter("exhaust.tailpipe_cd", 0.5, 1.0, 0.03, "-",
              "silencer outlet Cd (back pressure) [A]"),
    Parameter("intake_valves.max_lift_m", 0.0080, 0.0105, 0.0002, "m",
              "intake valve peak lift (valve flow area); L/D 0.30-0.39 [H ch. 6]"),
    Parameter("intake_valves.diameter_m", 0.0250, 0.0290, 0.0003, "m",
              "intake valve head diameter (valve flow area); 0.37-0.43 bore [H ch. 6]"),
    Parameter("exhaust_valves.diameter_m", 0.0210, 0.0245, 0.0003, "m",
              "exhaust valve head diameter; 0.31-0.37 bore [H ch. 6]"),
)


@dataclass(frozen=True)
class Sensitivity:
    """Ga_REL at a base point and its derivatives.

    r0 : (n,) Ga_REL [%] at the base; jac : (n, k) d Ga_REL / d parameter [% per unit];
    names : k dotted spec names; base : {name: value}; speed_rpm : (n,).
    """

    r0: np.ndarray
    jac: np.ndarray
    names: tuple
    base: dict
    speed_rpm: np.ndarray
    simulations: int

    def table(self) -> pd.DataFrame:
        """Long form: one row per (parameter, point) with the change of Ga_REL per parameter step."""
        return pd.DataFrame(self.jac, columns=list(self.names)).assign(speed_rpm=self.speed_rpm,
                                                                      ga_rel_pct=self.r0)


def sensitivities(meas: pd.DataFrame, evaluate: Evaluate, base: dict, candidates=CANDIDATES) -> Sensitivity:
    """Ga_REL [%] at ``base`` (all candidates at their ``base`` values) and central differences.

    Parameters
    ----------
    meas : DataFrame
        Validated bench data.
    evaluate : callable(plan) -> results
        Runs simulations (one batch of ``(2 k + 1) n`` rows).
    base : dict
        ``{dotted name: value}`` for every candidate (the point the derivatives are taken at).
    candidates : sequence of Parameter
        Step ``Parameter.step`` each side (one-sided at a bound).
    """
    params = tuple(candidates)
    missing = [p.name for p in params if p.name not in base]
    if missing:
        raise ValueError(f"sensitivities: base has no value for {missing}")
    prob = AirflowProblem(meas, evaluate, params)
    x0 = np.array([base[p.name] for p in params], float)
    xs, hs = [x0], []
    for j, p in enumerate(params):
        lo_, hi_ = max(x0[j] - p.step, p.low), min(x0[j] + p.step, p.high)
        for v in (hi_, lo_):
            x = x0.copy()
            x[j] = v
            xs.append(x)
        hs.append(hi_ - lo_)
    r = prob.many(xs)
    jac = np.column_stack([(r[1 + 2 * j] - r[2 + 2 * j]) / hs[j] for j in range(len(params))])
    return Sensitivity(r[0], jac, tuple(p.name for p in params), dict(base),
                       prob.meas["speed_rpm"].to_numpy(float), prob.simulations)


def _minimax(r0, J, lo, hi):
    """min_x max_i |r0_i + (J x)_i| subject to lo <= x <= hi (linear programme); returns (t, x)."""
    from scipy.optimize import linprog

    n, k = J.shape
    one = np.ones((n, 1))
    A = np.vstack([np.hstack([J, -one]), np.hstack([-J, -one])])
    b = np.concatenate([-r0, r0])
    c = np.zeros(k + 1)
    c[-1] = 1.0
    res = linprog(c, A_ub=A, b_ub=b, bounds=list(zip(lo, hi)) + [(0, None)], method="highs")
    if not res.success:
        return np.nan, np.full(k, np.nan)
    return float(res.x[-1]), res.x[:k]


def rank_subsets(sens: Sensitivity, candidates=CANDIDATES, size: int = 3, spec_values: dict | None = None,
                 trust: float = 0.25, must_include=()) -> pd.DataFrame:
    """Linearised best fit of every subset of ``size`` candidates (see module docstring).

    Parameters
    ----------
    sens : Sensitivity
    candidates : sequence of Parameter
        Bounds of each parameter.
    size : int
        Parameters per subset (the issue allows at most three).
    spec_values : dict, optional
        ``{name: value}`` the left-out candidates return to (default: their ``base`` value, i.e. held).
    trust : float
        Moves limited to +- ``trust`` x (high - low) around the base, besides the bounds.
    must_include : sequence of str
        Only subsets containing all of these.

    Returns
    -------
    DataFrame
        One row per subset, best minimax first: ``parameters, max_abs_minimax_pct, max_abs_ls_pct,
        rms_ls_pct, max_abs_corr, cond``, the minimax moves ``d:<name>`` and the Ga_REL of each point.
    """
    from scipy.optimize import lsq_linear

    by = {p.name: p for p in candidates}
    names = list(sens.names)
    spec_values = dict(spec_values or {})
    rows = []
    for sub in itertools.combinations(range(len(names)), size):
        sn = [names[j] for j in sub]
        if not set(must_include) <= set(sn):
            continue
        r0 = sens.r0.copy()
        for j, nm in enumerate(names):
            if j not in sub and nm in spec_values:
                r0 = r0 + sens.jac[:, j] * (spec_values[nm] - sens.base[nm])
        J = sens.jac[:, sub]
        lo = np.array([max(by[nm].low, sens.base[nm] - trust * (by[nm].high - by[nm].low)) - sens.base[nm]
                       for nm in sn])
        hi = np.array([min(by[nm].high, sens.base[nm] + trust * (by[nm].high - by[nm].low)) - sens.base[nm]
                       for nm in sn])
        ls = lsq_linear(J, -r0, bounds=(lo, hi))
        r_ls = r0 + J @ ls.x
        t, x_mm = _minimax(r0, J, lo, hi)
        scale = np.array([by[nm].high - by[nm].low for nm in sn])
        Js = J * scale
        cov = np.linalg.pinv(Js.T @ Js)
        d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
        corr = cov / np.outer(d, d)
        off = np.abs(corr[~np.eye(size, dtype=bool)]) if size > 1 else np.zeros(1)
        sv = np.linalg.svd(Js, compute_uv=False)
        row = {"parameters": " + ".join(sn), "max_abs_minimax_pct": t,
               "max_abs_ls_pct": float(np.max(np.abs(r_ls))), "rms_ls_pct": float(np.sqrt(np.mean(r_ls ** 2))),
               "max_abs_corr": float(off.max()), "cond": float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf}
        row.update({f"d:{nm}": float(v) for nm, v in zip(sn, x_mm)})
        row.update({f"ga_rel_ls|{s:.0f}": float(v) for s, v in zip(sens.speed_rpm, r_ls)})
        rows.append(row)
    return pd.DataFrame(rows).sort_values(["max_abs_minimax_pct", "rms_ls_pct"], kind="stable").reset_index(drop=True)


def smooth_floor(speed_rpm, air_kg_h, degree: int) -> tuple[float, np.ndarray]:
    """Smallest max |Ga_REL| [%] that a VE polynomial of ``degree`` in speed can reach on the data.

    Volumetric efficiency is proportional to Ga / N at fixed intake state, so the question is how close
    ``Ga_sim = N p(N)`` with ``p`` any polynomial of the given degree can get to every measured ``Ga``
    in the paper's measure ``(Ga_sim - Ga_meas) / Ga_sim``.  Solved exactly as a linear programme in
    ``1 / Ga_sim``-scaled form: ``|p(N_i) - v_i| <= t p(N_i)`` with ``v_i = Ga_i / N_i``.

    Returns
    -------
    (float, ndarray)
        The floor [%] and the Ga_REL [%] of the optimal curve at each point.
    """
    from scipy.optimize import linprog

    n = np.asarray(speed_rpm, float)
    v = np.asarray(air_kg_h, float) / n
    x = (n - n.mean()) / max(np.ptp(n), 1.0)
    V = np.vander(x, degree + 1)
    # p - v <= t p  ->  (1 - t) p - v <= 0 is bilinear; bisection on t keeps it linear
    lo_t, hi_t = 0.0, 0.5
    best = None
    for _ in range(40):
        t = 0.5 * (lo_t + hi_t)
        A = np.vstack([V * (1 - t), -V * (1 + t)])
        b = np.concatenate([v, -v])
        res = linprog(np.zeros(degree + 1), A_ub=A, b_ub=b, bounds=[(None, None)] * (degree + 1), method="highs")
        if res.success:
            hi_t, best = t, res.x
        else:
            lo_t = t
    if best is None:
        return np.nan, np.full(len(n), np.nan)
    p = V @ best
    return 100.0 * hi_t, 100.0 * (p - v) / p
