"""The ``run`` flow: the whole pipeline so far, on the embedded R6 spec and the packaged bench data.

    bench data -> plan of the bench points -> sweep (Dask) -> simulated vs measured report
    DOE full factorial on the ECU grid -> feasibility (knock / near-zero BMEP) -> sweep -> operating map

Everything lands in one run folder, written as ``<folder>.partial/`` and renamed
when complete (an interrupted run never looks finished; running the same
``--out`` again resumes its sweeps instead of recomputing them).
"""

from __future__ import annotations

import datetime as _dt
import shutil
import sys
import time
from pathlib import Path

import pandas as pd

from . import prefect_env
from .sweep import DEFAULT_WORKERS, dask_runner, sweep_flow

from prefect import flow  # noqa: E402

from engine_model import SolverSettings, __version__, doe, load_spec  # noqa: E402
from engine_model.bench import load_bench  # noqa: E402
from engine_model.io import write_csv, write_json, write_parquet, write_text  # noqa: E402
from engine_model.report import comparison_table, plot_comparison, plot_operating_map, plot_traces  # noqa: E402
from flows import store  # noqa: E402


MAP_SPEEDS = tuple(range(3000, 13001, 1000))       # [rpm]
MAP_THROTTLES = (10, 20, 30, 40, 60, 80, 100)     # [%]


def default_run_dir(tag: str) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("results") / f"{stamp}-{tag[:8]}"


def bench_plan(bench: pd.DataFrame, bdur_10_90: float, wiebe_m: float) -> pd.DataFrame:
    """The bench points as a simulation plan at one combustion setting."""
    plan = bench[["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda"]].copy()
    plan["bdur_10_90_deg"] = bdur_10_90
    plan["wiebe_m"] = wiebe_m
    return plan


@flow(name="run", log_prints=False, validate_parameters=False)
def run_flow(out: str, bench: str | None = None, spec: str | None = None, bdur_10_90: float = 24.0,
             wiebe_m: float = 6.4, eta_trans: float = 0.95, step_deg: float = 0.5, workers: int = DEFAULT_WORKERS,
             dask_address: str | None = None, progress: bool = True) -> dict:
    """Bench points -> sweep -> comparison, into the folder ``out`` (see module docstring)."""
    t0 = time.perf_counter()
    eng = load_spec(spec)
    meas = load_bench(bench)
    final = Path(out)
    work = final.with_name(final.name + ".partial")
    if final.exists() and not work.exists():
        final.rename(work)          # update in place: the sweeps inside resume
    work.mkdir(parents=True, exist_ok=True)

    runner = dask_runner(workers, dask_address)

    # 1) the bench points at the given combustion setting
    plan = bench_plan(meas, bdur_10_90, wiebe_m)
    plan_path = write_parquet(plan, work / "plans" / "bench_points.parquet")
    sweep_dir = work / "bench_sweep"
    sweep = sweep_flow.with_options(task_runner=runner)
    sweep_man = sweep(plan=str(plan_path), out=str(sweep_dir), spec=spec, step_deg=step_deg, progress=progress)
    sim = store.read_results(sweep_dir)

    # 2) the operating map: an ECU-grid full factorial at the MBT spark and combustion estimates, the
    #    knock-limited and near-zero-BMEP zones flagged by a quick model check (paper, Figure 1), swept
    map_plan = doe.with_combustion(doe.bench_order(doe.feasibility(
        doe.full_factorial(speed_rpm=MAP_SPEEDS, throttle_pct=MAP_THROTTLES), spec=eng)))
    saved = doe.save_plan(map_plan, "map_full_factorial", directory=work / "plans")
    map_man = sweep(plan=str(saved["parquet"]), out=str(work / "map_sweep"), spec=spec, step_deg=step_deg,
                    progress=progress)
    map_res = store.read_results(work / "map_sweep")
    plot_operating_map(map_res, work / "operating_map.png")

    cmp_ = comparison_table(meas, sim, eta_trans)
    write_parquet(sim, work / "simulated.parquet")
    write_csv(cmp_, work / "comparison.csv", float_format="%.4g")
    with pd.option_context("display.width", 200, "display.max_columns", 30):
        text = cmp_.round(2).to_string(index=False)
    write_text(text + "\n", work / "comparison.txt")
    plot_comparison(cmp_, work / "wot_comparison.png", eta_trans)
    mid = meas.iloc[len(meas) // 2]
    plot_traces(eng, mid, bdur_10_90, wiebe_m, SolverSettings(step_deg=step_deg),
                work / f"pressure_traces_{int(mid['speed_rpm'])}.png")
    man = {
        "kind": "run", "package_version": __version__, "engine": eng.name, "spec_hash": eng.spec_hash(),
        "bench": "packaged Table 2" if bench is None else str(bench), "bdur_10_90_deg": bdur_10_90,
        "wiebe_m": wiebe_m, "eta_trans": eta_trans, "step_deg": step_deg, "points": len(sim),
        "not_converged": int((~sim["converged"].astype(bool)).sum()),
        "sweeps": {name: {k: m[k] for k in ("plan_hash", "counts", "timings", "dask")}
                   for name, m in (("bench_sweep", sweep_man), ("map_sweep", map_man))},
        "map_infeasible": map_plan["infeasible_reason"].value_counts().to_dict(),
        "wall_time_s": round(time.perf_counter() - t0, 2),
        "created": _dt.datetime.now().isoformat(timespec="seconds"), "status": "complete",
    }
    write_json(man, work / "manifest.json")
    if final.exists():
        shutil.rmtree(final)
    work.rename(final)
    if progress:
        print(f"\nTable 2 (WOT, lambda 0.9), BDUR10-90 = {bdur_10_90:g} deg, m = {wiebe_m:g}, measured torque/"
              f"power divided by eta_trans = {eta_trans:g}:\n\n{text}\n\nresults: {final}/ (simulated.parquet, "
              "comparison.csv, wot_comparison.png, pressure_traces_*.png, operating_map.png, plans/, bench_sweep/, "
              "map_sweep/, manifest.json)",
              file=sys.stdout)
    return man


def run_pipeline(out=None, bench=None, spec=None, **kwargs) -> dict:
    """Validate the inputs, then run :func:`run_flow` under one Prefect API for the whole run."""
    eng = load_spec(spec)
    load_bench(bench)   # bad bench data fails here, before any folder exists
    final = Path(out) if out else default_run_dir(eng.spec_hash())
    with prefect_env.prefect_api(verbose=kwargs.get("progress", True)):
        return run_flow(out=str(final), bench=None if bench is None else str(bench), spec=spec, **kwargs)
