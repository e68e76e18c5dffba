"""Number text shared by the ECU file formats: formatting with fixed decimals, parsing, table construction.

Used by the TunerStudio ``.table``, DCM and CSV readers and writers
(:mod:`engine_model.tables.ecu_files`, :mod:`~engine_model.tables.ecu_dcm`,
:mod:`~engine_model.tables.ecu_csv`).
"""

from __future__ import annotations

import re

import numpy as np

from .ecu_table import EcuTable

__all__ = ["NUMBER", "fmt_number", "axis_decimals", "decimals_of", "parse_floats", "build_table"]

#: A plain decimal number (optional sign and exponent), the whole token.
NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\Z")


def fmt_number(v: float, decimals: int) -> str:
    return f"{float(v) + 0.0:.{decimals}f}"


def axis_decimals(values) -> int:
    """Fewest decimals (0-6) that print every breakpoint exactly."""
    for d in range(7):
        if np.allclose(np.round(values, d), values, rtol=0, atol=1e-9):
            return d
    return 6


def decimals_of(tokens) -> int:
    return min(6, max((len(t.split(".")[1].rstrip("0")) if "." in t and "e" not in t.lower() else 0)
                      for t in tokens)) if tokens else 0


def parse_floats(tokens, where: str) -> np.ndarray:
    for t in tokens:
        if not NUMBER.match(t):
            raise ValueError(f"{where}: {t!r} is not a number")
    return np.array([float(t) for t in tokens])


def build_table(where: str, **kw) -> EcuTable:
    try:
        return EcuTable(**kw)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
