"""TunerStudio ``.msq`` tune files for Speeduino and rusEFI: the spark, VE and target-lambda/AFR tables.

An msq is TunerStudio's XML tune: ``<msq xmlns="http://www.msefi.com/:msq">``
with ``<bibliography>``, ``<versionInfo ... signature=...>`` and ``<page>``
elements holding ``<constant name= rows= cols= units= digits=>`` whose text is
the array, one table row per line, row 0 = the first (lowest) load
breakpoint, columns in rpm order (as in Speeduino's published base tunes
and rusEFI's generated ``simulator_tune.msq``).  Values are user units: the
ini's ``(raw + translate) * scale``.

Definitions followed (constant names, storage, sizes)
-----------------------------------------------------
Speeduino, ``reference/speeduino.ini`` of release tag ``202501.7``
(``signature = "speeduino 202501"``, same names in 202207-202501 and in the
2025 dev ini), sizes fixed at 16 x 16:

==========  =======================  ==============  ====================================  ==========
kind        table (ini page)         x axis          y axis (load)                         stored as
==========  =======================  ==============  ====================================  ==========
ignition    ``advTable1`` (3)        ``rpmBins2``    ``mapBins1``                          U08, 1 deg, -40..70
ve          ``veTable`` (2)          ``rpmBins``     ``fuelLoadBins``                      U08, 1 %, 0..255
lambda/afr  ``afrTable`` (5)         ``rpmBinsAFR``  ``loadBinsAFR``                       U08, 0.1 AFR, 7..25.5
==========  =======================  ==============  ====================================  ==========

rpm axes U08 x 100 rpm (100..25500); load axes U08 x 2 kPa (MAP, 0..510) or
x 0.5 % (TPS, 0..100), chosen by ``algorithm`` (fuel, AFR) / ``ignAlgorithm``
(spark) = "MAP" or "TPS", which this module does not write: set it in the
project.  Note: the ignition load axis of the primary table is ``mapBins1``;
``mapBins2`` / ``rpmBins3`` belong to the second table ``advTable2``
(``tpsBins2`` does not exist in these versions).  Lambda is written as
``afrTable`` = lambda * ``stoich`` (default 14.7, Speeduino's ``stoich``
constant); ``lambdaTable`` is an alias of the same bytes (``lastOffset``)
and is read too.

rusEFI, ``firmware/integration/rusefi_config.txt`` (rusefi/rusefi master,
commit 0002c517, ``FLASH_DATA_VERSION 260805``) with names and layout
confirmed by the generated ``simulator/generated/simulator_tune.msq``
(``signature="rusEFI master.2024.09.28..."``); sizes 16 x 16
(``IGN_LOAD_COUNT x IGN_RPM_COUNT``, ``VE_LOAD_COUNT x VE_RPM_COUNT``,
``FUEL_LOAD_COUNT x FUEL_RPM_COUNT``; a board's ``prepend.txt`` may change
them: pass ``shape=``):

==========  =================  =====================  =====================  ======================
kind        table              x axis                 y axis (load)          stored as
==========  =================  =====================  =====================  ======================
ignition    ``ignitionTable``  ``ignitionRpmBins``    ``ignitionLoadBins``   S16, 0.1 deg, -20..90
ve          ``veTable``        ``veRpmBins``          ``veLoadBins``         U16, 0.1 %, 0..999
lambda      ``lambdaTable``    ``lambdaRpmBins``      ``lambdaLoadBins``     U08, 1/147 lambda, 0.6..1.5
==========  =================  =====================  =====================  ======================

rpm axes U16, 1 rpm (0..18000); load axes U16, 1 kPa or 1 % TPS (metric
units on the interface: ``useMetricOnInterface``; in psi mode the file would
hold psi).  ``lambdaTable`` stores lambda * 147 in a byte and shows lambda
or AFR (= lambda * 14.7, whatever the fuel) depending on
``useLambdaOnInterface``: pass ``lambda_units="afr"`` for the latter (0.1 AFR).
The load source (``fuelAlgorithm``, ``ignOverrideMode``, ...) is not written.

Rounding: every value is rounded to what the firmware stores (the raw
count above) and printed with enough decimals to identify that count:
Speeduino spark to 1 deg, VE to 1 %, AFR to 0.1; rusEFI spark to 0.1 deg,
VE to 0.1 %, lambda to 1/147 (~0.007, printed with 4 decimals).  Values
outside the ini's lo..hi and breakpoints not on the storage step are
refused (ValueError), never clipped.

Partial msq or full msq
-----------------------
By default the writer produces a partial msq holding only the constants it
produces (table + its two axes) inside their ``<page>`` elements, plus
``versionInfo``.  TunerStudio matches constants by name; I found no
TunerStudio documentation stating what it does with constants that are
absent from a loaded msq, and TunerStudio warns when the file's signature
differs from the project's.  So for a tune to load into TunerStudio use
``merge_into=<your current full msq saved by TunerStudio>``: the file is
then that tune with only our constants' values replaced (units checked), a
complete msq.  The single-table route that TunerStudio documents is the
table editor's table export/import (``.table``, see
:mod:`engine_model.tables.ecu_files`).
"""

