"""Coverage of a bench plan over speed (and throttle): the gap constraint of the discrimination design.

A discrimination plan (:mod:`engine_model.gap.design`) that puts its points where the linearised effects
differ most can leave whole speed bands empty, and an effect localised there (an airflow resonance, say)
is then invisible to it.  An :class:`AxisCoverage` states the requirement on one axis: over the range
``[low, high]`` no gap between neighbouring planned values, nor between ``low`` and the first or the last
and ``high``, is wider than ``max_gap``.  :meth:`AxisCoverage.deficit` is the least number of further
candidates that would make a partial plan satisfy it (a greedy jump over the sorted values, exact for this
one-dimensional covering), which lets the selection refuse any move that would leave the plan unable to
cover the range with the points it has left.  :func:`coverage_summary` says what a plan covers and what
it misses.

Default limits: :data:`MAX_SPEED_GAP_RPM` = 1000 rpm, the speed spacing of the ECU tables the calibration
fills (``mbc run --speed`` default ``1000:13000:1000``, :mod:`engine_model.tables.grid`), so every speed
breakpoint of the map has a bench point within one breakpoint of it.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import pandas as pd

__all__ = ["AxisCoverage", "MAX_SPEED_GAP_RPM", "min_points_to_cover", "largest_gap", "coverage_summary",
           "summary_markdown"]

#: Default largest speed gap of a plan [rpm]: the ECU tables' speed breakpoint spacing (module docstring).
MAX_SPEED_GAP_RPM = 1000.0

_REL = 1e-9          # relative tolerance of the gap comparisons (float rounding of rpm values)


def min_points_to_cover(low: float, high: float, max_gap: float) -> int:
    """Fewest points that can cover ``[low, high]`` with gaps <= ``max_gap``, candidates anywhere.

    The first point may sit ``max_gap`` above ``low`` and the last ``max_gap`` below ``high``, so ``m`` points
    span at most ``(m + 1) * max_gap``: ``m >= (high - low) / max_gap - 1``, and at least 1.  A discrete
    candidate pool may need more (:meth:`AxisCoverage.deficit` of the empty plan).
    """
    if not max_gap > 0:
        raise ValueError(f"coverage: max_gap = {max_gap} must be > 0")
    if not high >= low:
        raise ValueError(f"coverage: range {low:g}-{high:g} is empty (high < low)")
    return max(1, math.ceil((high - low) / max_gap * (1 - _REL) - 1.0))


class AxisCoverage:
    """Gap constraint on one axis of a candidate pool.

    Parameters
    ----------
    name : str
        Axis name for messages, e.g. ``"speed_rpm"``.
    values : array (n,)
        The axis value of every candidate (e.g. engine speed [rpm]).
    low, high : float
        Range to cover, same unit.
    max_gap : float
        Largest allowed gap between neighbouring planned values and at the two ends, same unit.
    """

    def __init__(self, name: str, values, low: float, high: float, max_gap: float):
        self.name = str(name)
        self.values = np.asarray(values, dtype=float)
        if self.values.ndim != 1 or not np.all(np.isfinite(self.values)):
            raise ValueError(f"coverage {name}: values must be a finite 1-D array")
        self.low, self.high, self.max_gap = float(low), float(high), float(max_gap)
        min_points_to_cover(self.low, self.high, self.max_gap)        # validates range and gap
        self._tol = _REL * max(abs(self.low), abs(self.high), self.max_gap)

    @property
    def n(self) -> int:
        return self.values.size

    def deficit(self, chosen: Sequence[int]) -> float:
        """Least number of further candidates that make ``chosen`` cover the range (``inf``: none can).

        Greedy jump from ``low``: go to the farthest chosen value within reach (free), else to the farthest
        unchosen candidate within reach (one more point), until ``high`` is within reach.
        """
        mask = np.zeros(self.n, bool)
        mask[np.asarray(chosen, dtype=int)] = True
        xc = np.sort(self.values[mask])
        xf = np.sort(self.values[~mask])
        g = self.max_gap + self._tol
        cur, count, floor = self.low, 0, self.low - self._tol     # floor: a value at ``low`` itself counts once
        while self.high - cur > g:
            reach = cur + g
            i = np.searchsorted(xc, reach, side="right") - 1
            if i >= 0 and xc[i] > floor:
                cur, floor = xc[i], xc[i]
                continue
            j = np.searchsorted(xf, reach, side="right") - 1
            if j >= 0 and xf[j] > floor:
                cur, floor, count = xf[j], xf[j], count + 1
                continue
            return math.inf
        return float(count)

    def holds(self, chosen: Sequence[int]) -> bool:
        """True when the candidates ``chosen`` alone cover the range."""
        gap, _, _ = largest_gap(self.values[np.asarray(chosen, dtype=int)], self.low, self.high)
        return gap <= self.max_gap + self._tol

    def uncoverable_gap(self) -> tuple[float, float] | None:
        """The first stretch of the range that no candidate can bridge (None if the pool can cover it)."""
        x = np.sort(self.values[(self.values >= self.low - self._tol) & (self.values <= self.high + self._tol)])
        edges = np.concatenate([[self.low], x, [self.high]])
        d = np.diff(edges)
        bad = np.flatnonzero(d > self.max_gap + self._tol)
        return None if bad.size == 0 else (float(edges[bad[0]]), float(edges[bad[0] + 1]))


def largest_gap(x, low: float, high: float) -> tuple[float, float, float]:
    """Largest gap of the values ``x`` over ``[low, high]``, the ends included: (gap, from, to).

    Values outside the range do not count; with none inside, the gap is the whole range.
    """
    x = np.asarray(x, dtype=float)
    x = np.sort(x[(x >= low) & (x <= high)])
    edges = np.concatenate([[low], x, [high]])
    d = np.diff(edges)
    k = int(np.argmax(d))
    return float(d[k]), float(edges[k]), float(edges[k + 1])


def coverage_summary(plan: pd.DataFrame, speed_range: tuple[float, float], max_speed_gap: float,
                     throttle_range: tuple[float, float] | None = None) -> dict:
    """What a plan covers over speed and throttle, and what it misses.

    Parameters
    ----------
    plan : DataFrame
        ``speed_rpm`` [rpm] and ``throttle_pct`` [%] per bench point.
    speed_range : (float, float)
        Requested speed range [rpm].
    max_speed_gap : float
        Gap limit [rpm]; the report bands are ``ceil(range / limit)`` equal speed bands (each <= the limit).
    throttle_range : (float, float), optional
        Requested throttle range [%] (for the throttle gap); default the plan's own.

    Returns
    -------
    dict
        ``largest_speed_gap_rpm`` and ``largest_speed_gap_at`` (from, to) [rpm], ``speed_covered`` and
        ``throttle_covered`` (min, max of the plan), ``largest_throttle_gap_pct``, ``bands`` (DataFrame per
        speed band: ``speed_from_rpm, speed_to_rpm, points, throttle_min_pct, throttle_max_pct``),
        ``single_point_bands`` and ``empty_bands`` (lists of (from, to) [rpm]), ``max_speed_gap_rpm``,
        ``speed_range``.
    """
    n = plan["speed_rpm"].to_numpy(float)
    t = plan["throttle_pct"].to_numpy(float)
    lo, hi = float(speed_range[0]), float(speed_range[1])
    gap, a, b = largest_gap(n, lo, hi)
    tr = (float(t.min()), float(t.max())) if throttle_range is None else tuple(map(float, throttle_range))
    tgap, _, _ = largest_gap(t, *tr)
    nb = max(1, math.ceil((hi - lo) / max_speed_gap * (1 - _REL)))
    edges = np.linspace(lo, hi, nb + 1)
    band = np.clip(np.searchsorted(edges, n, side="right") - 1, 0, nb - 1)
    inside = (n >= lo) & (n <= hi)
    rows = []
    for k in range(nb):
        sel = inside & (band == k)
        rows.append({"speed_from_rpm": edges[k], "speed_to_rpm": edges[k + 1], "points": int(sel.sum()),
                     "throttle_min_pct": float(t[sel].min()) if sel.any() else math.nan,
                     "throttle_max_pct": float(t[sel].max()) if sel.any() else math.nan})
    bands = pd.DataFrame(rows)
    pick = lambda m: [(float(r.speed_from_rpm), float(r.speed_to_rpm)) for r in bands[m].itertuples()]
    return {"largest_speed_gap_rpm": gap, "largest_speed_gap_at": (a, b),
            "speed_covered": (float(n.min()), float(n.max())), "throttle_covered": (float(t.min()), float(t.max())),
            "largest_throttle_gap_pct": tgap, "bands": bands, "single_point_bands": pick(bands["points"] == 1),
            "empty_bands": pick(bands["points"] == 0), "max_speed_gap_rpm": float(max_speed_gap),
            "speed_range": (lo, hi)}


def summary_markdown(cov: dict, closest: tuple[str, str | None] | None = None, min_d2: float | None = None,
                     error_bound: float | None = None, error_bound_free: float | None = None) -> str:
    """A short markdown statement of a plan's coverage (and, if given, its weakest hypothesis pair)."""
    lo, hi = cov["speed_range"]
    a, b = cov["largest_speed_gap_at"]
    lines = ["# Bench plan coverage", "",
             f"* speed range requested {lo:.0f}-{hi:.0f} rpm, gap limit {cov['max_speed_gap_rpm']:.0f} rpm",
             f"* largest speed gap {cov['largest_speed_gap_rpm']:.0f} rpm ({a:.0f}-{b:.0f} rpm, range ends included)",
             f"* speed covered {cov['speed_covered'][0]:.0f}-{cov['speed_covered'][1]:.0f} rpm, throttle covered "
             f"{cov['throttle_covered'][0]:.0f}-{cov['throttle_covered'][1]:.0f} % (largest throttle gap "
             f"{cov['largest_throttle_gap_pct']:.0f} %-points)",
             "* speed bands with a single point: " + (", ".join(f"{x:.0f}-{y:.0f}" for x, y in cov["single_point_bands"])
                                                       or "none"),
             "* empty speed bands: " + (", ".join(f"{x:.0f}-{y:.0f}" for x, y in cov["empty_bands"]) or "none")]
    if closest is not None:
        i, j = closest
        lines.append(f"* closest hypotheses: {i} vs {j or 'no effect'} (d2 = {min_d2:.1f} in noise units)")
    if error_bound is not None:
        extra = "" if error_bound_free is None else f" (without the coverage constraint {error_bound_free:.3f})"
        lines.append(f"* misnaming bound {error_bound:.3f}{extra}")
    lines += ["", "| speed band [rpm] | points | throttle [%] |", "|---|---|---|"]
    for r in cov["bands"].itertuples():
        thr = "-" if r.points == 0 else f"{r.throttle_min_pct:.0f}-{r.throttle_max_pct:.0f}"
        lines.append(f"| {r.speed_from_rpm:.0f}-{r.speed_to_rpm:.0f} | {r.points} | {thr} |")
    return "\n".join(lines) + "\n"
