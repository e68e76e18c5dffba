"""ECU table files: writers and readers, format detection, breakpoints of a current map, comparison.

Formats (``FORMATS``; name -> suffix)
-------------------------------------
``tunerstudio-table`` (``.table``)
    TunerStudio's single-table export, firmware independent: root
    ``<tableData xmlns="http://www.EFIAnalytics.com/:table">`` with
    ``<bibliography>``, ``<versionInfo fileFormat="1.0">`` and ``<table
    rows= cols=>`` holding ``<xAxis cols= name=>`` (rpm, one breakpoint per
    line), ``<yAxis rows= name=>`` (load) and ``<zValues rows= cols=>`` (one
    row per line, rows in the order of ``yAxis``, which is ascending).  This
    is the structure TunerStudio's own table export writes and its import
    reads (elements found by tag; ``rows``/``cols``/``name`` read).  It has no
    unit attributes; this writer adds ``units`` to the three elements (an
    extension TunerStudio ignores, ``units=False`` leaves it out) so a
    round trip keeps units.  Flags and uncertainty are not written.
``speeduino-msq``, ``rusefi-msq`` (``.msq``)
    :mod:`engine_model.tables.ecu_msq` (constant names, sizes, rounding,
    partial vs full msq are documented there).
``dcm`` (``.dcm``)
    ASAM/ETAS DCM 2.0, :mod:`engine_model.tables.ecu_dcm`: ``KENNFELD name nx ny`` with
    ``LANGNAME``, ``EINHEIT_X`` (rpm), ``EINHEIT_Y`` (load unit),
    ``EINHEIT_W``, ``ST/X`` lines (x = rpm breakpoints, 6 per line), then per
    load breakpoint an ``ST/Y`` line and its ``WERT`` lines, ``END``.  Several
    tables may share a file.  Flags and uncertainty, when present, go into
    companion maps ``<name>_flag`` (0/1) and ``<name>_uncertainty``.
``csv`` (``.csv``)
    :mod:`engine_model.tables.ecu_csv`: key lines ``table,<name>`` / ``unit,<unit>`` / ``row_axis,<name>,<unit>``
    / ``column_axis,speed_rpm,rpm`` / ``decimals,<n>`` (+ ``description``,
    ``flag_meaning``), then ``[values]`` and a wide grid (first column load,
    header rpm), optionally ``[flags]`` and ``[uncertainty]`` grids.
    :func:`read_table` also reads the plain wide CSVs of
    :func:`engine_model.tables.export.write_maps` (header ``throttle_pct,<rpm>...``).

Numbers are written with the table's ``decimals`` (msq: the firmware's
storage step).  :func:`read_table` detects the format from suffix and
content; :func:`read_axes` gives the breakpoints of a current map;
:func:`compare` (:mod:`engine_model.tables.ecu_compare`) puts a proposed table
on a current table's breakpoints; :func:`plot_difference` draws the result.
"""

from __future__ import annotations

import datetime as _dt
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import NamedTuple
from xml.sax.saxutils import quoteattr

import numpy as np

from .ecu_compare import compare, plot_difference
from .ecu_csv import read_csv, write_csv
from .ecu_dcm import read_dcm, write_dcm
from .ecu_msq import MsqReport, read_msq, write_encoded, write_msq
from .ecu_table import LOAD_KINDS, EcuTable, Resampled, resample, to_map_kpa
from .ecu_text import axis_decimals, build_table, decimals_of, fmt_number, parse_floats

__all__ = ["FORMATS", "TS_TABLE_NS", "write_table", "read_table", "read_axes", "Axes",
           "write_tunerstudio_table", "read_tunerstudio_table", "write_dcm", "read_dcm", "write_csv", "read_csv",
           "compare", "plot_difference",
           # re-exported so that one import serves a caller
           "EcuTable", "Resampled", "resample", "to_map_kpa", "write_msq", "read_msq", "MsqReport"]

FORMATS = {"tunerstudio-table": ".table", "speeduino-msq": ".msq", "rusefi-msq": ".msq", "dcm": ".dcm", "csv": ".csv"}
TS_TABLE_NS = "http://www.EFIAnalytics.com/:table"
_TS_LOAD_NAME = {"throttle_pct": "throttle", "map_kpa": "map"}


# --------------------------------------------------------------------------- TunerStudio .table