from __future__ import annotations

import datetime as _dt
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io import atomic_write
from .ecu_table import EcuTable, resample

__all__ = ["MSQ_NS", "IniField", "FirmwareTable", "FIRMWARE_TABLES", "DEFAULT_SIGNATURES", "MsqReport",
           "write_msq", "read_msq", "msq_signature", "table_kind", "write_encoded"]

MSQ_NS = "http://www.msefi.com/:msq"
DEFAULT_SIGNATURES = {"speeduino": "speeduino 202501", "rusefi": "rusEFI"}
_NPAGES = {"speeduino": 15}          # speeduino.ini: nPages = 15
_RAW = {"U08": (0, 255), "S16": (-32768, 32767), "U16": (0, 65535)}


@dataclass(frozen=True)
class IniField:
    """One ini constant: user value = ``(raw + translate) * scale``, raw in the type's range, lo..hi enforced."""

    name: str
    units: str
    kind: str           # U08 / S16 / U16
    scale: float
    translate: float
    lo: float
    hi: float
    digits: int

    @property
    def decimals(self) -> int:
        """Decimals that print every storable value exactly (4 where the scale is not a decimal fraction)."""
        for d in range(5):
            if abs(round(self.scale * 10 ** d) - self.scale * 10 ** d) < 1e-9:
                return d
        return 4

    def quantize(self, values: np.ndarray, what: str, exact: bool = False) -> np.ndarray:
        """Values rounded to the storable ones; ValueError outside lo..hi or (``exact``) not on the step."""
        v = np.asarray(values, float)
        raw = np.floor(v / self.scale - self.translate + 0.5)     # half up, as TunerStudio (Java Math.round)
        q = (raw + self.translate) * self.scale
        rmin, rmax = _RAW[self.kind]
        lo, hi = max(self.lo, (rmin + self.translate) * self.scale), min(self.hi, (rmax + self.translate) * self.scale)
        bad = np.flatnonzero(((v < lo - 1e-9) | (v > hi + 1e-9)).ravel())
        if bad.size:
            k = bad[0]
            raise ValueError(f"{what}: value {v.ravel()[k]:g} at position {np.unravel_index(k, v.shape)} is outside "
                             f"{self.name}'s range {lo:g}..{hi:g} {self.units}")
        if exact:
            off = np.flatnonzero((np.abs(q - v) > 1e-6 * np.maximum(1.0, np.abs(v))).ravel())
            if off.size:
                k = off[0]
                raise ValueError(f"{what}: breakpoint {v.ravel()[k]:g} cannot be stored in {self.name} (steps of "
                                 f"{self.scale:g} {self.units}); choose breakpoints on that step")
        return q + 0.0


@dataclass(frozen=True)
class FirmwareTable:
    """Where one kind of table lives in a firmware's definition."""

    firmware: str
    kind: str                    # ignition / ve / lambda
    z: IniField
    x: IniField                  # rpm
    y: dict                      # load_kind -> IniField
    shape: tuple = (16, 16)      # (load rows, rpm columns)
    page: int | None = None      # msq page number (ini page - 1)
    page_size: int | None = None
    value_unit: str = ""         # EcuTable unit of the values read back


