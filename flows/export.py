"""``mbc export`` and ``mbc compare``: the ECU files of a run's maps, and a proposed table against the car's.

Both run in this process (no Prefect, no Dask): they read ``<run>/maps/cells.parquet``
(the per-cell results of the maps stage) and, for the injector, displacement and fuel,
``<run>/engine.toml`` (or ``--spec``).  Every input is checked before anything is written.

    mbc export  --run DIR [--out DIR/exports] [--format all] [--rpm-bins] [--load-bins] [--axes-from FILE]
                [--load-axis throttle|kpa] [--fuel injection-time|fuel-mass|ve] [--battery-v V]
    mbc compare --run DIR --current FILE [--table spark|injection|lambda] [--out DIR/compare]
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from engine_model.calibrated import CalibratedEngine
from engine_model.io import atomic_write, read_table, write_csv
from engine_model.tables.ecu_export import EXPORT_FORMATS, ExportOptions, export_tables, write_exports
from engine_model.tables.ecu_files import compare, plot_difference, read_axes
from engine_model.tables.ecu_files import read_table as read_ecu_table
from engine_model.tables.grid import parse_breakpoints

__all__ = ["ENGINE_FILE", "load_run", "run_export", "run_compare", "COMPARE_TABLES"]

#: The run's calibrated engine (the name the pipeline writes it under).
ENGINE_FILE = "engine.toml"
#: --table -> (export table names it can be, msq table kind)
COMPARE_TABLES = {"spark": (("spark_advance",), "ignition"),
                  "injection": (("injection_time", "fuel_mass", "ve"), "ve"),
                  "lambda": (("lambda_target",), "lambda")}
_FUEL_BY_UNIT = {"ms": "injection-time", "mg": "fuel-mass", "%": "ve"}
_AFR_STOICH = 14.7


def load_run(run, spec=None):
    """(cells, engine spec or None, cells path) of a run folder; ValueError naming what is missing."""
    run = Path(run)
    if not run.is_dir():
        raise ValueError(f"--run {run}: no such folder")
    cells_path = run / "maps" / "cells.parquet"
    if not cells_path.is_file():
        raise ValueError(f"{run}: no maps/cells.parquet; run the maps stage into this folder first "
                         "(mbc run --out DIR, or mbc maps --out DIR)")
    cells = read_table(cells_path)
    engine_file = Path(spec) if spec else run / ENGINE_FILE
    eng = None
    if spec or engine_file.is_file():
        eng = CalibratedEngine.load(engine_file).spec
        summary = run / "maps" / "maps.json"
        if summary.is_file():
            want = json.loads(summary.read_text()).get("spec_hash")
            if want and want != eng.spec_hash():
                raise ValueError(f"{engine_file}: engine spec {eng.spec_hash()} is not the one the maps were built "
                                 f"for ({want}, {summary}); give that run's engine with --spec")
    return cells, eng, cells_path


def _need_engine(eng, run, opts: ExportOptions) -> None:
    if eng is None and (opts.fuel != "injection-time" or opts.battery_v is not None):
        what = f"--fuel {opts.fuel}" if opts.fuel != "injection-time" else "--battery-v"
        raise ValueError(f"{run}: no {ENGINE_FILE}; {what} needs the engine (injector, displacement, fuel): "
                         "give it with --spec")


def _bins(text, what):
    return None if text is None else parse_breakpoints(text, what)


def _options(args_axes_from, rpm_bins, load_bins, load_axis, fuel, battery_v):
    """ExportOptions from the command's values (breakpoints from text or a table file)."""
    if args_axes_from is not None:
        if rpm_bins is not None or load_bins is not None:
            raise ValueError("give either --axes-from or --rpm-bins/--load-bins, not both")
        # an msq holds several tables: the spark table's breakpoints
        axes = read_axes(args_axes_from, table="ignition" if Path(args_axes_from).suffix.lower() == ".msq" else None)
        kind = "kpa" if axes.load_kind == "map_kpa" else "throttle"
        if load_axis is not None and load_axis != kind:
            raise ValueError(f"--axes-from {args_axes_from}: its load axis is {axes.load_kind}, not --load-axis "
                             f"{load_axis}")
        return ExportOptions(tuple(axes.rpm), tuple(axes.load), kind, fuel, battery_v)
    return ExportOptions(_bins(rpm_bins, "rpm"), _bins(load_bins, "load"), load_axis or "throttle", fuel, battery_v)


def run_export(run, out=None, fmt="all", rpm_bins=None, load_bins=None, axes_from=None, load_axis=None,
               fuel="injection-time", battery_v=None, spec=None) -> dict:
    """``mbc export``: the run's tables on the ECU's breakpoints into ``out`` (default ``<run>/exports``)."""
    if fmt != "all" and fmt not in EXPORT_FORMATS:
        raise ValueError(f"--format {fmt!r}: expected all or one of {list(EXPORT_FORMATS)}")
    opts = _options(axes_from, rpm_bins, load_bins, load_axis, fuel, battery_v)
    cells, eng, cells_path = load_run(run, spec)
    _need_engine(eng, run, opts)
    out = Path(run) / "exports" if out is None else Path(out)
    if not out.parent.is_dir():
        raise ValueError(f"--out {out}: its parent folder {out.parent} does not exist")
    es = export_tables(cells, eng, opts, source=str(cells_path))
    res = write_exports(es, out, list(EXPORT_FORMATS) if fmt == "all" else [fmt])
    t = es.tables[0]
    print(f"export: {len(es.tables)} tables ({', '.join(f'{x.name} [{x.unit}]' for x in es.tables)}) on "
          f"{t.shape[1]} rpm x {t.shape[0]} {t.load_column} [{t.load_unit}] breakpoints -> {out}/")
    for name in sorted(res["files"]):
        print(f"  {name}")
    for n in res["notes"]:
        print(f"  note: {n}")
    return res


