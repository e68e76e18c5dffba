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
from importlib import resources
from pathlib import Path

from flows import eta, prefect_env
from flows.evaluate import shared_cluster
from flows.lifeline import checkpoint, is_stop
from flows.settings import QUICK, STAGES, RunSettings, settings_from_dict, settings_to_dict  # noqa: F401
from flows.stages import calibration, gap, maps, model
from flows.stages.context import BENCH_FILE, ENGINE_FILE, StageContext
from flows.sweep import DEFAULT_WORKERS

from prefect import flow  # noqa: E402

from engine_model.bench import load_bench, packaged_bench_path  # noqa: E402
from engine_model.calibrated import CalibratedEngine  # noqa: E402
from engine_model.contracts import throttle_to_pct  # noqa: E402
from engine_model.io import read_table, write_json, write_parquet  # noqa: E402
from engine_model.report import format_mapping, format_parameters, format_value, write_index  # noqa: E402
from engine_model.version import package_version  # noqa: E402

#: What a stage leaves in the run folder that a later stage needs (checked when the stage is not run).
STAGE_OUTPUTS = {"calibration": (ENGINE_FILE, "calibration/summary.json"), "model": ("model/model.json",),
                 "maps": ("maps/ecu_tables.parquet",), "gap": ("gap/run.json",)}
#: How the manifest names the packaged bench data.
PACKAGED_BENCH = "packaged Table 2 (paper, WOT, lambda 0.9)"
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


def run_bench(folder: Path, bench, stages: tuple[str, ...]) -> tuple[str | None, str]:
    """(bench file or None for the packaged data, how the manifest names it) for a run into ``folder``.

    ``--bench`` wins.  Without it, a run that does not re-run the calibration takes the copy of the bench
    data an earlier run of the folder kept (:data:`BENCH_FILE`, the data the engine was calibrated on);
    a folder calibrated on other data that kept no copy is refused (ValueError) rather than diagnosed on
    the packaged data.
    """
    if bench is not None:
        return str(bench), str(bench)
    if "calibration" in stages:
        return None, PACKAGED_BENCH
    old = _manifest(folder).get("bench", PACKAGED_BENCH)
    if (folder / BENCH_FILE).is_file():
        return str(folder / BENCH_FILE), old
    if old != PACKAGED_BENCH:
        raise ValueError(f"{folder} was calibrated on the bench data '{old}' and holds no copy ({BENCH_FILE}); "
                         "give that file with --bench")
    return None, PACKAGED_BENCH


def _manifest(folder: Path) -> dict:
    """The run's manifest.json ({} when missing or unreadable)."""
    import json

    try:
        return json.loads((folder / "manifest.json").read_text())
    except (OSError, ValueError):
        return {}


def _keep_bench_copy(bench: str | None, work: Path, throttle_unit: str = "pct") -> None:
    """The bench data as read (before validation; throttle in percent) into ``work/bench.parquet``, for later
    stages and rebuilds."""
    if bench is None:
        with resources.as_file(packaged_bench_path()) as p:
            raw = read_table(p)
    else:
        raw = read_table(bench)
    write_parquet(throttle_to_pct(raw, f"bench file {bench}", throttle_unit), work / BENCH_FILE)


