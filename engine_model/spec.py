"""Engine specification: frozen, validated dataclasses in SI units.

An :class:`EngineSpec` is built from a TOML file (see ``engines/``) whose keys
carry their unit in the name (``bore_m``, ``volume_m3``, ``timing_deg``) and
whose comments give the source of every constant.  All validation happens at
construction and names the field, the value and the allowed range.

Crank-angle convention: degrees, 0 = firing TDC of the cylinder, ATDC positive,
one cycle spans 720 deg.  Valve events are given as on a timing diagram
(opening BTDC / closing ABDC and so on) and converted here to cycle angles in
[0, 720).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from engine_model.thermo import FuelSpec

__all__ = [
    "Geometry", "ValveSet", "IntakeSpec", "ExhaustSpec", "HeatTransferSpec",
    "FrictionSpec", "KnockSpec", "InjectorSpec", "AmbientSpec", "LossSpec", "EngineSpec",
    "load_spec", "default_spec", "DEFAULT_ENGINE",
]

DEFAULT_ENGINE = "yamaha_r6_fs"


def _check(owner: str, name: str, value, lo=None, hi=None, lo_open=False, hi_open=False):
    """Raise ValueError unless ``lo (<|<=) value (<|<=) hi`` and value is finite."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.{name}: expected a number, got {value!r}") from None
    ok = math.isfinite(v)
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if not ok:
        lo_s = "-inf" if lo is None else f"{lo:g}"
        hi_s = "inf" if hi is None else f"{hi:g}"
        lb = "(" if lo_open or lo is None else "["
        rb = ")" if hi_open or hi is None else "]"
        raise ValueError(f"{owner}.{name} = {value!r} is outside the allowed range {lb}{lo_s}, {hi_s}{rb}")


def _check_segments(owner: str, n):
    """Runner segment count: an integer in [1, 8]."""
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 8:
        raise ValueError(f"{owner}.runner_segments = {n!r} must be an integer in [1, 8]")


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
        _check(o, "bore_m", self.bore_m, 0.0, 0.5, lo_open=True)
        _check(o, "stroke_m", self.stroke_m, 0.0, 0.5, lo_open=True)
        _check(o, "compression_ratio", self.compression_ratio, 1.0, 30.0, lo_open=True)
        if not (isinstance(self.n_cylinders, int) and 1 <= self.n_cylinders <= 16):
            raise ValueError(f"geometry.n_cylinders = {self.n_cylinders!r} must be an integer in [1, 16]")
        # A con-rod shorter than the crank radius cannot turn the crank.
        _check(o, "conrod_m", self.conrod_m, self.stroke_m / 2.0, 2.0, lo_open=True)
        fo = tuple(int(c) for c in self.firing_order)
        if sorted(fo) != list(range(1, self.n_cylinders + 1)):
            raise ValueError(
                f"geometry.firing_order = {self.firing_order!r} must list each cylinder "
                f"1..{self.n_cylinders} exactly once")
        object.__setattr__(self, "firing_order", fo)
        _check(o, "max_speed_rpm", self.max_speed_rpm, 500.0, 30000.0)

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
        Seat-to-seat opening and closing angles in cycle degrees [0, 720)
        (0 = firing TDC).  Derived from the timing diagram by the loader.
    lift_shape : float
        Exponent k of the lift profile L = L_max * sin(pi*x)**k, x the fraction
        of the open period [-].
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
    lift_shape: float
    cd_ld: tuple[float, ...]
    cd: tuple[float, ...]
    side: str = "valves"

    def __post_init__(self):
        o = f"{self.side}"
        if not (isinstance(self.n_valves, int) and 1 <= self.n_valves <= 5):
            raise ValueError(f"{o}.n_valves = {self.n_valves!r} must be an integer in [1, 5]")
        _check(o, "diameter_m", self.diameter_m, 0.0, 0.2, lo_open=True)
        _check(o, "max_lift_m", self.max_lift_m, 0.0, 0.05, lo_open=True)
        _check(o, "open_deg", self.open_deg, 0.0, 720.0, hi_open=True)
        _check(o, "close_deg", self.close_deg, 0.0, 1440.0)
        dur = self.duration_deg
        if not (60.0 <= dur <= 400.0):
            raise ValueError(
                f"{o}: open {self.open_deg:g} -> close {self.close_deg:g} deg gives a duration of "
                f"{dur:g} deg; expected 60-400 deg (inconsistent valve timing)")
        _check(o, "lift_shape", self.lift_shape, 0.2, 4.0)
        cd_ld = tuple(float(v) for v in self.cd_ld)
        cd = tuple(float(v) for v in self.cd)
        if len(cd_ld) != len(cd) or len(cd) < 2:
            raise ValueError(f"{o}.cd_ld and {o}.cd must have the same length >= 2")
        if any(b <= a for a, b in zip(cd_ld, cd_ld[1:])):
            raise ValueError(f"{o}.cd_ld = {cd_ld} must be strictly increasing")
        for v in cd:
            _check(o, "cd", v, 0.0, 1.0, lo_open=True)
        object.__setattr__(self, "cd_ld", cd_ld)
        object.__setattr__(self, "cd", cd)

    @property
    def duration_deg(self) -> float:
        """Seat-to-seat open duration [deg]."""
        return (self.close_deg - self.open_deg) % 720.0


