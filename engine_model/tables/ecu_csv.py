"""ECU tables as CSV with a units header.

Key lines ``table,<name>`` / ``unit,<unit>`` / ``row_axis,<name>,<unit>`` /
``column_axis,speed_rpm,rpm`` / ``decimals,<n>`` (+ ``description``,
``flag_meaning``), then ``[values]`` and a wide grid (first column load,
header rpm), optionally ``[flags]`` and ``[uncertainty]`` grids.
:func:`read_csv` also reads the plain wide CSVs of
:func:`engine_model.tables.export.write_maps` (header ``throttle_pct,<rpm>...``).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from .ecu_msq import write_encoded
from .ecu_table import LOAD_KINDS, EcuTable
from .ecu_text import axis_decimals, build_table, decimals_of, fmt_number, parse_floats

__all__ = ["write_csv", "read_csv", "WIDE_CSV_UNITS"]


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
    xd, yd = axis_decimals(table.rpm), axis_decimals(table.load)
    corner = f"{table.load_column} \\ speed_rpm"

    def grid(title, values, fmt):
        w.writerow([title])
        w.writerow([corner] + [fmt_number(v, xd) for v in table.rpm])
        for load, row in zip(table.load, values):
            w.writerow([fmt_number(load, yd)] + [fmt(v) for v in row])

    grid("[values]", table.rounded(), lambda v: fmt_number(v, table.decimals))
    if table.flags is not None:
        grid("[flags]", table.flags, lambda v: "1" if v else "0")
    if table.uncertainty is not None:
        grid("[uncertainty]", table.uncertainty, lambda v: fmt_number(v, table.decimals + 1))
    write_encoded(path, buf.getvalue(), "utf-8")
    return path


WIDE_CSV_UNITS = {"spark_advance": "deg BTDC", "spark_start_retarded": "deg BTDC", "injection_time": "ms",
                  "lambda_target": "-"}


def read_csv(path, *, load_kind: str | None = None) -> EcuTable:
    """A units-header CSV, or a plain wide CSV of the maps (first header cell ``throttle_pct``)."""
    p = Path(path)
    try:
        with open(p, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.reader(fh)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"{p}: could not be read as CSV: {exc}") from None
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        raise ValueError(f"{p}: empty file")
    if rows[0][0].strip() == "throttle_pct":          # the maps' wide table
        return _grid_table(p, rows, 0, dict(table=p.stem, unit=WIDE_CSV_UNITS.get(p.stem, "")), "throttle_pct")
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
    x = parse_floats([c.strip() for c in head[1:] if c.strip()], f"{where}, header")
    load, vals, tok = [], [], []
    k = start + 1
    while k < len(rows) and not rows[k][0].startswith("["):
        r = [c.strip() for c in rows[k]]
        cells = r[1:1 + x.size]
        if len(cells) != x.size or any(c == "" for c in cells):
            raise ValueError(f"{where}: row {r[0]!r} has {len([c for c in cells if c])} values for {x.size} "
                             "rpm columns")
        load.append(float(parse_floats(r[:1], where)[0]))
        vals.append(parse_floats(cells, where))
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
        dec = int(info["decimals"]) if "decimals" in info else decimals_of(tok)
    except ValueError:
        raise ValueError(f"{p}: decimals {info['decimals']!r} is not an integer") from None
    return build_table(str(p), name=info.get("table", p.stem), values=v, rpm=x, load=y, load_kind=kind,
                  unit=info.get("unit", ""), decimals=dec, flag_meaning=info.get("flag_meaning", ""),
                  description=info.get("description", ""), **extra)