def _expected_times(rs: RunSettings, bench_points: int, workers: int | None) -> dict:
    """Rough expected wall time [s] of each requested stage (:mod:`flows.eta`)."""
    cells = maps.ecu_grid(rs.map_throttle, rs.map_speed).shape
    return {s: eta.expected_stage_s(s, rs.quick, rs.step_deg, bench_points, rs.doe_points, cells[0] * cells[1],
                                    workers) for s in rs.stages}


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
             workers: int = DEFAULT_WORKERS, dask_address: str | None = None, progress: bool = True,
             throttle_unit: str = "pct") -> dict:
    """The pipeline into the folder ``out`` (see module docstring); ``settings``: :func:`settings_to_dict` form.

    ``throttle_unit`` "fraction" reads the bench file's ``throttle_pct`` as 0-1 and converts it to percent."""
    rs = settings_from_dict(settings)
    t0 = time.perf_counter()
    engine = CalibratedEngine.from_spec(spec)
    final = Path(out)
    work = final.with_name(final.name + ".partial")
    if final.exists() and not work.exists():
        final.rename(work)          # update in place: the sweeps inside resume
    given = bench
    bench, source = run_bench(work, bench, rs.stages)
    unit = throttle_unit if given is not None else "pct"    # the run's own copy is kept in percent
    meas = load_bench(bench, unit)
    work.mkdir(parents=True, exist_ok=True)
    if "calibration" in rs.stages:
        _keep_bench_copy(bench, work, unit)
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
            expect = _expected_times(rs, len(meas), None if dask_address else workers)
            for name, module in (("calibration", calibration), ("model", model), ("maps", maps), ("gap", gap)):
                t = time.perf_counter()
                checkpoint()   # SIGTERM stops like Ctrl-C; a stop a library lost is acted on here (lifeline)
                if name in rs.stages:
                    if progress:   # the overall line: which stage of how many, time so far, rough time left
                        left = sum(v for k, v in expect.items() if rs.stages.index(k) >= rs.stages.index(name))
                        print(f"== stage {rs.stages.index(name) + 1}/{len(rs.stages)} {name}: run time so far "
                              f"{eta.minutes(time.perf_counter() - t0)}; expected ~{eta.minutes(expect[name])} for "
                              f"this stage, ~{eta.minutes(left)} to the end of the run", file=sys.stderr)
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


def _identification_text(idn: dict) -> str:
    """'6 of 7 bench points identified' plus the points whose parameters lie at the edge of the search."""
    rng = idn.get("search_range") or {"bdur_10_90_deg": [20.0, 50.0], "wiebe_m": [2.0, 8.0]}
    text = f"{idn['fit_ok']} of {idn['points']} bench points identified"
    flags = []
    for key, label in (("bdur_10_90_deg", "BDUR10-90"), ("wiebe_m", "m")):
        lo, hi = rng[key]
        for side, b in (("lower", lo), ("upper", hi)):
            at = [r["point_id"] for r in idn.get("per_point", []) if r.get(key) is not None
                  and abs(r[key] - b) <= 0.01 * (hi - lo)]
            if at:
                flags.append(f"{label} at its {side} search bound {format_value(float(b), key)} at {len(at)} "
                             f"point(s) ({', '.join(at)})")
    return text + ("; " + "; ".join(flags) if flags else "")


def index_summary(man: dict) -> list[tuple[str, str]]:
    """The key-figure rows at the top of a run's index.html, from its manifest: rounded numbers with units,
    the run mode, and parameters at (or near) their search bounds flagged."""
    from engine_model.calibration import DEFAULT_PARAMETERS

    cal = man["calibration"]
    air = cal["airflow"]
    bounds = air.get("bounds") or {p.name: (p.low, p.high) for p in DEFAULT_PARAMETERS}
    st = man.get("settings", {})
    mode = (f"stages {', '.join(man['stages'])}; " + ("--quick (small smoke-run settings: coarse searches, "
            "small tables)" if man.get("quick") else "full settings")
            + (f"; crank step {st['step_deg']:g} deg" if isinstance(st.get("step_deg"), (int, float)) else ""))
    summary = [("engine", f"{man['engine']} (spec {man['spec_hash'][:12]}, calibrated {man['calibrated_spec_hash'][:12]}"
                          f"; {ENGINE_FILE})"),
               ("bench data", man["bench"]),
               ("run mode", mode),
               ("airflow match", format_parameters(air["parameters"], bounds, air.get("at_bound"))
                + f"; max |Ga_REL| {air['max_abs_ga_rel_pct']:.2f} %"),
               ("identification", _identification_text(cal["identification"]))]
    if "model" in man:
        h = man["model"]["holdout"]
        summary.append(("global model", f"{format_mapping(man['model']['model_chosen'])}; error vs hidden law "
                                        f"BDUR10-90 {h['bdur_rmse_deg']:.2f} deg, m {h['m_rmse']:.2f}"))
    if "gap" in man:
        summary.append(("gap diagnosis", man["gap"]["statement"]))
        if man["gap"].get("pair_statement"):
            summary.append(("gap, two effects at once", man["gap"]["pair_statement"]))
    summary.append(("wall time", f"{man.get('wall_time_s', 0):.0f} s ("
                    + ", ".join(f"{k} {v:.0f} s" for k, v in man.get("timings_s", {}).items()) + ")"))
    return summary