def write_tunerstudio_table(table: EcuTable, path, *, units: bool = True, x_name: str = "rpm",
                            y_name: str | None = None, author: str = "engine_model ECU export",
                            write_date: str | None = None) -> Path:
    """TunerStudio ``.table`` export of one table (see module docstring); returns the path."""
    path = Path(path)
    nl, nr = table.shape
    y_name = y_name or _TS_LOAD_NAME[table.load_kind]
    date = write_date or _dt.datetime.now().strftime("%a %b %d %H:%M:%S %Y")

    def u(unit):
        return f" units={quoteattr(unit)}" if units else ""

    xd, yd = axis_decimals(table.rpm), axis_decimals(table.load)
    vals = table.rounded()
    lines = ['<?xml version="1.0" encoding="UTF-8" standalone="no"?>',
             f'<tableData xmlns="{TS_TABLE_NS}">',
             f"    <bibliography author={quoteattr(author)} writeDate={quoteattr(date)}/>",
             '    <versionInfo fileFormat="1.0"/>',
             f'    <table cols="{nr}" rows="{nl}">',
             f'        <xAxis cols="{nr}" name={quoteattr(x_name)}{u("rpm")}>']
    lines += [f"            {fmt_number(v, xd)}" for v in table.rpm]
    lines += ["        </xAxis>", f'        <yAxis name={quoteattr(y_name)} rows="{nl}"{u(table.load_unit)}>']
    lines += [f"            {fmt_number(v, yd)}" for v in table.load]
    lines += ["        </yAxis>", f'        <zValues cols="{nr}" rows="{nl}"{u(table.unit)}>']
    lines += ["            " + " ".join(fmt_number(v, table.decimals) for v in row) for row in vals]
    lines += ["        </zValues>", "    </table>", "</tableData>"]
    write_encoded(path, "\n".join(lines) + "\n", "utf-8")
    return path


def _local(el: ET.Element) -> str:
    return el.tag.split("}")[-1]


def _ts_load_kind(y_el: ET.Element, given: str | None, where: str) -> str:
    if given is not None:
        return given
    units = (y_el.get("units") or "").strip().lower()
    name = (y_el.get("name") or "").lower()
    if units == "kpa" or (not units and ("map" in name or "kpa" in name)):
        return "map_kpa"
    if units in ("%", "% tps", "tps") or (not units and ("tps" in name or "throttle" in name)):
        return "throttle_pct"
    raise ValueError(f"{where}: cannot tell whether the load axis (name {y_el.get('name')!r}, units "
                     f"{y_el.get('units')!r}) is throttle [%] or MAP [kPa]; pass load_kind=")


def read_tunerstudio_table(path, *, name: str | None = None, load_kind: str | None = None) -> EcuTable:
    """A TunerStudio ``.table`` file; name from ``name`` or the file stem, axes reordered ascending if needed."""
    p = Path(path)
    try:
        root = ET.parse(p).getroot()
    except (OSError, ET.ParseError) as exc:
        raise ValueError(f"{p}: not a readable TunerStudio .table (XML): {exc}") from None
    if _local(root) != "tableData":
        raise ValueError(f"{p}: root element <{_local(root)}> is not <tableData>")
    found = {_local(e): e for e in root.iter() if _local(e) in ("table", "xAxis", "yAxis", "zValues")}
    missing = [k for k in ("xAxis", "yAxis", "zValues") if k not in found]
    if missing:
        raise ValueError(f"{p}: element(s) {missing} missing; a .table needs <xAxis>, <yAxis> and <zValues>")
    x = parse_floats((found["xAxis"].text or "").split(), f"{p}: <xAxis>")
    y = parse_floats((found["yAxis"].text or "").split(), f"{p}: <yAxis>")
    ztok = (found["zValues"].text or "").split()
    z = parse_floats(ztok, f"{p}: <zValues>")
    for tag, n in (("xAxis", x.size), ("yAxis", y.size)):
        want = found[tag].get("cols" if tag == "xAxis" else "rows")
        if want is not None and int(want) != n:
            raise ValueError(f"{p}: <{tag}> says {want} breakpoints but holds {n}")
    if z.size != x.size * y.size:
        raise ValueError(f"{p}: <zValues> holds {z.size} numbers for {y.size} rows x {x.size} columns")
    z = z.reshape(y.size, x.size)
    if x.size > 1 and x[0] > x[-1]:
        x, z = x[::-1], z[:, ::-1]
    if y.size > 1 and y[0] > y[-1]:
        y, z = y[::-1], z[::-1, :]
    return build_table(str(p), name=name or p.stem, values=z, rpm=x, load=y,
                  load_kind=_ts_load_kind(found["yAxis"], load_kind, str(p)),
                  unit=found["zValues"].get("units", ""), decimals=decimals_of(ztok))


