"""ECU exports of a built map: spark, fuel and lambda tables on the ECU's own breakpoints, in every file format.

    cells.parquet of a map build (one row per throttle x rpm cell)
      -> source tables on the build's grid (throttle % load axis)      :func:`source_tables`
      -> the ECU's load axis: throttle % (alpha-N) or MAP kPa (speed density, from the
         model's cycle-mean plenum pressure of every cell)              :func:`export_tables`
      -> the ECU's breakpoints (bilinear; outside the build's grid the edge is held and counted)
      -> files: TunerStudio .table, Speeduino / rusEFI .msq, DCM 2.0, units-header CSV
                                                                         :func:`write_exports`

Fuel forms (``fuel=``)
----------------------
``injection-time``
    pulse width [ms] at ``battery_v`` (dead time of the spec's injector at that voltage);
    the build's table with its dead time swapped for the one at ``battery_v``.
``fuel-mass``
    fuel per cylinder per cycle [mg]: the build's pulse width without dead time times the
    injector flow, so cells the build filled are filled here too.
``ve``
    volumetric efficiency [%] (:func:`engine_model.tables.ecu_table.ve_percent`) of the air
    that fuel mass burns at the cell's lambda: relative to the cell's plenum pressure on a
    kPa load axis (speed density), to 101.325 kPa on a throttle axis (alpha-N); both at
    ``ve_ref_temp_k``.

The msq tables of both firmwares are 16 x 16.  A table of another size is put on 16 x 16
breakpoints spread over the same range (rpm on 100 rpm, throttle on 1 %, MAP on 2 kPa:
steps both firmwares store) when the axes are the build's own; breakpoints the user chose
must be 16 x 16 for an msq.
"""

from __future__ import annotations

import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .. import thermo
from ..io import make_temp_dir, write_text
from ..spec import EngineSpec
from .ecu_csv import write_csv
from .ecu_dcm import write_dcm
from .ecu_files import write_tunerstudio_table
from .ecu_msq import FIRMWARE_TABLES, write_msq
from .ecu_table import EcuTable, resample, to_map_kpa, ve_percent
from .injection import injection_time_ms
from .smoothing import smooth_table

__all__ = ["FUEL_FORMS", "LOAD_AXES", "EXPORT_FORMATS", "VE_REF_KPA_ALPHA_N", "ExportOptions", "ExportSet",
           "source_tables", "plenum_kpa", "export_tables", "msq_axes", "write_exports"]

FUEL_FORMS = ("injection-time", "fuel-mass", "ve")
LOAD_AXES = ("throttle", "kpa")
#: format name -> what it writes
EXPORT_FORMATS = {"table": "TunerStudio .table per table", "msq-speeduino": "speeduino.msq",
                  "msq-rusefi": "rusefi.msq", "dcm": "ecu_tables.dcm (all tables)", "csv": "units-header CSV per table"}
#: VE reference pressure on a throttle (alpha-N) load axis [kPa]: a standard atmosphere
VE_REF_KPA_ALPHA_N = 101.325
_FUEL_TABLE = {"injection-time": ("injection_time", "ms", 3, "Injection time (pulse width incl. dead time)"),
               "fuel-mass": ("fuel_mass", "mg", 2, "Fuel mass per cylinder per cycle"),
               "ve": ("ve", "%", 1, "Volumetric efficiency")}
_NEEDED = ("throttle_pct", "speed_rpm", "spark_deg_btdc", "lambda", "injection_time_ms", "dead_time_ms")
_MSQ_SHAPE = (16, 16)
_MSQ_STEPS = {"throttle_pct": 1.0, "map_kpa": 2.0}


