"""The ``mbc`` command line.

    mbc run      main job: bench data -> sweep on Dask -> report, under results/<run-id>/
    mbc sweep    simulate any plan of operating points in chunks on Dask workers (resumable)
    mbc plan     generate a DOE test plan into doe_plans/
    mbc maps     ECU spark-advance / injection-time / lambda tables from a combustion model file or a finished run
    mbc serve    serve Prefect deployments (parameterised sweep, scheduled bench-folder watcher)
    mbc simulate simulate a small table in this process (no Prefect, no Dask)
    mbc calibrate airflow matching + Wiebe combustion identification on bench data (Dask sweeps)
    mbc gap      sim-to-real gap diagnosis of bench data (where, which effect, how far it shrinks), or of a run
    mbc gap-benchmark  prove the gap diagnosis on withheld effects (virtual bench; --suite outside:
                       truths outside its library)
    mbc gap-plan       propose bench points that tell the gap library's effects apart

It lives in ``flows`` because it drives Prefect and Dask; ``engine_model``
stays free of both.
"""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import signal
import sys
import time
from pathlib import Path

from engine_model.version import package_version


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
    from engine_model import SolverSettings, load_spec
    from engine_model.sim import simulate
    from engine_model.contracts import throttle_to_pct
    from engine_model.io import read_table, write_parquet

    spec = load_spec(args.spec)
    points = throttle_to_pct(read_table(args.points), f"points file {args.points}", args.throttle_unit)
    out = Path(args.out)
    res = simulate(spec, points, SolverSettings(step_deg=args.step_deg), progress=_progress("simulating"))
    write_parquet(res.drop(columns=["sim_time_s"], errors="ignore"), out)
    n_bad = int((~res["converged"]).sum())
    print(f"{len(res)} points -> {out}  ({n_bad} not converged or failed)")
    return 0


def cmd_sweep(args) -> int:
    from engine_model.io import read_table

    from flows.sweep import run_sweep
    from flows.store import frame_hash

    out = args.out
    if out is None:
        from flows.run import default_run_dir

        out = default_run_dir(frame_hash(read_table(args.plan)))
    t0 = time.perf_counter()
    man = run_sweep(args.plan, out, spec=args.spec, workers=args.workers, dask_address=args.dask_address,
                    step_deg=args.step_deg, tolerance=args.tolerance, chunk_size=args.chunk_size,
                    throttle_unit=args.throttle_unit)
    c = man["counts"]
    wall = time.perf_counter() - t0
    print(f"\nsweep {man['status']}: {c['points']}/{man['points']} points ({c['ok']} ok, "
          f"{c['not_converged']} not converged, {c['failed']} failed); "
          f"{man['chunks_computed']} chunks computed, {man['chunks_skipped']} resumed from disk; "
          f"{man['timings']['points_per_s']:.1f} points/s, {wall:.1f} s in all\n"
          f"results: {Path(out) / 'sweep'}/part-*.parquet (one dataset), {Path(out) / 'manifest.json'}")
    return 0


def cmd_run(args) -> int:
    import dataclasses

    from flows.run import run_pipeline
    from flows.settings import QUICK, RunSettings, parse_stages

    base = QUICK if args.quick else RunSettings()
    changes = {"eta_trans": args.eta_trans}
    if args.step_deg is not None:
        changes["step_deg"] = args.step_deg
    if args.doe_points is not None:
        changes["doe_points"] = args.doe_points
    if args.doe_fill_points is not None:
        changes["doe_fill_points"] = args.doe_fill_points
    if args.doe_seed is not None:
        changes["doe_seed"] = args.doe_seed
    if args.stages:
        changes["stages"] = parse_stages(args.stages)
    for name in ("throttle", "speed"):
        if getattr(args, name) is not None:
            changes[f"map_{name}"] = getattr(args, name)
    run_pipeline(out=args.out, bench=args.bench, spec=args.spec, settings=dataclasses.replace(base, **changes),
                 workers=args.workers, dask_address=args.dask_address, throttle_unit=args.throttle_unit)
    return 0