# --------------------------------------------------------------------------- dispatch

def _sniff(p: Path) -> str:
    if not p.is_file():
        raise ValueError(f"{p}: file not found")
    try:
        head = p.read_bytes()[:4096].decode("utf-8", errors="replace")
    except OSError as exc:
        raise ValueError(f"{p}: could not be read: {exc}") from None
    suffix = p.suffix.lower()
    if "<tableData" in head or (suffix == ".table" and "<" in head):
        return "tunerstudio-table"
    if "<msq" in head or suffix == ".msq":
        return "msq"
    if "KONSERVIERUNG_FORMAT" in head or suffix == ".dcm":
        return "dcm"
    if suffix == ".csv" or head.startswith(("table,", "throttle_pct,")):
        return "csv"
    raise ValueError(f"{p}: unknown table file format (suffix {p.suffix!r}); expected a TunerStudio .table or "
                     ".msq, a DCM 2.0 or an ECU-table CSV")


def read_table(path, *, table: str | None = None, load_kind: str | None = None) -> EcuTable:
    """Read one table from any supported file; the format is detected from suffix and content.

    ``table`` chooses the table in multi-table files (msq: ignition / ve /
    lambda or a constant name; DCM: the KENNFELD name; .table: the name to
    give it).  ``load_kind`` overrides or supplies the load axis kind where
    the file does not say it.  Anything unreadable is a ValueError naming the file.
    """
    p = Path(path)
    fmt = _sniff(p)
    if load_kind is not None and load_kind not in LOAD_KINDS:
        raise ValueError(f"load_kind {load_kind!r}: expected one of {sorted(LOAD_KINDS)}")
    if fmt == "tunerstudio-table":
        return read_tunerstudio_table(p, name=table, load_kind=load_kind)
    if fmt == "msq":
        return read_msq(p, table, load_kind=load_kind)
    if fmt == "dcm":
        return read_dcm(p, table, load_kind=load_kind)
    return read_csv(p, load_kind=load_kind)


class Axes(NamedTuple):
    """Breakpoints of a table: rpm [rpm], load (unit of load_kind), load_kind."""

    rpm: np.ndarray
    load: np.ndarray
    load_kind: str


def read_axes(path, *, table: str | None = None, load_kind: str | None = None) -> Axes:
    """The breakpoints of a table file ("use the breakpoints of my current map")."""
    t = read_table(path, table=table, load_kind=load_kind)
    return Axes(t.rpm, t.load, t.load_kind)


def write_table(tables, path, fmt: str | None = None, **options):
    """Write with a format name of :data:`FORMATS` (default from the suffix; ``.msq`` needs the format).

    ``options`` go to the writer (msq: see :func:`engine_model.tables.ecu_msq.write_msq`).
    Returns the path (msq: the :class:`~engine_model.tables.ecu_msq.MsqReport`).
    """
    path = Path(path)
    if fmt is None:
        fmt = {".table": "tunerstudio-table", ".dcm": "dcm", ".csv": "csv"}.get(path.suffix.lower())
        if fmt is None:
            raise ValueError(f"{path}: cannot choose a format from suffix {path.suffix!r}; pass fmt= one of "
                             f"{sorted(FORMATS)}")
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: expected one of {sorted(FORMATS)}")
    if fmt.endswith("-msq"):
        return write_msq(tables, path, fmt.split("-")[0], **options)
    if fmt == "dcm":
        return write_dcm(tables, path, **options)
    many = not isinstance(tables, EcuTable)
    if many and len(tables) != 1:
        raise ValueError(f"format {fmt}: one table per file, got {len(tables)}")
    one = tables[0] if many else tables
    return write_tunerstudio_table(one, path, **options) if fmt == "tunerstudio-table" else write_csv(one, path)