@dataclass(frozen=True)
class IntakeSpec:
    """Intake path: throttle -> throttle-body duct -> restrictor -> plenum -> runners -> ports.

    All lengths [m], volumes [m^3]; discharge coefficients and loss factors [-].
    ``restrictor_recovery`` is the fraction of the throat's dynamic pressure the
    diffuser recovers (0 = plain orifice).  ``runner_loss_k`` is the runner's
    minor (local) pressure-loss factor in units of its dynamic head: entry,
    bends, obstructions; the exit (dump) loss of one dynamic head is added by the
    model, and wall friction is computed from ``runner_roughness_m`` (Darcy,
    Haaland friction factor at the instantaneous Reynolds number).
    ``runner_inertia`` switches the lumped gas-inertia (momentum) equation of the
    runners on; off makes them quasi-steady resistances.
    ``runner_volume_at_port`` is the fraction of a runner's gas volume lumped
    with the port (the rest goes to the plenum): 0 is the Helmholtz-resonator
    lumping (runner = neck, port + cylinder = cavity), 0.5 the symmetric
    pi-network lumping of a pipe.  ``runner_segments`` splits each runner into
    that many lumped segments in series (a staggered-grid discretisation of the
    1D pipe: a momentum equation per segment, a gas volume at each joint), so the
    runner carries its own compliance and its higher acoustic modes;
    ``runner_volume_at_port`` then applies to the valve-end segment.  With
    inertia off a runner is always a single quasi-steady resistance.
    ``runner_backflow_slug`` (with inertia on) keeps the gas a port pushes back
    into its runner as a slug in the runner's plenum-side gas share, drawn back
    first on the next intake stroke, instead of mixing it into the plenum: a
    lumped runner has no gas volume of its own, so without the slug the burned
    gas and fuel vapour of the valve overlap and of the backflow before IVC
    spread through the whole plenum (1-5 % burned gas there at WOT, where a
    finely segmented runner keeps the plenum clean).
    """

    throttle_bore_m: float
    throttle_shaft_m: float
    throttle_closed_deg: float
    throttle_cd: float
    throttle_body_volume_m3: float
    restrictor_throat_m: float
    restrictor_cd: float
    restrictor_recovery: float
    plenum_volume_m3: float
    runner_length_m: float
    runner_diameter_m: float
    runner_loss_k: float
    port_volume_m3: float
    runner_inertia: bool = True
    wall_temp_k: float = 320.0
    throttle_leak_area_m2: float = 3.0e-6
    runner_volume_at_port: float = 0.5
    runner_segments: int = 1
    runner_roughness_m: float = 0.0
    runner_inertance_factor: float = 1.0
    runner_backflow_slug: bool = False

    def __post_init__(self):
        o = "intake"
        _check(o, "throttle_bore_m", self.throttle_bore_m, 0.0, 0.2, lo_open=True)
        _check(o, "throttle_shaft_m", self.throttle_shaft_m, 0.0, self.throttle_bore_m / 2, hi_open=True)
        _check(o, "throttle_closed_deg", self.throttle_closed_deg, 0.0, 20.0)
        _check(o, "throttle_cd", self.throttle_cd, 0.0, 1.0, lo_open=True)
        _check(o, "throttle_body_volume_m3", self.throttle_body_volume_m3, 0.0, 0.05, lo_open=True)
        _check(o, "restrictor_throat_m", self.restrictor_throat_m, 0.0, 0.2, lo_open=True)
        _check(o, "restrictor_cd", self.restrictor_cd, 0.0, 1.0, lo_open=True)
        _check(o, "restrictor_recovery", self.restrictor_recovery, 0.0, 0.98)
        _check(o, "plenum_volume_m3", self.plenum_volume_m3, 0.0, 0.1, lo_open=True)
        _check(o, "runner_length_m", self.runner_length_m, 0.0, 2.0, lo_open=True)
        _check(o, "runner_diameter_m", self.runner_diameter_m, 0.0, 0.2, lo_open=True)
        _check(o, "runner_loss_k", self.runner_loss_k, 0.0, 50.0)
        _check(o, "port_volume_m3", self.port_volume_m3, 0.0, 0.01, lo_open=True)
        _check(o, "wall_temp_k", self.wall_temp_k, 200.0, 600.0)
        _check(o, "throttle_leak_area_m2", self.throttle_leak_area_m2, 0.0, 1e-3)
        _check(o, "runner_volume_at_port", self.runner_volume_at_port, 0.0, 1.0)
        _check_segments(o, self.runner_segments)
        _check(o, "runner_roughness_m", self.runner_roughness_m, 0.0, 0.1 * self.runner_diameter_m)
        _check(o, "runner_inertance_factor", self.runner_inertance_factor, 0.05, 5.0)