def cmd_calibrate(args) -> int:
    from flows.stages.calibration import run_calibration

    grid = tuple(int(v) for v in args.airflow_grid.split("x"))
    run_calibration(out=args.out, bench=args.bench, spec=args.spec, eta_trans=args.eta_trans,
                    step_deg=args.step_deg, workers=args.workers, dask_address=args.dask_address,
                    n_bdur=args.n_bdur, n_m=args.n_m, airflow_grid=grid, airflow_max_nfev=args.airflow_max_nfev,
                    airflow_step_deg=args.airflow_step_deg, throttle_unit=args.throttle_unit)
    return 0


def _reach(text: str) -> float | None:
    """``--bench-offset-reach``: a distance in rpm, or 'none' (carry nothing)."""
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--bench-offset-reach {text!r}: expected a distance in rpm or 'none'") from None


def cmd_maps(args) -> int:
    from flows.stages.maps import run_maps

    settings = {k: v for k, v in (("knock_margin", args.knock_margin), ("safety_retard_deg", args.safety_retard),
                                  ("start_retard_deg", args.start_retard), ("battery_v", args.battery_v),
                                  ("knock_uncertainty_z", args.knock_uncertainty_z))
                if v is not None}
    if args.bench_offset_reach is not None:
        settings["bench_offset_reach_rpm"] = _reach(args.bench_offset_reach)
    kw = dict(throttle=args.throttle, speed=args.speed, lambda_table=args.lambda_table, settings=settings,
              grid=args.grid, step_deg=args.step_deg, workers=args.workers, dask_address=args.dask_address)
    if args.run:
        from flows.rebuild import rebuild_maps

        rebuild_maps(args.run, args.out, model=args.model, spec=args.spec, **kw)
        return 0
    if not (args.model and args.out):
        raise ValueError("mbc maps: give --run DIR (a finished `mbc run` folder), or --model FILE and --out DIR")
    run_maps(args.model, args.out, spec=args.spec, **kw)
    return 0


def cmd_export(args) -> int:
    from flows.export import run_export

    run_export(args.run, out=args.out, fmt=args.format, rpm_bins=args.rpm_bins, load_bins=args.load_bins,
               axes_from=args.axes_from, load_axis=args.load_axis, fuel=args.fuel, battery_v=args.battery_v,
               spec=args.spec)
    return 0


def cmd_compare(args) -> int:
    from flows.export import run_compare

    run_compare(args.run, args.current, table=args.table, out=args.out, spec=args.spec, fuel=args.fuel)
    return 0


def cmd_plan(args) -> int:
    from flows.plan import plan_from_args

    plan_from_args(args)
    return 0


def cmd_serve(args) -> int:
    from flows.deploy import serve_deployments

    serve_deployments(watch=args.watch, cron=args.cron, interval_s=args.interval, workers=args.workers,
                      dask_address=args.dask_address, results=args.results)
    return 0


def cmd_gap(args) -> int:
    from flows.stages.gap import run_gap

    overrides = {}
    for item in args.override or []:
        key, sep, val = item.partition("=")
        try:
            overrides[key.strip()] = float(val)
        except ValueError:
            raise ValueError(f"--override {item!r}: expected SECTION.FIELD=NUMBER, e.g. intake.restrictor_cd=0.9") from None
        if not sep:
            raise ValueError(f"--override {item!r}: expected SECTION.FIELD=NUMBER")
    kw = dict(bench=args.bench, spec=args.spec, workers=args.workers, dask_address=args.dask_address,
              overrides=overrides or None, throttle_unit=args.throttle_unit)
    if args.run:
        from flows.rebuild import rebuild_gap

        rebuild_gap(args.run, args.out, step_deg=args.step_deg, **kw)
        return 0
    if not args.out:
        raise ValueError("mbc gap: give --out DIR, or --run DIR (a finished `mbc run` folder)")
    run_gap(out=args.out, step_deg=0.5 if args.step_deg is None else args.step_deg, **kw)
    return 0


def cmd_gap_benchmark(args) -> int:
    from flows.stages.gap import run_gap_benchmark

    if args.suite == "outside":
        run_gap_benchmark(out=args.out, seeds=args.seeds, spec=args.spec, suite="outside", workers=args.workers,
                          dask_address=args.dask_address, seed_start=args.seed_start, null_seeds=args.null_seeds,
                          plan=args.plan)
        return 0
    if args.plan is not None:
        raise ValueError("mbc gap-benchmark: --plan is an option of --suite outside")
    run_gap_benchmark(out=args.out, seeds=args.seeds, small=args.small, spec=args.spec, workers=args.workers,
                      dask_address=args.dask_address, seed_start=args.seed_start, design=args.design)
    return 0


