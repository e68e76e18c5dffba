"""The ``run`` flow: the whole pipeline, on the embedded R6 spec and the packaged bench data by default.

    bench data --> calibration (airflow match + Wiebe identification)            calibration/, engine.toml
        |           (the calibrated engine is used by every later stage)
        +--> model: DOE plan on the virtual bench (truth engine = calibrated      virtual_bench/, model/
        |    model + hidden burn law + noise) --> identification --> global map-wide model
        |    (BDUR10-90, m) = f(load, speed, spark) + learning curve
        +--> maps: spark advance (MBT, knock-limited), injection time,            maps/
        |    target lambda, retarded starting map
        +--> gap: sim-to-real gap diagnosis of the bench data                     gap/
        --> index.html linking every figure and file, manifest.json

Each stage is a module of :mod:`flows.stages` with the signature ``run(ctx) -> dict``.  One local Dask
cluster (or ``--dask-address``) serves every stage; every simulation is a resumable Parquet sweep
(``sweeps/``).  The run folder is written as ``<folder>.partial/`` and renamed when complete, so an
interrupted run never looks finished; running the same ``--out`` again resumes, and a stage left out of
``--stages`` is taken from that folder (refused, before any work, if it is not there).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import shutil
import sys
import time
from pathlib import Path

from flows import prefect_env
from flows.evaluate import shared_cluster
from flows.lifeline import is_stop
from flows.settings import QUICK, STAGES, RunSettings, settings_from_dict, settings_to_dict  # noqa: F401
from flows.stages import calibration, gap, maps, model
from flows.stages.context import ENGINE_FILE, StageContext
from flows.sweep import DEFAULT_WORKERS

from prefect import flow  # noqa: E402

from engine_model.bench import load_bench  # noqa: E402
from engine_model.calibrated import CalibratedEngine  # noqa: E402
from engine_model.io import write_json  # noqa: E402
from engine_model.report import write_index  # noqa: E402
from engine_model.version import package_version  # noqa: E402

#: What a stage leaves in the run folder that a later stage needs (checked when the stage is not run).
STAGE_OUTPUTS = {"calibration": (ENGINE_FILE, "calibration/summary.json"), "model": ("model/model.json",),
                 "maps": ("maps/ecu_tables.parquet",), "gap": ("gap/run.json",)}
#: Which earlier stages each stage needs.
NEEDS = {"calibration": (), "model": ("calibration",), "maps": ("calibration", "model"), "gap": ("calibration",)}


def default_run_dir(tag: str) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("results") / f"{stamp}-{tag[:8]}"


def check_stage_inputs(folder: Path, stages: tuple[str, ...]) -> None:
    """ValueError unless every stage a requested stage needs is requested too or already in ``folder``."""
    for st in stages:
        for need in NEEDS[st]:
            if need in stages:
                continue
            missing = [f for f in STAGE_OUTPUTS[need] if not (folder / f).exists()]
            if missing:
                raise ValueError(f"--stages {','.join(stages)}: stage '{st}' needs the '{need}' stage's output "
                                 f"{missing} in {folder}, which is not there; add '{need}' to --stages or give "
                                 "--out a finished run that has it")


def _previous(work: Path, manifest: dict, stage: str) -> dict:
    """A stage's summary from an earlier run in the same folder (it was not asked to run again)."""
    import json

    old = work / "manifest.json"
    if old.exists():
        try:
            prev = json.loads(old.read_text())
        except ValueError:
            prev = {}
        if stage in prev:
            return prev[stage]
    if stage == "calibration":
        return json.loads((work / "calibration" / "summary.json").read_text())
    return {}