@dataclass(frozen=True)
class ExportOptions:
    """What to export and on which breakpoints (validated at construction).

    rpm_bins, load_bins : tuple of float, optional
        The ECU's breakpoints (default: the build's grid; on a kPa axis the load default is
        spread over the plenum pressures of the build).
    load_axis : {"throttle", "kpa"}
    fuel : {"injection-time", "fuel-mass", "ve"}
    battery_v : float, optional
        Battery voltage of the injection-time dead time [V] (default: the build's).
    ve_ref_temp_k : float
        Reference temperature of the VE [K].
    """

    rpm_bins: tuple | None = None
    load_bins: tuple | None = None
    load_axis: str = "throttle"
    fuel: str = "injection-time"
    battery_v: float | None = None
    ve_ref_temp_k: float = 293.15

    def __post_init__(self):
        if self.load_axis not in LOAD_AXES:
            raise ValueError(f"load axis {self.load_axis!r}: expected one of {list(LOAD_AXES)}")
        if self.fuel not in FUEL_FORMS:
            raise ValueError(f"fuel {self.fuel!r}: expected one of {list(FUEL_FORMS)}")
        if self.battery_v is not None and not (math.isfinite(self.battery_v) and 6.0 <= self.battery_v <= 30.0):
            raise ValueError(f"battery voltage {self.battery_v!r} V: expected a number in [6, 30] V")
        if not (math.isfinite(self.ve_ref_temp_k) and self.ve_ref_temp_k > 0):
            raise ValueError(f"VE reference temperature {self.ve_ref_temp_k!r} K: must be > 0 K")
        lo, unit = (0.0, "%") if self.load_axis == "throttle" else (0.0, "kPa")
        for name, bins, low, high, u in (("rpm", self.rpm_bins, 0.0, 25000.0, "rpm"),
                                         ("load", self.load_bins, lo, 100.0 if unit == "%" else 600.0, unit)):
            if bins is None:
                continue
            arr = np.asarray(bins, float)
            if arr.size < 2:
                raise ValueError(f"{name} breakpoints: need at least 2, got {arr.size}")
            bad = np.flatnonzero(~np.isfinite(arr) | (arr < low) | (arr > high) | ((arr <= 0) & (u != "%")))
            if bad.size:
                raise ValueError(f"{name} breakpoint {bad[0]} = {arr[bad[0]]:g} {u}: expected a number in "
                                 f"{'(0' if u != '%' else '[0'}, {high:g}] {u}")
            d = np.flatnonzero(np.diff(arr) <= 0)
            if d.size:
                k = int(d[0])
                raise ValueError(f"{name} breakpoints: {arr[k + 1]:g} {u} (position {k + 1}) does not exceed "
                                 f"{arr[k]:g} {u}; breakpoints must be strictly increasing")
            object.__setattr__(self, f"{name}_bins", tuple(float(v) for v in arr))

    @property
    def load_kind(self) -> str:
        """The :class:`EcuTable` load kind of :attr:`load_axis`."""
        return "throttle_pct" if self.load_axis == "throttle" else "map_kpa"


@dataclass(frozen=True, eq=False)
class ExportSet:
    """Tables on the ECU's breakpoints, the cells outside the build's grid, and notes for the reader."""

    tables: tuple
    outside: np.ndarray
    notes: tuple
    axes_given: bool

    def table(self, name: str) -> EcuTable:
        for t in self.tables:
            if t.name == name:
                return t
        raise ValueError(f"no table {name!r} in the export (have {[t.name for t in self.tables]})")


def _grid(cells: pd.DataFrame, source: str):
    """(throttle bins, rpm bins, row-major order of the cells) of a full grid; ValueError naming the hole."""
    missing = [c for c in _NEEDED if c not in cells.columns]
    if missing:
        raise ValueError(f"{source}: column(s) {missing} missing; a map build's cells.parquet has {list(_NEEDED)}")
    thr = np.unique(cells["throttle_pct"].to_numpy(float))
    rpm = np.unique(cells["speed_rpm"].to_numpy(float))
    if len(cells) != thr.size * rpm.size or cells.duplicated(["throttle_pct", "speed_rpm"]).any():
        raise ValueError(f"{source}: {len(cells)} rows are not one per cell of a {thr.size} x {rpm.size} "
                         "throttle x rpm grid")
    order = cells.sort_values(["throttle_pct", "speed_rpm"])
    return thr, rpm, order


def _values(order: pd.DataFrame, col: str, shape, source: str, positive: bool = False) -> np.ndarray:
    v = pd.to_numeric(order[col], errors="coerce").to_numpy(float)
    bad = np.flatnonzero(~np.isfinite(v) | ((v <= 0) if positive else False))
    if bad.size:
        r = order.iloc[bad[0]]
        raise ValueError(f"{source}: cell (throttle {r['throttle_pct']:g} %, {r['speed_rpm']:g} rpm), column "
                         f"'{col}': value {r[col]!r} is not a finite{' positive' if positive else ''} number")
    return v.reshape(shape)