def cmd_gap_plan(args) -> int:
    """Propose the bench points that tell the library's effects apart (base model only, in-process).

    Writes the plan CSV and, next to it, ``<plan>.coverage.md``: what the plan covers over speed and throttle
    and what it misses (:func:`engine_model.gap.coverage.summary_markdown`).
    """
    from pathlib import Path

    from engine_model.gap.bench_procedure import BENCH_SOLVER
    from engine_model import load_spec
    from engine_model.gap.coverage import min_points_to_cover, summary_markdown
    from engine_model.gap.design import discrimination_plan
    from engine_model.io import write_csv, write_text
    from engine_model.sim.simulate import simulate

    if args.points < 2:
        raise ValueError(f"--points {args.points}: need at least 2 bench points")
    if not args.max_speed_gap_rpm > 0:
        raise ValueError(f"--max-speed-gap-rpm {args.max_speed_gap_rpm:g}: must be > 0")
    if not args.speed_min < args.speed_max:
        raise ValueError(f"--speed-min {args.speed_min:g} must be below --speed-max {args.speed_max:g}")
    need = min_points_to_cover(args.speed_min, args.speed_max, args.max_speed_gap_rpm)
    if args.points < need:
        raise ValueError(f"--points {args.points}: covering {args.speed_min:g}-{args.speed_max:g} rpm with speed gaps "
                         f"<= {args.max_speed_gap_rpm:g} rpm needs at least {need} points; ask for --points {need} "
                         "or more, or widen --max-speed-gap-rpm")
    eng = load_spec(args.spec)
    plan, info = discrimination_plan(args.points, eng, lambda p: simulate(eng, p, BENCH_SOLVER),
                                     n_candidates=args.candidates, speed_rpm=(args.speed_min, args.speed_max),
                                     max_speed_gap_rpm=args.max_speed_gap_rpm)
    path = write_csv(plan, args.out)
    cov, free = info["coverage"], info.get("free", {})
    md = write_text(summary_markdown(cov, info["closest"], info["min_d2"], info["error_bound"],
                                     free.get("error_bound")), Path(path).with_suffix(".coverage.md"))
    i, j = info["closest"]
    a, b = cov["largest_speed_gap_at"]
    print(f"{len(plan)} points -> {path}; closest hypotheses: {i} vs {j or 'no effect'} "
          f"(d2 = {info['min_d2']:.1f} in noise units), misnaming bound {info['error_bound']:.3f}"
          + (f" (without the speed coverage {free['error_bound']:.3f}, largest speed gap "
             f"{free['coverage']['largest_speed_gap_rpm']:.0f} rpm)" if free else "")
          + f"; {info['simulations']} linearisation simulations + {len(info['pool']) * 5} knock checks")
    print(f"coverage -> {md}: largest speed gap {cov['largest_speed_gap_rpm']:.0f} rpm ({a:.0f}-{b:.0f}), "
          f"speed {cov['speed_covered'][0]:.0f}-{cov['speed_covered'][1]:.0f} rpm, throttle "
          f"{cov['throttle_covered'][0]:.0f}-{cov['throttle_covered'][1]:.0f} %; single-point speed bands: "
          + (", ".join(f"{x:.0f}-{y:.0f}" for x, y in cov["single_point_bands"]) or "none"))
    return 0


