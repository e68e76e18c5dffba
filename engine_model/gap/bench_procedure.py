"""How the bench is run for the gap diagnosis: the solver both sides use, and the operator's knock back-off.

Shared by the benchmark (:mod:`engine_model.gap.benchmark`) and the discrimination design
(:mod:`engine_model.gap.design`).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import pandas as pd

from engine_model import priors
from engine_model.sim.prepare import SolverSettings

__all__ = ["BENCH_SOLVER", "LINEARISATION_TOLERANCE", "BENCH_BACKOFF_DEG", "BENCH_BACKOFF_STEPS", "knock_backoff", "backoff_id",
           "measure_with_backoff"]


#: Cycle-convergence tolerance of every simulation the diagnosis linearises [-].  The Jacobian is a finite
#: difference of converged cycles, so the cycle's distance from the periodic solution must sit well below an
#: effect's size: at the default 1e-3 the same bench case, compiled for two CPUs (FMA on / off), gave torques
#: 0.07 % apart and Jacobian entries up to 0.27 sigma apart, and on a 12-point benchmark the top-1 rates moved
#: by up to 55 points between the two builds (40 seeds); at 1e-4 they agreed within a few points
#: (docs/testing.md, "Solver noise").
LINEARISATION_TOLERANCE = 1e-4

#: Solver of the benchmark's truth and model (the same for both, so the comparison is about physics, not
#: discretisation; 1 deg steps are 2x cheaper than 0.5 deg and change outputs < 1 %).
BENCH_SOLVER = SolverSettings(step_deg=1.0, tolerance=LINEARISATION_TOLERANCE)


def knock_backoff(ops: pd.DataFrame, spark_top: np.ndarray, ev: Callable, knock_target: float,
                   retards: Sequence[float]) -> np.ndarray:
    """Retard [deg] from ``spark_top`` an operator backs off to where the model (prior burn) predicts no knock."""
    frames = []
    for k, ret in enumerate(retards):
        p = priors.with_combustion(ops.assign(spark_deg_btdc=spark_top - ret))
        p["point_id"] = p["point_id"].astype(str) + f"#r{k}"
        frames.append(p)
    res = ev(pd.concat(frames, ignore_index=True))
    ki = pd.to_numeric(res["knock_index"], errors="coerce").to_numpy(float).reshape(len(retards), len(ops))
    chosen = np.full(len(ops), float(retards[-1]))
    for i in range(len(ops)):
        okk = np.flatnonzero(ki[:, i] < knock_target)
        if okk.size:
            chosen[i] = retards[int(okk[0])]
    return chosen


#: Operator's knock back-off on the bench: a point that knocks is re-run this much later [deg CA], at most
#: :data:`BENCH_BACKOFF_STEPS` times (the plan's own back-off steps of 4 deg; the paper's sweeps stop "at
#: MBT or knock" [P]).  Without it the truth bench lost 7 of the 32 points (all below 7800 rpm, where
#: blow-by, knock retard and the combustion losses differ most from a driveline loss) to knock aborts.
BENCH_BACKOFF_DEG = 4.0


BENCH_BACKOFF_STEPS = 3


def backoff_id(point_id: str, retard_deg: float) -> str:
    """Point id of a plan point re-run ``retard_deg`` later on the bench (``'<id>~r<deg>'``)."""
    return f"{point_id}~r{retard_deg:g}"


def measure_with_backoff(bench, plan: pd.DataFrame, evaluate: Callable, step_deg: float = BENCH_BACKOFF_DEG,
                         max_steps: int = BENCH_BACKOFF_STEPS) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Run ``plan`` on ``bench`` as an operator does: a point aborted for knock is re-run ``step_deg`` later.

    The model-based back-off of :func:`benchmark_plan` cannot know the engine's real knock limit; on the
    bench the operator retards a knocking point until it runs (at most ``max_steps`` times) and logs the
    spark it ran at.  A point that still knocks stays flagged (``knock_abort``).

    Parameters
    ----------
    bench : VirtualBench
        Anything with ``measure(plan, evaluate)``.
    plan : DataFrame
        Needs ``point_id`` and ``spark_deg_btdc``.
    evaluate : callable

    Returns
    -------
    plan_run : DataFrame
        The plan as run: backed-off points with the later spark and the id :func:`backoff_id`, and
        ``bench_backoff_deg`` (0 where the plan's spark ran).
    measured : DataFrame
        The bench rows, same order and ids as ``plan_run``.
    """
    run = plan.reset_index(drop=True).copy()
    run["point_id"] = run["point_id"].astype(str)
    orig_ids = run["point_id"].to_numpy().copy()
    run["bench_backoff_deg"] = 0.0
    meas = bench.measure(run, evaluate).reset_index(drop=True)
    for k in range(1, max_steps + 1):
        knock = (meas["status"].astype(str) == "knock_abort").to_numpy()
        if not knock.any():
            break
        idx = np.flatnonzero(knock)
        run.loc[idx, "spark_deg_btdc"] = run.loc[idx, "spark_deg_btdc"].to_numpy(float) - step_deg
        run.loc[idx, "bench_backoff_deg"] = k * step_deg
        run.loc[idx, "point_id"] = [backoff_id(orig_ids[i], k * step_deg) for i in idx]
        redo = bench.measure(run.loc[idx].reset_index(drop=True), evaluate)
        redo.index = idx
        meas = meas.drop(index=idx)
        meas = pd.concat([meas, redo]).sort_index()
        meas = meas.reset_index(drop=True)
    return run, meas
