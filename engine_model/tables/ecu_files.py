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
    ASAM/ETAS DCM ``KONSERVIERUNG_FORMAT 2.0``: ``KENNFELD name nx ny`` with
    ``LANGNAME``, ``EINHEIT_X`` (rpm), ``EINHEIT_Y`` (load unit),
    ``EINHEIT_W``, ``ST/X`` lines (x = rpm breakpoints, 6 per line), then per
    load breakpoint an ``ST/Y`` line and its ``WERT`` lines, ``END``.  Several
    tables may share a file.  Flags and uncertainty, when present, go into
    companion maps ``<name>_flag`` (0/1) and ``<name>_uncertainty``.
``csv`` (``.csv``)
    Key lines ``table,<name>`` / ``unit,<unit>`` / ``row_axis,<name>,<unit>``
    / ``column_axis,speed_rpm,rpm`` / ``decimals,<n>`` (+ ``description``,
    ``flag_meaning``), then ``[values]`` and a wide grid (first column load,
    header rpm), optionally ``[flags]`` and ``[uncertainty]`` grids.
    :func:`read_table` also reads the plain wide CSVs of
    :func:`engine_model.maps_io.write_maps` (header ``throttle_pct,<rpm>...``).

Numbers are written with the table's ``decimals`` (msq: the firmware's
storage step).  :func:`read_table` detects the format from suffix and
content; :func:`read_axes` gives the breakpoints of a current map;
:func:`compare` puts a proposed table on a current table's breakpoints;
:func:`plot_difference` draws the result.
"""

from __future__ import annotations

import csv
import datetime as _dt
import io
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import NamedTuple
from xml.sax.saxutils import quoteattr

import numpy as np
import pandas as pd

from .ecu_msq import MsqReport, _write_atomic, read_msq, write_msq
from .ecu_table import LOAD_KINDS, EcuTable, Resampled, resample, to_map_kpa

__all__ = ["FORMATS", "TS_TABLE_NS", "write_table", "read_table", "read_axes", "Axes",
           "write_tunerstudio_table", "read_tunerstudio_table", "write_dcm", "read_dcm", "write_csv", "read_csv",
           "compare", "plot_difference",
           # re-exported so that one import serves a caller
           "EcuTable", "Resampled", "resample", "to_map_kpa", "write_msq", "read_msq", "MsqReport"]

FORMATS = {"tunerstudio-table": ".table", "speeduino-msq": ".msq", "rusefi-msq": ".msq", "dcm": ".dcm", "csv": ".csv"}
TS_TABLE_NS = "http://www.EFIAnalytics.com/:table"
_TS_LOAD_NAME = {"throttle_pct": "throttle", "map_kpa": "map"}
_NUM = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\Z")


def _fmt(v: float, decimals: int) -> str:
    return f"{float(v) + 0.0:.{decimals}f}"


def _axis_decimals(values) -> int:
    """Fewest decimals (0-6) that print every breakpoint exactly."""
    for d in range(7):
        if np.allclose(np.round(values, d), values, rtol=0, atol=1e-9):
            return d
    return 6


def _decimals_of(tokens) -> int:
    return min(6, max((len(t.split(".")[1].rstrip("0")) if "." in t and "e" not in t.lower() else 0)
                      for t in tokens)) if tokens else 0


def _floats(tokens, where: str) -> np.ndarray:
    for t in tokens:
        if not _NUM.match(t):
            raise ValueError(f"{where}: {t!r} is not a number")
    return np.array([float(t) for t in tokens])


def _build(where: str, **kw) -> EcuTable:
    try:
        return EcuTable(**kw)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


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

    xd, yd = _axis_decimals(table.rpm), _axis_decimals(table.load)
    vals = table.rounded()
    lines = ['<?xml version="1.0" encoding="UTF-8" standalone="no"?>',
             f'<tableData xmlns="{TS_TABLE_NS}">',
             f"    <bibliography author={quoteattr(author)} writeDate={quoteattr(date)}/>",
             '    <versionInfo fileFormat="1.0"/>',
             f'    <table cols="{nr}" rows="{nl}">',
             f'        <xAxis cols="{nr}" name={quoteattr(x_name)}{u("rpm")}>']
    lines += [f"            {_fmt(v, xd)}" for v in table.rpm]
    lines += ["        </xAxis>", f'        <yAxis name={quoteattr(y_name)} rows="{nl}"{u(table.load_unit)}>']
    lines += [f"            {_fmt(v, yd)}" for v in table.load]
    lines += ["        </yAxis>", f'        <zValues cols="{nr}" rows="{nl}"{u(table.unit)}>']
    lines += ["            " + " ".join(_fmt(v, table.decimals) for v in row) for row in vals]
    lines += ["        </zValues>", "    </table>", "</tableData>"]
    _write_atomic(path, "\n".join(lines) + "\n", "utf-8")
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
    x = _floats((found["xAxis"].text or "").split(), f"{p}: <xAxis>")
    y = _floats((found["yAxis"].text or "").split(), f"{p}: <yAxis>")
    ztok = (found["zValues"].text or "").split()
    z = _floats(ztok, f"{p}: <zValues>")
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
    return _build(str(p), name=name or p.stem, values=z, rpm=x, load=y,
                  load_kind=_ts_load_kind(found["yAxis"], load_kind, str(p)),
                  unit=found["zValues"].get("units", ""), decimals=_decimals_of(ztok))


# --------------------------------------------------------------------------- DCM 2.0

_DCM_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_\[\].]*\Z")


def _dcm_lines(key: str, values, decimals: int, per_line: int = 6) -> list[str]:
    vals = [_fmt(v, decimals) for v in values]
    return [f"   {key:<5}" + "".join(f"{v:>12}" for v in vals[k:k + per_line]) for k in range(0, len(vals), per_line)]


def _dcm_map(name: str, langname: str, table: EcuTable, values: np.ndarray, unit: str, decimals: int) -> list[str]:
    if not _DCM_NAME.match(name):
        raise ValueError(f"DCM name {name!r}: must start with a letter or '_' and hold only letters, digits, "
                         "'_', '.', '[', ']'")
    nl, nr = table.shape
    out = [f"KENNFELD {name} {nr} {nl}", f"   LANGNAME {_dcm_str(langname)}", '   EINHEIT_X "rpm"',
           f"   EINHEIT_Y {_dcm_str(table.load_unit)}", f"   EINHEIT_W {_dcm_str(unit)}"]
    out += _dcm_lines("ST/X", table.rpm, _axis_decimals(table.rpm))
    yd = _axis_decimals(table.load)
    for i in range(nl):
        out.append(f"   ST/Y   {_fmt(table.load[i], yd)}")
        out += _dcm_lines("WERT", values[i], decimals)
    return out + ["END", ""]


def _dcm_str(s: str) -> str:
    return '"' + str(s).replace("\\", "\\\\").replace('"', "'") + '"'


def write_dcm(tables, path, *, header: str = "engine_model ECU export") -> Path:
    """A DCM 2.0 file with one ``KENNFELD`` per table (+ ``_flag`` / ``_uncertainty`` companions); returns the path."""
    path = Path(path)
    tables = [tables] if isinstance(tables, EcuTable) else list(tables)
    out = [f"* {line}" for line in header.splitlines()]
    out += [f"* load axis of {t.name}: {t.load_kind} [{t.load_unit}]" for t in tables]
    out += ["", "KONSERVIERUNG_FORMAT 2.0", ""]
    for t in tables:
        out += _dcm_map(t.name, t.description or t.name, t, t.rounded(), t.unit, t.decimals)
        if t.flags is not None:
            out += _dcm_map(f"{t.name}_flag", f"{t.name}: 1 = {t.flag_meaning or 'flagged'}", t,
                            t.flags.astype(float), "-", 0)
        if t.uncertainty is not None:
            out += _dcm_map(f"{t.name}_uncertainty", f"{t.name}: uncertainty (1 sigma)", t,
                            np.round(t.uncertainty, t.decimals + 1), t.unit, t.decimals + 1)
    _write_atomic(path, "\n".join(out) + "\n", "utf-8")
    return path


def _dcm_tokens(line: str) -> list[str]:
    return [a or b for a, b in re.findall(r'"((?:[^"\\]|\\.)*)"|(\S+)', line)]


def _parse_dcm(p: Path) -> dict:
    """name -> dict(kind, nx, ny, x, y, w rows, units, langname, wtokens) of every KENNFELD/KENNLINIE."""
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        text = p.read_text(encoding="latin-1")
    except OSError as exc:
        raise ValueError(f"{p}: could not be read: {exc}") from None
    lines = [ln.strip() for ln in text.splitlines()]
    body = [(n + 1, ln) for n, ln in enumerate(lines) if ln and ln[0] not in "*!." and not ln.startswith("//")]
    if not any(ln.startswith("KONSERVIERUNG_FORMAT") for _, ln in body):
        raise ValueError(f"{p}: no 'KONSERVIERUNG_FORMAT 2.0' line; not a DCM 2.0 file")
    maps, cur = {}, None
    for n, ln in body:
        tok = _dcm_tokens(ln)
        key = tok[0]
        where = f"{p}, line {n}"
        if cur is None:
            if key in ("KENNFELD", "KENNLINIE"):
                try:
                    dims = [int(t) for t in tok[2:4 if key == "KENNFELD" else 3]]
                except (ValueError, IndexError):
                    raise ValueError(f"{where}: {key} needs a name and integer sizes, got {ln!r}") from None
                if len(dims) != (2 if key == "KENNFELD" else 1):
                    raise ValueError(f"{where}: {key} needs a name and integer sizes, got {ln!r}")
                cur = dict(kind=key, name=tok[1], nx=dims[0], ny=dims[1] if key == "KENNFELD" else 1, x=[], y=[],
                           w=[], units={}, langname="", wtok=[], line=n)
            elif key in ("FESTWERT", "FESTWERTEBLOCK", "FESTKENNLINIE", "FESTKENNFELD", "GRUPPENKENNLINIE",
                         "GRUPPENKENNFELD", "STUETZSTELLENVERTEILUNG", "TEXTSTRING", "FUNKTIONEN",
                         "VARIANTENKODIERUNG"):
                cur = dict(kind="skip")
            continue
        if key == "END":
            if cur["kind"] != "skip":
                maps[cur["name"]] = cur
            cur = None
        elif cur["kind"] == "skip":
            continue
        elif key in ("EINHEIT_X", "EINHEIT_Y", "EINHEIT_W"):
            cur["units"][key[-1]] = tok[1] if len(tok) > 1 else ""
        elif key == "LANGNAME":
            cur["langname"] = tok[1] if len(tok) > 1 else ""
        elif key == "ST/X":
            cur["x"] += list(_floats(tok[1:], where))
        elif key == "ST/Y":
            cur["y"].append(float(_floats(tok[1:2], where)[0]))
            cur["w"].append([])
        elif key == "WERT":
            if not cur["w"]:
                cur["w"].append([])
            cur["w"][-1] += list(_floats(tok[1:], where))
            cur["wtok"] += tok[1:]
    if cur is not None:
        raise ValueError(f"{p}: {cur.get('kind')} {cur.get('name', '')} is not closed by END")
    for m in maps.values():
        where = f"{p}: {m['kind']} {m['name']} (line {m['line']})"
        if len(m["x"]) != m["nx"]:
            raise ValueError(f"{where}: {len(m['x'])} ST/X breakpoints for nx = {m['nx']}")
        if m["kind"] == "KENNFELD" and len(m["y"]) != m["ny"]:
            raise ValueError(f"{where}: {len(m['y'])} ST/Y breakpoints for ny = {m['ny']}")
        bad = next((k for k, row in enumerate(m["w"]) if len(row) != m["nx"]), None)
        if bad is not None:
            raise ValueError(f"{where}: WERT row {bad} has {len(m['w'][bad])} values for nx = {m['nx']}")
    return maps


def _load_kind_from_unit(unit: str, given: str | None, where: str) -> str:
    if given is not None:
        return given
    u = unit.strip().lower()
    for kind, (_col, lu, _lab) in LOAD_KINDS.items():
        if u == lu.lower():
            return kind
    raise ValueError(f"{where}: load axis unit {unit!r} is neither '%' (throttle) nor 'kPa' (MAP); pass load_kind=")


def read_dcm(path, name: str | None = None, *, load_kind: str | None = None) -> EcuTable:
    """One KENNFELD of a DCM file (``name``, or the only one that is not a ``_flag``/``_uncertainty`` companion)."""
    p = Path(path)
    maps = {k: m for k, m in _parse_dcm(p).items() if m["kind"] == "KENNFELD"}
    mains = [k for k in maps if not k.endswith(("_flag", "_uncertainty"))]
    if name is None:
        if len(mains) != 1:
            raise ValueError(f"{p}: holds maps {mains or 'none'}; pass name= to choose one")
        name = mains[0]
    if name not in maps:
        raise ValueError(f"{p}: no KENNFELD {name!r} (have {sorted(maps)})")
    m = maps[name]
    kind = _load_kind_from_unit(m["units"].get("Y", ""), load_kind, f"{p}: {name}")
    extra = {}
    for suffix, key in (("_flag", "flags"), ("_uncertainty", "uncertainty")):
        c = maps.get(name + suffix)
        if c is not None:
            if c["x"] != m["x"] or c["y"] != m["y"]:
                raise ValueError(f"{p}: {name}{suffix} has other breakpoints than {name}")
            extra[key] = np.array(c["w"]) if key == "uncertainty" else np.array(c["w"]) != 0
    flag_meaning = ""
    if "flags" in extra:
        flag_meaning = re.sub(r"^.*?: 1 = ", "", maps[name + "_flag"]["langname"])
    return _build(f"{p}: {name}", name=name, values=np.array(m["w"]), rpm=m["x"], load=m["y"], load_kind=kind,
                  unit=m["units"].get("W", ""), decimals=_decimals_of(m["wtok"]), flag_meaning=flag_meaning,
                  description=m["langname"] if m["langname"] != name else "", **extra)


# --------------------------------------------------------------------------- CSV with units

def write_csv(table: EcuTable, path) -> Path:
    """The units-header CSV (see module docstring); returns the path."""
    path = Path(path)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["table", table.name])
    w.writerow(["unit", table.unit])
    w.writerow(["row_axis", table.load_column, table.load_unit])
    w.writerow(["column_axis", "speed_rpm", "rpm"])
    w.writerow(["decimals", table.decimals])
    if table.description:
        w.writerow(["description", table.description])
    if table.flags is not None and table.flag_meaning:
        w.writerow(["flag_meaning", table.flag_meaning])
    xd, yd = _axis_decimals(table.rpm), _axis_decimals(table.load)
    corner = f"{table.load_column} \\ speed_rpm"

    def grid(title, values, fmt):
        w.writerow([title])
        w.writerow([corner] + [_fmt(v, xd) for v in table.rpm])
        for load, row in zip(table.load, values):
            w.writerow([_fmt(load, yd)] + [fmt(v) for v in row])

    grid("[values]", table.rounded(), lambda v: _fmt(v, table.decimals))
    if table.flags is not None:
        grid("[flags]", table.flags, lambda v: "1" if v else "0")
    if table.uncertainty is not None:
        grid("[uncertainty]", table.uncertainty, lambda v: _fmt(v, table.decimals + 1))
    _write_atomic(path, buf.getvalue(), "utf-8")
    return path


_MAPS_IO_UNITS = {"spark_advance": "deg BTDC", "spark_start_retarded": "deg BTDC", "injection_time": "ms",
                  "lambda_target": "-"}


def read_csv(path, *, load_kind: str | None = None) -> EcuTable:
    """A units-header CSV, or a plain wide CSV of maps_io (first header cell ``throttle_pct``)."""
    p = Path(path)
    try:
        with open(p, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.reader(fh)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"{p}: could not be read as CSV: {exc}") from None
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        raise ValueError(f"{p}: empty file")
    if rows[0][0].strip() == "throttle_pct":          # maps_io wide table
        return _grid_table(p, rows, 0, dict(table=p.stem, unit=_MAPS_IO_UNITS.get(p.stem, "")), "throttle_pct")
    meta, k = {}, 0
    while k < len(rows) and not rows[k][0].startswith("["):
        meta[rows[k][0].strip()] = rows[k][1:]
        k += 1
    if "table" not in meta or k == len(rows) or rows[k][0].strip() != "[values]":
        raise ValueError(f"{p}: not an ECU table CSV (expected key lines 'table,...' ... then '[values]')")
    info = {key: (v[0] if v else "") for key, v in meta.items()}
    axis = meta.get("row_axis", [""])
    kind = load_kind or next((kk for kk, v in LOAD_KINDS.items() if v[0] == axis[0].strip()), None)
    if kind is None:
        raise ValueError(f"{p}: row_axis {axis!r} is not one of {[v[0] for v in LOAD_KINDS.values()]}")
    return _grid_table(p, rows, k + 1, info, kind)


def _read_grid(p: Path, rows: list, start: int, title: str):
    head = rows[start]
    where = f"{p}: {title} grid (line block starting {head[0]!r})"
    x = _floats([c.strip() for c in head[1:] if c.strip()], f"{where}, header")
    load, vals, tok = [], [], []
    k = start + 1
    while k < len(rows) and not rows[k][0].startswith("["):
        r = [c.strip() for c in rows[k]]
        cells = r[1:1 + x.size]
        if len(cells) != x.size or any(c == "" for c in cells):
            raise ValueError(f"{where}: row {r[0]!r} has {len([c for c in cells if c])} values for {x.size} "
                             "rpm columns")
        load.append(float(_floats(r[:1], where)[0]))
        vals.append(_floats(cells, where))
        tok += cells
        k += 1
    return x, np.array(load), np.array(vals), tok, k


def _grid_table(p: Path, rows: list, start: int, info: dict, kind: str) -> EcuTable:
    x, y, v, tok, k = _read_grid(p, rows, start, "values")
    extra = {}
    while k < len(rows):
        title = rows[k][0].strip()
        if title not in ("[flags]", "[uncertainty]"):
            raise ValueError(f"{p}: unknown section {title!r} (expected [flags] or [uncertainty])")
        x2, y2, g, _t, k = _read_grid(p, rows, k + 1, title)
        if not (np.array_equal(x2, x) and np.array_equal(y2, y)):
            raise ValueError(f"{p}: {title} grid has other breakpoints than [values]")
        extra["flags" if title == "[flags]" else "uncertainty"] = g != 0 if title == "[flags]" else g
    try:
        dec = int(info["decimals"]) if "decimals" in info else _decimals_of(tok)
    except ValueError:
        raise ValueError(f"{p}: decimals {info['decimals']!r} is not an integer") from None
    return _build(str(p), name=info.get("table", p.stem), values=v, rpm=x, load=y, load_kind=kind,
                  unit=info.get("unit", ""), decimals=dec, flag_meaning=info.get("flag_meaning", ""),
                  description=info.get("description", ""), **extra)


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


# --------------------------------------------------------------------------- compare

def _norm_unit(u: str) -> str:
    u = u.strip().lower().replace("°", "deg")
    return {"lambda": "-", "": "-", "deg btdc": "deg", "degbtdc": "deg"}.get(u, u)


def compare(current: EcuTable, proposed: EcuTable) -> pd.DataFrame:
    """The proposed table on the current table's breakpoints, cell by cell.

    Returns one row per cell of ``current`` (row-major):
    ``i, j, <load column>, speed_rpm, current, proposed, difference``
    (proposed - current), ``outside`` (the current cell lies outside the
    proposed table's breakpoints: edge value held, see :func:`resample`), and
    where given ``proposed_flag``, ``proposed_uncertainty`` and
    ``within_uncertainty`` (``|difference| <= proposed_uncertainty``), and
    ``current_flag``.  ``attrs`` hold name, unit, load kind and unit.
    Different load kinds or units are a ValueError (convert first).
    """
    if current.load_kind != proposed.load_kind:
        raise ValueError(f"compare: current table {current.name!r} has load axis {current.load_kind}, proposed "
                         f"{proposed.name!r} {proposed.load_kind}; convert one (to_map_kpa) first")
    if _norm_unit(current.unit) != _norm_unit(proposed.unit):
        raise ValueError(f"compare: current table {current.name!r} is in {current.unit!r}, proposed "
                         f"{proposed.name!r} in {proposed.unit!r}")
    on, outside = resample(proposed, current.rpm, current.load)
    df = current.to_frame().rename(columns={"value": "current"})
    df = df.drop(columns=[c for c in ("flag", "uncertainty") if c in df.columns])
    df["proposed"] = on.values.ravel()
    df["difference"] = df["proposed"] - df["current"]
    df["outside"] = outside.ravel()
    if on.flags is not None:
        df["proposed_flag"] = on.flags.ravel()
    if on.uncertainty is not None:
        df["proposed_uncertainty"] = on.uncertainty.ravel()
        df["within_uncertainty"] = df["difference"].abs() <= df["proposed_uncertainty"]
    if current.flags is not None:
        df["current_flag"] = current.flags.ravel()
    df.attrs.update(name=current.name, proposed=proposed.name, unit=current.unit, load_kind=current.load_kind,
                    load_unit=current.load_unit, decimals=current.decimals)
    return df


def plot_difference(diff: pd.DataFrame, path, title: str | None = None) -> Path:
    """Heatmap of :func:`compare`'s ``difference`` (rows load, columns rpm), matplotlib Agg; returns the path.

    Diverging colours centred on 0; cells outside the proposed table hatched;
    flagged proposed cells marked '*'; cells within the proposed uncertainty
    drawn with grey text.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    load_col = next(c for c in (v[0] for v in LOAD_KINDS.values()) if c in diff.columns)
    loads = np.unique(diff[load_col].to_numpy(float))
    rpms = np.unique(diff["speed_rpm"].to_numpy(float))
    nl, nr = loads.size, rpms.size
    d = diff.sort_values(["i", "j"])
    vals = d["difference"].to_numpy(float).reshape(nl, nr)

    def grid(col, default=False):
        return d[col].to_numpy().reshape(nl, nr) if col in d.columns else np.full((nl, nr), default)

    outside, flagged, within = grid("outside"), grid("proposed_flag"), grid("within_uncertainty")
    lim = float(np.max(np.abs(vals))) or 1.0
    fig, ax = plt.subplots(figsize=(1.2 + 0.62 * nr, 1.3 + 0.42 * nl))
    im = ax.imshow(vals, origin="lower", aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim)
    dec = int(diff.attrs.get("decimals", 2))
    for i in range(nl):
        for j in range(nr):
            if outside[i, j]:
                ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="///", edgecolor="0.4",
                                           linewidth=0))
            ax.text(j, i, f"{vals[i, j]:+.{dec}f}" + ("*" if flagged[i, j] else ""), ha="center", va="center",
                    fontsize=6.5, color="0.55" if within[i, j] else "black")
    ax.set_xticks(range(nr), [f"{n:g}" for n in rpms], fontsize=7, rotation=90)
    ax.set_yticks(range(nl), [f"{t:g}" for t in loads], fontsize=7)
    ax.set_xlabel("engine speed [rpm]")
    ax.set_ylabel(f"{load_col} [{diff.attrs.get('load_unit', '')}]")
    unit = diff.attrs.get("unit", "")
    ax.set_title(title or f"{diff.attrs.get('proposed', 'proposed')} - {diff.attrs.get('name', 'current')} [{unit}]"
                 "\nhatched: outside proposed table; *: flagged; grey: within uncertainty", fontsize=8)
    fig.colorbar(im, ax=ax, label=f"difference [{unit}]", fraction=0.04, pad=0.02)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
