"""Engine load from the calibrated simulator: a table over (throttle, speed) for the global combustion model.

Burn rate follows the charge state (density, residual dilution), not the
throttle angle: at part load the intake-manifold pressure, and with it the
charge density and the residual fraction, is a steep, nonlinear function of
throttle opening and speed (a butterfly's open area grows like
``1 - cos(angle)`` while the engine's demand grows with speed), and it is
nearly flat above ~60 % throttle.  An engine calibrator therefore maps burn
parameters against *load* (relative air charge or manifold pressure,
[H] sec. 9.3; Bosch ECUs use the relative air charge "rl" as the load axis of
their ignition maps [B]), not against pedal or throttle position.

:func:`build_load_table` runs the calibrated cycle model once on a
throttle x speed grid (spark at the MBT prior, burn at the DOE prior: load
hardly depends on either) and stores the chosen load quantity; a
:class:`LoadTable` interpolates it (PCHIP, shape-preserving, in both
directions) at any (throttle, speed) inside the grid.  The global model
(:class:`engine_model.globalmodel.mapmodel.MapModel` with ``load_table=``) then uses the
load instead of the throttle as its first coordinate; the table is stored
inside the model file, so predictions need no simulator.

Quantities (chosen explicitly, :data:`QUANTITIES`):

* ``plenum_pressure_ratio``: cycle-mean plenum pressure / ambient pressure [-]
  (the simulator's ``plenum_pressure_bar``);
* ``vol_eff``: volumetric efficiency referred to ambient [-] (relative air
  charge).

The table is built for one engine spec; its hash is stored and a model refuses
a table of another engine.

References
----------
.. [H] J.B. Heywood, Internal Combustion Engine Fundamentals, 1988, sec. 9.3
   (burn angles vs load, residual fraction, spark).
.. [B] Robert Bosch GmbH, Gasoline Engine Management, 3rd ed., 2006 (ME-Motronic
   torque structure: relative air charge as the load signal of the ignition map).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import pandas as pd

from engine_model import priors
from engine_model.contracts import check_breakpoints

__all__ = ["LoadTable", "build_load_table", "QUANTITIES", "DEFAULT_THROTTLE_PCT", "DEFAULT_SPEED_RPM"]

#: Load quantities a table can hold: name -> (description, unit).
QUANTITIES = {
    "plenum_pressure_ratio": ("cycle-mean plenum pressure / ambient pressure", "-"),
    "vol_eff": ("volumetric efficiency referred to ambient (relative air charge)", "-"),
}

#: Default grid: dense at small throttle, where the load changes fastest; the paper's speed range.
DEFAULT_THROTTLE_PCT = (10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 50.0, 60.0, 70.0, 80.0, 90.0, 100.0)
DEFAULT_SPEED_RPM = tuple(float(n) for n in range(1000, 13001, 1000))


def _load_solver():
    from engine_model.sim.prepare import SolverSettings
    return SolverSettings(step_deg=1.0, tolerance=1e-2, max_cycles=60)


#: Default solver of :func:`build_load_table`.
LOAD_SOLVER = _load_solver()


def _axis(values, name: str, lo: float, hi: float) -> tuple[float, ...]:
    unit = "%" if name == "throttle_pct" else "rpm"
    return tuple(check_breakpoints(f"LoadTable.{name}", values, unit, lo, hi, min_count=4).tolist())   # 4: PCHIP


@dataclass(frozen=True)
class LoadTable:
    """A load quantity on a throttle x speed grid, interpolated by PCHIP.

    Attributes
    ----------
    throttle_pct : tuple of float, n_t >= 4, strictly ascending [%]
    speed_rpm : tuple of float, n_n >= 4, strictly ascending [rpm]
    values : tuple of tuples, shape (n_t, n_n)
        The load quantity at each node [-]; finite and > 0.
    quantity : str
        One of :data:`QUANTITIES`.
    spec_hash : str or None
        Engine spec the table was simulated for.
    filled : tuple of (throttle, speed) pairs
        Nodes whose simulation failed and whose value was filled along the
        throttle axis (flagged, never silent).
    """

    throttle_pct: tuple
    speed_rpm: tuple
    values: tuple
    quantity: str = "plenum_pressure_ratio"
    spec_hash: str | None = None
    filled: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "throttle_pct", _axis(self.throttle_pct, "throttle_pct", 0.0, 100.0))
        object.__setattr__(self, "speed_rpm", _axis(self.speed_rpm, "speed_rpm", 1.0, 20000.0))
        if self.quantity not in QUANTITIES:
            raise ValueError(f"LoadTable.quantity = {self.quantity!r}; choose from {sorted(QUANTITIES)}")
        v = np.asarray(self.values, dtype=float)
        shape = (len(self.throttle_pct), len(self.speed_rpm))
        if v.shape != shape:
            raise ValueError(f"LoadTable.values: shape {v.shape}, expected {shape} (throttle x speed)")
        bad = np.argwhere(~(np.isfinite(v) & (v > 0)))
        if bad.size:
            i, j = bad[0]
            raise ValueError(f"LoadTable.values: throttle {self.throttle_pct[i]:g} %, speed {self.speed_rpm[j]:g} "
                             f"rpm: {float(v[i, j])!r} is not a finite number > 0")
        object.__setattr__(self, "values", tuple(tuple(float(x) for x in row) for row in v))
        object.__setattr__(self, "filled", tuple((float(t), float(n)) for t, n in self.filled))

    @property
    def array(self) -> np.ndarray:
        """Values as an array of shape (n_throttle, n_speed)."""
        return np.asarray(self.values, dtype=float)

    def covers(self, throttle_pct, speed_rpm) -> np.ndarray:
        """True where (throttle, speed) lies inside the table's grid."""
        t = np.asarray(throttle_pct, dtype=float)
        n = np.asarray(speed_rpm, dtype=float)
        return ((t >= self.throttle_pct[0] - 1e-9) & (t <= self.throttle_pct[-1] + 1e-9)
                & (n >= self.speed_rpm[0] - 1e-9) & (n <= self.speed_rpm[-1] + 1e-9))

    def __call__(self, throttle_pct, speed_rpm) -> np.ndarray:
        """The load at (throttle [%], speed [rpm]) (broadcast); outside the grid, the value at its edge.

        Use :meth:`covers` to find points outside (the map model flags them).
        """
        from scipy.interpolate import RegularGridInterpolator

        t, n = np.broadcast_arrays(np.asarray(throttle_pct, dtype=float), np.asarray(speed_rpm, dtype=float))
        pts = np.column_stack([np.clip(t.ravel(), self.throttle_pct[0], self.throttle_pct[-1]),
                               np.clip(n.ravel(), self.speed_rpm[0], self.speed_rpm[-1])])
        f = RegularGridInterpolator((np.asarray(self.throttle_pct), np.asarray(self.speed_rpm)), self.array,
                                    method="pchip")
        return f(pts).reshape(t.shape)

    def check_spec(self, spec) -> None:
        """ValueError unless the table was simulated for ``spec`` (EngineSpec or hash); None passes."""
        want = spec if isinstance(spec, str) or spec is None else spec.spec_hash()
        if self.spec_hash is not None and want is not None and want != self.spec_hash:
            raise ValueError(f"LoadTable: simulated for engine spec {self.spec_hash}, not for spec {want}; "
                             "rebuild it with build_load_table for this engine")

    def to_dict(self) -> dict:
        return {"throttle_pct": list(self.throttle_pct), "speed_rpm": list(self.speed_rpm),
                "values": [list(r) for r in self.values], "quantity": self.quantity, "spec_hash": self.spec_hash,
                "filled": [list(p) for p in self.filled]}

    @classmethod
    def from_dict(cls, d: dict) -> "LoadTable":
        return cls(throttle_pct=d["throttle_pct"], speed_rpm=d["speed_rpm"], values=d["values"],
                   quantity=d.get("quantity", "plenum_pressure_ratio"), spec_hash=d.get("spec_hash"),
                   filled=d.get("filled", ()))

    def to_frame(self) -> pd.DataFrame:
        """Long form: ``throttle_pct, speed_rpm, <quantity>, filled``."""
        t, n = np.meshgrid(self.throttle_pct, self.speed_rpm, indexing="ij")
        fill = {(a, b) for a, b in self.filled}
        return pd.DataFrame({"throttle_pct": t.ravel(), "speed_rpm": n.ravel(), self.quantity: self.array.ravel(),
                             "filled": [(a, b) in fill for a, b in zip(t.ravel(), n.ravel())]})


