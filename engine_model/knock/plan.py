"""Knock-onset spark sweeps for the dyno: the paper's procedure as a test plan.

At each chosen operating point the bench starts from the retarded start map and advances
the spark step by step, logging knock (0/1) at every step, and stops at the first knock
onset or when torque stops rising (MBT).  The plan lists every step a sweep may need; the
rows the bench did not reach are simply not run.  Sites are spread over speed at high load
(where the knock border lies), the most knock-prone first (lowest speed, widest throttle).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

__all__ = ["knock_sweep_plan"]


def _spread(cands: np.ndarray, k: int) -> list[int]:
    """``k`` indices of ``cands`` (rows of normalised coordinates) by greedy maximin, starting at row 0."""
    chosen = [0]
    d = np.linalg.norm(cands - cands[0], axis=1)
    while len(chosen) < min(k, len(cands)):
        i = int(np.argmax(d))
        if d[i] <= 0:
            break
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(cands - cands[i], axis=1))
    return chosen


def knock_sweep_plan(start_spark, speeds, throttles, max_points: int = 40, step_deg: float = 3.0,
                     retard_deg: float = 12.0, beyond_deg: float = 6.0, lambda_value: float = 0.9) -> pd.DataFrame:
    """Spark sweeps in the advance direction: ``start_spark(speed, throttle)`` [deg BTDC] is the map's spark.

    Each sweep runs from the map's spark minus ``retard_deg`` (the start map) to the map's spark plus
    ``beyond_deg`` in ``step_deg`` steps; as many sweeps as fit in ``max_points``, sites spread over
    ``speeds`` x ``throttles``.  Columns: ``point_id, sweep_id, step, speed_rpm, throttle_pct,
    spark_deg_btdc, lambda, knock`` (``knock`` empty: the bench fills 0/1 for the steps it runs).
    """
    speeds = np.asarray(speeds, float)
    throttles = np.asarray(throttles, float)
    if speeds.size == 0 or throttles.size == 0:
        raise ValueError("knock sweeps need at least one speed and one throttle")
    if not (0 < step_deg <= 10):
        raise ValueError(f"step_deg = {step_deg!r}: expected (0, 10] deg")
    n_steps = int(math.floor((retard_deg + beyond_deg) / step_deg + 1e-9)) + 1
    n_sweeps = max_points // n_steps
    if n_sweeps < 1:
        raise ValueError(f"{max_points} points do not hold one sweep of {n_steps} steps "
                         f"({retard_deg:g} deg retard to {beyond_deg:g} deg beyond, step {step_deg:g})")
    sites = [(n, t) for t in sorted(throttles, reverse=True) for n in sorted(speeds)]
    norm_xy = np.array([[(n - speeds.min()) / max(np.ptp(speeds), 1.0), (t - throttles.min()) / max(np.ptp(throttles), 1.0)]
                        for n, t in sites])
    rows = []
    for j, i in enumerate(_spread(norm_xy, n_sweeps)):
        n, t = sites[i]
        s_map = float(start_spark(n, t))
        for k in range(n_steps):
            rows.append({"point_id": f"ks{j + 1:02d}-{k + 1:02d}", "sweep_id": f"ks{j + 1:02d}", "step": k + 1,
                         "speed_rpm": n, "throttle_pct": t,
                         "spark_deg_btdc": round(s_map - retard_deg + k * step_deg, 1), "lambda": lambda_value,
                         "knock": np.nan})
    return pd.DataFrame(rows)