def _f(name, units, kind, scale, translate, lo, hi, digits):
    return IniField(name, units, kind, scale, translate, lo, hi, digits)


_SP_RPM = {"ignition": "rpmBins2", "ve": "rpmBins", "lambda": "rpmBinsAFR"}
_SP_LOAD = {"ignition": "mapBins1", "ve": "fuelLoadBins", "lambda": "loadBinsAFR"}


def _sp_axes(kind):
    return dict(x=_f(_SP_RPM[kind], "RPM", "U08", 100.0, 0, 100, 25500, 0),
                y={"map_kpa": _f(_SP_LOAD[kind], "kPa", "U08", 2.0, 0, 0, 511, 0),
                   "throttle_pct": _f(_SP_LOAD[kind], "% TPS", "U08", 0.5, 0, 0, 100, 1)})


def _re_axes(prefix):
    load = _f(f"{prefix}LoadBins", "kPa", "U16", 1.0, 0, 0, 65535, 0)
    return dict(x=_f(f"{prefix}RpmBins", "RPM", "U16", 1.0, 0, 0, 18000, 0),
                y={"map_kpa": load, "throttle_pct": IniField(load.name, "%", "U16", 1.0, 0, 0, 100, 0)})


#: (firmware, kind) -> FirmwareTable
FIRMWARE_TABLES = {
    ("speeduino", "ignition"): FirmwareTable("speeduino", "ignition",
                                             _f("advTable1", "deg", "U08", 1.0, -40, -40, 70, 0),
                                             page=2, page_size=288, value_unit="deg", **_sp_axes("ignition")),
    ("speeduino", "ve"): FirmwareTable("speeduino", "ve", _f("veTable", "%", "U08", 1.0, 0, 0, 255, 0),
                                       page=1, page_size=288, value_unit="%", **_sp_axes("ve")),
    ("speeduino", "lambda"): FirmwareTable("speeduino", "lambda", _f("afrTable", "AFR", "U08", 0.1, 0, 7, 25.5, 1),
                                           page=4, page_size=288, value_unit="AFR", **_sp_axes("lambda")),
    ("rusefi", "ignition"): FirmwareTable("rusefi", "ignition",
                                          _f("ignitionTable", "deg", "S16", 0.1, 0, -20, 90, 1),
                                          page=0, value_unit="deg", **_re_axes("ignition")),
    ("rusefi", "ve"): FirmwareTable("rusefi", "ve", _f("veTable", "%", "U16", 0.1, 0, 0, 999, 1),
                                    page=0, value_unit="%", **_re_axes("ve")),
    ("rusefi", "lambda"): FirmwareTable("rusefi", "lambda",
                                        _f("lambdaTable", "lambda", "U08", 1 / 147, 0, 0.6, 1.5, 2),
                                        page=0, value_unit="-", **_re_axes("lambda")),
}
_ALIASES = {("speeduino", "lambdaTable"): "lambda"}   # read-only alias of afrTable's bytes (values in lambda)
_UNITS = {"ignition": ("deg", "deg btdc", "degbtdc", "°", "deg crank"), "ve": ("%", "pct", "percent"),
          "lambda": ("-", "lambda", "λ", ""), "afr": ("afr",)}


def table_kind(table: EcuTable) -> str:
    """ignition / ve / lambda / afr from the table's unit (ValueError if the unit says none of them)."""
    u = table.unit.strip().lower()
    for kind, units in _UNITS.items():
        if u in units:
            return kind
    raise ValueError(f"table {table.name!r}: unit {table.unit!r} is not a spark (deg), VE (%), lambda (-) or "
                     "AFR unit; pass kinds= to say which firmware table it is")


@dataclass
class MsqReport:
    """What :func:`write_msq` wrote."""

    path: Path
    firmware: str
    signature: str
    constants: list = field(default_factory=list)
    max_rounding: dict = field(default_factory=dict)     # table constant -> max |stored - value|
    outside: dict = field(default_factory=dict)          # table constant -> outside mask of resampling (or None)
    merged_into: Path | None = None


def _fmt(v: np.ndarray, decimals: int) -> list[str]:
    return [f"{x:.{max(decimals, 1)}f}" for x in np.asarray(v, float).ravel()]


