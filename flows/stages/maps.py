"""The maps stage (and the ``mbc maps`` flow): ECU spark-advance, injection-time and target-lambda tables.

    calibrated engine + combustion model --> engine_model.tables.build_maps (search stages, verification)
                      --> every batch of simulations a ``sweep`` subflow on one Dask scheduler (``<out>/sweeps/``)
                      --> engine_model.tables.write_maps into ``<out>/maps/``

No physics here: the stage wires the evaluations to Dask and writes the files.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import os
import time
from pathlib import Path

from flows import prefect_env, store
from flows.evaluate import shared_cluster
from flows.settings import RunSettings
from flows.stages.context import StageContext
from flows.sweep import DEFAULT_WORKERS

from prefect import flow  # noqa: E402

import pandas as pd  # noqa: E402

from engine_model import knock  # noqa: E402
from engine_model.bench.measured import validate_bench  # noqa: E402
from engine_model.calibrated import CalibratedEngine  # noqa: E402
from engine_model.io import write_csv, write_json  # noqa: E402
from engine_model.tables import (EcuGrid, LambdaTable, MapSettings, build_maps, load_model,  # noqa: E402
                                 parse_breakpoints, write_maps)
from engine_model.version import package_version  # noqa: E402

#: Where the model stage leaves the global model in a run folder.
MODEL_FILE = Path("model") / "model.json"


def ecu_grid(throttle: str | None, speed: str | None, grid_csv: str | None = None) -> EcuGrid:
    """The ECU grid from breakpoint strings ('0,5,10' or 'start:stop:step'), a wide CSV, or the defaults."""
    if grid_csv and (throttle or speed):
        raise ValueError("give either a grid CSV or throttle/speed breakpoints, not both")
    if grid_csv:
        return EcuGrid.from_csv(grid_csv)
    return EcuGrid(parse_breakpoints(throttle, "throttle") if throttle else EcuGrid().throttle_pct,
                   parse_breakpoints(speed, "speed") if speed else EcuGrid().speed_rpm)


def batch_label(model_file, grid: EcuGrid, lam: LambdaTable | None, st: MapSettings, spec_hash: str,
                step_deg: float, speed_term=None) -> str:
    """Sweep label of the maps batches, from every input: the same inputs resume the same sweep folders,
    other inputs (a rebuild with another grid or settings) get their own, since a sweep folder refuses a
    different plan."""
    parts = {"model": store.sha256_text(Path(model_file).read_text()) if model_file else None,
             "throttle": [float(v) for v in grid.throttle_pct], "speed": [float(v) for v in grid.speed_rpm],
             "lambda": None if lam is None else repr(lam), "settings": dataclasses.asdict(st), "spec": spec_hash,
             "step_deg": step_deg}
    if speed_term is not None:      # (absent from older labels: a run without the speed term resumes as before)
        parts["knock_speed_term"] = speed_term
    return "maps-" + store.sha256_text(json.dumps(parts, sort_keys=True, default=str))[:8]


def build_into(ctx: StageContext, model, grid: EcuGrid, lam: LambdaTable | None = None,
               st: MapSettings | None = None, model_file=None, knock_evidence=None,
               calibration_summary=None) -> dict:
    """Build the tables with ``model`` (read from ``model_file``) on ``grid`` and write them into
    ``ctx.work/maps``; returns the summary.  ``ctx.bench`` (if any) pins the cells the bench ran clean at
    MBT; ``knock_evidence`` (default ``ctx.work/calibration/knock_evidence.parquet``) feeds the report
    against the bench; ``calibration_summary`` (default ``ctx.work/calibration/summary.json``) gives the
    speed-dependent knock multiplier when the calibration says the tables use it."""
    t0 = time.perf_counter()
    eng = ctx.engine.spec
    st = MapSettings() if st is None else st
    speed_term = knock_speed_term(Path(calibration_summary) if calibration_summary
                                  else ctx.work / "calibration" / "summary.json")
    table_m = speed_term["table_multipliers"] if speed_term else None
    label = batch_label(model_file, grid, lam, st, eng.spec_hash(), ctx.settings.step_deg, table_m)
    evaluate = ctx.evaluator(label)
    if table_m is not None:
        inner = evaluate

        def evaluate(plan):     # every row at its speed's calibrated multiplier (a spec override per row)
            return inner(knock.with_speed_multiplier(plan, table_m))
    res = build_maps(eng, model, grid=grid, lambda_table=lam, evaluate=evaluate, settings=st, bench=ctx.bench)
    paths = write_maps(res, ctx.work / "maps", spec=eng)
    consistency = _bench_consistency(ctx, res, eng, paths, knock_evidence, table_m)
    summary = {"kind": "maps", "package_version": package_version(), "spec_hash": eng.spec_hash(),
               "model": res.model_name, "grid": list(grid.shape), "step_deg": ctx.settings.step_deg,
               "settings": dataclasses.asdict(st),   # what a rebuild (mbc maps --run) starts from
               "created": _dt.datetime.now().isoformat(timespec="seconds"), "stats": res.stats,
               "files": {k: os.path.relpath(v, ctx.work) for k, v in paths.items()},   # relative: the run folder is renamed
               "wall_s": round(time.perf_counter() - t0, 1),
               "knock_multiplier": ({"kind": "speed term", "table_multipliers": table_m} if table_m is not None
                                    else {"kind": "one multiplier", "value": eng.knock.delay_multiplier})}
    if consistency is not None:
        summary["bench_consistency"] = consistency
    write_json(summary, ctx.work / "maps" / "run.json")
    return summary


def knock_speed_term(summary_file: Path) -> dict | None:
    """The calibration's speed-dependent knock multiplier (``knock.speed_term`` of a calibration
    ``summary.json``) when it says the tables use it, else None (also when the file does not exist)."""
    f = Path(summary_file)
    if not f.is_file():
        return None
    term = (json.loads(f.read_text()).get("knock") or {}).get("speed_term") or {}
    return term if term.get("used") else None


def _bench_consistency(ctx: StageContext, res, eng, paths: dict, knock_evidence=None,
                       table_m=None) -> dict | None:
    """``maps/bench_consistency.csv`` and ``.png`` from the calibration's knock evidence (None without it)."""
    ev_file = Path(knock_evidence) if knock_evidence else ctx.work / "calibration" / "knock_evidence.parquet"
    if not ev_file.is_file():
        return None
    evidence = pd.read_parquet(ev_file)
    mult = (knock.multiplier_at(table_m, evidence["speed_rpm"].to_numpy(float)) if table_m is not None
            else eng.knock.delay_multiplier)
    tab = knock.bench_consistency(evidence, res.cells, mult)
    paths["bench_consistency"] = write_csv(tab, ctx.work / "maps" / "bench_consistency.csv")
    paths["bench_consistency_png"] = knock.plot_consistency(tab, ctx.work / "maps" / "bench_consistency.png")
    return {**knock.consistency_summary(tab), "trends": knock.table_trends(res.cells, bench=evidence),
            "rows": tab.round(3).to_dict(orient="records")}


