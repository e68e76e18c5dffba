"""The virtual-bench campaign: plan, measure, identify, fit the global model, and score it against the truth.

    screened D-optimal operating points -> spark sweep at each -> virtual bench measures them
      -> joint spark-sweep identification of (BDUR10-90, m) per operating point
      -> global map-wide model fitted on the identified points
      -> scored against the bench's hidden burn law: at the identified points, on the runnable hold-out grid
      -> learning curve of DOE designs at the identification error measured here

This is the study a team would run on a real bench with the plan of
:func:`engine_model.calibration.sweeps.choose_operating_points`; on the
virtual bench the hidden burn law is known, so every step can be scored.  It
needs two kinds of simulation: the bench's own (its truth engine, through
:meth:`VirtualBench.measure`) and the identification sweeps of the model; both
go through ``make_evaluate(label, solver)``, which returns an ``evaluate(plan)
-> results`` callable (in-process :func:`engine_model.simulate` by default;
the flows route it to Dask).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pandas as pd

from engine_model import priors
from engine_model.bench.burnlaw import BurnLaw
from engine_model.bench.virtual import NoiseModel, VirtualBench
from engine_model.calibration.identify import BDUR_RANGE_DEG, identification_plan
from engine_model.calibration.sweeps import choose_operating_points, identify_sweeps, sweep_plan
from engine_model.doe import QUICK_SOLVER, feasibility
from engine_model.globalmodel import learning
from engine_model.globalmodel.mapmodel import MapModel, fit_map_model
from engine_model.sim.prepare import SolverSettings
from engine_model.spec import EngineSpec

__all__ = ["CampaignSettings", "CampaignResult", "run_campaign", "identification_bdur_nodes", "identification_error",
           "holdout_error", "MIN_IDENTIFIED", "measure_with_resweeps", "MAX_RESWEEPS"]

#: Fewest identified operating points a global model is fitted on (one spark sweep each).
MIN_IDENTIFIED = 6

#: Retarded repeats of a sweep that knocked before it had three runnable sparks (each moves the whole sweep
#: later by its span plus one step, so its most advanced spark sits a step behind the most retarded one that
#: knocked).  Two repeats reach 50 deg behind the MBT prior with the default offsets.
MAX_RESWEEPS = 2


@dataclass(frozen=True)
class CampaignSettings:
    """How the virtual-bench campaign runs.

    Attributes
    ----------
    eta_trans : float
        Transmission efficiency [-] of the virtual bench and of the identification.
    step_deg : float
        Crank-angle step of the bench measurements and the identification [deg].
    doe_points : int
        Operating points (one spark sweep each) over throttle x speed from screened candidates: D-optimal for a
        quadratic surface, the last ``doe_fill_points`` of them where that design leaves the largest gaps.
    doe_fill_points : int
        Of ``doe_points``, the space-filling ones (:func:`engine_model.doe.maximin_augment`); 0 by default
        (4 of 20 were tried: docs/sections/globalmodel.md).
    spark_offsets : tuple of float
        Sparks of each sweep relative to the MBT prior [deg].
    doe_bounds : dict, optional
        Throttle / speed bounds of the candidate operating points.
    doe_seed : int
        Seed of the design and of the bench's noise.
    ident_grid : (int, int)
        BDUR10-90 x m grid of the identification sweep at each bench point over the paper's plane, the
        BDUR10-90 axis extended downward for fast low-speed burns (:func:`identification_bdur_nodes`).
    learning_sizes, learning_seeds : tuple of int
        Learning curve: design sizes and seeds.
    holdout : dict
        Keyword arguments of :func:`engine_model.globalmodel.learning.holdout_grid`.
    """

    eta_trans: float = 0.95
    step_deg: float = 0.5
    doe_points: int = 16
    doe_fill_points: int = 0
    spark_offsets: tuple = (-15, -10, -5, 0, 5)
    doe_bounds: dict = field(default_factory=dict)
    doe_seed: int = 0
    ident_grid: tuple = (6, 6)
    learning_sizes: tuple = (12, 16, 24, 32, 48, 64)
    learning_seeds: tuple = (0, 1, 2)
    holdout: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.doe_points < MIN_IDENTIFIED:
            raise ValueError(f"CampaignSettings.doe_points = {self.doe_points!r}: at least {MIN_IDENTIFIED} "
                             "operating points are needed (one spark sweep each)")
        fill = self.doe_fill_points
        if isinstance(fill, bool) or not isinstance(fill, (int, np.integer)) or not 0 <= fill <= self.doe_points - 6:
            raise ValueError(f"CampaignSettings.doe_fill_points = {fill!r} must be an integer in [0, doe_points - 6 "
                             f"= {self.doe_points - 6}] (the D-optimal part needs >= 6 points)")
        if not 0.5 <= self.eta_trans <= 1.0:
            raise ValueError(f"CampaignSettings.eta_trans = {self.eta_trans!r} must lie in [0.5, 1]")
        if isinstance(self.doe_seed, bool) or not isinstance(self.doe_seed, (int, np.integer)) or self.doe_seed < 0:
            raise ValueError(f"CampaignSettings.doe_seed = {self.doe_seed!r} must be an integer >= 0")


@dataclass
class CampaignResult:
    """Everything the campaign produced (tables are DataFrames; scores are plain dicts)."""

    operating_points: pd.DataFrame
    plan: pd.DataFrame
    measured: pd.DataFrame
    identified: pd.DataFrame
    identification_error: dict
    fallback: str
    model: MapModel
    holdout_status: pd.DataFrame
    holdout_error: dict
    learning_curve: pd.DataFrame
    learning_summary: pd.DataFrame
    noise_used: tuple[float, float]

    def lines(self, settings: CampaignSettings) -> list[str]:
        """A short account in words (report and console)."""
        meas, ide, held = self.measured, self.identification_error, self.holdout_error
        n_re = int(self.plan["op_id"].nunique() - len(self.operating_points)) if "op_id" in self.plan else 0
        again = f" (with {n_re} sweep(s) repeated retarded after knocking)" if n_re else ""
        fill = f", {settings.doe_fill_points} of them space-filling" if settings.doe_fill_points else ""
        out = [f"Virtual bench: {len(self.operating_points)} operating points (D-optimal over throttle x speed from "
               f"screened candidates{fill}, seed {settings.doe_seed}) x spark offsets "
               f"{list(settings.spark_offsets)} deg = {len(meas)} bench points{again}; status "
               + ", ".join(f"{k} {n}" for k, n in meas["status"].value_counts().items()) + ".",
               f"Joint spark-sweep identification at {ide['points']} of {ide['of']} operating points against the "
               f"hidden law: BDUR10-90 RMSE {ide['bdur_rmse_deg']:.2f} deg (bias {ide['bdur_bias_deg']:+.2f}), "
               f"m RMSE {ide['m_rmse']:.2f} (bias {ide['m_bias']:+.2f}).",
               "Global model (chosen per output by K-fold CV: "
               + ", ".join(f"{k} {v}" for k, v in dict(self.model.chosen_).items())
               + f"); error against the hidden law "
               f"on the {held['points']} runnable points of the {held['of']}-point hold-out grid: BDUR10-90 "
               f"{held['bdur_rmse_deg']:.2f} deg, m {held['m_rmse']:.2f}."]
        if self.fallback:
            out.append(self.fallback)
        sb, sm = self.noise_used
        out.append(f"Learning curve: identification noise {sb:.2f} deg / {sm:.2f} (as measured above), designs "
                   "against a full grid.")
        return out


def _in_process(spec: EngineSpec):
    from engine_model.sim.simulate import simulate

    def make(label: str, solver: SolverSettings):
        return lambda plan: simulate(spec, plan, solver)
    return make


def identification_error(ident: pd.DataFrame, law: BurnLaw) -> tuple[pd.DataFrame, dict]:
    """Add the hidden law's (BDUR10-90, m) to an identification table and score the identified points.

    Returns the table with ``bdur_10_90_deg_truth, wiebe_m_truth`` and ``{points, of, bdur_rmse_deg,
    bdur_bias_deg, m_rmse, m_bias}`` over the points that met the identification's tolerances.
    """
    ident = ident.copy()
    ran = ident[np.isfinite(ident["bdur_10_90_deg"].to_numpy(float))].index
    truth = law.predict(ident.loc[ran, ["throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda"]])
    ident["bdur_10_90_deg_truth"] = np.nan
    ident["wiebe_m_truth"] = np.nan
    ident.loc[ran, "bdur_10_90_deg_truth"] = truth["bdur_10_90_deg"].to_numpy()
    ident.loc[ran, "wiebe_m_truth"] = truth["wiebe_m"].to_numpy()
    good = ident[ident["fit_ok"].astype(bool)] if "fit_ok" in ident.columns else ident
    err_b = good["bdur_10_90_deg"] - good["bdur_10_90_deg_truth"]
    err_m = good["wiebe_m"] - good["wiebe_m_truth"]
    return ident, {"points": int(len(good)), "of": int(len(ident)),
                   "bdur_rmse_deg": float(np.sqrt(np.mean(err_b ** 2))), "bdur_bias_deg": float(err_b.mean()),
                   "m_rmse": float(np.sqrt(np.mean(err_m ** 2))), "m_bias": float(err_m.mean())}


#: Lowest BDUR10-90 node of an extended identification plane [deg] [A]: far below any burn of this engine
#: (the prior gives 11.5 deg at 1000 rpm); it only bounds the extension.
IDENT_BDUR_FLOOR_DEG = 5.0


def identification_bdur_nodes(speed_rpm: float, n_bdur: int) -> tuple[float, int]:
    """Lower edge [deg] and node count of the BDUR10-90 axis that identifies a sweep at ``speed_rpm``.

    The paper's plane (:data:`engine_model.calibration.identify.BDUR_RANGE_DEG`, 20-50 deg) with ``n_bdur``
    nodes was set for 8000-11000 rpm.  Burns are shorter in crank degrees at low speed (angle ~ N^(1/3),
    Hires et al., Heywood sec. 9.3): at 3000 rpm the prior expects ~17 deg, below the plane, and an
    estimate pinned to the plane's edge is no estimate.  So the axis is extended downward by whole steps of
    the paper's grid (its nodes stay where they were) until the prior's WOT burn angle at ``speed_rpm``
    (before the prior's clip) lies at least one step above the lower edge, not below
    :data:`IDENT_BDUR_FLOOR_DEG`.  Returns ``(lower edge, node count)``; the upper edge stays 50 deg.
    """
    if not (speed_rpm > 0 and math.isfinite(speed_rpm)):
        raise ValueError(f"identification_bdur_nodes: speed_rpm = {speed_rpm!r} must be a finite speed > 0")
    if int(n_bdur) < 3:
        raise ValueError(f"identification_bdur_nodes: n_bdur = {n_bdur!r}, need >= 3 nodes")
    lo, hi = BDUR_RANGE_DEG
    step = (hi - lo) / (int(n_bdur) - 1)
    prior = priors.BDUR_REF_DEG * (speed_rpm / priors.SPEED_REF_RPM) ** priors.SPEED_EXPONENT
    k = 0
    while prior - (lo - k * step) < step and lo - (k + 1) * step >= IDENT_BDUR_FLOOR_DEG:
        k += 1
    return lo - k * step, int(n_bdur) + k


def campaign_identification_plan(ok: pd.DataFrame, n_bdur: int, n_m: int) -> pd.DataFrame:
    """:func:`~engine_model.calibration.identify.identification_plan` of the runnable sweep points, each sweep
    on the BDUR10-90 axis of :func:`identification_bdur_nodes` for its speed (m over the paper's range)."""
    frames = []
    for speed, g in ok.groupby("speed_rpm", sort=True):
        lo, n = identification_bdur_nodes(float(speed), n_bdur)
        frames.append(identification_plan(g, {}, n, n_m, bdur_range=(lo, BDUR_RANGE_DEG[1])))
    return pd.concat(frames, ignore_index=True)


def training_points(ident: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    """The identified points a global model is fitted on, and a note when tolerance misses had to be used.

    Points within the identification's tolerances (``fit_ok``) are used; with fewer than
    :data:`MIN_IDENTIFIED` of them, every finite estimate is (flagged in the note).  Fewer than that in
    all is a RuntimeError naming the counts.
    """
    good = ident[ident["fit_ok"].astype(bool)] if "fit_ok" in ident.columns else ident
    note = ""
    if len(good) < MIN_IDENTIFIED:
        finite = ident[np.isfinite(ident["bdur_10_90_deg"].to_numpy(float))]
        if len(finite) >= MIN_IDENTIFIED:
            note = (f"Only {len(good)} sweeps met the identification tolerances; the model is fitted on all "
                    f"{len(finite)} finite estimates (tolerance misses included, flagged in identified.parquet).")
            good = finite
    if len(good) < MIN_IDENTIFIED:
        raise RuntimeError(f"identification: only {len(good)} of {len(ident)} virtual-bench points were identified "
                           f"within tolerance; a map model needs >= {MIN_IDENTIFIED} (see identified.parquet)")
    return good, note


def holdout_error(model, law: BurnLaw, points: pd.DataFrame) -> dict:
    """RMS error of a combustion model against the hidden law at ``points`` (BDUR10-90 [deg], m [-])."""
    pred = model.predict(points)
    tru = law.predict(points)
    return {"points": int(len(points)),
            "bdur_rmse_deg": float(np.sqrt(np.mean((pred["bdur_10_90_deg"] - tru["bdur_10_90_deg"]) ** 2))),
            "m_rmse": float(np.sqrt(np.mean((pred["wiebe_m"] - tru["wiebe_m"]) ** 2)))}


def measure_with_resweeps(bench, plan: pd.DataFrame, evaluate: Callable,
                          max_resweeps: int = MAX_RESWEEPS) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Run spark sweeps on ``bench``; a sweep that knocked before three sparks ran is repeated retarded.

    The MBT prior the sweeps are centred on is a population guess; where the engine burns faster than it
    assumes (low speed) the whole sweep can sit past MBT and knock.  An operator then moves the sweep later
    rather than give up the operating point.  Here: an ``op_id`` with fewer than three 'ok' rows and at least
    one knock abort is re-run as a new sweep ``<op_id>r<k>`` (point ids ``<op_id>r<k>-s<j>``) with every
    spark moved later by the sweep's span plus its smallest step; at most ``max_resweeps`` times.  The
    knocking sweep stays in the result (its rows are measurements: nothing is dropped); identification sees
    the two as separate sweeps, so an over-advanced point that happened to run past the knocking ones never
    sits inside the retarded sweep's torque curve.

    Parameters
    ----------
    bench : VirtualBench
        Anything with ``measure(plan, evaluate)``.
    plan : DataFrame
        :func:`engine_model.calibration.sweeps.sweep_plan` output (``op_id``, ``point_id``, ``spark_deg_btdc``,
        ``spark_offset_deg``, ``run_order``).
    evaluate : callable

    Returns
    -------
    plan_run, measured : DataFrame
        The plan as run (original sweeps then the repeats, ``resweep`` = 0, 1, ...) and the bench rows in
        the same order.
    """
    run = plan.reset_index(drop=True).copy()
    run["resweep"] = 0
    meas = bench.measure(run, evaluate=evaluate).reset_index(drop=True)
    todo = run
    for k in range(1, max_resweeps + 1):
        st = meas.loc[meas["op_id"].isin(todo["op_id"])]
        n_ok = st["status"].eq("ok").groupby(st["op_id"]).sum()
        n_kn = st["status"].eq("knock_abort").groupby(st["op_id"]).sum()
        again = [o for o in todo["op_id"].unique() if n_ok.get(o, 0) < 3 and n_kn.get(o, 0) > 0]
        if not again:
            break
        rows = []
        for oid in again:
            g = todo[todo["op_id"] == oid].sort_values("spark_deg_btdc")
            sp = g["spark_deg_btdc"].to_numpy(float)
            shift = float(sp[-1] - sp[0]) + float(np.min(np.diff(sp)))
            base = oid.rsplit("r", 1)[0] if k > 1 else oid
            new = g.copy()
            new["op_id"] = f"{base}r{k}"
            new["point_id"] = [f"{base}r{k}-s{j}" for j in range(len(new))]
            new["spark_deg_btdc"] = sp - shift
            if "spark_offset_deg" in new.columns:
                new["spark_offset_deg"] = new["spark_offset_deg"].to_numpy(float) - shift
            new["resweep"] = k
            rows.append(new)
        todo = pd.concat(rows, ignore_index=True)
        todo["run_order"] = np.arange(len(run) + 1, len(run) + len(todo) + 1)
        redo = bench.measure(todo, evaluate=evaluate).reset_index(drop=True)
        run = pd.concat([run, todo], ignore_index=True)
        meas = pd.concat([meas, redo], ignore_index=True)
    return run, meas


def run_campaign(spec: EngineSpec, settings: CampaignSettings | None = None,
                 make_evaluate: Callable[[str, SolverSettings], Callable] | None = None,
                 law: BurnLaw | None = None) -> CampaignResult:
    """Run the campaign on the virtual bench built on ``spec`` (the calibrated engine's spec).

    Parameters
    ----------
    spec : EngineSpec
        Engine of the truth and of the identification (the airflow-matched spec).
    settings : CampaignSettings, optional
    make_evaluate : callable(label, SolverSettings) -> evaluate, optional
        Factory of ``evaluate(plan) -> results`` callables, one per kind of batch ('feasibility',
        'vbench', 'ident', 'holdout'); default in-process simulation.
    law : BurnLaw, optional
        The bench's hidden burn law (default :class:`BurnLaw` ()).

    Returns
    -------
    CampaignResult
    """
    st = CampaignSettings() if settings is None else settings
    make = _in_process(spec) if make_evaluate is None else make_evaluate
    law = BurnLaw() if law is None else law
    bench = VirtualBench(spec=spec, law=law, eta_trans=st.eta_trans, seed=st.doe_seed)
    quick = SolverSettings(step_deg=max(QUICK_SOLVER.step_deg, st.step_deg), tolerance=QUICK_SOLVER.tolerance,
                           max_cycles=QUICK_SOLVER.max_cycles)
    full = SolverSettings(step_deg=st.step_deg)
    ev_feas = make("feasibility", quick)

    def feasible(points: pd.DataFrame) -> np.ndarray:
        # like a real first session: a quick model check at the sweep's most retarded spark screens the
        # candidate points for the paper's two infeasible zones, so the design wastes no bench time on them
        pts = points.reset_index(drop=True).copy()
        pts["spark_deg_btdc"] = pts["spark_deg_btdc"] + min(st.spark_offsets)
        pts = priors.with_combustion(pts)
        if "point_id" not in pts.columns:
            pts["point_id"] = [f"c{i:05d}" for i in range(len(pts))]
        return feasibility(pts, evaluate=ev_feas)["feasible"].to_numpy(bool)

    ops = choose_operating_points(st.doe_points, feasible=feasible, seed=st.doe_seed,
                                  bounds=dict(st.doe_bounds) if st.doe_bounds else None, fill=st.doe_fill_points)
    plan, meas = measure_with_resweeps(bench, sweep_plan(ops, offsets=st.spark_offsets), make("vbench", full))
    ok = meas[meas["status"] == "ok"].reset_index(drop=True)
    if len(ok) < MIN_IDENTIFIED:
        raise RuntimeError(f"virtual bench: only {len(ok)} of {len(meas)} DOE points could be run "
                           f"({meas['status'].value_counts().to_dict()}); too few for a map model")
    ok["at_mbt"] = False
    n_b, n_m = st.ident_grid
    ident = identify_sweeps(meas, make("ident", full)(campaign_identification_plan(ok, n_b, n_m)),
                            eta_trans=st.eta_trans)
    ident, id_err = identification_error(ident, law)
    good, note = training_points(ident)
    model = fit_map_model(good, spec=spec)

    # where can the truth engine run?  The hold-out grid once through the noise-free virtual bench (quick
    # solver); the map is scored there, and the learning curve loses the points the bench would abort
    test = learning.holdout_grid(**st.holdout)
    test["point_id"] = [f"h{i:04d}" for i in range(len(test))]
    quiet = dataclasses.replace(bench, noise=NoiseModel.none())
    hold = quiet.measure(test, evaluate=make("holdout", quick))
    runnable = (hold["status"] == "ok").to_numpy()
    feas = learning.nearest_feasible(test, runnable)
    test_ok = test[runnable].reset_index(drop=True)
    held = {**holdout_error(model, law, test_ok), "of": int(len(test))}

    # learning curve: identification error as measured above, designs against a full grid
    sb, sm = max(id_err["bdur_rmse_deg"], 0.1), max(id_err["m_rmse"], 0.02)
    if not (math.isfinite(sb) and math.isfinite(sm)):
        raise RuntimeError(f"identification error not finite ({id_err}); no learning curve")
    curve = learning.learning_curve(None, law, sizes=st.learning_sizes, seeds=st.learning_seeds,
                                    designs=("grid", "d_optimal_feasible", "sobol"), test_points=test_ok,
                                    feasible=feas,
                                    identify_seeded=lambda s: learning.noisy_truth(law, sb, sm, seed=s,
                                                                                   feasible=feas))
    return CampaignResult(operating_points=ops, plan=plan, measured=meas, identified=ident,
                          identification_error=id_err, fallback=note, model=model, holdout_status=hold,
                          holdout_error=held, learning_curve=curve, learning_summary=learning.summarise(curve),
                          noise_used=(sb, sm))
