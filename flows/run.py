"""The ``run`` flow: the whole pipeline, on the embedded R6 spec and the packaged bench data by default.

    bench data --> calibration (airflow match + Wiebe identification)            calibration/
        |           (the airflow-matched spec is used by every later stage)
        +--> DOE plan on the virtual bench (truth engine = matched model +         virtual_bench/
        |    hidden burn law + noise) --> Wiebe identification at every DOE point
        +--> global map-wide model (BDUR10-90, m) = f(load, speed, spark)           model/
        |    (+ learning curve of DOE designs against a full grid)
        +--> ECU tables: spark advance (MBT, knock-limited), injection time,       maps/
        |    target lambda, retarded starting map
        +--> sim-to-real gap diagnosis of the bench data                           gap/
        --> index.html linking every figure and file, manifest.json

One local Dask cluster (or ``--dask-address``) serves every stage; every
simulation is a resumable Parquet sweep (``*/sweeps/``).  The run folder is
written as ``<folder>.partial/`` and renamed when complete, so an interrupted
run never looks finished; running the same ``--out`` again resumes.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from . import prefect_env
from .calibrate import CalibrationSettings, calibrate_into
from .evaluate import SweepEvaluator, shared_cluster
from .gap import gap_into
from .sweep import DEFAULT_WORKERS

from prefect import flow  # noqa: E402

from engine_model import __version__, load_spec  # noqa: E402
from engine_model.bench import load_bench  # noqa: E402
from engine_model.io import write_json, write_parquet  # noqa: E402
from engine_model.report import write_index, write_report  # noqa: E402

STAGES = ("calibration", "virtual_bench", "model", "maps", "gap")


@dataclass(frozen=True)
class RunSettings:
    """Knobs of ``mbc run`` (defaults: the full job; :data:`QUICK` is the small one the tests run).

    eta_trans [-]: transmission efficiency assumed between crank and brake (paper: 0.95).
    step_deg [deg]: crank-angle step of every simulation.
    calibration: airflow-match and identification settings (grid sizes, iterations).
    doe_points, doe_seed, spark_offsets, doe_bounds: operating points on the virtual bench (D-optimal over throttle x speed
        from screened candidates) and the spark sweep run at each, offsets from the MBT prior [deg].
    ident_grid: (n_bdur, n_m) of the cheap identification at the DOE points.
    map_throttle, map_speed: ECU breakpoints ('0,5,10' or 'start:stop:step'; None = EcuGrid default).
    learning_sizes, learning_seeds: learning curve of DOE designs (cheap: truth + the identification
        error measured in this run, see engine_model.learning.noisy_truth).
    stages: which stages run (later stages need the earlier ones).
    """

    eta_trans: float = 0.95
    step_deg: float = 0.5
    calibration: CalibrationSettings = field(default_factory=CalibrationSettings)
    doe_design: str = "d_optimal_feasible"
    doe_points: int = 10
    spark_offsets: tuple = (-15, -10, -5, 0, 5)
    doe_bounds: dict = field(default_factory=dict)
    doe_seed: int = 0
    ident_grid: tuple = (6, 6)
    map_throttle: str | None = None
    map_speed: str | None = None
    learning_sizes: tuple = (12, 16, 24, 32, 48, 64)
    learning_seeds: tuple = (0, 1, 2)
    holdout: dict = field(default_factory=dict)
    stages: tuple = STAGES

    def __post_init__(self):
        bad = [s for s in self.stages if s not in STAGES]
        if bad:
            raise ValueError(f"RunSettings.stages: unknown stage(s) {bad}; known: {list(STAGES)}")
        if not 0.5 <= self.eta_trans <= 1.0:
            raise ValueError(f"RunSettings.eta_trans = {self.eta_trans!r} must lie in [0.5, 1]")
        if self.doe_points < 6:
            raise ValueError(f"RunSettings.doe_points = {self.doe_points!r}: at least 6 operating points are "
                             "needed (one spark sweep each)")


#: A small run for tests and smoke checks: 1 deg step, coarse searches, a 3 x 3 ECU grid.
QUICK = RunSettings(
    step_deg=1.0,
    calibration=CalibrationSettings(step_deg=1.0, airflow_grid=(2, 2, 1), airflow_starts=1, airflow_max_nfev=2,
                                    n_bdur=7, n_m=7, surface="cubic"),
    doe_points=10, spark_offsets=(-10, -5, 0),
    # the small run stays where the (uncalibrated, pessimistic) knock model lets sweeps run
    doe_bounds={"throttle_pct": (30.0, 100.0), "speed_rpm": (6000.0, 13000.0)}, ident_grid=(5, 5), map_throttle="30,60,100", map_speed="6000,9000,12000",
    learning_sizes=(12, 16), learning_seeds=(0,),
    holdout={"throttle_pct": (20, 60, 100), "speed_rpm": (6000, 9000, 12000), "spark_offset": (-15, -5, 5)})


def settings_to_dict(rs: RunSettings) -> dict:
    """Plain-JSON form of :class:`RunSettings` (flow parameters must serialise)."""
    return dataclasses.asdict(rs)


def settings_from_dict(d: dict | RunSettings | None) -> RunSettings:
    """Inverse of :func:`settings_to_dict`; ``None`` gives the defaults."""
    if d is None:
        return RunSettings()
    if isinstance(d, RunSettings):
        return d
    d = dict(d)
    cal = d.pop("calibration", None)
    tuples = {f.name for f in dataclasses.fields(RunSettings) if f.type == "tuple"}
    d = {k: tuple(v) if k in tuples and v is not None else v for k, v in d.items()}
    if cal is not None and not isinstance(cal, CalibrationSettings):
        cal = dict(cal)
        if "airflow_grid" in cal:
            cal["airflow_grid"] = tuple(cal["airflow_grid"])
        cal = CalibrationSettings(**cal)
    return RunSettings(**d, **({"calibration": cal} if cal is not None else {}))


def default_run_dir(tag: str) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("results") / f"{stamp}-{tag[:8]}"


def _stage_time(timings: dict, name: str, t0: float) -> float:
    now = time.perf_counter()
    timings[name] = round(now - t0, 1)
    return now


def _virtual_bench_stage(work: Path, cal_spec, overrides: dict, spec: str | None, addr: str, rs: RunSettings,
                         progress: bool) -> dict:
    """DOE plan -> virtual bench -> identification at the feasible points -> global model (+ learning curve)."""
    from engine_model import doe, learning
    from engine_model.burnlaw import BurnLaw
    from engine_model.identify import identification_plan
    from engine_model.identify_sweep import choose_operating_points, identify_sweeps, sweep_plan
    from engine_model.mapmodel import fit_map_model
    from engine_model.virtual_bench import NoiseModel, VirtualBench

    vdir, mdir = work / "virtual_bench", work / "model"
    vdir.mkdir(parents=True, exist_ok=True)
    mdir.mkdir(parents=True, exist_ok=True)

    def ev(label):
        return SweepEvaluator(work / "sweeps", addr, spec=spec, step_deg=rs.step_deg, label=label,
                              progress=progress, overrides=overrides)

    law = BurnLaw()
    bench = VirtualBench(spec=cal_spec, law=law, eta_trans=rs.eta_trans, seed=rs.doe_seed)
    # like a real first session: a quick model check (MBT prior, burn-duration prior) screens the candidate
    # points for the paper's two infeasible zones, so the design does not waste bench time on them
    quick = doe.QUICK_SOLVER
    ev_feas = SweepEvaluator(work / "sweeps", addr, spec=spec, step_deg=max(quick.step_deg, rs.step_deg),
                             tolerance=quick.tolerance, label="feasibility", progress=progress, overrides=overrides)

    def feasible(points: pd.DataFrame) -> np.ndarray:
        # can the sweep run at all?  Screened at its most retarded spark (candidates come at the MBT prior)
        pts = points.reset_index(drop=True).copy()
        pts["spark_deg_btdc"] = pts["spark_deg_btdc"] + min(rs.spark_offsets)
        pts = doe.with_combustion(pts)
        if "point_id" not in pts.columns:
            pts["point_id"] = [f"c{i:05d}" for i in range(len(pts))]
        return doe.feasibility(pts, evaluate=ev_feas)["feasible"].to_numpy(bool)

    # the paper's bench procedure: per operating point (D-optimal over throttle x speed, screened) a spark
    # sweep around the MBT prior; the sweep is identified jointly (engine_model.identify_sweep), which pins
    # the burn far better than each point alone (torque and exhaust T only; no CA50 away from MBT)
    ops = choose_operating_points(rs.doe_points, feasible=feasible, seed=rs.doe_seed,
                                  bounds=dict(rs.doe_bounds) if rs.doe_bounds else None)
    plan = sweep_plan(ops, offsets=rs.spark_offsets)
    write_parquet(plan, vdir / "plan.parquet")
    meas = bench.measure(plan, evaluate=ev("vbench"))
    write_parquet(meas, vdir / "measured.parquet")
    ok = meas[meas["status"] == "ok"].reset_index(drop=True)
    if len(ok) < 6:
        raise RuntimeError(f"virtual bench: only {len(ok)} of {len(meas)} DOE points could be run "
                           f"({meas['status'].value_counts().to_dict()}); too few for a map model")
    ok["at_mbt"] = False
    n_b, n_m = rs.ident_grid
    ident_plan = identification_plan(ok, {f"spec.{k}": v for k, v in overrides.items()}, n_b, n_m)
    ident = identify_sweeps(meas, ev("ident")(ident_plan), eta_trans=rs.eta_trans)
    ran = ident[np.isfinite(ident["bdur_10_90_deg"].to_numpy(float))].index
    truth = law.predict(ident.loc[ran, ["throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda"]])
    ident["bdur_10_90_deg_truth"] = np.nan
    ident["wiebe_m_truth"] = np.nan
    ident.loc[ran, "bdur_10_90_deg_truth"] = truth["bdur_10_90_deg"].to_numpy()
    ident.loc[ran, "wiebe_m_truth"] = truth["wiebe_m"].to_numpy()
    write_parquet(ident, vdir / "identified.parquet")
    good = ident[ident["fit_ok"].astype(bool)] if "fit_ok" in ident.columns else ident
    err_b = good["bdur_10_90_deg"] - good["bdur_10_90_deg_truth"]
    err_m = good["wiebe_m"] - good["wiebe_m_truth"]
    id_err = {"points": int(len(good)), "of": int(len(ident)), "bench_points": int(len(meas)),
              "bdur_rmse_deg": float(np.sqrt(np.mean(err_b ** 2))), "bdur_bias_deg": float(err_b.mean()),
              "m_rmse": float(np.sqrt(np.mean(err_m ** 2))), "m_bias": float(err_m.mean())}

    fallback = ""
    if len(good) < 6:
        finite = ident[np.isfinite(ident["bdur_10_90_deg"].to_numpy(float))]
        if len(finite) >= 6:
            fallback = (f"Only {len(good)} sweeps met the identification tolerances; the model is fitted on all "
                        f"{len(finite)} finite estimates (tolerance misses included, flagged in identified.parquet).")
            good = finite
    if len(good) < 6:
        raise RuntimeError(f"identification: only {len(good)} of {len(ident)} virtual-bench points were identified "
                           "within tolerance; a map model needs >= 6 (see virtual_bench/identified.parquet)")
    model = fit_map_model(good, spec=cal_spec)
    model.save(mdir / "model.json")
    cv = model.cv_table()
    write_parquet(cv, mdir / "cv.parquet")

    # where can the truth engine run?  The hold-out grid once through the noise-free virtual bench (quick
    # solver); the map is scored there, and the learning curve loses the points the bench would abort
    test = learning.holdout_grid(**rs.holdout)
    test["point_id"] = [f"h{i:04d}" for i in range(len(test))]
    quiet = dataclasses.replace(bench, noise=NoiseModel.none())
    ev_hold = SweepEvaluator(work / "sweeps", addr, spec=spec, step_deg=max(quick.step_deg, rs.step_deg),
                             tolerance=quick.tolerance, label="holdout", progress=progress, overrides=overrides)
    hold = quiet.measure(test, evaluate=ev_hold)
    write_parquet(hold, vdir / "holdout_status.parquet")
    runnable = (hold["status"] == "ok").to_numpy()
    feas = learning.nearest_feasible(test, runnable)
    test_ok = test[runnable].reset_index(drop=True)
    pred = model.predict(test_ok)
    tru = law.predict(test_ok)
    held = {"points": int(len(test_ok)), "of": int(len(test)),
            "bdur_rmse_deg": float(np.sqrt(np.mean((pred["bdur_10_90_deg"] - tru["bdur_10_90_deg"]) ** 2))),
            "m_rmse": float(np.sqrt(np.mean((pred["wiebe_m"] - tru["wiebe_m"]) ** 2)))}

    # learning curve: identification error as measured above, designs against a full grid
    sb, sm = max(id_err["bdur_rmse_deg"], 0.1), max(id_err["m_rmse"], 0.02)
    curve = learning.learning_curve(None, law, sizes=rs.learning_sizes, seeds=rs.learning_seeds,
                                    designs=("grid", "d_optimal_feasible", "sobol"), test_points=test_ok,
                                    feasible=feas,
                                    identify_seeded=lambda s: learning.noisy_truth(law, sb, sm, seed=s,
                                                                                   feasible=feas))
    write_parquet(curve, mdir / "learning_curve.parquet")
    learning.plot_learning_curve(curve, mdir / "learning_curve.png")
    summ = learning.summarise(curve)
    write_parquet(summ, mdir / "learning_summary.parquet")
    lines = [f"Virtual bench: {len(ops)} operating points (D-optimal over throttle x speed from screened "
             f"candidates, seed {rs.doe_seed}) x spark offsets {list(rs.spark_offsets)} deg = {len(meas)} bench points; status "
             f"{meas['status'].value_counts().to_dict()}.",
             f"Joint spark-sweep identification at {id_err['points']} of {id_err['of']} operating points against the hidden law: "
             f"BDUR10-90 RMSE {id_err['bdur_rmse_deg']:.2f} deg (bias {id_err['bdur_bias_deg']:+.2f}), m RMSE "
             f"{id_err['m_rmse']:.2f} (bias {id_err['m_bias']:+.2f}).",
             f"Global model (chosen per output by K-fold CV: {model.chosen_}); error against the hidden law on "
             f"the {held['points']} runnable points of the {held['of']}-point hold-out grid: BDUR10-90 "
             f"{held['bdur_rmse_deg']:.2f} deg, m {held['m_rmse']:.2f}.",
             *([fallback] if fallback else []),
             f"Learning curve: identification noise {sb:.2f} deg / {sm:.2f} (as measured above), designs "
             "against a full grid."]
    write_report(mdir, "model", "Virtual bench, identification and the global model",
                 [("Summary", lines), ("Cross-validation", [cv]), ("Learning curve", [summ, mdir / "learning_curve.png"])])
    return {"doe_points": len(meas), "status": meas["status"].value_counts().to_dict(), "identification": id_err,
            "model_chosen": dict(model.chosen_), "holdout": held, "model_path": str(mdir / "model.json"),
            "lines": lines}


def _maps_stage(work: Path, cal_spec, overrides: dict, spec: str | None, addr: str, rs: RunSettings,
                progress: bool) -> dict:
    from engine_model.mapmodel import load as load_model
    from engine_model.maps import EcuGrid, build_maps, parse_breakpoints
    from engine_model.maps_io import write_maps

    model = load_model(work / "model" / "model.json", spec=cal_spec)
    grid = EcuGrid(parse_breakpoints(rs.map_throttle, "throttle") if rs.map_throttle else EcuGrid().throttle_pct,
                   parse_breakpoints(rs.map_speed, "speed") if rs.map_speed else EcuGrid().speed_rpm)
    ev = SweepEvaluator(work / "sweeps", addr, spec=spec, step_deg=rs.step_deg, label="maps", progress=progress,
                        overrides=overrides)
    res = build_maps(cal_spec, model, grid=grid, evaluate=ev)
    paths = write_maps(res, work / "maps")
    return {"stats": res.stats, "files": {k: str(v) for k, v in paths.items()}}


@flow(name="run", log_prints=False, validate_parameters=False)
def run_flow(out: str, bench: str | None = None, spec: str | None = None, settings: dict | None = None,
             workers: int = DEFAULT_WORKERS, dask_address: str | None = None, progress: bool = True) -> dict:
    """The pipeline into the folder ``out`` (see module docstring); ``settings``: :func:`settings_to_dict` form."""
    rs = settings_from_dict(settings)
    t0 = time.perf_counter()
    eng = load_spec(spec)
    meas = load_bench(bench)
    source = "packaged Table 2 (paper, WOT, lambda 0.9)" if bench is None else str(bench)
    final = Path(out)
    work = final.with_name(final.name + ".partial")
    if final.exists() and not work.exists():
        final.rename(work)          # update in place: the sweeps inside resume
    work.mkdir(parents=True, exist_ok=True)
    timings: dict = {}
    man: dict = {"kind": "run", "package_version": __version__, "engine": eng.name, "spec_hash": eng.spec_hash(),
                 "bench": source, "settings": dataclasses.asdict(rs), "stages": list(rs.stages)}
    t = t0
    with shared_cluster(workers, dask_address) as addr:
        cal = calibrate_into(work / "calibration", meas, eng, spec, addr,
                             dataclasses.replace(rs.calibration, eta_trans=rs.eta_trans, step_deg=rs.step_deg),
                             progress)
        overrides = {k: float(v) for k, v in cal["airflow"]["parameters"].items()}
        cal_spec = eng.with_values(overrides)
        man["calibration"] = cal
        man["calibrated_spec_hash"] = cal_spec.spec_hash()
        t = _stage_time(timings, "calibration", t)
        if "virtual_bench" in rs.stages or "model" in rs.stages:
            man["model"] = _virtual_bench_stage(work, cal_spec, overrides, spec, addr, rs, progress)
            t = _stage_time(timings, "virtual_bench_and_model", t)
        if "maps" in rs.stages and "model" in man:
            man["maps"] = _maps_stage(work, cal_spec, overrides, spec, addr, rs, progress)
            t = _stage_time(timings, "maps", t)
        if "gap" in rs.stages:
            man["gap"] = gap_into(work, meas, source, spec, addr, rs.step_deg, progress, overrides=overrides)
            t = _stage_time(timings, "gap", t)
    man["timings_s"] = timings
    man["wall_time_s"] = round(time.perf_counter() - t0, 1)
    man["created"] = _dt.datetime.now().isoformat(timespec="seconds")
    man["status"] = "complete"
    write_json(man, work / "manifest.json")
    _write_index(work, man)
    if final.exists():
        shutil.rmtree(final)
    work.rename(final)
    if progress:
        print(_summary_text(man, final), file=sys.stdout)
    return man


def _write_index(work: Path, man: dict) -> Path:
    cal = man["calibration"]
    air = cal["airflow"]
    summary = [("engine", f"{man['engine']} (spec {man['spec_hash'][:12]}, matched {man['calibrated_spec_hash'][:12]})"),
               ("bench data", man["bench"]),
               ("airflow match", f"parameters {air['parameters']}; max |Ga_REL| {air['max_abs_ga_rel_pct']:.2f} %"),
               ("identification", f"{cal['identification']['fit_ok']} of {cal['identification']['points']} "
                                  "bench points identified")]
    if "model" in man:
        h = man["model"]["holdout"]
        summary.append(("global model", f"{man['model']['model_chosen']}; error vs hidden law BDUR10-90 "
                                        f"{h['bdur_rmse_deg']:.2f} deg, m {h['m_rmse']:.2f}"))
    if "gap" in man:
        summary.append(("gap diagnosis", man["gap"]["statement"]))
        if man["gap"].get("pair_statement"):
            summary.append(("gap, two effects at once", man["gap"]["pair_statement"]))
    summary.append(("wall time", f"{man.get('wall_time_s', 0):.0f} s ({man.get('timings_s', {})})"))
    cal_figs = sorted(p.relative_to(work) for p in (work / "calibration" / "figures").glob("*.png"))
    sections = [("Calibration on the bench data", "Airflow matching and Wiebe identification (report: "
                 "calibration/calibration.html).",
                 ["calibration/calibration.html", "calibration/airflow_match.parquet",
                  "calibration/combustion_params.parquet", *cal_figs])]
    if "model" in man:
        sections.append(("Virtual bench and global model", " ".join(man["model"]["lines"]),
                         ["model/model.html", "model/model.json", "model/learning_curve.png",
                          "virtual_bench/measured.parquet", "virtual_bench/identified.parquet"]))
    if "maps" in man:
        mfiles = sorted(p.relative_to(work) for p in (work / "maps").glob("*") if p.is_file())
        sections.append(("ECU tables", "Spark advance (MBT, knock-limited), injection time, target lambda and the "
                         "retarded starting map.", mfiles))
    if "gap" in man:
        gfiles = sorted(p.relative_to(work) for p in (work / "gap").glob("*") if p.is_file())
        sections.append(("Sim-to-real gap", man["gap"]["statement"], gfiles))
    sections.append(("Run", "", ["manifest.json", "sweeps"]))
    return write_index(work, "mbc run: Yamaha R6 FS calibration", summary, sections)


def _summary_text(man: dict, final: Path) -> str:
    cal = man["calibration"]["airflow"]
    lines = ["", f"run complete in {man['wall_time_s']:.0f} s ({man['timings_s']})",
             f"airflow match: {cal['parameters']}, max |Ga_REL| = {cal['max_abs_ga_rel_pct']:.2f} %"]
    if "model" in man:
        lines += man["model"]["lines"][1:3]
    if "maps" in man:
        lines.append(f"ECU tables: {final}/maps/ (ecu_tables.parquet, spark_advance.csv, injection_time.csv, "
                     "lambda_target.csv, PNGs)")
    if "gap" in man:
        lines.append("gap: " + man["gap"]["statement"])
        if man["gap"].get("pair_statement"):
            lines.append("gap, pairs: " + man["gap"]["pair_statement"])
    lines.append(f"index: {final}/index.html")
    return "\n".join(lines)


def run_pipeline(out=None, bench=None, spec=None, settings: RunSettings | None = None, **kwargs) -> dict:
    """Validate the inputs, then run :func:`run_flow` under one Prefect API for the whole run."""
    settings = settings_to_dict(RunSettings() if settings is None else settings)
    eng = load_spec(spec)
    load_bench(bench)   # bad bench data fails here, before any folder exists
    final = Path(out) if out else default_run_dir(eng.spec_hash())
    with prefect_env.prefect_api(verbose=kwargs.get("progress", True)):
        return run_flow(out=str(final), bench=None if bench is None else str(bench), spec=spec, settings=settings,
                        **kwargs)
