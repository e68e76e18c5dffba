"""One ECU table on its breakpoints, putting it on other breakpoints, and the fuel quantities it can hold.

:class:`EcuTable` is what every reader in :mod:`engine_model.tables.ecu_files`
returns and every writer takes: values ``[n_load, n_rpm]`` (rows = load
axis, as the ECU table editors show them), the rpm axis, the load axis and
its kind, the value unit, the number of decimals the value is written with,
and optionally a flag per cell (e.g. knock-limited) and a per-cell
uncertainty in the value unit.

Load axis kinds
---------------
``"throttle_pct"``
    alpha-N: throttle opening [%], what the team's DTA S60 (and Speeduino /
    rusEFI in TPS or Alpha-N mode) look the table up with.
``"map_kpa"``
    speed density: manifold absolute pressure [kPa].

Putting a table on other breakpoints
------------------------------------
:func:`resample`
    bilinear inside the source grid (exact for any ``a + b*rpm + c*load +
    d*rpm*load``); outside it the edge value is held and the cell is
    reported in the returned ``outside`` mask, never silently extrapolated.
:func:`to_map_kpa`
    a throttle-% table onto a MAP axis, inverting each rpm column's
    throttle -> plenum pressure map (see its docstring for the rules at
    plateaus, dips and pressures a column does not reach).

Fuel quantities
---------------
:func:`fuel_mg`, :func:`injection_ms` (via
:func:`engine_model.tables.injection.injection_time_ms`, dead time vs battery
voltage included) and :func:`ve_percent` (volumetric efficiency relative to
the air a cylinder holds at a reference pressure and temperature; the
convention of each ECU is in its docstring).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import pandas as pd

from .. import thermo
from ..contracts import check_breakpoints
from ..spec import EngineSpec
from .injection import injection_time_ms

__all__ = ["LOAD_KINDS", "DEFAULT_DECIMALS", "R_AIR_J_KG_K", "EcuTable", "Resampled", "resample", "to_map_kpa",
           "air_mg_per_cycle", "fuel_mg", "injection_ms", "ve_percent"]

#: load kind -> (axis column name, unit, short label)
LOAD_KINDS = {"throttle_pct": ("throttle_pct", "%", "throttle"), "map_kpa": ("map_kpa", "kPa", "MAP")}
#: decimals of the project's tables (as in the wide CSVs of engine_model.tables.export); others default to 2
DEFAULT_DECIMALS = {"spark_advance": 1, "spark_start_retarded": 1, "injection_time": 3, "lambda_target": 3,
                    "ve": 1, "fuel_mass": 2}
#: Specific gas constant of dry air [J/(kg K)]: R / M_air with M_air = 28.9647 g/mol (ISO 2533 standard
#: atmosphere).  rusEFI's speed-density code uses 0.28705 J/(g K), the same to 4 digits.
R_AIR_J_KG_K = thermo.R_UNIVERSAL / 0.0289647


# --------------------------------------------------------------------------- the table

def _axis(owner: str, field: str, values, unit: str) -> np.ndarray:
    arr = check_breakpoints(f"{owner}.{field}", values, unit)
    arr.setflags(write=False)
    return arr


def _grid(owner: str, field: str, values, shape, load, rpm, load_unit: str, dtype=float) -> np.ndarray:
    try:
        arr = np.array(values, dtype=dtype)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.{field}: could not be read as an array of numbers") from None
    if arr.shape != shape:
        raise ValueError(f"{owner}.{field}: shape {arr.shape} does not match (len(load), len(rpm)) = {shape}; "
                         "rows are load breakpoints, columns rpm breakpoints")
    if dtype is float:
        bad = np.argwhere(~np.isfinite(arr))
        if bad.size:
            i, j = bad[0]
            raise ValueError(f"{owner}.{field}: cell [{i}, {j}] (load {load[i]:g} {load_unit}, {rpm[j]:g} rpm) "
                             f"= {arr[i, j]} is not a finite number")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class EcuTable:
    """One 2-D ECU table; rows = load breakpoints, columns = rpm breakpoints.

    Parameters
    ----------
    name : str
        Table name (e.g. ``spark_advance``); a file's table name where the format has one.
    values : array_like, shape (n_load, n_rpm)
        Finite values in ``unit``.
    rpm : array_like
        Engine-speed breakpoints [rpm], strictly increasing, >= 2.
    load : array_like
        Load breakpoints in the unit of ``load_kind`` (throttle [%] or MAP [kPa]), strictly increasing, >= 2.
    load_kind : {"throttle_pct", "map_kpa"}
    unit : str
        Unit of the values (``deg BTDC``, ``ms``, ``-`` for lambda, ``%`` for VE, ...).
    decimals : int
        Decimals the values are written with (0-6).
    flags : array_like of bool, optional
        Cells that carry the flag ``flag_meaning`` (e.g. knock-limited).
    flag_meaning : str
        What a flagged cell means; written next to the flags where the format allows.
    uncertainty : array_like, optional
        Per-cell uncertainty (one standard deviation) in ``unit``, finite and >= 0.
    description : str
        Free text (long name).

    Arrays are copied and made read-only; construction validates every field
    and raises ValueError naming the field, the offending value and what was
    expected.
    """

    name: str
    values: np.ndarray
    rpm: np.ndarray
    load: np.ndarray
    load_kind: str = "throttle_pct"
    unit: str = ""
    decimals: int = 2
    flags: np.ndarray | None = None
    flag_meaning: str = ""
    uncertainty: np.ndarray | None = None
    description: str = ""

    def __post_init__(self):
        name = str(self.name).strip()
        if not name:
            raise ValueError("EcuTable.name: empty; every table needs a name")
        owner = f"EcuTable {name!r}"
        object.__setattr__(self, "name", name)
        if self.load_kind not in LOAD_KINDS:
            raise ValueError(f"{owner}.load_kind: {self.load_kind!r} is not one of {sorted(LOAD_KINDS)}")
        load_unit = LOAD_KINDS[self.load_kind][1]
        rpm = _axis(owner, "rpm", self.rpm, "rpm")
        load = _axis(owner, "load", self.load, load_unit)
        object.__setattr__(self, "rpm", rpm)
        object.__setattr__(self, "load", load)
        shape = (load.size, rpm.size)
        object.__setattr__(self, "values", _grid(owner, "values", self.values, shape, load, rpm, load_unit))
        if not (isinstance(self.decimals, (int, np.integer)) and 0 <= int(self.decimals) <= 6):
            raise ValueError(f"{owner}.decimals: {self.decimals!r} must be an integer 0..6")
        object.__setattr__(self, "decimals", int(self.decimals))
        object.__setattr__(self, "unit", str(self.unit))
        if self.flags is not None:
            raw = np.asarray(self.flags)
            if raw.dtype != bool and not np.isin(raw, (0, 1)).all():
                raise ValueError(f"{owner}.flags: must be booleans (or 0/1), got values {np.unique(raw)[:5]}")
            object.__setattr__(self, "flags", _grid(owner, "flags", raw.astype(bool), shape, load, rpm,
                                                    load_unit, dtype=bool))
        if self.uncertainty is not None:
            unc = _grid(owner, "uncertainty", self.uncertainty, shape, load, rpm, load_unit)
            if np.any(unc < 0):
                i, j = np.argwhere(unc < 0)[0]
                raise ValueError(f"{owner}.uncertainty: cell [{i}, {j}] = {unc[i, j]:g} is negative")
            object.__setattr__(self, "uncertainty", unc)

    # ----------------------------------------------------------------- views
    @property
    def shape(self) -> tuple[int, int]:
        """(number of load rows, number of rpm columns)."""
        return self.values.shape

    @property
    def load_unit(self) -> str:
        """``%`` (throttle) or ``kPa`` (MAP)."""
        return LOAD_KINDS[self.load_kind][1]

    @property
    def load_column(self) -> str:
        """``throttle_pct`` or ``map_kpa``: the load column name of :meth:`to_frame`."""
        return LOAD_KINDS[self.load_kind][0]

    def rounded(self) -> np.ndarray:
        """Values rounded to :attr:`decimals` (what the text formats write)."""
        return np.round(self.values, self.decimals) + 0.0   # + 0.0: no '-0.0'

    def replace(self, **changes) -> "EcuTable":
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)

    def to_frame(self) -> pd.DataFrame:
        """Long form, row-major (load outer): ``i, j, <load column>, speed_rpm, value[, flag][, uncertainty]``."""
        nl, nr = self.shape
        i, j = np.divmod(np.arange(nl * nr), nr)
        df = pd.DataFrame({"i": i, "j": j, self.load_column: self.load[i], "speed_rpm": self.rpm[j],
                           "value": self.values.ravel()})
        if self.flags is not None:
            df["flag"] = self.flags.ravel()
        if self.uncertainty is not None:
            df["uncertainty"] = self.uncertainty.ravel()
        return df

    @classmethod
    def from_long_form(cls, df: pd.DataFrame, table: str, *, load_column: str = "throttle_pct",
                       rpm_column: str = "speed_rpm", value_column: str = "value", unit: str | None = None,
                       decimals: int | None = None, flag_column: str | None = None, flag_value=None,
                       uncertainty_column: str | None = None, description: str = "") -> "EcuTable":
        """One table out of a long-form frame such as the maps' ``ecu_tables.parquet``.

        ``df`` has one row per cell; if it has a ``table`` column only rows
        with ``table == table`` are used.  ``flag_column``/``flag_value``
        flag the cells where that column equals the value (e.g.
        ``flag_column="limited_by", flag_value="knock"``).  The unit is taken
        from a ``unit`` column when not given.  Missing or duplicate cells
        raise a ValueError naming them.
        """
        sub = df[df["table"] == table] if "table" in df.columns else df
        if sub.empty:
            raise ValueError(f"long form: no rows for table {table!r}")
        for col in (load_column, rpm_column, value_column):
            if col not in sub.columns:
                raise ValueError(f"long form: column {col!r} missing (have {list(sub.columns)})")
        dup = sub.duplicated([load_column, rpm_column])
        if dup.any():
            r = sub[dup].iloc[0]
            raise ValueError(f"long form, table {table!r}: cell ({load_column} {r[load_column]:g}, "
                             f"{r[rpm_column]:g} rpm) appears more than once")
        load = np.unique(sub[load_column].to_numpy(float))
        rpm = np.unique(sub[rpm_column].to_numpy(float))
        if len(sub) != load.size * rpm.size:
            have = set(zip(sub[load_column].astype(float), sub[rpm_column].astype(float)))
            miss = next((a, b) for a in load for b in rpm if (a, b) not in have)
            raise ValueError(f"long form, table {table!r}: cell ({load_column} {miss[0]:g}, {miss[1]:g} rpm) is "
                             "missing; the table must be a full grid")
        order = sub.sort_values([load_column, rpm_column])

        def grid(col):
            return order[col].to_numpy().reshape(load.size, rpm.size)

        if unit is None:
            units = order["unit"].unique() if "unit" in order.columns else [""]
            unit = str(units[0]) if len(units) else ""
        kind = next((k for k, v in LOAD_KINDS.items() if v[0] == load_column), None)
        if kind is None:
            raise ValueError(f"long form: load column {load_column!r} is not one of "
                             f"{[v[0] for v in LOAD_KINDS.values()]}")
        flags = None
        meaning = ""
        if flag_column is not None:
            flags = grid(flag_column) == flag_value
            meaning = f"{flag_column} == {flag_value}"
        return cls(table, grid(value_column).astype(float), rpm, load, kind, unit,
                   DEFAULT_DECIMALS.get(table, 2) if decimals is None else decimals, flags, meaning,
                   None if uncertainty_column is None else grid(uncertainty_column).astype(float), description)


# --------------------------------------------------------------------------- breakpoints

class Resampled(NamedTuple):
    """A table put on other breakpoints and the cells that could not be interpolated.

    ``outside[i, j]`` is True where the new cell lies outside what the source
    covers (the edge value was held), or for :func:`to_map_kpa` also where the
    pressure cannot identify the throttle row (see there).
    """

    table: EcuTable
    outside: np.ndarray


def _brackets(src: np.ndarray, dst: np.ndarray):
    """Lower/upper source index, weight of the upper one, and the outside mask of ``dst`` on ascending ``src``.

    Outside ``[src[0], src[-1]]`` the coordinate is clamped to the edge.
    """
    tol = 1e-9 * max(1.0, float(np.max(np.abs(src))))
    outside = (dst < src[0] - tol) | (dst > src[-1] + tol)
    x = np.clip(dst, src[0], src[-1])
    hi = np.clip(np.searchsorted(src, x, side="right"), 1, src.size - 1)
    lo = hi - 1
    w = np.clip((x - src[lo]) / (src[hi] - src[lo]), 0.0, 1.0)
    return lo, hi, w, outside


def _corners(lo_r, hi_r, w_r, lo_c, hi_c, w_c):
    """The four (row index, column index, weight) corners of each target cell, as broadcast arrays."""
    wr, wc = w_r[:, None], w_c[None, :]
    return [(lo_r[:, None], lo_c[None, :], (1 - wr) * (1 - wc)), (lo_r[:, None], hi_c[None, :], (1 - wr) * wc),
            (hi_r[:, None], lo_c[None, :], wr * (1 - wc)), (hi_r[:, None], hi_c[None, :], wr * wc)]


def resample(table: EcuTable, rpm_bins, load_bins) -> Resampled:
    """The table on the ECU's own breakpoints.

    Bilinear interpolation inside the source grid; outside it each coordinate
    is clamped to the nearest edge (the edge value is held) and the cell is
    marked in ``outside``.  Flags of the result: a cell is flagged when any
    source corner with a non-zero weight is flagged; its uncertainty is the
    largest of those corners' (conservative; interpolation would understate
    it between a well- and a poorly-known cell).

    Parameters
    ----------
    table : EcuTable
    rpm_bins : array_like
        New rpm breakpoints [rpm], strictly increasing.
    load_bins : array_like
        New load breakpoints, same kind and unit as ``table.load``.

    Returns
    -------
    Resampled
        ``(table, outside)``; ``outside`` has the new table's shape.
    """
    owner = f"resample({table.name!r})"
    rpm_new = _axis(owner, "rpm_bins", rpm_bins, "rpm")
    load_new = _axis(owner, "load_bins", load_bins, table.load_unit)
    lo_c, hi_c, w_c, out_c = _brackets(table.rpm, rpm_new)
    lo_r, hi_r, w_r, out_r = _brackets(table.load, load_new)
    corners = _corners(lo_r, hi_r, w_r, lo_c, hi_c, w_c)
    vals = sum(w * table.values[r, c] for r, c, w in corners)
    flags = unc = None
    if table.flags is not None:
        flags = np.zeros(vals.shape, bool)
        for r, c, w in corners:
            flags |= (w > 0) & table.flags[r, c]
    if table.uncertainty is not None:
        unc = np.zeros(vals.shape)
        for r, c, w in corners:
            unc = np.maximum(unc, np.where(w > 0, table.uncertainty[r, c], 0.0))
    outside = out_r[:, None] | out_c[None, :]
    new = replace(table, values=vals, rpm=rpm_new, load=load_new, flags=flags, uncertainty=unc)
    outside.setflags(write=False)
    return Resampled(new, outside)


def _throttle_positions(p: np.ndarray, k: float, tol: float) -> tuple[list[float], bool]:
    """Fractional throttle-row positions where the piecewise-linear p(row) equals k, and whether p is flat at k."""
    pos = [float(i) for i in np.flatnonzero(np.abs(p - k) <= tol)]
    flat = False
    for i, (a, b) in enumerate(zip(p[:-1], p[1:])):
        if abs(a - b) <= tol:
            flat |= abs(a - k) <= tol
        elif min(a, b) + tol < k < max(a, b) - tol:
            pos.append(i + (k - a) / (b - a))
    return sorted(pos), flat


def to_map_kpa(table: EcuTable, map_kpa_per_cell, kpa_bins) -> Resampled:
    """A throttle-% table on a MAP [kPa] load axis, from the model's plenum pressure of every cell.

    Per rpm column ``j`` the throttle rows give pressures ``p[i, j]``, taken
    piecewise linear between rows.  For a requested pressure ``k`` the
    throttle position where ``p = k`` is found and the table value is
    interpolated linearly between the two throttle rows around it.  This
    inverts throttle -> kPa and is exact for a table linear in throttle
    between rows.  Where the column is not one-to-one:

    * ``k`` below / above every pressure of the column: the value of the row
      with the lowest / highest pressure is held (clamp) and the cell is
      flagged in ``outside``;
    * ``k`` reached at several throttle positions (a dip) or on a flat
      stretch (a plateau: a restricted engine whose plenum pressure
      saturates at part throttle): the lowest such throttle position is used
      and the cell is flagged, since an ECU looking up by MAP cannot tell
      these throttle positions apart.

    The ECU's MAP is assumed to equal the model's plenum pressure of the
    cell (cycle average): with Speeduino set ``mapSample`` to "Cycle
    Average", with rusEFI use its MAP averaging window; instantaneous
    sampling of a single-throttle-per-cylinder intake reads differently.

    Flags and uncertainty: from the two rows around the position (OR, max),
    as in :func:`resample`.

    Parameters
    ----------
    table : EcuTable
        ``load_kind == "throttle_pct"``.
    map_kpa_per_cell : array_like, shape table.shape
        Plenum pressure [kPa] of every cell of ``table``.
    kpa_bins : array_like
        Requested MAP breakpoints [kPa], strictly increasing.

    Returns
    -------
    Resampled
        ``(table on (kpa_bins, table.rpm) with load_kind "map_kpa", outside)``.
    """
    owner = f"to_map_kpa({table.name!r})"
    if table.load_kind != "throttle_pct":
        raise ValueError(f"{owner}: the table's load axis is {table.load_kind!r}; only a throttle_pct table can "
                         "be converted to MAP")
    p = _grid(owner, "map_kpa_per_cell", map_kpa_per_cell, table.shape, table.load, table.rpm, "%")
    if np.any(p <= 0):
        i, j = np.argwhere(p <= 0)[0]
        raise ValueError(f"{owner}.map_kpa_per_cell: cell [{i}, {j}] = {p[i, j]:g} kPa must be > 0")
    kpa = _axis(owner, "kpa_bins", kpa_bins, "kPa")
    nk, nr, nl = kpa.size, table.rpm.size, table.load.size
    pos = np.empty((nk, nr))
    outside = np.zeros((nk, nr), bool)
    for j in range(nr):
        col = p[:, j]
        tol = 1e-9 * max(1.0, float(np.max(col)))
        for m, k in enumerate(kpa):
            if k < col.min() - tol:
                pos[m, j], outside[m, j] = float(np.argmin(col)), True
            elif k > col.max() + tol:
                pos[m, j], outside[m, j] = float(np.argmax(col)), True
            else:
                found, flat = _throttle_positions(col, k, tol)
                pos[m, j], outside[m, j] = found[0], len(found) != 1 or flat
    lo = np.clip(np.floor(pos).astype(int), 0, nl - 1)
    hi = np.minimum(lo + 1, nl - 1)
    w = pos - lo
    cols = np.broadcast_to(np.arange(nr), (nk, nr))
    vals = (1 - w) * table.values[lo, cols] + w * table.values[hi, cols]
    flags = unc = None
    if table.flags is not None:
        flags = ((w < 1) & table.flags[lo, cols]) | ((w > 0) & table.flags[hi, cols])
    if table.uncertainty is not None:
        unc = np.maximum(np.where(w < 1, table.uncertainty[lo, cols], 0.0),
                         np.where(w > 0, table.uncertainty[hi, cols], 0.0))
    new = replace(table, values=vals, load=kpa, load_kind="map_kpa", flags=flags, uncertainty=unc)
    outside.setflags(write=False)
    return Resampled(new, outside)


# --------------------------------------------------------------------------- fuel quantities

def air_mg_per_cycle(air_flow_kg_h, speed_rpm, n_cylinders: int) -> np.ndarray:
    """Air per cylinder per cycle [mg] from engine air flow [kg/h] (four-stroke: N/120 cycles per second)."""
    return _air_mg(air_flow_kg_h, speed_rpm, n_cylinders)


def _air_mg(air_flow_kg_h, speed_rpm, n_cylinders: int) -> np.ndarray:
    n = np.asarray(speed_rpm, float)
    return np.asarray(air_flow_kg_h, float) / 3600.0 / (n / 120.0) / n_cylinders * 1e6


def _air_flow_kg_h(speed_rpm, spec: EngineSpec, air_mg_per_cycle_, air_flow_kg_h, who: str) -> np.ndarray:
    if (air_mg_per_cycle_ is None) == (air_flow_kg_h is None):
        raise ValueError(f"{who}: give exactly one of air_mg_per_cycle [mg per cylinder per cycle] or "
                         "air_flow_kg_h [kg/h of the engine]")
    if air_flow_kg_h is not None:
        return np.asarray(air_flow_kg_h, float)
    n = np.asarray(speed_rpm, float)
    return np.asarray(air_mg_per_cycle_, float) * 1e-6 * spec.geometry.n_cylinders * n / 120.0 * 3600.0


def fuel_mg(speed_rpm, lam, spec: EngineSpec, *, air_mg_per_cycle=None, air_flow_kg_h=None) -> np.ndarray:
    """Fuel per cylinder per cycle [mg]: ``m_air / (lambda * AFR_st)``, AFR_st = :func:`thermo.stoich_afr` of the spec's fuel.

    Give the air as ``air_mg_per_cycle`` [mg per cylinder per cycle] or
    ``air_flow_kg_h`` [kg/h, whole engine]; arrays broadcast.
    """
    ga = _air_flow_kg_h(speed_rpm, spec, air_mg_per_cycle, air_flow_kg_h, "fuel_mg")
    air = _air_mg(ga, speed_rpm, spec.geometry.n_cylinders)
    return air / (np.asarray(lam, float) * thermo.stoich_afr(spec.fuel))


def injection_ms(speed_rpm, lam, spec: EngineSpec, *, air_mg_per_cycle=None, air_flow_kg_h=None,
                 battery_v: float = 14.0) -> np.ndarray:
    """Injector pulse width [ms], one injection per cylinder per cycle, dead time at ``battery_v`` included.

    ``t = m_fuel / (k q_static) + t_dead(U)`` with ``k = injector.per_cylinder``
    injectors of static flow ``q_static`` and ``t_dead(U) = t_dead,ref + s (U -
    U_ref)`` clipped at 0: :func:`engine_model.tables.injection.injection_time_ms`,
    which this calls.  An ECU that adds its own dead time (Speeduino
    ``injOpen``, rusEFI battery lag curve) wants the pulse width without it:
    subtract ``injection_ms(...) - fuel_mg(...) / (k q_static)``, or use
    :func:`fuel_mg` directly for a fuel-mass ECU.
    """
    ga = _air_flow_kg_h(speed_rpm, spec, air_mg_per_cycle, air_flow_kg_h, "injection_ms")
    return injection_time_ms(ga, speed_rpm, lam, spec, battery_v=battery_v)["injection_time_ms"]


def ve_percent(speed_rpm, spec: EngineSpec, *, map_kpa=None, air_mg_per_cycle=None, air_flow_kg_h=None,
               ref_temp_k: float = 293.15, ref_pressure_kpa: float | None = None) -> np.ndarray:
    """Volumetric efficiency [%] for a speed-density (or alpha-N VE) ECU.

    ``VE = 100 * m_air / (p_ref * V_d / (R_air * T_ref))``: the trapped air
    per cylinder per cycle relative to the air one swept volume ``V_d``
    (``spec.geometry.displacement_m3``) holds at ``p_ref`` and ``T_ref``;
    ``R_air`` = :data:`R_AIR_J_KG_K`.

    ECU conventions
    ---------------
    rusEFI, speed density (``speed_density_base.cpp``: ``airmass = VE *
    displacement * MAP / (0.28705 * T_charge)``)
        ``p_ref`` = the cell's MAP (``map_kpa``; leave ``ref_pressure_kpa``
        None) and ``T_ref`` = the charge temperature rusEFI estimates (IAT /
        CLT blend): pass that temperature.
    rusEFI, alpha-N (``alphan_airmass.cpp``)
        ``ref_pressure_kpa=101.325, ref_temp_k=293.0``: VE relative to a
        standard atmosphere.
    Speeduino
        ``PW = reqFuel * VE * f(MAP) * corrections`` where ``f`` is set by
        ``multiplyMAP``: "Fixed" (MAP/100) makes VE the one above with
        ``p_ref`` = MAP, provided reqFuel is computed for 100 kPa at
        ``T_ref`` and the IAT density curve (``airDenRates``) is 100 % at
        ``T_ref``; "Off" makes VE relative to a fixed 100 kPa
        (``ref_pressure_kpa=100``); "Baro" relative to the barometric
        pressure (``ref_pressure_kpa=baro``).

    Parameters
    ----------
    speed_rpm : array_like
    spec : EngineSpec
    map_kpa : array_like, optional
        Manifold pressure [kPa]; required unless ``ref_pressure_kpa`` is given.
    air_mg_per_cycle, air_flow_kg_h : array_like
        The air, as for :func:`fuel_mg` (exactly one).
    ref_temp_k : float
        Reference temperature [K] (default 20 degC).
    ref_pressure_kpa : float, optional
        Fixed reference pressure [kPa] instead of the cell's MAP.
    """
    ga = _air_flow_kg_h(speed_rpm, spec, air_mg_per_cycle, air_flow_kg_h, "ve_percent")
    air = _air_mg(ga, speed_rpm, spec.geometry.n_cylinders) * 1e-6
    if ref_pressure_kpa is None:
        if map_kpa is None:
            raise ValueError("ve_percent: give map_kpa (VE relative to manifold pressure) or ref_pressure_kpa "
                             "(VE relative to a fixed pressure)")
        p = np.asarray(map_kpa, float) * 1e3
    else:
        p = float(ref_pressure_kpa) * 1e3
    if not (math.isfinite(ref_temp_k) and ref_temp_k > 0):
        raise ValueError(f"ve_percent: ref_temp_k = {ref_temp_k!r} must be a temperature > 0 K")
    if np.any(np.asarray(p) <= 0):
        raise ValueError("ve_percent: reference pressure must be > 0 kPa")
    full = p * spec.geometry.displacement_m3 / (R_AIR_J_KG_K * ref_temp_k)
    return 100.0 * air / full