def _text(arr: np.ndarray, decimals: int) -> str:
    """An msq array text as TunerStudio writes it: one row per line, leading newline, closing indentation."""
    rows = np.atleast_2d(arr) if arr.ndim == 2 else arr.reshape(-1, 1)
    lines = ["         " + " ".join(_fmt(r, decimals)) + " " for r in rows]
    return "\n" + "\n".join(lines) + "\n      "


def _prepare(table: EcuTable, firmware: str, kind: str, resample_to, shape, stoich: float, lambda_units: str):
    """(definition, z field, y field, z values, x values, y values, outside) for one table."""
    key = (firmware, "lambda" if kind == "afr" else kind)
    if key not in FIRMWARE_TABLES:
        raise ValueError(f"{firmware}: no {kind!r} table defined (have {sorted(k for f, k in FIRMWARE_TABLES if f == firmware)})")
    d = FIRMWARE_TABLES[key]
    need = tuple(shape) if shape is not None else d.shape
    outside = None
    if table.shape != need:
        if resample_to is None:
            raise ValueError(f"{firmware} {d.z.name} is {need[0]}x{need[1]} ({need[0]} load rows x {need[1]} rpm "
                             f"columns); table {table.name!r} is {table.shape[0]}x{table.shape[1]}. Resample it "
                             f"(resample_to=(rpm_bins, load_bins) with {need[1]} rpm and {need[0]} load breakpoints)")
        rpm_bins, load_bins = resample_to
        table, outside = resample(table, rpm_bins, load_bins)
        if table.shape != need:
            raise ValueError(f"{firmware} {d.z.name} is {need[0]}x{need[1]}; resample_to gives "
                             f"{table.shape[0]}x{table.shape[1]} (len(load_bins) x len(rpm_bins))")
    z = d.z
    vals = table.values
    if kind in ("lambda", "afr"):
        lam = vals / stoich if kind == "afr" else vals
        if firmware == "speeduino":
            vals = lam * stoich                       # afrTable holds AFR with the ECU's stoich
        elif lambda_units == "afr":
            vals = lam * 14.7                         # rusEFI packs lambda*147: its AFR view is lambda*14.7
            z = _f("lambdaTable", "afr", "U08", 0.1, 0, 0, 25, 1)
        else:
            vals = lam
    y = d.y[table.load_kind]
    who = f"{firmware} {z.name} from table {table.name!r}"
    zq = z.quantize(vals, who)
    xq = d.x.quantize(table.rpm, f"{who}, rpm axis {d.x.name}", exact=True)
    yq = y.quantize(table.load, f"{who}, load axis {y.name}", exact=True)
    return d, z, y, zq, float(np.max(np.abs(zq - vals))), xq, yq, outside


