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
import difflib
import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from engine_model.spec.machine import Geometry, ValveSet
from engine_model.spec.paths import ExhaustSpec, GasExchangeSpec, IntakeSpec
from engine_model.spec.submodels import (AmbientSpec, ChargeSpec, FrictionSpec, HeatTransferSpec, InjectorSpec,
                                         KnockSpec, LossSpec)
from engine_model.thermo import FuelSpec

__all__ = ["EngineSpec", "load_spec", "default_spec", "spec_from_dict", "DEFAULT_ENGINE", "SECTIONS"]

DEFAULT_ENGINE = "yamaha_r6_fs"


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
    gas_exchange: GasExchangeSpec = field(default_factory=GasExchangeSpec)
    charge: ChargeSpec = field(default_factory=ChargeSpec)
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
                names = [f"{f.name}.{g.name}" for f in dataclasses.fields(self)
                         if dataclasses.is_dataclass(getattr(self, f.name))
                         for g in dataclasses.fields(getattr(self, f.name))]
                raise ValueError(f"spec override {key!r}: no such field{_nearest(key, names)} (expected "
                                 "'<section>.<field>', e.g. 'intake.restrictor_cd')")
            cur = getattr(sec, field)
            if isinstance(cur, bool):
                val = bool(val)
            elif isinstance(cur, int):
                if float(val) != int(val):
                    raise ValueError(f"spec override {key!r}: value {val!r} must be a whole number")
                val = int(val)
            elif isinstance(cur, float):
                val = float(val)
            elif isinstance(cur, str) and isinstance(val, str):
                pass
            else:
                raise ValueError(f"spec override {key!r}: field of type {type(cur).__name__} cannot be overridden "
                                 f"by {val!r}")
            changes.setdefault(section, {})[field] = val
        new = {}
        for section, fields in changes.items():
            try:
                new[section] = dataclasses.replace(getattr(self, section), **fields)
            except ValueError as exc:
                raise ValueError(f"spec override {sorted(section + '.' + f for f in fields)}: {exc}") from None
        return dataclasses.replace(self, **new)


# --------------------------------------------------------------------------- loading

#: TOML sections of an engine file: name -> (dataclass, required).  ``[calibration]`` (the record a calibrated
#: engine file carries, see :mod:`engine_model.calibrated`) and ``[sources]`` are read as they are.
SECTIONS = {
    "geometry": (Geometry, True), "intake_valves": (ValveSet, True), "exhaust_valves": (ValveSet, True),
    "intake": (IntakeSpec, True), "exhaust": (ExhaustSpec, True), "heat_transfer": (HeatTransferSpec, True),
    "friction": (FrictionSpec, True), "fuel": (FuelSpec, True), "knock": (KnockSpec, True),
    "injector": (InjectorSpec, True), "ambient": (AmbientSpec, True), "gas_exchange": (GasExchangeSpec, False),
    "charge": (ChargeSpec, False), "losses": (LossSpec, False),
}
_FREE_SECTIONS = ("calibration", "sources")
#: Keys of the valve sections as written in a file (timing-diagram angles instead of cycle angles).
_VALVE_KEYS = {"intake": ("opens_deg_btdc", "closes_deg_abdc"), "exhaust": ("opens_deg_bbdc", "closes_deg_atdc")}


def _nearest(word: str, choices, prefix: str = "") -> str:
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.5)
    return f"; did you mean '{prefix}{close[0]}'?" if close else ""


#: Unit of a key, from the suffix of its name (longest suffix first), for messages.
_KEY_UNITS = (("_pa_s2_per_m2", "Pa s^2/m^2"), ("_pa_s_per_m", "Pa s/m"), ("_s_per_v", "s/V"),
              ("_j_per_kg", "J/kg"), ("_kg_s", "kg/s"), ("_m3", "m^3"), ("_m2", "m^2"), ("_deg_btdc", "deg BTDC"),
              ("_deg_abdc", "deg ABDC"), ("_deg_bbdc", "deg BBDC"), ("_deg_atdc", "deg ATDC"), ("_deg", "deg"),
              ("_rpm", "rpm"), ("_pa", "Pa"), ("_m", "m"), ("_k", "K"), ("_s", "s"), ("_v", "V"))


def _unit_of(key: str) -> str:
    for suffix, unit in _KEY_UNITS:
        if key.endswith(suffix):
            return f" in {unit}"
    return ""


_KINDS = {"float": "a number", "int": "a whole number", "bool": "true or false", "str": "a text in quotes",
          "tuple": "a list of numbers"}
_TOML_KINDS = {"str": "a text (in quotes)", "int": "a whole number", "float": "a number", "bool": "true/false",
               "list": "a list", "dict": "a table"}


def _file_keys(name: str, cls) -> dict:
    """Key -> expected Python type of section ``name`` as written in an engine file."""
    keys = {}
    for f in dataclasses.fields(cls):
        if f.name in ("side", "open_deg", "close_deg"):
            continue
        keys[f.name] = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    if name in ("intake_valves", "exhaust_valves"):
        for k in _VALVE_KEYS[name.split("_")[0]]:
            keys[k] = "float"
    return keys


def _type_ok(want: str, val) -> bool:
    if want.startswith("float"):
        return isinstance(val, (int, float)) and not isinstance(val, bool)
    if want.startswith("int"):
        return isinstance(val, int) and not isinstance(val, bool)
    if want.startswith("bool"):
        return isinstance(val, bool)
    if want.startswith("str"):
        return isinstance(val, str)
    if want.startswith("tuple"):
        return isinstance(val, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in val)
    return True


