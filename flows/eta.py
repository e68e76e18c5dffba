"""Rough expected stage times for the progress lines of ``mbc run``.

A stage's total work is not known when it starts (the airflow match, the identification and the map
search each decide their next batch from the last one), so a stage cannot count down points it has
not planned yet.  What it can say is how long the same stage took in a reference run, scaled by the
work this run asks for.  The figures are wall times of complete runs on 2 local Dask workers of a
2-core machine with the 1D gas exchange and nothing else running, measured 2026-11-27 (the default
model stage 2026-11-28, once its design reached down to 2000 rpm; ``docs/history.md``, "Stage times");
the progress line calls the result "expected ~", never a promise.
"""

from __future__ import annotations

#: Stage wall time [s] of the reference runs: default settings and ``--quick`` (7 bench points,
#: 16 / 10 DOE points, 13 x 11 ECU cells default / 3 x 3 quick, crank step 0.5 / 1 deg).
REFERENCE_STAGE_S = {
    False: {"calibration": 261.0, "model": 616.0, "maps": 241.0, "gap": 26.0},
    True: {"calibration": 38.0, "model": 60.0, "maps": 12.0, "gap": 18.0},
}
REFERENCE_WORKERS = 2
REFERENCE_BENCH_POINTS = 7
REFERENCE_DOE_POINTS = {False: 16, True: 10}
REFERENCE_CELLS = {False: 143, True: 9}
REFERENCE_STEP_DEG = {False: 0.5, True: 1.0}


def expected_stage_s(stage: str, quick: bool, step_deg: float, bench_points: int, doe_points: int,
                     map_cells: int, workers: int | None) -> float:
    """Expected wall time [s] of ``stage``: the reference run's, scaled by the work asked for.

    Linear in the stage's own count (bench points for calibration and gap, DOE points for the model
    stage, ECU cells for maps), inversely proportional to the crank step and to the number of local
    workers; ``workers`` None (an external cluster of unknown size) keeps the reference's 2.
    """
    ref = REFERENCE_STAGE_S[bool(quick)][stage]
    count = {"calibration": bench_points / REFERENCE_BENCH_POINTS, "gap": bench_points / REFERENCE_BENCH_POINTS,
             "model": doe_points / REFERENCE_DOE_POINTS[bool(quick)], "maps": map_cells / REFERENCE_CELLS[bool(quick)]}[stage]
    step = REFERENCE_STEP_DEG[bool(quick)] / step_deg
    speed = 1.0 if workers is None else REFERENCE_WORKERS / max(int(workers), 1)
    return ref * count * step * speed


def minutes(seconds: float) -> str:
    """'45 s', '12 min' or '1 h 05 min' for a progress line."""
    s = max(float(seconds), 0.0)
    if s < 90:
        return f"{s:.0f} s"
    if s < 3600:
        return f"{s / 60:.0f} min"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"