def write_msq(tables, path, firmware: str, *, kinds=None, resample_to=None, shape=None, signature: str | None = None,
              stoich: float = 14.7, lambda_units: str = "lambda", merge_into=None,
              author: str = "engine_model ECU export", write_date: str | None = None) -> MsqReport:
    """Write tables into a TunerStudio msq for ``firmware`` ("speeduino" or "rusefi").

    Parameters
    ----------
    tables : EcuTable or sequence of EcuTable
        At most one per kind; spark (unit deg...), VE (%), lambda (-) or AFR.
    path : path
        The msq to write (replaced atomically).
    firmware : {"speeduino", "rusefi"}
    kinds : sequence of str, optional
        ignition / ve / lambda / afr per table (default: from each table's unit, :func:`table_kind`).
    resample_to : (rpm_bins, load_bins), optional
        Resample tables whose size differs from the firmware's onto these
        breakpoints (:func:`resample`; the ``outside`` masks are in the
        report).  Without it a size mismatch is a ValueError.
    shape : (n_load, n_rpm), optional
        Override the firmware table size (rusEFI boards that change it).
    signature : str, optional
        ``versionInfo`` signature; use the one of your project
        (:func:`msq_signature` of a tune it saved).  Ignored with ``merge_into``.
    stoich : float
        AFR at lambda 1 as the ECU is set up (Speeduino ``stoich``): lambda
        tables go into Speeduino's ``afrTable`` as lambda * stoich, and an AFR
        table (kind "afr") is turned into lambda as AFR / stoich.  rusEFI's
        AFR display is lambda * 14.7 regardless.
    lambda_units : {"lambda", "afr"}
        rusEFI only: the project's ``useLambdaOnInterface`` (lambda) or AFR display.
    merge_into : path, optional
        A full msq of the same firmware: write a copy of it with only our
        constants' values replaced (rows/cols and units must match).
    author, write_date : str
        ``bibliography`` attributes (write_date defaults to now).

    Returns
    -------
    MsqReport
    """
    firmware = str(firmware).lower()
    if firmware not in ("speeduino", "rusefi"):
        raise ValueError(f"firmware {firmware!r}: expected 'speeduino' or 'rusefi'")
    if lambda_units not in ("lambda", "afr"):
        raise ValueError(f"lambda_units {lambda_units!r}: expected 'lambda' or 'afr'")
    tables = [tables] if isinstance(tables, EcuTable) else list(tables)
    if not tables:
        raise ValueError("write_msq: no tables given")
    kinds = [table_kind(t) for t in tables] if kinds is None else list(kinds)
    if len(kinds) != len(tables):
        raise ValueError(f"write_msq: {len(kinds)} kinds for {len(tables)} tables")
    seen = {}
    for t, k in zip(tables, kinds):
        base = "lambda" if k == "afr" else k
        if base in seen:
            raise ValueError(f"write_msq: tables {seen[base]!r} and {t.name!r} both go to the {base} table")
        seen[base] = t.name
    path = Path(path)
    report = MsqReport(path, firmware, signature or DEFAULT_SIGNATURES[firmware])
    pages: dict = {}
    for t, k in zip(tables, kinds):
        d, z, y, zq, rounding, xq, yq, outside = _prepare(t, firmware, k, resample_to, shape, stoich, lambda_units)
        pages.setdefault((d.page, d.page_size), []).extend(
            [(z, zq, zq.shape[1], zq.shape[0]), (d.x, xq, 1, xq.size), (y, yq, 1, yq.size)])
        report.constants += [z.name, d.x.name, y.name]
        report.max_rounding[z.name] = rounding
        report.outside[z.name] = outside
    if merge_into is not None:
        _merge(pages, Path(merge_into), path, firmware)
        report.merged_into = Path(merge_into)
        report.signature = msq_signature(merge_into)
        return report
    date = write_date or _dt.datetime.now().strftime("%a %b %d %H:%M:%S %Y")
    comment = _q("partial tune: " + ", ".join(report.constants))
    out = ['<?xml version="1.0" encoding="ISO-8859-1"?>', f'<msq xmlns="{MSQ_NS}">',
           f"    <bibliography author={_q(author)} tuneComment={comment} writeDate={_q(date)}/>"]
    npages = f' nPages="{_NPAGES[firmware]}"' if firmware in _NPAGES else ""
    out.append(f'    <versionInfo fileFormat="5.0"{npages} signature={_q(report.signature)}/>')
    for (page, size) in sorted(pages, key=lambda p: p[0]):
        size_attr = f' size="{size}"' if size else ""
        out.append(f'    <page number="{page}"{size_attr}>')
        for f_, arr, cols, rows in pages[(page, size)]:
            out.append(f'        <constant cols="{cols}" digits="{f_.digits}" name="{f_.name}" rows="{rows}" '
                       f'units={_q(f_.units)}>{_text(arr, f_.decimals)}</constant>')
        out.append("    </page>")
    out.append("</msq>")
    write_encoded(path, "\n".join(out) + "\n", "iso-8859-1")
    return report


def _q(s: str) -> str:
    from xml.sax.saxutils import quoteattr
    return quoteattr(str(s))


def write_encoded(path: Path, text: str, encoding: str) -> Path:
    """Write ``text`` in ``encoding`` with ``\\n`` line ends, atomically (:func:`engine_model.io.atomic_write`)."""
    data = text.encode(encoding)
    return atomic_write(Path(path), lambda tmp: Path(tmp).write_bytes(data))


