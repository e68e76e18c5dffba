"""Knock calibration on bench data and the knock-onset sweep plan.

    calibrate   bench points with identified burns -> spark sweeps on the cycle model -> the
                Douaud-Eyzat delay multiplier (posterior over bench evidence) and the model's
                MBT at every point
    plan        knock-onset spark sweeps for the dyno (``mbc plan knock-sweeps``)
    consistency a built spark table against the real bench points
"""

from engine_model.knock.calibrate import (KnockCalibration, bench_sweep_plan, calibrate_knock,
                                          point_evidence)
from engine_model.knock.consistency import (FULL_CHARGE, LIGHT_LOAD_CHARGE, bench_consistency, consistency_summary,
                                            plot_consistency, table_trends)
from engine_model.knock.plan import knock_sweep_plan
from engine_model.knock.plots import plot_evidence
from engine_model.knock.speed_term import (KnockSpeedCalibration, calibrate_knock_speed, multiplier_at,
                                           with_speed_multiplier)

__all__ = ["FULL_CHARGE", "LIGHT_LOAD_CHARGE", "KnockCalibration", "KnockSpeedCalibration", "bench_consistency",
           "bench_sweep_plan", "calibrate_knock", "calibrate_knock_speed", "consistency_summary", "knock_sweep_plan",
           "multiplier_at", "plot_consistency", "plot_evidence", "point_evidence", "table_trends",
           "with_speed_multiplier"]