@dataclass(frozen=True)
class ExhaustSpec:
    """Exhaust path: ports -> runners (lumped inertia) -> collector -> tailpipe orifice -> ambient.

    ``tailpipe_diameter_m`` with ``tailpipe_cd`` sets the silencer/tailpipe
    effective flow area, i.e. the back pressure at a given flow.
    ``runner_volume_at_port`` as for the intake (fraction of the runner's gas
    volume lumped with the exhaust port; the rest with the collector),
    ``runner_segments`` (lumped segments in series per runner), and
    ``runner_loss_k`` / ``runner_roughness_m`` (minor losses; wall friction).
    """

    port_volume_m3: float
    runner_length_m: float
    runner_diameter_m: float
    runner_loss_k: float
    collector_volume_m3: float
    tailpipe_diameter_m: float
    tailpipe_cd: float
    runner_inertia: bool = True
    runner_volume_at_port: float = 0.5
    runner_segments: int = 1
    runner_roughness_m: float = 0.0

    def __post_init__(self):
        o = "exhaust"
        _check(o, "port_volume_m3", self.port_volume_m3, 0.0, 0.01, lo_open=True)
        _check(o, "runner_length_m", self.runner_length_m, 0.0, 3.0, lo_open=True)
        _check(o, "runner_diameter_m", self.runner_diameter_m, 0.0, 0.2, lo_open=True)
        _check(o, "runner_loss_k", self.runner_loss_k, 0.0, 50.0)
        _check(o, "collector_volume_m3", self.collector_volume_m3, 0.0, 0.1, lo_open=True)
        _check(o, "tailpipe_diameter_m", self.tailpipe_diameter_m, 0.0, 0.3, lo_open=True)
        _check(o, "tailpipe_cd", self.tailpipe_cd, 0.0, 1.0, lo_open=True)
        _check(o, "runner_volume_at_port", self.runner_volume_at_port, 0.0, 1.0)
        _check_segments(o, self.runner_segments)
        _check(o, "runner_roughness_m", self.runner_roughness_m, 0.0, 0.1 * self.runner_diameter_m)