def _merge(pages: dict, base: Path, path: Path, firmware: str) -> None:
    root, encoding = _parse(base)
    sig = msq_signature(base)
    if _firmware_of(sig, root) != firmware:
        raise ValueError(f"{base}: signature {sig!r} is not a {firmware} tune")
    ns = root.tag[1:].split("}")[0] if root.tag.startswith("{") else ""
    ET.register_namespace("", ns)
    by_name = {c.get("name"): c for c in root.iter(_tag(ns, "constant"))}
    for entries in pages.values():
        for f_, arr, cols, rows in entries:
            el = by_name.get(f_.name)
            if el is None:
                raise ValueError(f"{base}: has no constant {f_.name!r} to replace; is it a full {firmware} tune?")
            if (el.get("rows"), el.get("cols")) != (str(rows), str(cols)):
                raise ValueError(f"{base}: constant {f_.name} is {el.get('rows')}x{el.get('cols')} (rows x cols), "
                                 f"ours is {rows}x{cols}")
            units = el.get("units")
            if units is not None and _unit_class(units) != _unit_class(f_.units):
                raise ValueError(f"{base}: constant {f_.name} is in {units!r}, ours in {f_.units!r}; set the "
                                 "project to the same units (load source, metric/lambda display) or convert")
            el.text = _text(arr, f_.decimals)
    body = ET.tostring(root, encoding="unicode")
    write_encoded(path, f'<?xml version="1.0" encoding="{encoding}"?>\n{body}\n', encoding)


def _unit_class(u: str) -> str:
    u = u.strip().lower()
    for key, cls in (("kpa", "kpa"), ("psi", "psi"), ("tps", "pct"), ("%", "pct"), ("rpm", "rpm"), ("deg", "deg"),
                     ("afr", "afr"), ("lambda", "lambda")):
        if key in u:
            return cls
    return u


def _tag(ns: str, name: str) -> str:
    return f"{{{ns}}}{name}" if ns else name


def _parse(path) -> tuple[ET.Element, str]:
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: file not found")
    try:
        raw = p.read_bytes()
        root = ET.fromstring(raw)
    except (OSError, ET.ParseError) as exc:
        raise ValueError(f"{p}: not a readable XML msq: {exc}") from None
    if root.tag.split("}")[-1] != "msq":
        raise ValueError(f"{p}: root element <{root.tag.split('}')[-1]}> is not <msq>")
    m = re.match(rb'<\?xml[^>]*encoding="([^"]+)"', raw)
    return root, (m.group(1).decode() if m else "UTF-8")


def msq_signature(path) -> str:
    """The ``versionInfo`` signature of an msq ('' if none)."""
    root, _ = _parse(path)
    vi = next((e for e in root.iter() if e.tag.split("}")[-1] == "versionInfo"), None)
    return "" if vi is None else vi.get("signature", "")


def _firmware_of(signature: str, root: ET.Element) -> str | None:
    s = signature.lower()
    if s.startswith("speeduino"):
        return "speeduino"
    if any(w in s for w in ("rusefi", "fome", "epicefi")):
        return "rusefi"
    names = {e.get("name") for e in root.iter() if e.tag.split("}")[-1] == "constant"}
    if names & {"advTable1", "rpmBins2", "afrTable"}:
        return "speeduino"
    if names & {"ignitionTable", "veRpmBins", "lambdaTable"}:
        return "rusefi"
    return None


