"""ECU table axes: breakpoints, the throttle x speed grid, and the target-lambda table."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import priors
from engine_model.contracts import check_breakpoints
from engine_model.spec import EngineSpec

__all__ = ["DEFAULT_THROTTLE_PCT", "DEFAULT_SPEED_RPM", "LAMBDA_RANGE", "EcuGrid", "LambdaTable",
           "parse_breakpoints"]

#: Default ECU throttle breakpoints [%]: dense at small openings where load changes fastest.
DEFAULT_THROTTLE_PCT = (0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 50.0, 60.0, 80.0, 100.0)
#: Default ECU speed breakpoints [rpm]: 1000-13000 in 1000 rpm steps (R6 rev range).
DEFAULT_SPEED_RPM = tuple(float(n) for n in range(1000, 13001, 1000))


# --------------------------------------------------------------------------- grid

def parse_breakpoints(text: str, name: str) -> tuple[float, ...]:
    """Breakpoints from text: ``'0,5,10,20'`` or a range ``'1000:13000:1000'`` (start:stop:step, stop included).

    Raises ValueError naming ``name`` and the offending text.
    """
    text = str(text).strip()
    try:
        if ":" in text:
            parts = [float(p) for p in text.split(":")]
            if len(parts) != 3 or not parts[2] > 0:
                raise ValueError
            start, stop, step = parts
            n = int(math.floor((stop - start) / step + 1e-9)) + 1
            if n < 1 or n > 1000:
                raise ValueError
            return tuple(float(start + k * step) for k in range(n))
        return tuple(float(p) for p in text.split(",") if p.strip() != "")
    except ValueError:
        raise ValueError(f"{name} breakpoints {text!r}: expected comma-separated numbers '0,5,10' or "
                         "a range 'start:stop:step' with step > 0") from None


def _check_axis(name: str, values, lo: float, hi: float, unit: str) -> tuple[float, ...]:
    return tuple(check_breakpoints(f"EcuGrid.{name}", values, unit, lo, hi).tolist())


def _read_wide_csv(p: Path) -> list[list[str]]:
    """Rows of a wide-table CSV as text, header kept raw (pandas would rename duplicate headers)."""
    import csv

    try:
        with open(p, newline="") as fh:
            rows = [r for r in csv.reader(fh) if r]
    except (OSError, csv.Error, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: could not be read as CSV: {exc}") from None
    if len(rows) < 3 or len(rows[0]) < 3:
        raise ValueError(f"{p}: expected a wide table (header + >= 2 rows, throttle column + >= 2 speeds)")
    return rows


@dataclass(frozen=True)
class EcuGrid:
    """Breakpoints of the ECU tables: rows throttle [%] (0-100), columns speed [rpm] (> 0).

    Both strictly ascending, at least 2 each; unsorted or duplicate
    breakpoints raise a ValueError naming the axis, the positions and values.
    """

    throttle_pct: tuple[float, ...] = DEFAULT_THROTTLE_PCT
    speed_rpm: tuple[float, ...] = DEFAULT_SPEED_RPM

    def __post_init__(self):
        object.__setattr__(self, "throttle_pct", _check_axis("throttle_pct", self.throttle_pct, 0.0, 100.0, "%"))
        object.__setattr__(self, "speed_rpm", _check_axis("speed_rpm", self.speed_rpm, 1e-9, 1e6, "rpm"))

    @property
    def shape(self) -> tuple[int, int]:
        """(number of throttle rows, number of speed columns)."""
        return len(self.throttle_pct), len(self.speed_rpm)

    def cells(self) -> pd.DataFrame:
        """One row per cell, row-major (throttle outer): ``cell, i, j, throttle_pct, speed_rpm``."""
        nt, ns = self.shape
        i, j = np.divmod(np.arange(nt * ns), ns)
        return pd.DataFrame({"cell": np.arange(nt * ns), "i": i, "j": j,
                             "throttle_pct": np.asarray(self.throttle_pct)[i],
                             "speed_rpm": np.asarray(self.speed_rpm)[j]})

    @classmethod
    def from_csv(cls, path) -> "EcuGrid":
        """Breakpoints of a wide table CSV (first column throttle %, header speeds in rpm), e.g. an ECU export."""
        p = Path(path)
        if not p.is_file():
            raise ValueError(f"{p}: file not found")
        rows = _read_wide_csv(p)
        try:
            speeds = [float(str(c).strip().removesuffix("rpm").strip()) for c in rows[0][1:]]
            thr = [float(r[0]) for r in rows[1:]]
        except ValueError as exc:
            raise ValueError(f"{p}: breakpoints must be numbers (first column throttle %, header rpm): {exc}") from None
        try:
            return cls(tuple(thr), tuple(speeds))
        except ValueError as exc:
            raise ValueError(f"{p}: {exc}") from None

    def check_spec(self, spec: EngineSpec) -> None:
        """ValueError if a speed breakpoint exceeds the engine's maximum speed."""
        if self.speed_rpm[-1] > spec.geometry.max_speed_rpm:
            raise ValueError(f"EcuGrid.speed_rpm: breakpoint {self.speed_rpm[-1]:g} rpm exceeds the engine's "
                             f"max_speed_rpm {spec.geometry.max_speed_rpm:g}")