def load_plan(spec, throttle_pct=DEFAULT_THROTTLE_PCT, speed_rpm=DEFAULT_SPEED_RPM) -> pd.DataFrame:
    """The simulation plan of a load table: every node at the MBT prior spark, DOE-prior burn, target lambda.

    Rows of one throttle are consecutive with speed ascending (the simulator
    warm-starts along them).  ``p_amb_pa`` is the spec's ambient pressure.
    """

    t = _axis(throttle_pct, "throttle_pct", 0.0, 100.0)
    n = _axis(speed_rpm, "speed_rpm", 1.0, 20000.0)
    tt, nn = np.meshgrid(t, n, indexing="ij")
    plan = pd.DataFrame({"point_id": [f"load-t{a:g}-n{b:g}" for a, b in zip(tt.ravel(), nn.ravel())],
                         "speed_rpm": nn.ravel(), "throttle_pct": tt.ravel()})
    plan["spark_deg_btdc"] = np.atleast_1d(priors.spark_estimate(plan["speed_rpm"].to_numpy(),
                                                              plan["throttle_pct"].to_numpy()))
    plan["lambda"] = np.atleast_1d(priors.lambda_target(plan["throttle_pct"].to_numpy()))
    plan["p_amb_pa"] = float(spec.ambient.pressure_pa)
    return priors.with_combustion(plan)