@dataclass(frozen=True)
class HeatTransferSpec:
    """Woschni (1967) in-cylinder heat transfer and wall temperatures.

    h = coeff * B^-0.2 * p[kPa]^0.8 * T^-0.55 * w^0.8  [W/(m^2 K)],
    w = C1*Sp + C2*(Vd*T_r/(p_r*V_r))*(p - p_mot).
    """

    woschni_coeff: float
    c1_gas_exchange: float
    c1_closed: float
    c2_combustion: float
    multiplier: float
    head_temp_k: float
    piston_temp_k: float
    liner_temp_k: float
    head_area_factor: float
    piston_area_factor: float

    def __post_init__(self):
        o = "heat_transfer"
        _check(o, "woschni_coeff", self.woschni_coeff, 0.0, 20.0, lo_open=True)
        _check(o, "c1_gas_exchange", self.c1_gas_exchange, 0.0, 20.0)
        _check(o, "c1_closed", self.c1_closed, 0.0, 20.0)
        _check(o, "c2_combustion", self.c2_combustion, 0.0, 0.05)
        _check(o, "multiplier", self.multiplier, 0.0, 5.0)
        for n in ("head_temp_k", "piston_temp_k", "liner_temp_k"):
            _check(o, n, getattr(self, n), 250.0, 900.0)
        _check(o, "head_area_factor", self.head_area_factor, 1.0, 3.0)
        _check(o, "piston_area_factor", self.piston_area_factor, 1.0, 3.0)


@dataclass(frozen=True)
class FrictionSpec:
    """Chen-Flynn friction: FMEP = A + B*p_max + C*Sp + D*Sp^2 (SI: Pa, -, Pa s/m, Pa s^2/m^2)."""

    a_pa: float
    b: float
    c_pa_s_per_m: float
    d_pa_s2_per_m2: float

    def __post_init__(self):
        o = "friction"
        _check(o, "a_pa", self.a_pa, 0.0, 5e5)
        _check(o, "b", self.b, 0.0, 0.1)
        _check(o, "c_pa_s_per_m", self.c_pa_s_per_m, 0.0, 1e5)
        _check(o, "d_pa_s2_per_m2", self.d_pa_s2_per_m2, 0.0, 1e4)



@dataclass(frozen=True)
class KnockSpec:
    """Douaud-Eyzat ignition delay of the end gas, tau = A*(ON/100)^a * p[atm]^-n * exp(B/T).

    Integrated as a Livengood-Wu integral; knock index 1 = autoignition before the
    end gas is consumed.
    """

    octane_number: float
    delay_coeff_s: float
    octane_exponent: float
    pressure_exponent: float
    activation_temp_k: float

    def __post_init__(self):
        o = "knock"
        _check(o, "octane_number", self.octane_number, 40.0, 130.0)
        _check(o, "delay_coeff_s", self.delay_coeff_s, 0.0, 1.0, lo_open=True)
        _check(o, "octane_exponent", self.octane_exponent, 0.0, 10.0)
        _check(o, "pressure_exponent", self.pressure_exponent, 0.0, 5.0)
        _check(o, "activation_temp_k", self.activation_temp_k, 0.0, 20000.0)


@dataclass(frozen=True)
class InjectorSpec:
    """Port fuel injector: static flow [kg/s] at rated pressure and dead time [s] vs battery voltage."""

    static_flow_kg_s: float
    dead_time_s: float
    dead_time_ref_v: float
    dead_time_slope_s_per_v: float
    per_cylinder: int = 1

    def __post_init__(self):
        o = "injector"
        _check(o, "static_flow_kg_s", self.static_flow_kg_s, 0.0, 0.1, lo_open=True)
        _check(o, "dead_time_s", self.dead_time_s, 0.0, 0.01)
        _check(o, "dead_time_ref_v", self.dead_time_ref_v, 6.0, 30.0)
        _check(o, "dead_time_slope_s_per_v", self.dead_time_slope_s_per_v, -0.01, 0.0)


@dataclass(frozen=True)
class AmbientSpec:
    """Default test-cell state: pressure [Pa] and temperature [K]."""

    pressure_pa: float
    temperature_k: float

    def __post_init__(self):
        _check("ambient", "pressure_pa", self.pressure_pa, 5e4, 1.2e5)
        _check("ambient", "temperature_k", self.temperature_k, 230.0, 340.0)


