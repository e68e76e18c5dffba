"""Plans that need the model: quick evaluation, spark sweeps as run on the bench, feasibility screening.

References
----------
.. [P] Mrda et al., MVM2012-024 (Figure 1 zones, the bench's spark-sweep procedure).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import pandas as pd

from engine_model.doe.designs import PHYSICAL_RANGES, check_range, finish_plan
from engine_model.priors import MBT_CA50_DEG_ATDC, MIN_BMEP_BAR, lambda_target, spark_estimate, with_combustion
from engine_model.sim.prepare import SolverSettings
from engine_model.spec import EngineSpec, default_spec

__all__ = ["QUICK_SOLVER", "quick_evaluate", "spark_sweeps", "feasibility"]

#: Cheap cycle-solver settings for DOE screening: 1 deg steps, 1 % cycle-to-cycle
#: tolerance, at most 30 cycles.  Measured on the default R6 spec over a 4 x 4
#: throttle x speed grid of cold-started points: 140 ms per point against 530 ms
#: with the default ``SolverSettings()`` (3.7x cheaper; ~80 ms per point over a
#: 99-point grid); against the default settings brake torque agrees within
#: 1.5 % (7 % at near-zero-BMEP points), BMEP within 0.11 bar, knock index
#: within 0.08.  Good enough to place a plan, not for identification.
QUICK_SOLVER = SolverSettings(step_deg=1.0, tolerance=1e-2, max_cycles=30)


def quick_evaluate(points: pd.DataFrame, spec: EngineSpec | None = None,
                   solver: SolverSettings = QUICK_SOLVER, workers: int = 1) -> pd.DataFrame:
    """Cheap cycle-model evaluation of plan points (the DOE tools' default ``evaluate``).

    Parameters
    ----------
    points : DataFrame
        Plan rows; missing Wiebe columns are filled by :func:`with_combustion`.
    spec : EngineSpec, optional
        Default :func:`engine_model.default_spec`.
    solver : SolverSettings
        Default :data:`QUICK_SOLVER` (3-4x cheaper than the default).
    workers : int
        Processes to share the rows among (:func:`engine_model.simulate`).

    Returns
    -------
    DataFrame
        :func:`engine_model.simulate` output, one row per input row.  Rows whose
        quick run failed (the 1 deg step is unstable below ~10 % throttle) are
        re-run once at 0.5 deg; rows that fail again keep ``status`` 'failed: ...'
        and NaN results.
    """
    from engine_model.sim.simulate import simulate  # late import: keeps `import engine_model.doe` light

    spec = default_spec() if spec is None else spec
    pts = with_combustion(points).reset_index(drop=True)
    res = simulate(spec, pts, solver=solver, workers=workers)
    failed = res["status"].astype(str).str.startswith("failed").to_numpy()
    if failed.any() and solver.step_deg > 0.5:
        finer = SolverSettings(step_deg=0.5, tolerance=solver.tolerance, max_cycles=solver.max_cycles,
                               min_cycles=solver.min_cycles, accelerate=solver.accelerate)
        redo = simulate(spec, pts[failed].reset_index(drop=True), solver=finer)
        redo.index = np.flatnonzero(failed)
        res.loc[redo.index, redo.columns] = redo
    return res


def _evaluate(points: pd.DataFrame, spec, evaluate) -> pd.DataFrame:
    if evaluate is None:
        res = quick_evaluate(points, spec)
    else:
        res = evaluate(points.reset_index(drop=True))
    if len(res) != len(points):
        raise ValueError(f"evaluate returned {len(res)} rows for {len(points)} points")
    return res.reset_index(drop=True)


def spark_sweeps(pairs: Sequence[tuple[float, float]], spec: EngineSpec | None = None, step_deg: float = 2.0,
                 retard_deg: float = 12.0, evaluate: Callable[[pd.DataFrame], pd.DataFrame] | None = None,
                 max_steps: int = 12, knock_margin: float = 0.0) -> pd.DataFrame:
    """Spark sweeps as run on the bench: from a retarded start, advance to MBT or knock.

    Parameters
    ----------
    pairs : sequence of (throttle_pct, speed_rpm)
        Operating points [%, rpm]; one sweep each, in the given order.
    spec : EngineSpec, optional
        Used by the default evaluator.
    step_deg : float
        Advance per step [deg CA], > 0.
    retard_deg : float
        Start retard from :func:`spark_estimate` [deg CA]; the paper starts
        10-15 deg retarded [P].
    evaluate : callable(points DataFrame) -> DataFrame, optional
        Model of the engine: returns one row per point (same order) with
        ``brake_torque_nm``, ``knock_index`` and ``ca50_deg_atdc``.  Default
        :func:`quick_evaluate` (quick solver settings, combustion from
        :func:`combustion_estimate`).
    max_steps : int
        Maximum points per sweep.
    knock_margin : float
        Knock stop at ``knock_index >= 1 - knock_margin`` [-].

    Returns
    -------
    DataFrame
        The steps actually planned: ``point_id`` 'sw-001-00'..., plan columns,
        ``design`` = 'spark_sweep', ``sweep_id`` (1...), ``step`` (0...),
        ``stop_reason`` on each sweep's last row ('' elsewhere) and the
        evaluated ``brake_torque_est_nm``, ``knock_index_est``,
        ``ca50_est_deg_atdc``.  Spark rises strictly within a sweep.

    Notes
    -----
    A sweep stops at the first step where (checked in this order)
    'knock': knock_index >= 1 - knock_margin (the knocking step is the limit
    point and is kept: with a margin it is a safe approach to it);
    'failed': the model gave no torque;
    'mbt': torque did not increase over the previous step, or CA50 <= 8 deg
    ATDC (the paper's MBT window is CA50 = 8-10 deg ATDC);
    'max_steps': ``max_steps`` points or the 90 deg BTDC spark limit reached.
    The model is run on a pair's whole candidate sweep in one call (consecutive
    rows reuse the converged gas-exchange state, cheaper than point by point);
    only the steps up to the stop are planned.
    """
    if not step_deg > 0:
        raise ValueError(f"spark_sweeps: step_deg = {step_deg!r} must be > 0")
    if not 0 <= retard_deg <= 40:
        raise ValueError(f"spark_sweeps: retard_deg = {retard_deg!r} must lie in [0, 40]")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 1):
        raise ValueError(f"spark_sweeps: max_steps = {max_steps!r} must be a positive integer")
    if not 0 <= knock_margin < 1:
        raise ValueError(f"spark_sweeps: knock_margin = {knock_margin!r} must lie in [0, 1)")
    pairs = [tuple(map(float, p)) for p in pairs]
    if not pairs or any(len(p) != 2 for p in pairs):
        raise ValueError("spark_sweeps: pairs must be a non-empty sequence of (throttle_pct, speed_rpm)")
    for thr, spd in pairs:  # all checked before the first (costly) evaluation
        check_range("throttle_pct", thr, thr, "spark_sweeps")
        check_range("speed_rpm", spd, spd, "spark_sweeps")
    frames = []
    for sid, (thr, spd) in enumerate(pairs, start=1):
        start = spark_estimate(spd, thr) - retard_deg
        spark = start + step_deg * np.arange(max_steps)
        spark = spark[spark <= PHYSICAL_RANGES["spark_deg_btdc"][1]]
        if spark.size == 0:
            raise ValueError(f"spark_sweeps: start advance {start:.1f} deg BTDC at {thr:g} %, {spd:g} rpm "
                             "is past the 90 deg limit")
        cand = pd.DataFrame({"speed_rpm": spd, "throttle_pct": thr, "spark_deg_btdc": spark,
                             "lambda": lambda_target(thr)})
        res = _evaluate(cand, spec, evaluate)
        torque = res["brake_torque_nm"].to_numpy(float)
        knock = res["knock_index"].to_numpy(float)
        ca50 = res["ca50_deg_atdc"].to_numpy(float)
        last, reason = len(cand) - 1, "max_steps"
        for k in range(len(cand)):
            if knock[k] >= 1.0 - knock_margin:
                last, reason = k, "knock"
            elif not np.isfinite(torque[k]):
                last, reason = k, "failed"
            elif (k > 0 and torque[k] <= torque[k - 1]) or ca50[k] <= MBT_CA50_DEG_ATDC:
                last, reason = k, "mbt"
            else:
                continue
            break
        sw = cand.iloc[: last + 1].copy()
        sw["sweep_id"] = sid
        sw["step"] = np.arange(last + 1)
        sw["stop_reason"] = [""] * last + [reason]
        sw["brake_torque_est_nm"] = torque[: last + 1]
        sw["knock_index_est"] = knock[: last + 1]
        sw["ca50_est_deg_atdc"] = ca50[: last + 1]
        frames.append(sw)
    df = pd.concat(frames, ignore_index=True)
    plan = finish_plan(df, "sw", "spark_sweep",
                   {"generator": "spark_sweeps", "seed": None, "step_deg": step_deg,
                    "retard_deg": retard_deg, "max_steps": int(max_steps), "knock_margin": knock_margin})
    plan["point_id"] = [f"sw-{s:03d}-{k:02d}" for s, k in zip(plan["sweep_id"], plan["step"])]
    return plan


def feasibility(plan: pd.DataFrame, spec: EngineSpec | None = None,
                evaluate: Callable[[pd.DataFrame], pd.DataFrame] | None = None, knock_margin: float = 0.0,
                min_bmep_bar: float = MIN_BMEP_BAR, drop: bool = False) -> pd.DataFrame:
    """Flag (or drop) the points the bench cannot hold: the paper's Figure 1 zones.

    Parameters
    ----------
    plan : DataFrame
        A plan (its own spark and lambda are used).
    spec : EngineSpec, optional
        Used by the default evaluator.
    evaluate : callable(points DataFrame) -> DataFrame, optional
        Returns ``knock_index`` and ``bmep_bar`` per point (same order).
        Default :func:`quick_evaluate` with the plan's Wiebe columns if present,
        else :func:`combustion_estimate`.
    knock_margin : float
        Knock-limited when ``knock_index >= 1 - knock_margin`` [-].
    min_bmep_bar : float
        Near-zero-BMEP limit [bar]; default :data:`MIN_BMEP_BAR` = 1 bar.
    drop : bool
        False: keep every row and flag it; True: keep only feasible rows.

    Returns
    -------
    DataFrame
        The plan plus ``feasible`` (bool), ``infeasible_reason``
        ('knock-limited': zone 1, knock at the plan's spark; 'near-zero BMEP':
        zone 2; 'evaluation failed': the model gave no answer; '' if
        feasible), ``knock_index_est`` [-] and ``bmep_est_bar`` [bar].
        ``attrs['n_feasible']``, ``attrs['n_infeasible']`` count the input
        rows, ``attrs['n_dropped']`` the rows removed.

    Notes
    -----
    With spark at :func:`spark_estimate` (the MBT prior), 'knock-limited' means
    MBT cannot be reached; whether a retarded spark runs clean is what
    :func:`spark_sweeps` finds out.  A point that both knocks and has near-zero
    BMEP is reported as knock-limited (engine damage is the first concern).
    """
    if not 0 <= knock_margin < 1:
        raise ValueError(f"feasibility: knock_margin = {knock_margin!r} must lie in [0, 1)")
    res = _evaluate(plan, spec, evaluate)
    knock = res["knock_index"].to_numpy(float)
    bmep = res["bmep_bar"].to_numpy(float)
    reason = np.full(len(plan), "", dtype=object)
    reason[bmep < min_bmep_bar] = "near-zero BMEP"
    reason[knock >= 1.0 - knock_margin] = "knock-limited"
    reason[~(np.isfinite(knock) & np.isfinite(bmep))] = "evaluation failed"
    out = plan.reset_index(drop=True).copy()
    out["feasible"] = reason == ""
    out["infeasible_reason"] = reason.astype(str)
    out["knock_index_est"] = knock
    out["bmep_est_bar"] = bmep
    n_ok = int(out["feasible"].sum())
    attrs = dict(plan.attrs)
    attrs.update(n_feasible=n_ok, n_infeasible=len(out) - n_ok, knock_margin=knock_margin,
                 min_bmep_bar=min_bmep_bar)
    if drop:
        out = out[out["feasible"]].reset_index(drop=True)
    attrs["n_dropped"] = len(plan) - len(out)
    out.attrs = attrs
    return out
