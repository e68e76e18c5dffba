"""Airflow matching: identify a few global intake/exhaust parameters from measured air mass flow.

The paper's criterion (reference paper, section "Simulation model"):

    Ga_REL = (Ga_sim - Ga_meas) / Ga_sim * 100   [%]

is driven towards zero at every measured point by least squares over at most
three parameters that are *the same for every operating point* (geometry is
not allowed to change with speed; no per-point tuning).

Which parameters, and why
-------------------------
The paper does not give the manifolds.  With the assumed defaults (exhaust
primaries 0.45 m, intake runners 0.22 m, diffuser recovery 0.85) the 1D model
misses Table 2 by Ga_REL +0.9 % (8000 rpm) .. +17 % (11000 rpm): the pipes
tune the engine near 10000 rpm where the bench's volumetric efficiency is flat
near 0.85.  The default parameter set is

1. ``exhaust.runner_length_m`` (exhaust port to the merge), range 0.20-0.70 m
   [A, sport-bike and FS headers]: the speed of the exhaust scavenging waves.
2. ``intake.runner_length_m`` (plenum to valve seat, incl. head port), range
   0.10-0.35 m [A, FS intake manifolds]: the speed of the ram wave.
3. ``intake.restrictor_recovery``, range 0.30-0.95: the fraction of the
   throat's dynamic head the diffuser behind the 20 mm restrictor recovers.
   Long conical diffusers recover 0.8-0.9, short or partly stalled ones 0.5-0.7
   (White, Fluid Mechanics, 7th ed., sec. 6.11); a throat opening abruptly into
   a duct of twice its diameter recovers 2 s (1 - s) = 0.375 of it (Borda-Carnot,
   area ratio s = 0.25), hence the lower bound.  Its loss grows with the square
   of the flow, so it sets the level and tilts Ga_REL with speed; it also
   stands for the flow losses of that kind the model lacks (air filter, inlet
   duct).

Why these three (measured with the 1D model, 2026-11-26, docs/sections/calibration.md):
a differential-evolution search over each candidate triple (72 parameter sets
x 12 generations) reached rms Ga_REL 1.6 % with these three, 2.5 % with the
exhaust pipe diameter in place of the recovery (at its 40 mm bound), and no
linearised triple of the 17 screened candidates (:mod:`engine_model.calibration.screen`)
did better around the first match.  The same search with the valve timings
read at 1 mm lift instead of seat to seat reached only 9 %, which supports
reading the paper's timings seat to seat (``ValveSet.timing_lift_m``).  The
matched lengths lie near their lower bounds: the data want the wave tuning
out of the 8000-11000 rpm window, and a flat VE there is what the bench shows.
Other sets can be passed as ``parameters``.

Method
------
A coarse full-factorial search over the parameter ranges (the landscape is
rugged: several local minima), then ``scipy.optimize.least_squares``
(trust-region reflective, bounded) from the best few grid points.  The
Jacobian is by forward differences, evaluated as one batch per iteration so a
Dask-backed ``evaluate`` runs it in parallel.

Uncertainty: the covariance of the parameters is
``sigma^2 (J^T J)^-1`` with J the Jacobian of Ga_REL [%] at the optimum and
sigma = 1 % the assumed airflow-meter noise (a calibrated laminar/hot-film
air meter, ~1 % of reading [A]); 95 % intervals are +-1.96 standard errors.
The intervals from the residual variance (``SSR / (n - p)``) are reported
as well, because with 7 points and 3 parameters a misfit of the model shows
up there.  Both are linearised: in a rugged landscape they describe the
local minimum only.

Combustion during matching: airflow depends on the burn only through the
exhaust temperature and pressure waves (+-2 % near MBT combustion on this
model), so a fixed plausible burn is used: m = 6.25 (mid of the paper's
6.1-6.4 at 9000 rpm) and BDUR10-90 chosen so that CA50 = 9 deg ATDC at the
measured spark (MBT rule; paper eq 5); at points not at MBT, the prior
:func:`engine_model.priors.combustion_estimate`.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pandas as pd

from engine_model import wiebe
from engine_model.priors import CA50_TARGET_DEG_ATDC, WIEBE_M_REF, combustion_estimate

Evaluate = Callable[[pd.DataFrame], pd.DataFrame]


@dataclass(frozen=True)
class Parameter:
    """One global parameter of the airflow match: dotted spec name, bounds [unit of the field], FD step."""

    name: str
    low: float
    high: float
    step: float
    unit: str = ""
    why: str = ""

    def __post_init__(self):
        if not (self.low < self.high) or not (self.step > 0):
            raise ValueError(f"airflow parameter {self.name!r}: need low < high and step > 0, got "
                             f"{self.low}, {self.high}, {self.step}")


DEFAULT_PARAMETERS = (
    Parameter("exhaust.runner_length_m", 0.20, 0.70, 0.004, "m", "exhaust primary length: scavenging tuning"),
    Parameter("intake.runner_length_m", 0.10, 0.35, 0.004, "m", "intake runner length: ram tuning"),
    Parameter("intake.restrictor_recovery", 0.30, 0.95, 0.02, "-",
              "diffuser pressure recovery behind the restrictor: level, rising with speed"),
)
AIRFLOW_NOISE_PCT = 1.0     # [A] assumed 1-sigma airflow measurement noise, % of reading
MAX_PARAMETERS = 3          # issue 4: at most three global parameters
FAILED_RESIDUAL_PCT = 100.0  # Ga_REL given to a failed simulation so the optimiser moves away from it


def matching_burn(meas: pd.DataFrame) -> pd.DataFrame:
    """The fixed burn used while matching airflow: ``bdur_10_90_deg, wiebe_m`` per bench row.

    m = 6.25 and BDUR10-90 giving CA50 = 9 deg ATDC at the measured spark for
    MBT points (clipped to 15-60 deg); :func:`engine_model.priors.combustion_estimate`
    elsewhere.
    """
    spark = meas["spark_deg_btdc"].to_numpy(float)
    m = np.full(len(meas), WIEBE_M_REF)
    unit = wiebe.angle_at_fraction(0.5, 0.0, 1.0, WIEBE_M_REF)       # CA50 of a unit burn from SOC 0
    bdur_total = (CA50_TARGET_DEG_ATDC + spark) / unit
    b = np.clip(np.asarray(wiebe.bdur_to_bdur_10_90(np.maximum(bdur_total, 1.0), WIEBE_M_REF)), 15.0, 60.0)
    at_mbt = meas["at_mbt"].to_numpy(bool) if "at_mbt" in meas.columns else np.ones(len(meas), bool)
    if not at_mbt.all():
        est_b, est_m = combustion_estimate(meas["speed_rpm"].to_numpy(float), meas["throttle_pct"].to_numpy(float))
        b = np.where(at_mbt, b, est_b)
        m = np.where(at_mbt, m, est_m)
    return pd.DataFrame({"bdur_10_90_deg": b, "wiebe_m": m}, index=meas.index)


def airflow_plan(meas: pd.DataFrame, sets: list[dict], tag: str = "a") -> pd.DataFrame:
    """Plan: every bench point once per parameter set (``{dotted name: value}``), ``spec.*`` override columns."""
    base = meas[["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda"]].reset_index(drop=True)
    base = pd.concat([base, matching_burn(meas).reset_index(drop=True)], axis=1)
    for c in ("p_amb_pa", "t_amb_k"):
        if c in meas.columns:
            base[c] = meas[c].to_numpy(float)
    frames = []
    for k, vals in enumerate(sets):
        f = base.copy()
        f["bench_point_id"] = f["point_id"]
        f["point_id"] = [f"{tag}{k:04d}|{p}" for p in base["point_id"]]
        f["param_set"] = k
        for name, v in vals.items():
            f[f"spec.{name}"] = float(v)
        frames.append(f)
    return pd.concat(frames, ignore_index=True)


def ga_rel_pct(sim_kg_h, meas_kg_h):
    """Paper's airflow criterion ``(Ga_sim - Ga_meas) / Ga_sim * 100`` [%]."""
    sim = np.asarray(sim_kg_h, float)
    return (sim - np.asarray(meas_kg_h, float)) / sim * 100.0