@dataclass(frozen=True)
class LossSpec:
    """Losses the base model leaves out; neutral defaults (the gap-diagnosis library switches them on).

    Parameters
    ----------
    combustion_efficiency : float
        Fraction of the trapped fuel that burns [-]: the Wiebe burned fraction
        is scaled by it, the rest of the fresh mixture leaves unburned with the
        exhaust (incomplete combustion, crevice and blow-by losses of charge
        energy).  1 = complete combustion (the base assumption).  Heywood
        (Internal Combustion Engine Fundamentals, 1988, sec. 4.9.4) gives
        0.95-0.98 for SI engines at lambda <= 1... 1.1 (rich mixtures burn
        less completely; the lambda effect is in the kernel's equilibrium-free
        product model already, this factor is what is left).
    """

    combustion_efficiency: float = 1.0

    def __post_init__(self):
        _check("losses", "combustion_efficiency", self.combustion_efficiency, 0.5, 1.0)


@dataclass(frozen=True)
class EngineSpec:
    """A whole engine: geometry, valve train, intake, exhaust and sub-model constants (SI)."""

    name: str
    geometry: Geometry
    intake_valves: ValveSet
    exhaust_valves: ValveSet
    intake: IntakeSpec
    exhaust: ExhaustSpec
    heat_transfer: HeatTransferSpec
    friction: FrictionSpec
    fuel: FuelSpec
    knock: KnockSpec
    injector: InjectorSpec
    ambient: AmbientSpec
    losses: LossSpec = field(default_factory=LossSpec)
    sources: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    def __post_init__(self):
        iv, ev = self.intake_valves, self.exhaust_valves
        # Physical ordering of events on the cycle: EVO in the expansion stroke,
        # IVO before gas-exchange TDC (360), EVC after it, IVC in the compression stroke.
        if not (90.0 <= ev.open_deg <= 240.0):
            raise ValueError(f"exhaust_valves.open_deg = {ev.open_deg:g} (EVO) must lie in the expansion "
                             "stroke, 90-240 deg after firing TDC (inconsistent valve timing)")
        if not (270.0 <= iv.open_deg <= 400.0):
            raise ValueError(f"intake_valves.open_deg = {iv.open_deg:g} (IVO) must lie within 90 deg of "
                             "gas-exchange TDC (360) (inconsistent valve timing)")
        evc = ev.open_deg + ev.duration_deg
        ivc = iv.open_deg + iv.duration_deg
        if not (330.0 <= evc <= 450.0):
            raise ValueError(f"exhaust closing at {evc:g} deg must lie within 90 deg of gas-exchange TDC "
                             "(360) (inconsistent valve timing)")
        if not (540.0 <= ivc <= 720.0):
            raise ValueError(f"intake closing at {ivc:g} deg must lie in the compression stroke, "
                             "540-720 deg (inconsistent valve timing)")
        if ev.open_deg >= iv.open_deg:
            raise ValueError("exhaust must open before intake opens (inconsistent valve timing)")

    def to_dict(self) -> dict:
        """Plain nested dict of all fields (sources excluded)."""
        d = dataclasses.asdict(self)
        d.pop("sources", None)
        return d

    def spec_hash(self) -> str:
        """Stable SHA-256 (first 16 hex digits) of the spec's values; keys cached work."""
        blob = json.dumps(self.to_dict(), sort_keys=True, default=str).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def replace(self, **sections) -> "EngineSpec":
        """Copy with whole sections replaced, e.g. ``spec.replace(intake=new_intake)``."""
        return dataclasses.replace(self, **sections)

    def with_values(self, values: dict) -> "EngineSpec":
        """Copy with single fields changed by dotted name, e.g. ``{"intake.restrictor_cd": 0.95}``.

        Every changed section is re-validated; a ValueError names the key and
        the value when the name is unknown or the value is out of range.
        """
        changes: dict[str, dict] = {}
        for key, val in values.items():
            section, _, field = key.partition(".")
            sec = getattr(self, section, None) if section != "sources" else None
            if not field or sec is None or not dataclasses.is_dataclass(sec) or \
                    field not in {f.name for f in dataclasses.fields(sec)}:
                raise ValueError(f"spec override {key!r}: no such field (expected '<section>.<field>', e.g. "
                                 "'intake.restrictor_cd')")
            cur = getattr(sec, field)
            if isinstance(cur, bool):
                val = bool(val)
            elif isinstance(cur, int):
                if float(val) != int(val):
                    raise ValueError(f"spec override {key!r}: value {val!r} must be a whole number")
                val = int(val)
            elif isinstance(cur, float):
                val = float(val)
            else:
                raise ValueError(f"spec override {key!r}: field of type {type(cur).__name__} cannot be overridden "
                                 "by a number")
            changes.setdefault(section, {})[field] = val
        new = {}
        for section, fields in changes.items():
            try:
                new[section] = dataclasses.replace(getattr(self, section), **fields)
            except ValueError as exc:
                raise ValueError(f"spec override {sorted(section + '.' + f for f in fields)}: {exc}") from None
        return dataclasses.replace(self, **new)


