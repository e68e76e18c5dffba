"""ASAM/ETAS DCM 2.0 (``KONSERVIERUNG_FORMAT 2.0``): ``KENNFELD`` maps with axis points and units.

Writer: one ``KENNFELD name nx ny`` per table with ``LANGNAME``, ``EINHEIT_X``
(rpm), ``EINHEIT_Y`` (load unit: ``%`` or ``kPa``), ``EINHEIT_W`` (value
unit), ``ST/X`` lines (x = rpm breakpoints, 6 per line), then per load
breakpoint an ``ST/Y`` line and its ``WERT`` lines, ``END``.  Several tables
may share a file.  Flags and uncertainty, when present, go into companion
maps ``<name>_flag`` (0/1) and ``<name>_uncertainty``.

Reader: every ``KENNFELD`` / ``KENNLINIE`` of a file (other DCM blocks are
skipped), sizes checked against the breakpoints and values they hold.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .ecu_msq import write_encoded
from .ecu_table import LOAD_KINDS, EcuTable
from .ecu_text import axis_decimals, build_table, decimals_of, fmt_number, parse_floats

__all__ = ["write_dcm", "read_dcm"]


_DCM_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_\[\].]*\Z")


def _dcm_lines(key: str, values, decimals: int, per_line: int = 6) -> list[str]:
    vals = [fmt_number(v, decimals) for v in values]
    return [f"   {key:<5}" + "".join(f"{v:>12}" for v in vals[k:k + per_line]) for k in range(0, len(vals), per_line)]


def _dcm_map(name: str, langname: str, table: EcuTable, values: np.ndarray, unit: str, decimals: int) -> list[str]:
    if not _DCM_NAME.match(name):
        raise ValueError(f"DCM name {name!r}: must start with a letter or '_' and hold only letters, digits, "
                         "'_', '.', '[', ']'")
    nl, nr = table.shape
    out = [f"KENNFELD {name} {nr} {nl}", f"   LANGNAME {_dcm_str(langname)}", '   EINHEIT_X "rpm"',
           f"   EINHEIT_Y {_dcm_str(table.load_unit)}", f"   EINHEIT_W {_dcm_str(unit)}"]
    out += _dcm_lines("ST/X", table.rpm, axis_decimals(table.rpm))
    yd = axis_decimals(table.load)
    for i in range(nl):
        out.append(f"   ST/Y   {fmt_number(table.load[i], yd)}")
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
    write_encoded(path, "\n".join(out) + "\n", "utf-8")
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
            cur["x"] += list(parse_floats(tok[1:], where))
        elif key == "ST/Y":
            cur["y"].append(float(parse_floats(tok[1:2], where)[0]))
            cur["w"].append([])
        elif key == "WERT":
            if not cur["w"]:
                cur["w"].append([])
            cur["w"][-1] += list(parse_floats(tok[1:], where))
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
    return build_table(f"{p}: {name}", name=name, values=np.array(m["w"]), rpm=m["x"], load=m["y"], load_kind=kind,
                  unit=m["units"].get("W", ""), decimals=decimals_of(m["wtok"]), flag_meaning=flag_meaning,
                  description=m["langname"] if m["langname"] != name else "", **extra)