def _numbers(el: ET.Element, where: str) -> tuple[np.ndarray, int]:
    toks = (el.text or "").split()
    try:
        vals = np.array([float(t) for t in toks])
    except ValueError:
        bad = next(t for t in toks if not re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?", t))
        raise ValueError(f"{where}: {bad!r} is not a number") from None
    dec = max((len(t.split(".")[1].rstrip("0")) if "." in t and "e" not in t.lower() else 0) for t in toks) \
        if toks else 0
    return vals, min(dec, 6)


def _load_kind(root, y_el, d: FirmwareTable, given: str | None, where: str) -> str:
    if given is not None:
        return given
    units = (y_el.get("units") or "").lower()
    if "kpa" in units:
        return "map_kpa"
    if "tps" in units or units.strip() == "%":
        return "throttle_pct"
    consts = {e.get("name"): (e.text or "").strip().strip('"') for e in root.iter()
              if e.tag.split("}")[-1] == "constant"}
    src = consts.get("ignAlgorithm" if d.kind == "ignition" else "algorithm") if d.firmware == "speeduino" \
        else consts.get("fuelAlgorithm")
    if src in ("MAP", "Speed Density"):
        return "map_kpa"
    if src in ("TPS", "Alpha-N"):
        return "throttle_pct"
    raise ValueError(f"{where}: cannot tell whether load axis {d.y['map_kpa'].name} is MAP [kPa] or throttle [%] "
                     f"(units {y_el.get('units')!r}, load source {src!r}); pass load_kind=")


def read_msq(path, table: str | None = None, *, load_kind: str | None = None) -> EcuTable:
    """One table of an msq as an :class:`EcuTable`.

    ``table`` is a kind (ignition / ve / lambda) or a constant name
    (``advTable1``, ``veTable``, ...); it may be omitted when the file holds
    one known table.  The load kind comes from ``load_kind`` if given, else
    from the axis units, else from the firmware's load-source setting in the
    file (Speeduino ``algorithm`` / ``ignAlgorithm``; rusEFI
    ``fuelAlgorithm``, which assumes no ``ignOverrideMode``/``veOverrideMode``).
    Values are as stored (Speeduino ``afrTable`` in AFR, ``lambdaTable`` in lambda).
    """
    p = Path(path)
    root, _ = _parse(p)
    fw = _firmware_of(msq_signature(p), root)
    if fw is None:
        raise ValueError(f"{p}: neither a Speeduino nor a rusEFI tune (signature {msq_signature(p)!r})")
    consts = {}
    for e in root.iter():
        if e.tag.split("}")[-1] == "constant":
            consts.setdefault(e.get("name"), e)
    defs = {k: d for (f_, k), d in FIRMWARE_TABLES.items() if f_ == fw}
    aliases = {n: k for (f_, n), k in _ALIASES.items() if f_ == fw}
    zname = None
    if table is None:
        have = [k for k, d in defs.items() if d.z.name in consts or any(a in consts for a, ak in aliases.items()
                                                                         if ak == k)]
        if len(have) != 1:
            raise ValueError(f"{p}: holds tables {have or 'none'} of {sorted(defs)}; pass table= to choose one")
        kind = have[0]
    elif table in defs or table == "afr":
        kind = "lambda" if table == "afr" else table
    else:
        kind = next((k for k, d in defs.items() if d.z.name == table), aliases.get(table))
        if kind is None:
            raise ValueError(f"{p}: {table!r} is not a {fw} table this module knows ({sorted(defs)} or "
                             f"{[d.z.name for d in defs.values()] + list(aliases)})")
        zname = table
    d = defs[kind]
    if zname is None:
        zname = d.z.name if d.z.name in consts else \
            next((a for a, ak in aliases.items() if ak == kind and a in consts), d.z.name)
    names = (zname, d.x.name, d.y["map_kpa"].name)
    missing = [n for n in names if n not in consts]
    if missing:
        raise ValueError(f"{p}: constant(s) {missing} missing for the {fw} {kind} table")
    z_el, x_el, y_el = (consts[n] for n in names)
    z, dec = _numbers(z_el, f"{p}: {zname}")
    x, _ = _numbers(x_el, f"{p}: {d.x.name}")
    y, _ = _numbers(y_el, f"{p}: {names[2]}")
    rows, cols = int(z_el.get("rows", y.size)), int(z_el.get("cols", x.size))
    if z.size != rows * cols or (rows, cols) != (y.size, x.size):
        raise ValueError(f"{p}: {zname} has {z.size} values for {rows}x{cols} (rows x cols); axes have "
                         f"{y.size} load and {x.size} rpm breakpoints")
    kind_load = _load_kind(root, y_el, d, load_kind, str(p))
    unit = z_el.get("units") or d.value_unit
    if zname == "lambdaTable" and z_el.get("units") is None and np.median(z) > 3:
        unit = "AFR"                                  # rusEFI tune saved with AFR display and no units
    unit = "-" if unit.strip().lower() == "lambda" else unit
    try:
        return EcuTable(zname, z.reshape(rows, cols), x, y, kind_load, unit, dec,
                        description=f"{fw} {kind} table from {p.name}")
    except ValueError as exc:
        raise ValueError(f"{p}: {exc}") from None
