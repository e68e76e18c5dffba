"""The machine: cranktrain geometry and valve trains."""

from __future__ import annotations

import math
from dataclasses import dataclass

from engine_model.spec.checks import check

__all__ = ["Geometry", "ValveSet"]


@dataclass(frozen=True)
class Geometry:
    """Cranktrain geometry.

    Parameters
    ----------
    bore_m, stroke_m, conrod_m : float
        Bore, stroke and connecting-rod centre distance [m].
    compression_ratio : float
        Geometric compression ratio [-], > 1.
    n_cylinders : int
        Number of cylinders, all sharing one plenum.
    firing_order : tuple of int
        1-based cylinder numbers in firing order; cylinders fire 720/n deg apart.
    max_speed_rpm : float
        Highest speed the spec accepts [rpm] (rev limit).
    """

    bore_m: float
    stroke_m: float
    conrod_m: float
    compression_ratio: float
    n_cylinders: int
    firing_order: tuple[int, ...]
    max_speed_rpm: float

    def __post_init__(self):
        o = "geometry"
        check(o, "bore_m", self.bore_m, 0.0, 0.5, lo_open=True)
        check(o, "stroke_m", self.stroke_m, 0.0, 0.5, lo_open=True)
        check(o, "compression_ratio", self.compression_ratio, 1.0, 30.0, lo_open=True)
        if not (isinstance(self.n_cylinders, int) and 1 <= self.n_cylinders <= 16):
            raise ValueError(f"geometry.n_cylinders = {self.n_cylinders!r} must be an integer in [1, 16]")
        # A con-rod shorter than the crank radius cannot turn the crank.
        check(o, "conrod_m", self.conrod_m, self.stroke_m / 2.0, 2.0, lo_open=True)
        fo = tuple(int(c) for c in self.firing_order)
        if sorted(fo) != list(range(1, self.n_cylinders + 1)):
            raise ValueError(
                f"geometry.firing_order = {self.firing_order!r} must list each cylinder "
                f"1..{self.n_cylinders} exactly once")
        object.__setattr__(self, "firing_order", fo)
        check(o, "max_speed_rpm", self.max_speed_rpm, 500.0, 30000.0)

    @property
    def displacement_m3(self) -> float:
        """Swept volume of one cylinder [m^3]."""
        return math.pi / 4.0 * self.bore_m**2 * self.stroke_m

    @property
    def total_displacement_m3(self) -> float:
        """Swept volume of the engine [m^3]."""
        return self.displacement_m3 * self.n_cylinders

    @property
    def clearance_m3(self) -> float:
        """Clearance volume of one cylinder [m^3]."""
        return self.displacement_m3 / (self.compression_ratio - 1.0)

    def phase_deg(self) -> tuple[float, ...]:
        """Firing-TDC angle of each cylinder (index 0 = cylinder 1) in engine degrees [deg]."""
        spacing = 720.0 / self.n_cylinders
        phase = [0.0] * self.n_cylinders
        for k, cyl in enumerate(self.firing_order):
            phase[cyl - 1] = k * spacing
        return tuple(phase)


@dataclass(frozen=True)
class ValveSet:
    """One side (intake or exhaust) of the valve train of a cylinder.

    Parameters
    ----------
    n_valves : int
        Valves per cylinder on this side.
    diameter_m : float
        Inner seat (head) diameter of one valve [m].
    max_lift_m : float
        Peak lift [m].
    open_deg, close_deg : float
        Opening and closing angles in cycle degrees [0, 720) (0 = firing TDC) at
        which the lift is ``timing_lift_m``.  Derived from the timing diagram by the
        loader.
    ramp_height_m : float
        Lift at the end of the opening ramp (and the start of the closing ramp)
        [m]: the cam's constant-velocity ramp that takes up the valve clearance
        and sets the valve down gently.
    ramp_duration_deg : float
        Crank angle of each ramp [deg].
    timing_lift_m : float
        Lift at which ``open_deg`` and ``close_deg`` are read [m]; 0 = seat to
        seat (the valve leaves its seat at open_deg).  See
        :func:`engine_model.cycle.flow.valve_lift` for the profile.
    cd_ld : tuple of float
        L/D breakpoints [-] for the discharge coefficient table.
    cd : tuple of float
        Discharge coefficient based on the curtain area pi*D*L [-].
    """

    n_valves: int
    diameter_m: float
    max_lift_m: float
    open_deg: float
    close_deg: float
    ramp_height_m: float
    ramp_duration_deg: float
    cd_ld: tuple[float, ...]
    cd: tuple[float, ...]
    timing_lift_m: float = 0.0
    side: str = "valves"

    def __post_init__(self):
        o = f"{self.side}"
        if not (isinstance(self.n_valves, int) and 1 <= self.n_valves <= 5):
            raise ValueError(f"{o}.n_valves = {self.n_valves!r} must be an integer in [1, 5]")
        check(o, "diameter_m", self.diameter_m, 0.0, 0.2, lo_open=True)
        check(o, "max_lift_m", self.max_lift_m, 0.0, 0.05, lo_open=True)
        check(o, "open_deg", self.open_deg, 0.0, 720.0, hi_open=True)
        check(o, "close_deg", self.close_deg, 0.0, 1440.0)
        dur = self.duration_deg
        if not (60.0 <= dur <= 400.0):
            raise ValueError(
                f"{o}: open {self.open_deg:g} -> close {self.close_deg:g} deg gives a duration of "
                f"{dur:g} deg; expected 60-400 deg (inconsistent valve timing)")
        check(o, "ramp_height_m", self.ramp_height_m, 0.0, 0.25 * self.max_lift_m)
        check(o, "ramp_duration_deg", self.ramp_duration_deg, 0.0, 0.2 * dur)
        check(o, "timing_lift_m", self.timing_lift_m, 0.0, 0.5 * self.max_lift_m, hi_open=True)
        if self.timing_lift_m > 0.0 and self.timing_lift_m <= self.ramp_height_m:
            raise ValueError(f"{o}.timing_lift_m = {self.timing_lift_m!r} must lie above the ramp "
                             f"(ramp_height_m = {self.ramp_height_m!r}) or be 0 (seat to seat)")
        cd_ld = tuple(float(v) for v in self.cd_ld)
        cd = tuple(float(v) for v in self.cd)
        if len(cd_ld) != len(cd) or len(cd) < 2:
            raise ValueError(f"{o}.cd_ld and {o}.cd must have the same length >= 2")
        if any(b <= a for a, b in zip(cd_ld, cd_ld[1:])):
            raise ValueError(f"{o}.cd_ld = {cd_ld} must be strictly increasing")
        for v in cd:
            check(o, "cd", v, 0.0, 1.0, lo_open=True)
        object.__setattr__(self, "cd_ld", cd_ld)
        object.__setattr__(self, "cd", cd)

    @property
    def duration_deg(self) -> float:
        """Seat-to-seat open duration [deg]."""
        return (self.close_deg - self.open_deg) % 720.0