@dataclass(frozen=True)
class AirflowMatch:
    """Result of :func:`match_airflow`.

    Attributes
    ----------
    names : tuple of str
        Dotted spec names of the matched parameters.
    values, start, stderr, ci95, ci95_residual : dict
        Optimum, best coarse-grid start, standard error (assumed noise), 95 %
        half-widths from the assumed noise and from the residual variance
        (NaN when n <= p).
    correlation : list of lists
        Parameter correlation matrix.
    table : DataFrame
        ``point_id, speed_rpm, air_mass_flow_kg_h_meas, air_mass_flow_kg_h_sim, ga_rel_pct,
        converged, status`` at the optimum.
    grid : DataFrame
        The coarse search: one row per parameter set with ``rms_ga_rel_pct``,
        ``max_abs_ga_rel_pct`` and the Ga_REL of each point.
    """

    names: tuple
    values: dict
    start: dict
    stderr: dict
    ci95: dict
    ci95_residual: dict
    correlation: list
    table: pd.DataFrame
    grid: pd.DataFrame
    noise_pct: float
    simulations: int
    optimizer: dict = field(default_factory=dict)
    at_bound: dict = field(default_factory=dict)

    @property
    def rms_ga_rel_pct(self) -> float:
        return float(np.sqrt(np.mean(self.table["ga_rel_pct"].to_numpy(float) ** 2)))

    @property
    def max_abs_ga_rel_pct(self) -> float:
        return float(np.max(np.abs(self.table["ga_rel_pct"].to_numpy(float))))

    def spec_overrides(self) -> dict:
        """``{"spec.<section>.<field>": value}`` columns that put the match into a plan."""
        return {f"spec.{k}": float(v) for k, v in self.values.items()}

    def misses(self, limit_pct: float = 1.0) -> pd.DataFrame:
        """Points with |Ga_REL| above ``limit_pct``."""
        t = self.table
        return t.loc[t["ga_rel_pct"].abs() > limit_pct, ["point_id", "speed_rpm", "ga_rel_pct"]]

    def summary(self) -> str:
        parts = [f"{k} = {self.values[k]:.4g} +- {self.ci95[k]:.2g} (95 %, assumed {self.noise_pct:g} % airflow "
                 f"noise; +- {self.ci95_residual[k]:.2g} from the residual variance)"
                 + (" AT ITS BOUND (interval not meaningful)" if self.at_bound.get(k) else "") for k in self.names]
        miss = self.misses()
        s = (f"Airflow match over {len(self.table)} points with {len(self.names)} global parameters: "
             + "; ".join(parts) + f". Ga_REL rms {self.rms_ga_rel_pct:.2f} %, max |Ga_REL| "
             f"{self.max_abs_ga_rel_pct:.2f} % ({self.simulations} simulations).")
        if len(miss):
            s += " Outside +-1 %: " + ", ".join(f"{r.speed_rpm:.0f} rpm {r.ga_rel_pct:+.2f} %"
                                                for r in miss.itertuples()) + "."
        else:
            s += " All points within +-1 %."
        return s