def plenum_kpa(cells: pd.DataFrame, source: str = "cells") -> tuple[np.ndarray, int]:
    """Plenum pressure [kPa] of every cell (throttle rows, rpm columns) and how many cells were filled.

    Cells without a simulated pressure (failed points) take the minimum-curvature fill of
    their neighbours (:func:`engine_model.tables.smoothing.smooth_table`).
    """
    thr, rpm, order = _grid(cells, source)
    if "plenum_pressure_bar" not in cells.columns:
        raise ValueError(f"{source}: no 'plenum_pressure_bar' column (a map built before the plenum pressure was "
                         "kept); run the maps stage again for a kPa load axis or a VE table")
    p = pd.to_numeric(order["plenum_pressure_bar"], errors="coerce").to_numpy(float).reshape(thr.size, rpm.size) * 100
    have = np.isfinite(p) & (p > 0)
    if have.sum() < 2:
        raise ValueError(f"{source}: fewer than 2 cells have a plenum pressure; no MAP axis can be built")
    if have.all():
        return p, 0
    filled, _ = smooth_table(np.where(have, p, np.nan), have.astype(float), np.full(p.shape, 1.0),
                             np.full(p.shape, 1e3), None)
    return np.where(have, p, filled), int((~have).sum())


def _spark_uncertainty(order: pd.DataFrame, shape) -> np.ndarray | None:
    """1 sigma of the knock-safe spark [deg] in knock-limited cells (CA50 sigma x knock gain), 0 elsewhere."""
    if not {"phasing_std_deg", "knock_phasing_gain", "limited_by"} <= set(order.columns):
        return None
    sig = order["phasing_std_deg"].to_numpy(float) * order["knock_phasing_gain"].to_numpy(float)
    knock = order["limited_by"].astype(str).to_numpy() == "knock"
    return np.where(knock & np.isfinite(sig), np.abs(sig), 0.0).reshape(shape)


def _dead_ms(spec: EngineSpec, battery_v: float) -> float:
    return float(injection_time_ms(np.zeros(1), np.full(1, 1000.0), np.ones(1), spec, battery_v)["dead_time_ms"][0])


def source_tables(cells: pd.DataFrame, spec: EngineSpec | None, opts: ExportOptions,
                  source: str = "cells") -> tuple[dict, list]:
    """Spark, fuel and lambda tables on the build's own grid (throttle % rows); and notes.

    ``spec`` (the engine the map was built for) is needed for fuel mass, VE and an
    injection time at another battery voltage; ValueError otherwise.
    """
    thr, rpm, order = _grid(cells, source)
    shape = (thr.size, rpm.size)
    notes = []
    spark = _values(order, "spark_deg_btdc", shape, source)
    lam = _values(order, "lambda", shape, source, positive=True)
    t_inj = _values(order, "injection_time_ms", shape, source, positive=True)
    dead = _values(order, "dead_time_ms", shape, source)
    flags = (order["limited_by"].astype(str).to_numpy() == "knock").reshape(shape) \
        if "limited_by" in order.columns else None
    out = {"spark_advance": EcuTable("spark_advance", spark, rpm, thr, "throttle_pct", "deg BTDC", 1, flags,
                                     "knock-limited" if flags is not None else "", _spark_uncertainty(order, shape),
                                     "Spark advance")}
    name, unit, dec, desc = _FUEL_TABLE[opts.fuel]
    if spec is None and (opts.fuel != "injection-time" or opts.battery_v is not None):
        raise ValueError(f"fuel {opts.fuel!r}{' at another battery voltage' if opts.fuel == 'injection-time' else ''}"
                         " needs the engine (injector, displacement, fuel): give the run's engine.toml")
    if opts.fuel == "injection-time":
        fuel = t_inj
        if opts.battery_v is not None:
            fuel = t_inj - dead + _dead_ms(spec, opts.battery_v)
            notes.append(f"injection time at {opts.battery_v:g} V: dead time {_dead_ms(spec, opts.battery_v):.3f} ms "
                         f"(the build's {float(dead.flat[0]):.3f} ms)")
        desc += f", {opts.battery_v:g} V" if opts.battery_v is not None else ""
    else:
        inj = spec.injector
        fuel_mg = (t_inj - dead) * 1e-3 * inj.per_cylinder * inj.static_flow_kg_s * 1e6
        fuel = fuel_mg
        if opts.fuel == "ve":
            air = fuel_mg * lam * thermo.stoich_afr(spec.fuel)
            rpm2 = np.broadcast_to(rpm, shape)
            if opts.load_axis == "kpa":
                p, n_fill = plenum_kpa(cells, source)
                fuel = ve_percent(rpm2, spec, map_kpa=p, air_mg_per_cycle=air, ref_temp_k=opts.ve_ref_temp_k)
                desc += f" relative to the cell's MAP at {opts.ve_ref_temp_k:g} K"
                if n_fill:
                    notes.append(f"VE: {n_fill} cell(s) without a simulated plenum pressure use a filled one")
            else:
                fuel = ve_percent(rpm2, spec, air_mg_per_cycle=air, ref_temp_k=opts.ve_ref_temp_k,
                                  ref_pressure_kpa=VE_REF_KPA_ALPHA_N)
                desc += f" relative to {VE_REF_KPA_ALPHA_N:g} kPa at {opts.ve_ref_temp_k:g} K"
    out[name] = EcuTable(name, fuel, rpm, thr, "throttle_pct", unit, dec, description=desc)
    out["lambda_target"] = EcuTable("lambda_target", lam, rpm, thr, "throttle_pct", "-", 3,
                                    description="Target lambda")
    return out, notes


