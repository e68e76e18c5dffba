"""The ``maps`` flow: ECU spark-advance, injection-time and target-lambda tables from a combustion model.

    model file + spec --> engine_model.maps.build_maps (search stages, verification)
                      --> every batch of simulations a ``sweep`` subflow on one Dask scheduler
                          (flows.evaluate.SweepEvaluator, into <out>/sweeps/maps-NNN/)
                      --> engine_model.maps.write_maps into <out>/maps/

No physics here: the flow wires the evaluations to Dask and writes the files.
"""

from __future__ import annotations

import datetime as _dt
import time
from pathlib import Path

from . import prefect_env
from .evaluate import SweepEvaluator, shared_cluster
from .sweep import DEFAULT_WORKERS

from prefect import flow  # noqa: E402

from engine_model import __version__, load_spec  # noqa: E402
from engine_model.io import write_json  # noqa: E402
from engine_model.maps import (EcuGrid, LambdaTable, MapSettings, build_maps, load_model,  # noqa: E402
                               parse_breakpoints, write_maps)


def _inputs(model: str, spec: str | None, throttle: str | None, speed: str | None, lambda_table: str | None,
            settings: dict | None, grid_csv: str | None = None):
    """Load and check every input (before any cluster is started); ValueError on bad input."""
    eng = load_spec(spec)
    mdl = load_model(model)
    if grid_csv and (throttle or speed):
        raise ValueError("give either a grid CSV or throttle/speed breakpoints, not both")
    grid = EcuGrid.from_csv(grid_csv) if grid_csv else EcuGrid(parse_breakpoints(throttle, "throttle") if throttle else EcuGrid().throttle_pct,
                   parse_breakpoints(speed, "speed") if speed else EcuGrid().speed_rpm)
    grid.check_spec(eng)
    if callable(getattr(mdl, "check_spec", None)):
        mdl.check_spec(eng)
    lam = LambdaTable.from_csv(lambda_table) if lambda_table else None
    if lam is not None:
        lam.on_grid(grid)
    st = MapSettings(**(settings or {}))
    return eng, mdl, grid, lam, st


def maps_into(out: Path, eng, mdl, grid, lam, st, spec: str | None, address: str, step_deg: float,
              progress: bool) -> dict:
    """Build the tables on the Dask scheduler ``address`` and write them into ``out/maps``; returns the summary."""
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    ev = SweepEvaluator(out / "sweeps", address, spec=spec, step_deg=step_deg, label="maps", progress=progress)
    res = build_maps(eng, mdl, grid=grid, lambda_table=lam, evaluate=ev, settings=st)
    paths = write_maps(res, out / "maps")
    summary = {"kind": "maps", "package_version": __version__, "spec_hash": eng.spec_hash(),
               "model": res.model_name, "grid": list(grid.shape), "step_deg": step_deg,
               "created": _dt.datetime.now().isoformat(timespec="seconds"), "stats": res.stats,
               "files": {k: str(v) for k, v in paths.items()}, "wall_s": round(time.perf_counter() - t0, 1)}
    write_json(summary, out / "maps" / "run.json")
    return summary


@flow(name="maps", log_prints=False, validate_parameters=False)
def maps_flow(model: str, out: str, spec: str | None = None, throttle: str | None = None, speed: str | None = None,
              lambda_table: str | None = None, settings: dict | None = None, step_deg: float = 0.5,
              workers: int = DEFAULT_WORKERS, dask_address: str | None = None, progress: bool = True,
              grid: str | None = None) -> dict:
    """ECU tables from the combustion model file ``model`` into ``out``/maps/ (sweeps in ``out``/sweeps/)."""
    eng, mdl, grid, lam, st = _inputs(model, spec, throttle, speed, lambda_table, settings, grid)
    with shared_cluster(workers, dask_address) as addr:
        return maps_into(Path(out), eng, mdl, grid, lam, st, spec, addr, step_deg, progress)


def run_maps(model, out, spec=None, throttle=None, speed=None, lambda_table=None, settings=None, grid=None,
             **kwargs) -> dict:
    """``mbc maps``: validate inputs, then run :func:`maps_flow` under one Prefect API."""
    _inputs(str(model), spec, throttle, speed, lambda_table, settings, grid)
    with prefect_env.prefect_api(verbose=kwargs.get("progress", True)):
        res = maps_flow(model=str(model), out=str(out), spec=spec, throttle=throttle, speed=speed,
                        lambda_table=None if lambda_table is None else str(lambda_table), settings=settings,
                        grid=None if grid is None else str(grid), **kwargs)
    s = res["stats"]
    print(f"maps: {s['cells']} cells ({s['feasible']} feasible; infeasible {s['infeasible']}); limited by "
          f"{s['limited_by']}; {s['simulated_points']} simulations in {s['evaluate_calls']} batches; "
          f"smoothing max shift {s['smoothing']['max_shift_deg']:.2f} deg; {res['wall_s']} s\n"
          f"tables: {Path(out) / 'maps'}/ (ecu_tables.parquet, spark_advance.csv, injection_time.csv, "
          f"lambda_target.csv, spark_start_retarded.csv, *.png)")
    return res