def _trend_text(trends: dict | None) -> str:
    """One sentence on the table's physical trends (``engine_model.knock.table_trends``) for the index."""
    if not trends:
        return ""
    def cells(rows):
        return ", ".join(f"{r['speed_rpm']:.0f} rpm {r['throttle_pct']:g} %"
                         + (f" ({r['charge_vs_wot']:.2f} of WOT's charge)" if r.get("charge_vs_wot") is not None
                            else "") for r in rows) or "none"
    def spans(rows):
        by_speed: dict[float, list[float]] = {}
        for r in rows:
            by_speed.setdefault(r["speed_rpm"], []).append(r["throttle_pct"])
        return "; ".join(f"{n:.0f} rpm at {min(t):g} % (1 cell)" if len(t) == 1 else
                         f"{n:.0f} rpm at {min(t):g}-{max(t):g} % ({len(t)} cells)"
                         for n, t in sorted(by_speed.items())) or "none"
    small = trends.get("small_throttle_knock", [])
    lean = trends.get("full_charge_lean_knock", [])
    lean_text = (f" Knock-limited at >= 90 % of WOT's charge on a leaner target lambda than WOT's: {spans(lean)}"
                 f" (full load without WOT's enrichment; a richer target there raises the knock border)." if lean
                 else "")
    moves = trends.get("load_trend_moves", [])
    moved = (f" (the load-trend fit moved {len(moves)} MBT targets by more than 2 deg, up to "
             f"{max(abs(m['shift_deg']) for m in moves):.1f} deg, where the model's own MBT estimates ran against "
             f"the trend)" if moves else "")
    return (f"Trends: part-load cells more than 2 deg behind WOT: {len(trends.get('part_load_drops', []))}{moved}; "
            f"knock-limited cells at light load (< half of WOT's charge, >= 2000 rpm, <= 20 % throttle): "
            f"{cells(trends.get('light_load_knock', []))}; knock-limited at <= 20 % throttle all told: "
            f"{cells(small)}; knock even at full retard (zone 1): {spans(trends.get('zone1', []))}."
            f"{lean_text}{_evidence_text(trends)}")


def _evidence_text(trends: dict) -> str:
    """Where the table's knock border rests on bench evidence and where it is the model's extrapolation."""
    ev = trends.get("knock_evidence")
    if not ev:
        return ""
    (n0, n1), (t0, t1) = ev["speed_rpm"], ev["throttle_pct"]
    span = f"{n0:.0f}-{n1:.0f} rpm" if n1 > n0 else f"{n0:.0f} rpm"
    thr = f"{t0:g}-{t1:g} %" if t1 > t0 else f"{t0:g} %"
    outside = ev["outside_speeds_rpm"]
    where = (f" (at {', '.join(f'{n:.0f}' for n in outside)} rpm)" if outside else "")
    return (f" The knock evidence is {ev['points']} bench points at {span}, {thr} throttle; "
            f"{ev['knock_cells_outside_speeds']} of the {ev['knock_cells']} cells limited by knock lie outside "
            f"that speed span{where}, where the border is the calibrated model's extrapolation "
            f"(mbc plan knock-sweeps plans the onset sweeps that would measure it).")