def _default_kpa_bins(p: np.ndarray, n: int) -> np.ndarray:
    """``n`` MAP breakpoints on a 2 kPa step over the plenum pressures of the build (inside them)."""
    lo, hi = 2.0 * math.ceil(float(np.min(p)) / 2.0), 2.0 * math.floor(float(np.max(p)) / 2.0)
    if hi <= lo:
        raise ValueError(f"the build's plenum pressures span {np.min(p):.1f}..{np.max(p):.1f} kPa: too narrow for a "
                         "MAP axis; give --load-bins")
    bins = np.unique(2.0 * np.round(np.linspace(lo, hi, n) / 2.0))
    return bins


def export_tables(cells: pd.DataFrame, spec: EngineSpec | None, opts: ExportOptions,
                  source: str = "cells") -> ExportSet:
    """The tables of :func:`source_tables` on the load axis and breakpoints of ``opts``.

    Throttle axis: bilinear resampling (:func:`~engine_model.tables.ecu_table.resample`).
    kPa axis: per rpm column of the build the throttle -> plenum pressure map is inverted
    (:func:`~engine_model.tables.ecu_table.to_map_kpa`), then rpm is resampled.  ``outside``
    marks cells outside the build's grid or pressures (edge value held) and, on a kPa axis,
    pressures several throttle positions share.
    """
    src, notes = source_tables(cells, spec, opts, source)
    base = src["spark_advance"]
    rpm_bins = base.rpm if opts.rpm_bins is None else np.asarray(opts.rpm_bins)
    outside = None
    tables = []
    if opts.load_axis == "kpa":
        p, n_fill = plenum_kpa(cells, source)
        if n_fill:
            notes.append(f"MAP axis: {n_fill} cell(s) without a simulated plenum pressure use a filled one")
        kpa = _default_kpa_bins(p, base.load.size) if opts.load_bins is None else np.asarray(opts.load_bins)
        for t in src.values():
            on_kpa, out1 = to_map_kpa(t, p, kpa)
            new, out2 = resample(on_kpa, rpm_bins, kpa)
            rpm_out = resample(on_kpa.replace(values=out1.astype(float), flags=None, uncertainty=None),
                               rpm_bins, kpa).table.values > 0
            tables.append(new)
            outside = out2 | rpm_out if outside is None else outside
        notes.append(f"load axis MAP [kPa] from the model's cycle-mean plenum pressure; {kpa.size} breakpoints "
                     f"{kpa[0]:g}..{kpa[-1]:g} kPa (the ECU should average MAP over the cycle)")
    else:
        load = base.load if opts.load_bins is None else np.asarray(opts.load_bins)
        for t in src.values():
            new, out = resample(t, rpm_bins, load)
            tables.append(new)
            outside = out
    n_out = int(outside.sum())
    if n_out:
        notes.append(f"{n_out} of {outside.size} cells lie outside the build's grid or plenum pressures (or share a "
                     "pressure with other throttle positions): the nearest edge value is held there")
    outside.setflags(write=False)
    return ExportSet(tuple(tables), outside, tuple(notes), opts.rpm_bins is not None or opts.load_bins is not None)


def msq_axes(table: EcuTable) -> tuple[np.ndarray, np.ndarray]:
    """16 rpm and 16 load breakpoints over the table's range on steps both firmwares store (see module docstring)."""
    step = _MSQ_STEPS[table.load_kind]

    def spread(lo, hi, s, what):
        a, b = s * math.ceil(lo / s - 1e-9), s * math.floor(hi / s + 1e-9)
        v = np.unique(s * np.round(np.linspace(a, b, 16) / s))
        if v.size != 16:
            raise ValueError(f"{what} range {lo:g}..{hi:g} holds fewer than 16 breakpoints on a {s:g} step; "
                             "give 16 breakpoints of your own")
        return v

    return (spread(table.rpm[0], table.rpm[-1], 100.0, "rpm"),
            spread(table.load[0], table.load[-1], step, table.load_unit))