# --------------------------------------------------------------------------- loading

def _valves_from_toml(tbl: dict, side: str) -> ValveSet:
    if side == "intake":
        open_deg = 360.0 - float(tbl["opens_deg_btdc"])          # before gas-exchange TDC
        close_deg = 540.0 + float(tbl["closes_deg_abdc"])        # after BDC of the intake stroke
    else:
        open_deg = 180.0 - float(tbl["opens_deg_bbdc"])          # before BDC of the expansion stroke
        close_deg = 360.0 + float(tbl["closes_deg_atdc"])        # after gas-exchange TDC
    return ValveSet(
        n_valves=int(tbl["n_valves"]), diameter_m=tbl["diameter_m"], max_lift_m=tbl["max_lift_m"],
        open_deg=open_deg % 720.0, close_deg=close_deg, lift_shape=tbl["lift_shape"],
        cd_ld=tuple(tbl["cd_ld"]), cd=tuple(tbl["cd"]), side=f"{side}_valves")


def _section(doc: dict, name: str, path) -> dict:
    if name not in doc:
        raise ValueError(f"{path}: missing section [{name}]")
    return dict(doc[name])


def spec_from_dict(doc: dict, path="<dict>") -> EngineSpec:
    """Build an :class:`EngineSpec` from a parsed TOML document."""
    try:
        g = _section(doc, "geometry", path)
        g["firing_order"] = tuple(g["firing_order"])
        geometry = Geometry(**g)
        return EngineSpec(
            name=str(doc.get("name", Path(str(path)).stem)),
            geometry=geometry,
            intake_valves=_valves_from_toml(_section(doc, "intake_valves", path), "intake"),
            exhaust_valves=_valves_from_toml(_section(doc, "exhaust_valves", path), "exhaust"),
            intake=IntakeSpec(**_section(doc, "intake", path)),
            exhaust=ExhaustSpec(**_section(doc, "exhaust", path)),
            heat_transfer=HeatTransferSpec(**_section(doc, "heat_transfer", path)),
            friction=FrictionSpec(**_section(doc, "friction", path)),
            fuel=FuelSpec(**_section(doc, "fuel", path)),
            knock=KnockSpec(**_section(doc, "knock", path)),
            injector=InjectorSpec(**_section(doc, "injector", path)),
            ambient=AmbientSpec(**_section(doc, "ambient", path)),
            losses=LossSpec(**dict(doc.get("losses", {}))),
            sources=dict(doc.get("sources", {})),
        )
    except TypeError as exc:  # unknown or missing key in a section
        raise ValueError(f"{path}: {exc}") from None
    except KeyError as exc:
        raise ValueError(f"{path}: missing key {exc}") from None


def load_spec(path: str | Path | None = None) -> EngineSpec:
    """Load an engine spec from a TOML file; ``None`` loads the embedded default (Yamaha R6, FS)."""
    if path is None:
        text = resources.files("engine_model.engines").joinpath(f"{DEFAULT_ENGINE}.toml").read_text()
        src = f"engines/{DEFAULT_ENGINE}.toml"
    else:
        src = Path(path)
        if not src.is_file():
            raise ValueError(f"engine spec file not found: {src}")
        text = src.read_text()
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{src}: not valid TOML: {exc}") from None
    return spec_from_dict(doc, src)


def default_spec() -> EngineSpec:
    """The embedded Yamaha YZF-R6 Formula Student engine."""
    return load_spec(None)