def _write_index(work: Path, man: dict) -> Path:
    summary = index_summary(man)
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
        ecu = sorted(p.relative_to(work) for p in (work / "maps" / "ecu").glob("*") if p.is_file())
        sections.append(("ECU tables", "Spark advance (MBT, knock-limited), injection time, target lambda and the "
                         "retarded starting map; maps/ecu/ holds them as ECU files (TunerStudio .table, Speeduino "
                         "and rusEFI .msq, DCM 2.0, CSV with units; what was resampled: maps/ecu/README.txt). "
                         "Other breakpoints or a kPa load axis: mbc export --run <this folder>.", mfiles + ecu))
    bc = man.get("maps", {}).get("bench_consistency")
    if bc:
        sections.append(("Against the real bench", (
            "At each bench point: the spark the bench ran, the model's MBT at the identified burn, the knock index "
            "of the fastest cycles at the bench's spark (calibrated model), and the spark table there. "
            f"Model MBT within 2 deg of the bench: {bc['mbt_within_2deg']}; knock index < 1 at the points that "
            f"ran clean: {bc['knock_free_points_below_1']}; table within 3 deg of the bench: "
            f"{bc['table_within_3deg']}. {_trend_text(bc.get('trends'))}"),
            ["maps/bench_consistency.png", "maps/bench_consistency.csv", "calibration/knock_evidence.parquet"]))
    if "gap" in man:
        gfiles = sorted(p.relative_to(work) for p in (work / "gap").glob("*") if p.is_file())
        sections.append(("Sim-to-real gap", man["gap"]["statement"], gfiles))
    sections.append(("Run", "", ["manifest.json", "sweeps"]))
    return write_index(work, "mbc run: Yamaha R6 FS calibration", summary, sections)


def _summary_text(man: dict, final: Path) -> str:
    cal = man["calibration"]["airflow"]
    lines = ["", f"run complete in {man['wall_time_s']:.0f} s ("
             + ", ".join(f"{k} {v:.0f} s" for k, v in man["timings_s"].items()) + ")",
             f"airflow match: {format_parameters(cal['parameters'], cal.get('bounds'), cal.get('at_bound'))}, "
             f"max |Ga_REL| = {cal['max_abs_ga_rel_pct']:.2f} %"]
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
    final = Path(out) if out else default_run_dir(engine.spec_hash())
    folder = final if final.exists() else final.with_name(final.name + ".partial")
    check_stage_inputs(folder, rs.stages)
    unit = kwargs.get("throttle_unit", "pct") if bench is not None else "pct"   # the run's copy is in percent
    load_bench(run_bench(folder, bench, rs.stages)[0], unit)   # bad bench data fails here, before any folder exists
    with prefect_env.prefect_api(verbose=kwargs.get("progress", True)):
        return run_flow(out=str(final), bench=None if bench is None else str(bench), spec=spec,
                        settings=settings_to_dict(rs), **kwargs)


def record_stage(folder: Path, name: str, summary: dict, wall_s: float, settings: dict | None = None) -> dict:
    """Enter stage ``name`` re-run on the finished run ``folder`` (``mbc maps --run``, ``mbc gap --run``) into
    its manifest.json and index.html, as ``mbc run --stages NAME`` records it; ``settings``: run settings the
    re-run changed (e.g. the ECU breakpoints).  Returns the new manifest."""
    man = _manifest(folder)
    man.update({name: summary, "stages": [name], "timings_s": {name: round(wall_s, 1)}, "wall_time_s": round(wall_s, 1),
                "created": _dt.datetime.now().isoformat(timespec="seconds"),
                "settings": {**man.get("settings", {}), **(settings or {}), "stages": [name]}})
    write_json(man, folder / "manifest.json")
    _write_index(folder, man)
    return man
