"""The ``mbc`` command line.

    mbc run      main job: bench data -> sweep on Dask -> report, under results/<run-id>/
    mbc sweep    simulate any plan of operating points in chunks on Dask workers (resumable)
    mbc plan     generate a DOE test plan into doe_plans/
    mbc maps     ECU spark-advance / injection-time / lambda tables from a combustion model file
    mbc serve    serve Prefect deployments (parameterised sweep, scheduled bench-folder watcher)
    mbc simulate simulate a small table in this process (no Prefect, no Dask)
    mbc calibrate airflow matching + Wiebe combustion identification on bench data (Dask sweeps)

It lives in ``flows`` because it drives Prefect and Dask; ``engine_model``
stays free of both.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from engine_model import __version__


def _progress(label: str):
    start = time.perf_counter()

    def show(done: int, total: int):
        width = 30
        filled = int(width * done / max(total, 1))
        el = time.perf_counter() - start
        sys.stderr.write(f"\r{label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total}  {el:5.1f} s")
        if done == total:
            sys.stderr.write("\n")
        sys.stderr.flush()

    return show


def cmd_simulate(args) -> int:
    from engine_model import SolverSettings, load_spec, simulate
    from engine_model.io import read_table, write_parquet

    spec = load_spec(args.spec)
    points = read_table(args.points)
    out = Path(args.out)
    res = simulate(spec, points, SolverSettings(step_deg=args.step_deg), progress=_progress("simulating"))
    write_parquet(res.drop(columns=["sim_time_s"], errors="ignore"), out)
    n_bad = int((~res["converged"]).sum())
    print(f"{len(res)} points -> {out}  ({n_bad} not converged or failed)")
    return 0


def cmd_sweep(args) -> int:
    from engine_model.io import read_table

    from .sweep import run_sweep
    from .store import frame_hash

    out = args.out
    if out is None:
        from .run import default_run_dir

        out = default_run_dir(frame_hash(read_table(args.plan)))
    t0 = time.perf_counter()
    man = run_sweep(args.plan, out, spec=args.spec, workers=args.workers, dask_address=args.dask_address,
                    step_deg=args.step_deg, tolerance=args.tolerance, chunk_size=args.chunk_size)
    c = man["counts"]
    wall = time.perf_counter() - t0
    print(f"\nsweep {man['status']}: {c['points']}/{man['points']} points ({c['ok']} ok, "
          f"{c['not_converged']} not converged, {c['failed']} failed); "
          f"{man['chunks_computed']} chunks computed, {man['chunks_skipped']} resumed from disk; "
          f"{man['timings']['points_per_s']:.1f} points/s, {wall:.1f} s in all\n"
          f"results: {Path(out) / 'sweep'}/part-*.parquet (one dataset), {Path(out) / 'manifest.json'}")
    return 0


def cmd_run(args) -> int:
    from .run import run_pipeline

    run_pipeline(out=args.out, bench=args.bench, spec=args.spec, bdur_10_90=args.bdur_10_90,
                 wiebe_m=args.wiebe_m, eta_trans=args.eta_trans, step_deg=args.step_deg, workers=args.workers,
                 dask_address=args.dask_address)
    return 0


def cmd_maps(args) -> int:
    from .maps import run_maps

    settings = {k: v for k, v in (("knock_margin", args.knock_margin), ("safety_retard_deg", args.safety_retard),
                                  ("start_retard_deg", args.start_retard), ("battery_v", args.battery_v))
                if v is not None}
    run_maps(args.model, args.out, spec=args.spec, throttle=args.throttle, speed=args.speed,
             lambda_table=args.lambda_table, settings=settings, grid=args.grid, step_deg=args.step_deg,
             workers=args.workers, dask_address=args.dask_address)
    return 0


def cmd_calibrate(args) -> int:
    from .calibrate import run_calibration

    grid = tuple(int(v) for v in args.airflow_grid.split("x"))
    run_calibration(out=args.out, bench=args.bench, spec=args.spec, eta_trans=args.eta_trans,
                    step_deg=args.step_deg, workers=args.workers, dask_address=args.dask_address,
                    n_bdur=args.n_bdur, n_m=args.n_m, airflow_grid=grid, airflow_max_nfev=args.airflow_max_nfev)
    return 0


def cmd_plan(args) -> int:
    from .plan import plan_from_args

    plan_from_args(args)
    return 0


def cmd_serve(args) -> int:
    from .deploy import serve_deployments

    serve_deployments(watch=args.watch, cron=args.cron, interval_s=args.interval, workers=args.workers,
                      dask_address=args.dask_address, results=args.results)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mbc", description="Model-based calibration of a restricted race engine")
    p.add_argument("--version", action="version", version=f"mbc {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp):
        sp.add_argument("--spec", default=None, help="engine spec TOML (default: embedded Yamaha R6 FS)")
        sp.add_argument("--step-deg", type=float, default=0.5, help="crank-angle step [deg] (default 0.5)")

    def dask(sp):
        g = sp.add_mutually_exclusive_group()
        g.add_argument("--workers", type=int, default=2, help="local Dask workers x 1 thread (default 2)")
        g.add_argument("--dask-address", default=None, help="existing Dask scheduler, e.g. tcp://host:8786")

    s = sub.add_parser("simulate", help="simulate a small table of operating points in this process")
    s.add_argument("--points", required=True, help="CSV or Parquet with the operating-point columns")
    s.add_argument("--out", required=True, help="output Parquet file")
    common(s)
    s.set_defaults(func=cmd_simulate)

    w = sub.add_parser("sweep", help="simulate a plan on Dask workers into Parquet parts (re-run resumes)")
    w.add_argument("--plan", required=True, help="plan CSV/Parquet: contract columns incl. bdur_10_90_deg, wiebe_m")
    w.add_argument("--out", default=None, help="output folder (default results/<time>-<plan hash>/)")
    w.add_argument("--chunk-size", type=int, default=None, help="points per Dask task (default: ~3 s of work)")
    w.add_argument("--tolerance", type=float, default=1e-3, help="cycle convergence tolerance (default 1e-3)")
    common(w)
    dask(w)
    w.set_defaults(func=cmd_sweep)

    r = sub.add_parser("run", help="main job: bench data -> sweep -> report under results/<run-id>/")
    r.add_argument("--bench", default=None, help="bench data CSV/Parquet (default: packaged Table 2)")
    r.add_argument("--out", default=None, help="output folder (default results/<run-id>/)")
    r.add_argument("--bdur-10-90", type=float, default=24.0, help="10-90 %% burn duration [deg] (default 24)")
    r.add_argument("--wiebe-m", type=float, default=6.4, help="Wiebe shape m [-] (default 6.4)")
    r.add_argument("--eta-trans", type=float, default=0.95, help="transmission efficiency [-] (default 0.95)")
    common(r)
    dask(r)
    r.set_defaults(func=cmd_run)

    mp = sub.add_parser("maps", help="ECU tables (spark advance, injection time, lambda) from a combustion model")
    mp.add_argument("--model", required=True, help="combustion model file (fitted global model, or prior JSON)")
    mp.add_argument("--out", required=True, help="output folder; tables go to OUT/maps/, sweeps to OUT/sweeps/")
    mp.add_argument("--throttle", default=None, help="throttle breakpoints [%%], '0,5,10,...' or 'start:stop:step'")
    mp.add_argument("--speed", default=None, help="speed breakpoints [rpm], e.g. '1000:13000:1000' (the default)")
    mp.add_argument("--grid", default=None, help="take the breakpoints from a wide table CSV (e.g. an ECU export)")
    mp.add_argument("--lambda-table", default=None, help="target-lambda wide CSV (rows throttle %%, columns rpm)")
    mp.add_argument("--knock-margin", type=float, default=None, help="keep knock_index < 1 - margin (default 0.15)")
    mp.add_argument("--safety-retard", type=float, default=None, help="retard from MBT [deg] (default 0)")
    mp.add_argument("--start-retard", type=float, default=None, help="starting-map retard [deg] (default 12)")
    mp.add_argument("--battery-v", type=float, default=None, help="battery voltage for dead time [V] (default 14)")
    common(mp)
    dask(mp)
    mp.set_defaults(func=cmd_maps)

    c = sub.add_parser("calibrate", help="airflow matching + Wiebe identification on bench data")
    c.add_argument("--bench", default=None, help="bench data CSV/Parquet (default: packaged Table 2)")
    c.add_argument("--out", required=True, help="output folder")
    c.add_argument("--eta-trans", type=float, default=0.95, help="transmission efficiency [-] (default 0.95)")
    c.add_argument("--n-bdur", type=int, default=11, help="BDUR10-90 grid points over 20-50 deg (default 11)")
    c.add_argument("--n-m", type=int, default=13, help="Wiebe m grid points over 2-8 (default 13)")
    c.add_argument("--airflow-grid", default="6x6x1",
                   help="coarse airflow search per parameter (exhaust x intake runner x restrictor Cd; default 6x6x1)")
    c.add_argument("--airflow-max-nfev", type=int, default=15, help="least-squares iteration cap (default 15)")
    common(c)
    dask(c)
    c.set_defaults(func=cmd_calibrate)

    from .plan import add_plan_arguments

    pl = sub.add_parser("plan", help="generate a DOE test plan (Parquet + CSV + metadata)")
    add_plan_arguments(pl)
    pl.set_defaults(func=cmd_plan)

    sv = sub.add_parser("serve", help="serve Prefect deployments: parameterised sweep + scheduled bench watcher")
    sv.add_argument("--watch", default="bench_inbox", help="folder watched for new bench files (default bench_inbox/)")
    sv.add_argument("--results", default="results", help="where watcher runs write (default results/)")
    g = sv.add_mutually_exclusive_group()
    g.add_argument("--cron", default=None, help="watcher schedule as cron, e.g. '*/15 * * * *'")
    g.add_argument("--interval", type=float, default=None, help="watcher schedule in seconds (default 600)")
    dask(sv)
    sv.set_defaults(func=cmd_serve)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ValueError as exc:
        print(f"mbc: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\nmbc: interrupted; finished chunks are on disk, run the same command again to resume",
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