@flow(name="run", log_prints=False, validate_parameters=False)
def run_flow(out: str, bench: str | None = None, spec: str | None = None, settings: dict | None = None,
             workers: int = DEFAULT_WORKERS, dask_address: str | None = None, progress: bool = True) -> dict:
    """The pipeline into the folder ``out`` (see module docstring); ``settings``: :func:`settings_to_dict` form."""
    rs = settings_from_dict(settings)
    t0 = time.perf_counter()
    engine = CalibratedEngine.from_spec(spec)
    meas = load_bench(bench)
    source = "packaged Table 2 (paper, WOT, lambda 0.9)" if bench is None else str(bench)
    final = Path(out)
    work = final.with_name(final.name + ".partial")
    if final.exists() and not work.exists():
        final.rename(work)          # update in place: the sweeps inside resume
    work.mkdir(parents=True, exist_ok=True)
    man: dict = {"kind": "run", "package_version": package_version(), "engine": engine.spec.name,
                 "spec_hash": engine.spec_hash(), "bench": source, "settings": dataclasses.asdict(rs),
                 "stages": list(rs.stages), "quick": rs.quick}
    previous = {s: _previous(work, man, s) for s in STAGES if s not in rs.stages}
    timings: dict = {}
    write_json({**man, "status": "running"}, work / "running.json")
    try:
        with shared_cluster(workers, dask_address) as addr:
            ctx = StageContext(work=work, engine=engine, engine_file=spec, address=addr, settings=rs, bench=meas,
                               bench_source=source, progress=progress)
            for name, module in (("calibration", calibration), ("model", model), ("maps", maps), ("gap", gap)):
                t = time.perf_counter()
                if name in rs.stages:
                    if progress:   # the overall line: which stage of how many, time so far
                        print(f"== stage {rs.stages.index(name) + 1}/{len(rs.stages)} {name} "
                              f"(run time so far {time.perf_counter() - t0:.0f} s)", file=sys.stderr)
                    man[name] = module.run(dataclasses.replace(ctx, stage=name))
                    timings[name] = round(time.perf_counter() - t, 1)
                    if progress:
                        print(f"\n   stage {name} done in {timings[name]:.0f} s", file=sys.stderr)
                elif previous.get(name):
                    man[name] = previous[name]
                if name == "calibration":
                    if name in rs.stages:
                        ctx = ctx.with_engine(calibration.calibrated_engine(engine, man[name]))
                    else:
                        ctx = dataclasses.replace(ctx, engine=CalibratedEngine.load(work / ENGINE_FILE),
                                                  engine_file=str(work / ENGINE_FILE))
                    man["calibrated_spec_hash"] = ctx.engine.spec_hash()
    except BaseException as exc:
        state = "interrupted" if is_stop(exc) else "failed"
        write_json({**man, "status": state, "error": repr(exc)[:500]}, work / "running.json")
        raise
    man["timings_s"] = timings
    man["wall_time_s"] = round(time.perf_counter() - t0, 1)
    man["created"] = _dt.datetime.now().isoformat(timespec="seconds")
    man["status"] = "complete"
    write_json(man, work / "manifest.json")
    (work / "running.json").unlink(missing_ok=True)
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
    summary = [("engine", f"{man['engine']} (spec {man['spec_hash'][:12]}, calibrated {man['calibrated_spec_hash'][:12]}"
                          f"; {ENGINE_FILE})"),
               ("bench data", man["bench"]),
               ("run", f"stages {', '.join(man['stages'])}" + (" (--quick: small settings)" if man.get("quick") else "")),
               ("airflow match", ", ".join(f"{k} = {v:.4g}" for k, v in air["parameters"].items())
                + f"; max |Ga_REL| {air['max_abs_ga_rel_pct']:.2f} %"),
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
    summary.append(("wall time", f"{man.get('wall_time_s', 0):.0f} s ("
                    + ", ".join(f"{k} {v:.0f} s" for k, v in man.get("timings_s", {}).items()) + ")"))
    cal_figs = sorted(p.relative_to(work) for p in (work / "calibration" / "figures").glob("*.png"))
    sections = [("Calibration on the bench data", "Airflow matching and Wiebe identification (report: "
                 "calibration/calibration.html); the calibrated engine is engine.toml (--spec of any command).",
                 ["calibration/calibration.html", "calibration/airflow_match.parquet",
                  "calibration/combustion_params.parquet", ENGINE_FILE, *cal_figs])]
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
    rs = RunSettings() if settings is None else settings
    engine = CalibratedEngine.from_spec(spec)
    load_bench(bench)   # bad bench data fails here, before any folder exists
    final = Path(out) if out else default_run_dir(engine.spec_hash())
    folder = final if final.exists() else final.with_name(final.name + ".partial")
    check_stage_inputs(folder, rs.stages)
    with prefect_env.prefect_api(verbose=kwargs.get("progress", True)):
        return run_flow(out=str(final), bench=None if bench is None else str(bench), spec=spec,
                        settings=settings_to_dict(rs), **kwargs)