def build_load_table(spec, evaluate: Callable[[pd.DataFrame], pd.DataFrame] | None = None,
                     throttle_pct=DEFAULT_THROTTLE_PCT, speed_rpm=DEFAULT_SPEED_RPM,
                     quantity: str = "plenum_pressure_ratio", solver=None) -> LoadTable:
    """Simulate the load quantity on a throttle x speed grid (once per calibrated engine).

    Parameters
    ----------
    spec : EngineSpec
        The calibrated engine.
    evaluate : callable(plan) -> results, optional
        Cycle model (one row per plan row, same order); default in-process
        :func:`engine_model.simulate` with ``solver``.  The flow layer passes
        a Dask-backed one.
    throttle_pct, speed_rpm : sequence of float
        Grid breakpoints (>= 4 each, ascending) [%], [rpm].  The model's data
        and the ECU grid should lie inside.
    quantity : str
        One of :data:`QUANTITIES`.
    solver : SolverSettings, optional
        Default :data:`LOAD_SOLVER` (1 deg step, 1 % tolerance, up to 60
        cycles): the air charge converges long before the cycle's work does;
        30 cycles (``doe.QUICK_SOLVER``) left some 1000-2000 rpm nodes
        unconverged (measured).

    Returns
    -------
    LoadTable
        Nodes whose simulation failed or did not converge are filled along the
        throttle axis (linear in throttle from the nearest good nodes of the
        same speed) and listed in ``filled``; a speed with fewer than 2 good
        nodes is an error.
    """
    from engine_model.sim.simulate import simulate

    if quantity not in QUANTITIES:
        raise ValueError(f"build_load_table: quantity {quantity!r}; choose from {sorted(QUANTITIES)}")
    plan = load_plan(spec, throttle_pct, speed_rpm)
    if evaluate is None:
        sol = LOAD_SOLVER if solver is None else solver

        def evaluate(p):
            return simulate(spec, p, sol)
    res = evaluate(plan).reset_index(drop=True)
    if len(res) != len(plan):
        raise ValueError(f"build_load_table: evaluate returned {len(res)} rows for a plan of {len(plan)} points")
    if quantity == "plenum_pressure_ratio":
        p_bar = pd.to_numeric(res["plenum_pressure_bar"], errors="coerce").to_numpy(float)
        val = p_bar * 1e5 / plan["p_amb_pa"].to_numpy(float)
    else:
        val = pd.to_numeric(res["vol_eff"], errors="coerce").to_numpy(float)
    ok = np.isfinite(val) & (val > 0) & res["converged"].astype(bool).to_numpy()
    t = np.asarray(_axis(throttle_pct, "throttle_pct", 0.0, 100.0))
    n = np.asarray(_axis(speed_rpm, "speed_rpm", 1.0, 20000.0))
    v = np.array(val, dtype=float).reshape(t.size, n.size)     # a writable copy (pandas arrays may be read-only)
    good = ok.reshape(t.size, n.size)
    filled = []
    for j in range(n.size):
        if good[:, j].sum() < 2:
            raise ValueError(f"build_load_table: at {n[j]:g} rpm only {int(good[:, j].sum())} of {t.size} throttle "
                             f"nodes simulated ({res['status'].to_numpy()[j::n.size].tolist()}); need >= 2")
        if not good[:, j].all():
            v[~good[:, j], j] = np.interp(t[~good[:, j]], t[good[:, j]], v[good[:, j], j])
            filled += [(float(x), float(n[j])) for x in t[~good[:, j]]]
    return LoadTable(tuple(t), tuple(n), tuple(map(tuple, v)), quantity=quantity, spec_hash=spec.spec_hash(),
                     filled=tuple(filled))