def _check_section(tbl, name: str, cls, path) -> dict:
    """The section as a dict; ValueError naming the file, ``section.key`` and value for an unknown key (with
    the nearest valid name) or a value of the wrong type (with the type and unit expected)."""
    if not isinstance(tbl, dict):
        raise ValueError(f"{path}: [{name}] must be a table of keys, got {type(tbl).__name__}")
    keys = _file_keys(name, cls)
    for key, val in tbl.items():
        if key not in keys:
            raise ValueError(f"{path}: unknown key {name}.{key}{_nearest(key, keys, name + '.')} "
                             f"(keys of [{name}]: {', '.join(sorted(keys))})")
        want = keys[key]
        if not _type_ok(want, val):
            kind = _KINDS.get(want.split("[")[0], want)
            got = _TOML_KINDS.get(type(val).__name__, type(val).__name__)
            hint = "; write it without quotes" if isinstance(val, str) and kind.startswith("a number") else ""
            raise ValueError(f"{path}: {name}.{key} = {val!r} is {got}, expected {kind}{_unit_of(key)}{hint}")
    return dict(tbl)


#: Keys of the ``[calibration]`` record a calibrated engine file carries.
_CALIBRATION_KEYS = {"base_spec_hash": "str", "source": "str", "overrides": "dict"}


def _check_calibration(tbl, path) -> None:
    if not isinstance(tbl, dict):
        raise ValueError(f"{path}: [calibration] must be a table of keys, got {type(tbl).__name__}")
    for key, val in tbl.items():
        if key not in _CALIBRATION_KEYS:
            raise ValueError(f"{path}: unknown key calibration.{key}"
                             f"{_nearest(key, _CALIBRATION_KEYS, 'calibration.')} "
                             f"(keys of [calibration]: {', '.join(_CALIBRATION_KEYS)})")
        want = _CALIBRATION_KEYS[key]
        if type(val).__name__ != want:
            raise ValueError(f"{path}: calibration.{key} = {val!r} is "
                             f"{_TOML_KINDS.get(type(val).__name__, type(val).__name__)}, expected "
                             f"{_TOML_KINDS[want]}")
    for key, val in tbl.get("overrides", {}).items():
        if not isinstance(val, (int, float)) or isinstance(val, bool):
            raise ValueError(f"{path}: calibration.overrides.{key} = {val!r} is "
                             f"{_TOML_KINDS.get(type(val).__name__, type(val).__name__)}, expected a number"
                             f"{_unit_of(key)}")


def _valves_from_toml(tbl: dict, side: str) -> ValveSet:
    if side == "intake":
        open_deg = 360.0 - float(tbl.pop("opens_deg_btdc"))          # before gas-exchange TDC
        close_deg = 540.0 + float(tbl.pop("closes_deg_abdc"))        # after BDC of the intake stroke
    else:
        open_deg = 180.0 - float(tbl.pop("opens_deg_bbdc"))          # before BDC of the expansion stroke
        close_deg = 360.0 + float(tbl.pop("closes_deg_atdc"))        # after gas-exchange TDC
    tbl["cd_ld"], tbl["cd"] = tuple(tbl["cd_ld"]), tuple(tbl["cd"])
    return ValveSet(open_deg=open_deg % 720.0, close_deg=close_deg, side=f"{side}_valves", **tbl)


def spec_from_dict(doc: dict, path="<dict>") -> EngineSpec:
    """Build an :class:`EngineSpec` from a parsed TOML document.

    Every section and key is checked before anything is built: an unknown section or key, or a value of the
    wrong type, is a ValueError naming the file, the section, the key (with the nearest valid name) and the
    value.
    """
    for name in doc:
        if name == "name":
            if not isinstance(doc[name], str):
                raise ValueError(f"{path}: name = {doc[name]!r} is "
                                 f"{_TOML_KINDS.get(type(doc[name]).__name__, type(doc[name]).__name__)}, "
                                 "expected a text in quotes")
            continue
        if name == "calibration":
            _check_calibration(doc[name], path)
            continue
        if name in _FREE_SECTIONS:
            continue
        if name not in SECTIONS:
            raise ValueError(f"{path}: unknown section [{name}]{_nearest(name, SECTIONS)} "
                             f"(known: {', '.join(SECTIONS)})")
    secs = {}
    for name, (cls, required) in SECTIONS.items():
        if name not in doc:
            if required:
                raise ValueError(f"{path}: missing section [{name}]")
            continue
        secs[name] = _check_section(doc[name], name, cls, path)
    try:
        g = secs["geometry"]
        g["firing_order"] = tuple(g["firing_order"])
        built = {name: cls(**secs[name]) for name, (cls, _req) in SECTIONS.items()
                 if name in secs and name not in ("geometry", "intake_valves", "exhaust_valves")}
        return EngineSpec(
            name=str(doc.get("name", Path(str(path)).stem)), geometry=Geometry(**g),
            intake_valves=_valves_from_toml(secs["intake_valves"], "intake"),
            exhaust_valves=_valves_from_toml(secs["exhaust_valves"], "exhaust"),
            sources=dict(doc.get("sources", {})), **built)
    except TypeError as exc:  # a missing key in a section
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