def _read_current(path, table):
    """The current table of the car from any supported file; for msq/DCM the table of ``table``."""
    p = Path(path)
    names, kind = COMPARE_TABLES[table]
    if p.suffix.lower() == ".msq":
        return read_ecu_table(p, table=kind)
    if p.suffix.lower() == ".dcm":
        errors = []
        for name in (*names, None):
            try:
                return read_ecu_table(p, table=name)
            except ValueError as exc:
                errors.append(str(exc))
        raise ValueError(errors[-1])
    return read_ecu_table(p)


def run_compare(run, current, table="spark", out=None, spec=None, fuel=None) -> dict:
    """``mbc compare``: the proposed table on the current table's breakpoints, cell by cell (CSV + heatmap).

    A current file without units (TunerStudio's own .table export has none) is taken in the
    proposed table's unit (lambda: AFR when its values exceed 5); for the fuel table ``fuel``
    then says which form it is.
    """
    if table not in COMPARE_TABLES:
        raise ValueError(f"--table {table!r}: expected one of {list(COMPARE_TABLES)}")
    cur = _read_current(current, table)
    unit = cur.unit.strip().lower()
    notes = []
    if table == "injection":
        form = _FUEL_BY_UNIT.get(unit)
        if fuel is None and form is None:
            raise ValueError(f"{current}: fuel table in {cur.unit!r}; expected ms (injection time), mg (fuel mass) "
                             "or % (VE), or say which with --fuel")
        if fuel is not None and form is not None and fuel != form:
            raise ValueError(f"{current}: fuel table in {cur.unit!r} ({form}), not --fuel {fuel}")
        fuel = fuel or form
    else:
        fuel = "injection-time"
    afr = table == "lambda" and (unit == "afr" or (not unit and float(cur.values.max()) > 5.0))
    if not unit:
        notes.append(f"the current file states no unit: taken as {'AFR' if afr else 'the proposed table'}'s")
    cells, eng, cells_path = load_run(run, spec)
    out = Path(run) / "compare" if out is None else Path(out)
    if not out.parent.is_dir():
        raise ValueError(f"--out {out}: its parent folder {out.parent} does not exist")
    kind = "kpa" if cur.load_kind == "map_kpa" else "throttle"
    opts = ExportOptions(tuple(cur.rpm), tuple(cur.load), kind, fuel)
    _need_engine(eng, run, opts)
    es = export_tables(cells, eng, opts, source=str(cells_path))
    proposed = es.table(next(n for n in COMPARE_TABLES[table][0] if n in [t.name for t in es.tables]))
    if afr:
        proposed = proposed.replace(values=proposed.values * _AFR_STOICH, unit="AFR", decimals=1)
    if not unit:
        cur = cur.replace(unit=proposed.unit)
    diff = compare(cur, proposed)
    diff["outside"] = diff["outside"].to_numpy(bool) | es.outside.ravel()
    csv_path = write_csv(diff, out / f"{table}_difference.csv")
    png_path = atomic_write(out / f"{table}_difference.png", lambda tmp: plot_difference(diff, tmp))
    d = diff["difference"].to_numpy(float)
    k = int(np.argmax(np.abs(d)))
    r = diff.iloc[k]
    load_col = cur.load_column
    lines = [f"compare {table}: proposed ({proposed.name} [{proposed.unit}]) - current ({Path(current).name}) on "
             f"the current {cur.shape[1]} rpm x {cur.shape[0]} {load_col} [{cur.load_unit}] breakpoints",
             f"  max |difference| {abs(d[k]):.{cur.decimals}f} {cur.unit} at {r[load_col]:g} {cur.load_unit}, "
             f"{r['speed_rpm']:g} rpm (current {r['current']:g}, proposed {r['proposed']:.{cur.decimals + 1}f})",
             f"  mean difference {d.mean():+.{cur.decimals + 1}f}, mean |difference| {np.abs(d).mean():.{cur.decimals + 1}f}"
             f" {cur.unit}; {int((d > 0).sum())} cells higher, {int((d < 0).sum())} lower"]
    unc = diff["proposed_uncertainty"] if "proposed_uncertainty" in diff.columns else None
    has = np.zeros(len(diff), bool) if unc is None else unc.to_numpy(float) > 0
    if has.any():
        lines.append(f"  {int((has & diff['within_uncertainty']).sum())} of {int(has.sum())} cells with a model "
                     "uncertainty (knock-limited spark) differ by less than it")
    if diff["outside"].any():
        lines.append(f"  {int(diff['outside'].sum())} cells outside the model's grid (edge value held)")
    if afr:
        lines.append(f"  the current table is in AFR: proposed lambda x {_AFR_STOICH:g}")
    lines += [f"  note: {n}" for n in notes]
    lines.append(f"  -> {csv_path}, {png_path}")
    print("\n".join(lines))
    return {"csv": csv_path, "png": png_path, "diff": diff}
