"""The bench's measured MBT, carried from the cells it was measured in to their neighbours.

Where the bench ran a grid cell clean at MBT, the table takes the bench's spark there
(:func:`engine_model.tables.build.build_maps`).  The difference between that spark and the MBT the
cycle model finds in the same cell with the combustion model's burn is a measured error of the model's
MBT at that speed.  It comes mostly from the combustion model's burn-rate trend over speed (a global
model trained on a few operating points), which the cells next to the measured one share; leaving it
only in the measured cell puts a step between that cell and its neighbours (docs/sections/tables.md).

The carried offset at speed n:

* at the speeds of the measured cells: the mean of (bench spark - model MBT) over that speed's cells;
* between two measured speeds: linear in speed;
* beyond the measured range: the nearest measured offset, faded linearly to zero over
  ``reach_rpm`` (an error is not extrapolated far from where it was measured; the default 2000 rpm is
  an assumption of this project: two breakpoints of the default ECU grid, so the next speed beyond the
  measured range takes half the offset and the one after none).

It applies to every throttle at that speed (the measured points are at WOT; the offset is taken as a
function of speed only, the dimension the combustion model's design is thinnest in) and only to the
target the cell aims at when MBT-limited: the knock-safe border still caps it, so a positive offset
never advances a cell past the knock model's border.
"""

from __future__ import annotations

import numpy as np

__all__ = ["offset_at_speeds"]


def offset_at_speeds(measured_rpm: np.ndarray, measured_offset_deg: np.ndarray, speeds_rpm: np.ndarray,
                     reach_rpm: float) -> np.ndarray:
    """MBT offset [deg] at ``speeds_rpm`` from offsets measured at ``measured_rpm`` (see the module text).

    Several offsets at one speed are averaged.  No measured offset: zeros.
    """
    n = np.asarray(speeds_rpm, float)
    ms = np.asarray(measured_rpm, float)
    md = np.asarray(measured_offset_deg, float)
    ok = np.isfinite(ms) & np.isfinite(md)
    if not ok.any():
        return np.zeros_like(n)
    if reach_rpm < 0:
        raise ValueError(f"reach_rpm = {reach_rpm!r}: must be >= 0 rpm")
    u = np.unique(ms[ok])
    d = np.array([md[ok][ms[ok] == s].mean() for s in u])
    out = np.interp(n, u, d)                 # constant beyond the ends: the nearest measured offset
    dist = np.maximum(u[0] - n, n - u[-1])   # > 0 outside the measured range
    fade = np.where(dist <= 0, 1.0, 0.0 if reach_rpm == 0 else np.clip(1.0 - dist / max(reach_rpm, 1e-9), 0.0, 1.0))
    return out * fade