class AirflowProblem:
    """Residuals Ga_REL(x) [%] with a cache and batched evaluation of many parameter vectors."""

    def __init__(self, meas, evaluate, params):
        self.meas = meas.reset_index(drop=True)
        self.evaluate = evaluate
        self.params = params
        self.cache: dict[tuple, tuple[np.ndarray, pd.DataFrame]] = {}
        self.simulations = 0
        self.batch = 0

    def _key(self, x):
        return tuple(round(float(v), 10) for v in x)

    def many(self, xs):
        todo = []
        for x in xs:
            k = self._key(x)
            if k not in self.cache and k not in todo:
                todo.append(k)
        if todo:
            sets = [{p.name: v for p, v in zip(self.params, k)} for k in todo]
            plan = airflow_plan(self.meas, sets, tag=f"a{self.batch:02d}-")
            self.batch += 1
            res = self.evaluate(plan).reset_index(drop=True)
            self.simulations += len(plan)
            n = len(self.meas)
            for j, k in enumerate(todo):
                r = res.iloc[j * n:(j + 1) * n].reset_index(drop=True)
                ok = r["converged"].to_numpy(bool) & np.isfinite(r["air_mass_flow_kg_h"].to_numpy(float))
                g = ga_rel_pct(r["air_mass_flow_kg_h"].to_numpy(float), self.meas["air_mass_flow_kg_h"])
                g = np.where(ok, g, FAILED_RESIDUAL_PCT)
                self.cache[k] = (g, r)
        return [self.cache[self._key(x)][0] for x in xs]

    def _perturbed(self, x):
        x = np.asarray(x, float)
        xs, hs = [], []
        for j, p in enumerate(self.params):
            h = p.step if x[j] + p.step <= p.high else -p.step
            xp = x.copy()
            xp[j] += h
            xs.append(xp)
            hs.append(h)
        return xs, hs

    def fun(self, x):
        # speculative: the forward-difference points go into the same batch (most trial steps are
        # accepted, and then the Jacobian is needed there): one evaluate call per iteration
        return self.many([x] + self._perturbed(x)[0])[0]

    def jac(self, x):
        xs, hs = self._perturbed(x)
        r = self.many([x] + xs)
        return np.column_stack([(r[j + 1] - r[0]) / hs[j] for j in range(len(xs))])