def run(ctx: StageContext) -> dict:
    """The maps stage of a run: the global model of the model stage on the run's ECU grid."""
    model = load_model(ctx.work / MODEL_FILE)
    grid = ecu_grid(ctx.settings.map_throttle, ctx.settings.map_speed)
    res = build_into(ctx, model, grid, model_file=ctx.work / MODEL_FILE)
    out = {"stats": res["stats"], "files": res["files"]}
    if "bench_consistency" in res:
        out["bench_consistency"] = {k: v for k, v in res["bench_consistency"].items() if k != "rows"}
    return out


def _inputs(model: str, spec: str | None, throttle: str | None, speed: str | None, lambda_table: str | None,
            settings: dict | None, grid_csv: str | None = None):
    """Load and check every input (before any cluster is started); ValueError on bad input."""
    engine = CalibratedEngine.from_spec(spec)
    mdl = load_model(model)
    grid = ecu_grid(throttle, speed, grid_csv)
    grid.check_spec(engine.spec)
    if callable(getattr(mdl, "check_spec", None)):
        mdl.check_spec(engine.spec)
    lam = LambdaTable.from_csv(lambda_table) if lambda_table else None
    if lam is not None:
        lam.on_grid(grid)
    st = MapSettings(**(settings or {}))
    return engine, mdl, grid, lam, st


@flow(name="maps", log_prints=False, validate_parameters=False)
def maps_flow(model: str, out: str, spec: str | None = None, throttle: str | None = None, speed: str | None = None,
              lambda_table: str | None = None, settings: dict | None = None, step_deg: float = 0.5,
              workers: int = DEFAULT_WORKERS, dask_address: str | None = None, progress: bool = True,
              grid: str | None = None, bench: str | None = None, knock_evidence: str | None = None,
              calibration_summary: str | None = None) -> dict:
    """ECU tables from the combustion model file ``model`` into ``out``/maps/ (sweeps in ``out``/sweeps/).

    ``bench``: bench data (a run's ``bench.parquet``) whose clean MBT points pin their cells;
    ``knock_evidence``: a calibration's ``knock_evidence.parquet`` for the report against the bench;
    ``calibration_summary``: a calibration's ``summary.json`` (its speed-dependent knock multiplier, if used)."""
    engine, mdl, grid, lam, st = _inputs(model, spec, throttle, speed, lambda_table, settings, grid)
    meas = validate_bench(pd.read_parquet(bench), source=str(bench)) if bench else None
    with shared_cluster(workers, dask_address) as addr:
        ctx = StageContext(work=Path(out), engine=engine, engine_file=spec, address=addr,
                           settings=RunSettings(step_deg=step_deg, stages=("maps",)), progress=progress,
                           bench=meas, bench_source=str(bench or ""))
        return build_into(ctx, mdl, grid, lam, st, model_file=model, knock_evidence=knock_evidence,
                          calibration_summary=calibration_summary)


def run_maps(model, out, spec=None, throttle=None, speed=None, lambda_table=None, settings=None, grid=None,
             **kwargs) -> dict:
    """``mbc maps``: validate inputs, then run :func:`maps_flow` under one Prefect API."""
    _inputs(str(model), spec, throttle, speed, lambda_table, settings, grid)
    if kwargs.get("step_deg") is None:
        kwargs.pop("step_deg", None)
    with prefect_env.prefect_api(verbose=kwargs.get("progress", True)):
        res = maps_flow(model=str(model), out=str(out), spec=spec, throttle=throttle, speed=speed,
                        lambda_table=None if lambda_table is None else str(lambda_table), settings=settings,
                        grid=None if grid is None else str(grid), **kwargs)
    s = res["stats"]
    print(f"maps: {s['cells']} cells ({s['feasible']} feasible; infeasible {s['infeasible']}); limited by "
          f"{s['limited_by']}; {s['simulated_points']} simulations in {s['evaluate_calls']} batches; "
          f"smoothing max shift {s['smoothing']['max_shift_deg']:.2f} deg; {res['wall_s']} s\n"
          f"tables: {Path(out) / 'maps'}/ (ecu_tables.parquet, spark_advance.csv, injection_time.csv, "
          f"lambda_target.csv, spark_start_retarded.csv, *.png); ECU files: {Path(out) / 'maps' / 'ecu'}/ "
          "(mbc export for other breakpoints)")
    return res