def throttle_unit_option(sp):
    """``--throttle-unit`` of the commands that read bench files or plans."""
    sp.add_argument("--throttle-unit", choices=("pct", "fraction"), default="pct",
                    help="unit of the throttle_pct column: pct (0-100, the default; a column all within 0-1 is "
                         "refused as a likely fraction) or fraction (0-1, converted to %% on load)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mbc", description="Model-based calibration of a restricted race engine")
    p.add_argument("--version", action="version", version=f"mbc {package_version()}")
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
    throttle_unit_option(s)
    s.set_defaults(func=cmd_simulate)

    w = sub.add_parser("sweep", help="simulate a plan on Dask workers into Parquet parts (re-run resumes)")
    w.add_argument("--plan", required=True, help="plan CSV/Parquet: contract columns incl. bdur_10_90_deg, wiebe_m")
    w.add_argument("--out", default=None, help="output folder (default results/<time>-<plan hash>/)")
    w.add_argument("--chunk-size", type=int, default=None, help="points per Dask task (default: ~5 s of work)")
    w.add_argument("--tolerance", type=float, default=1e-3, help="cycle convergence tolerance (default 1e-3)")
    common(w)
    dask(w)
    throttle_unit_option(w)
    w.set_defaults(func=cmd_sweep)

    r = sub.add_parser("run", help="main job: bench data -> calibration -> virtual-bench DOE -> global model -> "
                                   "ECU tables -> gap report, under results/<run-id>/")
    r.add_argument("--bench", default=None, help="bench data CSV/Parquet (default: packaged Table 2)")
    r.add_argument("--out", default=None, help="output folder (default results/<run-id>/); tables in OUT/maps/")
    r.add_argument("--eta-trans", type=float, default=0.95, help="transmission efficiency [-] (default 0.95)")
    r.add_argument("--doe-points", type=int, default=None,
                   help="operating points (spark sweeps) on the virtual bench (default 16; --quick 10)")
    r.add_argument("--doe-fill-points", type=int, default=None,
                   help="of --doe-points, those placed where the D-optimal ones leave the largest gaps "
                        "(maximin distance; default 0)")
    r.add_argument("--doe-seed", type=int, default=None,
                   help="seed of the virtual bench's design and measurement noise (default 0)")
    r.add_argument("--throttle", default=None, help="ECU throttle breakpoints [%%] ('0,5,10' or 'start:stop:step')")
    r.add_argument("--speed", default=None, help="ECU speed breakpoints [rpm] (default 1000:13000:1000)")
    r.add_argument("--stages", default=None, help="comma list of calibration,model,maps,gap (default all); a stage "
                   "left out is taken from --out, which must then hold a run that has it")
    r.add_argument("--quick", action="store_true", help="small smoke run: 1 deg step, coarse searches, 3 x 3 tables")
    r.add_argument("--spec", default=None, help="engine spec TOML (default: embedded Yamaha R6 FS)")
    r.add_argument("--step-deg", type=float, default=None, help="crank-angle step [deg] (default 0.5; --quick 1)")
    dask(r)
    throttle_unit_option(r)
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("calibrate", help="airflow matching + Wiebe identification on bench data")
    c.add_argument("--bench", default=None, help="bench data CSV/Parquet (default: packaged Table 2)")
    c.add_argument("--out", required=True, help="output folder")
    c.add_argument("--eta-trans", type=float, default=0.95, help="transmission efficiency [-] (default 0.95)")
    c.add_argument("--n-bdur", type=int, default=11, help="BDUR10-90 grid points over 20-50 deg (default 11)")
    c.add_argument("--n-m", type=int, default=13, help="Wiebe m grid points over 2-8 (default 13)")
    c.add_argument("--airflow-grid", default="6x6x1",
                   help="coarse airflow search per parameter (exhaust x intake runner x diffuser recovery; default 6x6x1)")
    c.add_argument("--airflow-max-nfev", type=int, default=12, help="least-squares iteration cap (default 12)")
    c.add_argument("--airflow-step-deg", type=float, default=1.0,
                   help="crank step of the airflow match [deg] (default 1.0; airflow within 0.2 %% of 0.5 deg)")
    common(c)
    dask(c)
    throttle_unit_option(c)
    c.set_defaults(func=cmd_calibrate)

    mp = sub.add_parser("maps", help="ECU tables (spark advance, injection time, lambda) from a combustion model")
    mp.add_argument("--run", default=None, help="finished `mbc run` folder: its model, engine, grid, step and "
                    "settings (options given here win); writes into RUN/maps/ (and its index) unless --out")
    mp.add_argument("--model", default=None, help="combustion model file (fitted global model, or prior JSON); "
                    "not with --run")
    mp.add_argument("--out", default=None, help="output folder; tables go to OUT/maps/, sweeps to OUT/sweeps/")
    mp.add_argument("--throttle", default=None, help="throttle breakpoints [%%], '0,5,10,...' or 'start:stop:step'")
    mp.add_argument("--speed", default=None, help="speed breakpoints [rpm], e.g. '1000:13000:1000' (the default)")
    mp.add_argument("--grid", default=None, help="take the breakpoints from a wide table CSV (e.g. an ECU export)")
    mp.add_argument("--lambda-table", default=None, help="target-lambda wide CSV (rows throttle %%, columns rpm)")
    mp.add_argument("--knock-margin", type=float, default=None, help="keep the fastest cycles' knock_index < 1 - margin (default 0: the safety lies in the fastest cycles, the knock multiplier's quantile and the burn uncertainty)")
    mp.add_argument("--safety-retard", type=float, default=None, help="retard from MBT [deg] (default 0)")
    mp.add_argument("--start-retard", type=float, default=None, help="starting-map retard [deg] (default 12)")
    mp.add_argument("--battery-v", type=float, default=None, help="battery voltage for dead time [V] (default 14)")
    mp.add_argument("--knock-uncertainty-z", type=float, default=None,
                    help="retard the knock border by z sigmas of the model's CA50-offset uncertainty (default 1; 0 turns it off)")
    mp.add_argument("--bench-offset-reach", default=None,
                    help="carry the bench's MBT offset (bench spark - model MBT in a cell the bench ran clean at MBT) to "
                         "the cells at that speed, faded to zero over this distance beyond the measured speeds [rpm] "
                         "(default 2000; 'none' carries nothing)")
    common(mp)
    dask(mp)
    mp.set_defaults(func=cmd_maps, step_deg=None)   # None: the run's step with --run, else 0.5

    ex = sub.add_parser("export", help="a run's spark / fuel / lambda tables as ECU files on the ECU's breakpoints")
    ex.add_argument("--run", required=True, help="run folder holding maps/cells.parquet (and engine.toml)")
    ex.add_argument("--out", default=None, help="output folder (default RUN/exports/)")
    ex.add_argument("--format", default="all", choices=("all", "table", "msq-speeduino", "msq-rusefi", "dcm", "csv"),
                    help="TunerStudio .table, Speeduino / rusEFI .msq (16 x 16), DCM 2.0, units-header CSV (default all)")
    ex.add_argument("--rpm-bins", default=None, help="rpm breakpoints, '1000,2000,...' or 'start:stop:step'")
    ex.add_argument("--load-bins", default=None, help="load breakpoints [%% throttle or kPa]")
    ex.add_argument("--axes-from", default=None, help="take the breakpoints (and load axis) from a table file "
                                                      "(.table, .msq: its spark table, .dcm, .csv) of the ECU")
    ex.add_argument("--load-axis", default=None, choices=("throttle", "kpa"),
                    help="throttle %% (alpha-N, default) or manifold pressure kPa (speed density)")
    ex.add_argument("--fuel", default="injection-time", choices=("injection-time", "fuel-mass", "ve"),
                    help="fuel table as injection time [ms], fuel mass [mg/cycle] or VE [%%] (default injection-time)")
    ex.add_argument("--battery-v", type=float, default=None, help="battery voltage of the dead time [V] "
                                                                  "(default: the maps build's)")
    ex.add_argument("--spec", default=None, help="engine TOML (default RUN/engine.toml)")
    ex.set_defaults(func=cmd_export)

    cp = sub.add_parser("compare", help="a run's proposed table against the car's current table (CSV + heatmap)")
    cp.add_argument("--run", required=True, help="run folder holding maps/cells.parquet (and engine.toml)")
    cp.add_argument("--current", required=True, help="the current table: .table, .msq, .dcm or .csv")
    cp.add_argument("--table", default="spark", choices=("spark", "injection", "lambda"),
                    help="which table (default spark); injection follows the current file's unit (ms, mg or %%)")
    cp.add_argument("--fuel", default=None, choices=("injection-time", "fuel-mass", "ve"),
                    help="form of the current fuel table when its file states no unit")
    cp.add_argument("--out", default=None, help="output folder (default RUN/compare/)")
    cp.add_argument("--spec", default=None, help="engine TOML (default RUN/engine.toml)")
    cp.set_defaults(func=cmd_compare)

    from flows.plan import add_plan_arguments

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
    gp = sub.add_parser("gap", help="sim-to-real gap diagnosis of bench data into <out>/gap/")
    gp.add_argument("--bench", default=None, help="bench data CSV/Parquet (default: packaged Table 2)")
    gp.add_argument("--run", default=None, help="finished `mbc run` folder: its engine and bench-data copy "
                    "(--bench wins); writes into RUN/gap/ (and its index) unless --out")
    gp.add_argument("--out", default=None, help="output folder (report under <out>/gap/)")
    gp.add_argument("--override", action="append", metavar="SECTION.FIELD=VALUE",
                    help="spec value from an earlier calibration step, e.g. intake.restrictor_cd=0.85 (repeatable)")
    common(gp)
    dask(gp)
    throttle_unit_option(gp)
    gp.set_defaults(func=cmd_gap, step_deg=None)   # None: the run's step with --run, else 0.5

    gb = sub.add_parser("gap-benchmark", help="gap diagnosis on withheld effects -> <out>/gap/gap_benchmark.csv")
    gb.add_argument("--out", required=True, help="output folder")
    gb.add_argument("--seeds", type=int, default=3, help="noise seeds per case (default 3)")
    gb.add_argument("--seed-start", type=int, default=0,
                    help="first noise seed (default 0); e.g. 5 for fresh seeds after tuning on 0-4")
    gb.add_argument("--design", choices=("discriminating", "sobol"), default="discriminating",
                    help="benchmark DOE: 32 points chosen from a candidate pool to tell the effects apart "
                         "(default, as mbc gap-plan), or 32 scattered Sobol' points (cheaper to plan)")
    gb.add_argument("--small", action="store_true", help="a few effects, one magnitude, 20 points")
    gb.add_argument("--suite", choices=("library", "outside"), default="library",
                    help="library (default): withheld effects of the diagnosis' own library; outside: functional "
                         "forms, sensor faults and structural truths the library lacks, plus the null "
                         "(engine_model.gap.outside) -> <out>/gap/outside_*.csv")
    gb.add_argument("--null-seeds", type=int, default=60,
                    help="--suite outside: noise seeds of the null case (default 60)")
    gb.add_argument("--plan", default=None,
                    help="--suite outside: plan CSV (e.g. from mbc gap-plan); default the 32-point "
                         "discriminating plan, computed first")
    gb.add_argument("--spec", default=None, help="engine spec TOML (default: embedded Yamaha R6 FS)")
    dask(gb)
    gb.set_defaults(func=cmd_gap_benchmark)

    gpl = sub.add_parser("gap-plan", help="propose bench points on which the gap library's effects differ most "
                                          "(model-discrimination design) -> CSV plan")
    gpl.add_argument("--out", required=True, help="plan CSV to write")
    gpl.add_argument("--points", type=int, default=32, help="bench points (default 32)")
    gpl.add_argument("--candidates", type=int, default=160,
                     help="candidate pool size (default 160; ~22 simulations each, in-process)")
    gpl.add_argument("--max-speed-gap-rpm", type=float, default=1000.0,
                     help="largest gap between neighbouring planned speeds and at the range's ends [rpm] "
                          "(default 1000, the ECU tables' speed spacing); too few --points for it is refused")
    gpl.add_argument("--speed-min", type=float, default=5000.0, help="low end of the speed range [rpm] (default 5000)")
    gpl.add_argument("--speed-max", type=float, default=12500.0, help="high end of the speed range [rpm] (default 12500)")
    gpl.add_argument("--spec", default=None, help="engine spec TOML (default: embedded Yamaha R6 FS)")
    gpl.set_defaults(func=cmd_gap_plan)
    return p


def main(argv=None) -> int:
    from flows.lifeline import is_stop, stop_signals

    args = build_parser().parse_args(argv)
    # `kill -USR1 <pid>` prints every thread's stack to stderr: where a run hangs.  Not where stderr is no
    # file (called in-process under a capturing test runner) or the platform has no SIGUSR1.
    with contextlib.suppress(AttributeError, OSError, ValueError):
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    try:
        with stop_signals():   # Ctrl-C and SIGTERM: KeyboardInterrupt once, clean-up, one line (flows/lifeline.py)
            return args.func(args)
    except BaseException as exc:
        if is_stop(exc):
            why = f" ({exc})" if isinstance(exc, KeyboardInterrupt) and str(exc) else ""
            tail = ("" if args.command == "serve" else
                    "; finished chunks are on disk, run the same command again to resume")
            print(f"\nmbc: interrupted{why}{tail}", file=sys.stderr)
            return 130
        if isinstance(exc, ValueError):
            print(f"mbc: error: {exc}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    raise SystemExit(main())