def _grid_sets(params, grid, spec) -> list[tuple]:
    axes = []
    for p, n in zip(params, grid):
        if n <= 1:
            cur = float(spec.to_dict()[p.name.split(".")[0]][p.name.split(".")[1]]) if spec is not None else None
            axes.append([cur if cur is not None and p.low <= cur <= p.high else 0.5 * (p.low + p.high)])
        else:
            axes.append(list(np.linspace(p.low, p.high, int(n))))
    return list(itertools.product(*axes))


def _default_evaluate(spec, solver=None) -> Evaluate:
    from engine_model.sim.prepare import SolverSettings
    from engine_model.sim.simulate import simulate

    def ev(plan):
        return simulate(spec, plan, solver or SolverSettings())
    return ev


def match_airflow(meas: pd.DataFrame, evaluate: Evaluate | None = None, spec=None,
                  parameters=DEFAULT_PARAMETERS, grid=(6, 6, 1), starts: int = 2, max_nfev: int = 12,
                  noise_pct: float = AIRFLOW_NOISE_PCT) -> AirflowMatch:
    """Identify global parameters so the simulated air mass flow matches the bench (paper's Ga_REL).

    Parameters
    ----------
    meas : DataFrame
        Validated bench data (:func:`engine_model.bench.validate_bench`); all rows are used
        (airflow does not depend on the torque channel, so torque/power flags do not exclude a row).
    evaluate : callable(plan DataFrame) -> results DataFrame, optional
        Runs simulations; default in-process :func:`engine_model.simulate` with ``spec``.
    spec : EngineSpec, optional
        Base spec (default :func:`engine_model.default_spec`); used for the default
        ``evaluate`` and for the value of parameters with a grid count of 1.
    parameters : sequence of Parameter
        At most three; default :data:`DEFAULT_PARAMETERS`.
    grid : sequence of int
        Coarse-search points per parameter (1: hold at the spec value).
    starts : int
        Local least-squares runs, from the best ``starts`` grid points.
    max_nfev : int
        Iteration cap of each local run (each iteration = one batch of (p + 1) x n simulations).
    noise_pct : float
        Assumed 1-sigma airflow noise [% of reading] for the confidence intervals.

    Returns
    -------
    AirflowMatch
    """
    from scipy.optimize import least_squares

    from engine_model.spec import default_spec

    params = tuple(parameters)
    if not 1 <= len(params) <= MAX_PARAMETERS:
        raise ValueError(f"match_airflow: 1 to {MAX_PARAMETERS} global parameters allowed, got {len(params)}")
    if len(grid) != len(params):
        raise ValueError(f"match_airflow: grid has {len(grid)} entries for {len(params)} parameters")
    spec = default_spec() if spec is None else spec
    evaluate = evaluate or _default_evaluate(spec)
    meas = meas.reset_index(drop=True)
    prob = AirflowProblem(meas, evaluate, params)

    sets = _grid_sets(params, grid, spec)
    res = prob.many([np.array(s) for s in sets])
    rows = []
    for s, g in zip(sets, res):
        row = {p.name: v for p, v in zip(params, s)}
        row["rms_ga_rel_pct"] = float(np.sqrt(np.mean(g ** 2)))
        row["max_abs_ga_rel_pct"] = float(np.max(np.abs(g)))
        row.update({f"ga_rel_pct|{pid}": float(v) for pid, v in zip(meas["point_id"], g)})
        rows.append(row)
    grid_df = pd.DataFrame(rows).sort_values("rms_ga_rel_pct", kind="stable").reset_index(drop=True)

    lo = np.array([p.low for p in params])
    hi = np.array([p.high for p in params])
    best, runs = None, []
    for k in range(min(starts, len(grid_df))):
        x0 = grid_df.loc[k, [p.name for p in params]].to_numpy(float)
        x0 = np.clip(x0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
        sol = least_squares(prob.fun, x0, jac=prob.jac, bounds=(lo, hi), method="trf", max_nfev=max_nfev,
                            x_scale=np.array([p.step for p in params]), diff_step=None)
        runs.append({"start": x0.tolist(), "x": sol.x.tolist(), "cost": float(sol.cost), "nfev": int(sol.nfev),
                     "status": int(sol.status), "message": str(sol.message)})
        if best is None or sol.cost < best[0].cost:
            best = (sol, x0)
    sol, x0 = best
    x = sol.x
    g = prob.fun(x)
    J = prob.jac(x)
    n, p = len(g), len(params)
    jtj_inv = np.linalg.pinv(J.T @ J)
    cov = noise_pct ** 2 * jtj_inv
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    s2 = float(g @ g) / (n - p) if n > p else math.nan
    se_res = np.sqrt(np.clip(np.diag(s2 * jtj_inv), 0, None)) if n > p else np.full(p, math.nan)
    d = np.where(se > 0, se, np.nan)
    corr = cov / np.outer(d, d)
    r = prob.cache[prob._key(x)][1]
    table = pd.DataFrame({
        "point_id": meas["point_id"].to_numpy(), "speed_rpm": meas["speed_rpm"].to_numpy(float),
        "throttle_pct": meas["throttle_pct"].to_numpy(float),
        "air_mass_flow_kg_h_meas": meas["air_mass_flow_kg_h"].to_numpy(float),
        "air_mass_flow_kg_h_sim": r["air_mass_flow_kg_h"].to_numpy(float),
        "ga_rel_pct": ga_rel_pct(r["air_mass_flow_kg_h"].to_numpy(float), meas["air_mass_flow_kg_h"]),
        "vol_eff_sim": r["vol_eff"].to_numpy(float),
        "converged": r["converged"].to_numpy(bool), "status": r["status"].astype(str).to_numpy(),
    })
    names = tuple(q.name for q in params)
    return AirflowMatch(
        names=names, values=dict(zip(names, map(float, x))), start=dict(zip(names, map(float, x0))),
        stderr=dict(zip(names, map(float, se))), ci95=dict(zip(names, map(float, 1.96 * se))),
        ci95_residual=dict(zip(names, map(float, 1.96 * se_res))), correlation=np.round(corr, 4).tolist(),
        table=table, grid=grid_df, noise_pct=noise_pct, simulations=prob.simulations,
        optimizer={"runs": runs, "jacobian_pct_per_unit": J.tolist()},
        at_bound={q.name: bool(min(v - q.low, q.high - v) < 0.01 * (q.high - q.low)) for q, v in zip(params, x)})