def _msq_tables(es: ExportSet, firmware: str) -> tuple[list, str | None]:
    """The tables of an msq (spark, VE if exported, lambda) on 16 x 16, and a note if resampled."""
    names = [t.name for t in es.tables if t.name in ("spark_advance", "ve", "lambda_target")]
    tables = [es.table(n) for n in names]
    shape = tables[0].shape
    if shape == _MSQ_SHAPE:
        return tables, None
    if es.axes_given:
        raise ValueError(f"{firmware} tables are 16 x 16 ({FIRMWARE_TABLES[(firmware, 'ignition')].z.name}); the "
                         f"breakpoints given make {shape[0]} x {shape[1]}: give 16 rpm and 16 load breakpoints "
                         "(or --axes-from a tune of that ECU) for an msq")
    rpm, load = msq_axes(tables[0])
    out = [resample(t, rpm, load).table for t in tables]
    return out, (f"{firmware}.msq: the {shape[0]} x {shape[1]} tables resampled (bilinear) to the firmware's 16 x 16: "
                 f"rpm {rpm[0]:g}..{rpm[-1]:g}, load {load[0]:g}..{load[-1]:g} {tables[0].load_unit}")


def _readme(es: ExportSet, files: dict, extra: list) -> str:
    t0 = es.tables[0]
    lines = ["ECU exports of this map build", "",
             f"load axis: {t0.load_column} [{t0.load_unit}], {t0.shape[0]} breakpoints; rpm: {t0.shape[1]} "
             "breakpoints", "tables: " + ", ".join(f"{t.name} [{t.unit}]" for t in es.tables), "", "files:"]
    lines += [f"  {name}" for name in sorted(files.values())]
    lines += ["", "Speeduino msq: speeduino.ini of release 202501.7 (advTable1/rpmBins2/mapBins1, veTable, afrTable "
              "as lambda x 14.7); rusEFI msq: rusefi_config.txt (ignitionTable, veTable, lambdaTable). Partial "
              "tunes: load them into your own project (or merge with write_msq(merge_into=...)); set the load "
              "source (TPS / MAP) in the project."]
    notes = list(es.notes) + extra
    if notes:
        lines += ["", "notes:"] + [f"  - {n}" for n in notes]
    return "\n".join(lines) + "\n"


def write_exports(es: ExportSet, out_dir, formats=tuple(EXPORT_FORMATS), readme: bool = True,
                  msq_set: ExportSet | None = None) -> dict:
    """Write the export set into ``out_dir`` in ``formats``; returns ``{"files": {name: path}, "notes": [...]}``.

    ``msq_set`` (default ``es``) supplies the msq tables, e.g. with the fuel as VE while the
    other files hold the injection time.  Everything is written into a temporary folder
    first and moved into ``out_dir`` only when every file was written (a failure leaves
    ``out_dir`` as it was).  An msq the firmware cannot hold (size, range, step) raises
    when it is the only format asked for; among several it is skipped with the reason in
    the notes (and the README).
    """
    formats = list(dict.fromkeys(formats))
    unknown = [f for f in formats if f not in EXPORT_FORMATS]
    if unknown or not formats:
        raise ValueError(f"format(s) {unknown or formats}: expected some of {list(EXPORT_FORMATS)}")
    msq_set = es if msq_set is None else msq_set
    extra = []
    out = Path(out_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(out.parent, f".{out.name}.")   # the umask's folder mode, not mkdtemp's 0700
    files = {}
    try:
        for t in es.tables:
            if "table" in formats:
                files[f"{t.name}.table"] = write_tunerstudio_table(t, tmp / f"{t.name}.table")
            if "csv" in formats:
                files[f"{t.name}.csv"] = write_csv(t, tmp / f"{t.name}.csv")
        if "dcm" in formats:
            files["ecu_tables.dcm"] = write_dcm(list(es.tables), tmp / "ecu_tables.dcm")
        for fw in ("speeduino", "rusefi"):
            if f"msq-{fw}" not in formats:
                continue
            try:
                tables, note = _msq_tables(msq_set, fw)
                write_msq(tables, tmp / f"{fw}.msq", fw)
            except ValueError as exc:
                if len(formats) == 1:
                    raise
                extra.append(f"{fw}.msq skipped: {exc}")
                continue
            files[f"{fw}.msq"] = tmp / f"{fw}.msq"
            extra += [f"{fw}.msq holds " + ", ".join(f"{t.name} [{t.unit}]" for t in tables)] + ([note] if note else [])
        if readme:
            files["README.txt"] = write_text(_readme(es, {k: k for k in files}, extra), tmp / "README.txt")
        out.mkdir(parents=True, exist_ok=True)
        for name in files:
            os.replace(tmp / name, out / name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"files": {k: out / k for k in files}, "notes": list(es.notes) + extra}
