"""A stage re-run from a finished run folder: ``mbc maps --run DIR`` and ``mbc gap --run DIR``.

    DIR/manifest.json (a complete ``mbc run``)  --> the run's engine (DIR/engine.toml), global model
    (DIR/model/model.json), bench data copy (DIR/bench.parquet), ECU grid, step and map settings
    --> flows.stages.maps.run_maps / flows.stages.gap.run_gap
    --> into DIR (DIR/maps or DIR/gap, then manifest.json and index.html updated as by
        ``mbc run --stages maps``) or into ``--out``

With ``--run``, the model and the engine are the run's: ``--model`` and ``--spec`` are refused (the global
model was fitted on the run's calibrated engine; a table from another pair is ``mbc maps --model M --spec S``).
The grid, the crank step and the map settings are the run's unless given.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from flows.run import record_stage, run_bench
from flows.stages.context import BENCH_FILE, ENGINE_FILE
from flows.stages.gap import run_gap
from flows.stages.maps import MODEL_FILE, ecu_grid, run_maps


def read_run(folder) -> dict:
    """The manifest of the finished ``mbc run`` folder ``folder``; ValueError saying why it is not one."""
    p = Path(folder)
    if not p.is_dir():
        partial = p.with_name(p.name + ".partial")
        hint = f" ({partial} is an unfinished run: run `mbc run --out {p}` again to finish it)" if partial.is_dir() else ""
        raise ValueError(f"--run {p}: no such folder{hint}")
    mf = p / "manifest.json"
    try:
        man = json.loads(mf.read_text())
    except FileNotFoundError:
        raise ValueError(f"--run {p}: not a run folder (no manifest.json); give a folder written by `mbc run`") from None
    except ValueError as exc:
        raise ValueError(f"--run {p}: manifest.json is not valid JSON ({exc})") from None
    if not isinstance(man, dict) or man.get("kind") != "run":
        kind = man.get("kind") if isinstance(man, dict) else type(man).__name__
        raise ValueError(f"--run {p}: manifest.json is of kind {kind!r}, not 'run'; give a folder written by `mbc run`")
    if man.get("status") != "complete":
        raise ValueError(f"--run {p}: the run's status is {man.get('status')!r}, not 'complete'")
    return man


def _need(folder: Path, files, what: str) -> None:
    missing = [str(f) for f in files if not (folder / f).is_file()]
    if missing:
        raise ValueError(f"--run {folder}: {what} needs {missing}, which the run does not hold "
                         f"(run `mbc run --out {folder}` with the stage that writes it)")


def _in_place(run: Path, out) -> bool:
    return out is None or Path(out).resolve() == run.resolve()


def maps_arguments(run, throttle=None, speed=None, grid=None, settings=None, step_deg=None) -> dict:
    """Keyword arguments of :func:`run_maps` that rebuild the run's tables (explicit arguments win)."""
    run = Path(run)
    man = read_run(run)
    _need(run, (ENGINE_FILE, MODEL_FILE), "the maps stage")
    rs = man.get("settings", {})
    if grid is None:   # a grid CSV replaces both axes; a breakpoint list replaces its own axis
        throttle = throttle if throttle is not None else rs.get("map_throttle")
        speed = speed if speed is not None else rs.get("map_speed")
    try:
        before = json.loads((run / "maps" / "run.json").read_text()).get("settings", {})
    except (OSError, ValueError):
        before = {}
    before = {k: tuple(v) if isinstance(v, list) else v for k, v in before.items()}
    # the run's bench copy pins the cells it ran clean at MBT; its knock evidence feeds the bench report
    bench = run / BENCH_FILE
    evidence = run / "calibration" / "knock_evidence.parquet"
    cal_summary = run / "calibration" / "summary.json"     # its speed-dependent knock multiplier, if used
    return {"model": str(run / MODEL_FILE), "spec": str(run / ENGINE_FILE), "throttle": throttle, "speed": speed,
            "grid": grid, "settings": {**before, **(settings or {})},
            "step_deg": step_deg if step_deg is not None else rs.get("step_deg"),
            "bench": str(bench) if bench.is_file() else None,
            "knock_evidence": str(evidence) if evidence.is_file() else None,
            "calibration_summary": str(cal_summary) if cal_summary.is_file() else None}


def rebuild_maps(run, out=None, model=None, spec=None, throttle=None, speed=None, grid=None, lambda_table=None,
                 settings=None, step_deg=None, **kwargs) -> dict:
    """``mbc maps --run DIR``: the maps stage again from the finished run ``DIR`` into DIR (default) or ``out``."""
    if model is not None or spec is not None:
        raise ValueError("--run takes the model and engine of the run (model/model.json, engine.toml); "
                         "leave out --model/--spec, or give --model and --spec without --run")
    run = Path(run)
    kw = maps_arguments(run, throttle, speed, grid, settings, step_deg)
    t0 = time.perf_counter()
    res = run_maps(out=run if out is None else out, lambda_table=lambda_table, **kw, **kwargs)
    if _in_place(run, out):
        changed = {}
        if throttle is not None or speed is not None or grid is not None:
            g = ecu_grid(kw["throttle"], kw["speed"], kw["grid"])
            changed = {"map_throttle": ",".join(f"{v:g}" for v in g.throttle_pct),
                       "map_speed": ",".join(f"{v:g}" for v in g.speed_rpm)}
        record_stage(run, "maps", {"stats": res["stats"], "files": res["files"]}, time.perf_counter() - t0, changed)
    return res


def rebuild_gap(run, out=None, bench=None, spec=None, step_deg=None, overrides=None, **kwargs) -> dict:
    """``mbc gap --run DIR``: the gap diagnosis again from the finished run ``DIR`` into DIR (default) or ``out``;
    the bench data is the run's copy unless ``bench`` is given."""
    if spec is not None or overrides:
        raise ValueError("--run takes the engine of the run (engine.toml); leave out --spec/--override, "
                         "or give them without --run")
    run = Path(run)
    man = read_run(run)
    _need(run, (ENGINE_FILE,), "the gap stage")
    bench_file, _ = run_bench(run, bench, ())
    step = step_deg if step_deg is not None else man.get("settings", {}).get("step_deg", 0.5)
    t0 = time.perf_counter()
    res = run_gap(out=run if out is None else out, bench=bench_file, spec=str(run / ENGINE_FILE), step_deg=step,
                  **kwargs)
    if _in_place(run, out):
        record_stage(run, "gap", res, time.perf_counter() - t0)
    return res