# --------------------------------------------------------------------------- target lambda

LAMBDA_RANGE = (0.6, 1.6)   # plausible SI targets [-]: richer than 0.6 misfires, leaner than 1.6 will not burn


@dataclass(frozen=True)
class LambdaTable:
    """Target excess-air ratio [-] on its own breakpoints; rows throttle [%], columns speed [rpm].

    ``values[i][j]`` belongs to ``throttle_pct[i]``, ``speed_rpm[j]``.  Holes
    (NaN), non-numbers and values outside :data:`LAMBDA_RANGE` raise a
    ValueError naming the row (throttle) and column (rpm).
    """

    throttle_pct: tuple[float, ...]
    speed_rpm: tuple[float, ...]
    values: tuple[tuple[float, ...], ...]
    source: str = field(default="<table>", compare=False)

    def __post_init__(self):
        grid = EcuGrid(self.throttle_pct, self.speed_rpm)  # same breakpoint rules
        object.__setattr__(self, "throttle_pct", grid.throttle_pct)
        object.__setattr__(self, "speed_rpm", grid.speed_rpm)
        rows = [tuple(r) for r in self.values]
        if len(rows) != len(grid.throttle_pct):
            raise ValueError(f"{self.source}: {len(rows)} rows of lambda values for {len(grid.throttle_pct)} "
                             "throttle breakpoints")
        clean = []
        for i, row in enumerate(rows):
            if len(row) != len(grid.speed_rpm):
                raise ValueError(f"{self.source}: row {i} (throttle {grid.throttle_pct[i]:g} %) has {len(row)} "
                                 f"values for {len(grid.speed_rpm)} speed columns")
            out = []
            for j, v in enumerate(row):
                where = f"{self.source}: row {i} (throttle {grid.throttle_pct[i]:g} %), column {j} " \
                        f"({grid.speed_rpm[j]:g} rpm)"
                try:
                    x = float(v)
                except (TypeError, ValueError):
                    raise ValueError(f"{where}: value {v!r} is not a number") from None
                if not math.isfinite(x):
                    raise ValueError(f"{where}: hole (value {v!r}); every cell needs a target lambda")
                if not LAMBDA_RANGE[0] <= x <= LAMBDA_RANGE[1]:
                    raise ValueError(f"{where}: lambda {x:g} is outside [{LAMBDA_RANGE[0]:g}, {LAMBDA_RANGE[1]:g}]")
                out.append(x)
            clean.append(tuple(out))
        object.__setattr__(self, "values", tuple(clean))

    @classmethod
    def default(cls, grid: EcuGrid) -> "LambdaTable":
        """0.9 at WOT, 1.0 at part load: :func:`engine_model.priors.lambda_target` per throttle row.

        The same rule the DOE plans use (1.0 up to 60 %, linear to 0.9 at 90 %
        and above; 0.9 is the paper's WOT setting, Table 2), so bench points
        and tables share the mixture.
        """
        lam = np.atleast_1d(priors.lambda_target(np.asarray(grid.throttle_pct)))
        return cls(grid.throttle_pct, grid.speed_rpm, tuple((float(v),) * len(grid.speed_rpm) for v in lam),
                   source="default lambda table")

    @classmethod
    def from_frame(cls, wide: pd.DataFrame, source: str = "<frame>") -> "LambdaTable":
        """From a wide table: first column throttle [%], the other column names speeds [rpm]."""
        if wide.shape[1] < 3 or wide.shape[0] < 2:
            raise ValueError(f"{source}: expected a wide table with a throttle column and >= 2 speed columns, "
                             f">= 2 rows; got {wide.shape[0]} rows x {wide.shape[1]} columns")
        speeds = []
        for c in wide.columns[1:]:
            try:
                speeds.append(float(str(c).strip().removesuffix("rpm").strip()))
            except ValueError:
                raise ValueError(f"{source}: column header {c!r} is not a speed [rpm]") from None
        thr = []
        for i, v in enumerate(wide.iloc[:, 0]):
            try:
                thr.append(float(v))
            except (TypeError, ValueError):
                raise ValueError(f"{source}: row {i}, throttle value {v!r} is not a number") from None
        vals = wide.iloc[:, 1:].to_numpy(dtype=object)
        try:
            return cls(tuple(thr), tuple(speeds), tuple(tuple(r) for r in vals), source=source)
        except ValueError as exc:
            msg = str(exc)
            raise ValueError(msg if msg.startswith(source) else f"{source}: {msg}") from None

    @classmethod
    def from_csv(cls, path) -> "LambdaTable":
        """From a wide CSV as written by :func:`engine_model.tables.export.write_maps` (``lambda_target.csv``)."""
        p = Path(path)
        if not p.is_file():
            raise ValueError(f"{p}: file not found")
        rows = _read_wide_csv(p)
        n = len(rows[0])
        if any(len(r) > n for r in rows[1:]):
            i = next(k for k, r in enumerate(rows[1:]) if len(r) > n)
            raise ValueError(f"{p}: row {i} has {len(rows[i + 1])} fields for {n} header columns")
        body = [[(v if v.strip() != "" else np.nan) for v in r] + [np.nan] * (n - len(r)) for r in rows[1:]]
        wide = pd.DataFrame(body, columns=pd.Index(rows[0]))   # raw header: duplicates stay duplicates
        return cls.from_frame(wide, source=str(p))

    def on_grid(self, grid: EcuGrid) -> np.ndarray:
        """Values on ``grid`` [-], shape (n_throttle, n_speed): bilinear; the grid must lie inside the table."""
        t, n = np.asarray(self.throttle_pct), np.asarray(self.speed_rpm)
        gt, gn = np.asarray(grid.throttle_pct), np.asarray(grid.speed_rpm)
        if gt[0] < t[0] or gt[-1] > t[-1] or gn[0] < n[0] or gn[-1] > n[-1]:
            raise ValueError(f"{self.source}: lambda table covers throttle {t[0]:g}-{t[-1]:g} %, speed "
                             f"{n[0]:g}-{n[-1]:g} rpm; the ECU grid needs {gt[0]:g}-{gt[-1]:g} %, "
                             f"{gn[0]:g}-{gn[-1]:g} rpm")
        v = np.asarray(self.values, dtype=float)
        along_n = np.array([np.interp(gn, n, row) for row in v])            # (len t, len gn)
        return np.array([np.interp(gt, t, col) for col in along_n.T]).T     # (len gt, len gn)


# --------------------------------------------------------------------------- small numerics









