"""The calibrated engine: an engine spec plus the values a calibration fixed, as one object.

Every stage of the pipeline takes a :class:`CalibratedEngine`; every run
writes it into its folder as a TOML engine file (``engine.toml``) that
``--spec`` accepts, so any stage can be re-run from a finished run::

    eng = CalibratedEngine.from_spec(load_spec(path))           # before calibration
    eng = eng.calibrated({"exhaust.runner_length_m": 0.275})     # after the airflow match
    eng.write(run_dir / "engine.toml")
    again = CalibratedEngine.load(run_dir / "engine.toml")       # the same spec, the same hash

The TOML file holds the whole resolved spec (every section, every value) and
a ``[calibration]`` table recording which values the calibration set and the
hash of the spec it started from; loading it gives back the identical spec
(same :meth:`EngineSpec.spec_hash`), which the writer checks.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from engine_model.io import write_text
from engine_model.spec import EngineSpec, load_spec, spec_from_dict

__all__ = ["CalibratedEngine", "spec_to_toml"]


@dataclass(frozen=True)
class CalibratedEngine:
    """An engine spec with calibrated values.

    Parameters
    ----------
    base : EngineSpec
        The spec the calibration started from.
    overrides : mapping {"section.field": value}
        Values the calibration fixed (SI units, as in the spec); empty before calibration.
    source : str
        Where ``base`` came from (a path, or the embedded engine's name), for reports.
    """

    base: EngineSpec
    overrides: Mapping[str, float] = field(default_factory=dict)
    source: str = ""
    spec: EngineSpec = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        ov = {str(k[5:] if str(k).startswith("spec.") else k): float(v) for k, v in dict(self.overrides).items()}
        object.__setattr__(self, "overrides", dict(sorted(ov.items())))
        # a ValueError here names the key and value of a bad override
        object.__setattr__(self, "spec", self.base.with_values(ov) if ov else self.base)

    @classmethod
    def from_spec(cls, spec: EngineSpec | str | Path | None = None, source: str | None = None) -> "CalibratedEngine":
        """Uncalibrated engine from a spec object, a TOML path, or None (the embedded default)."""
        if isinstance(spec, EngineSpec):
            return cls(spec, {}, source or spec.name)
        loaded = load_spec(spec)
        return cls(loaded, {}, source or (str(spec) if spec is not None else f"embedded {loaded.name}"))

    @classmethod
    def load(cls, path: str | Path) -> "CalibratedEngine":
        """Read an engine TOML written by :meth:`write` (or any engine spec file)."""
        p = Path(path)
        spec = load_spec(p)
        doc = tomllib.loads(p.read_text())
        cal = doc.get("calibration", {})
        return cls(spec, dict(cal.get("overrides", {})), str(cal.get("source", p)))

    def calibrated(self, values: Mapping[str, float]) -> "CalibratedEngine":
        """A copy with more calibrated values (later values win)."""
        return CalibratedEngine(self.base, {**self.overrides, **dict(values)}, self.source)

    def spec_hash(self) -> str:
        """Hash of the resolved spec (:meth:`EngineSpec.spec_hash`)."""
        return self.spec.spec_hash()

    def to_toml(self) -> str:
        """The resolved spec as an engine TOML file, with the calibration record."""
        head = (f"# Engine spec written by engine_model: {self.spec.name}, resolved spec hash {self.spec_hash()}.\n"
                f"# Started from {self.source or self.base.name} (hash {self.base.spec_hash()}); the values in\n"
                "# [calibration].overrides were set by the calibration, every other value is the starting spec's\n"
                "# (whose sources are documented in the packaged engine file).\n")
        doc = spec_to_toml(self.spec)
        cal = {"base_spec_hash": self.base.spec_hash(), "source": self.source or self.base.name,
               "overrides": dict(self.overrides)}
        return head + doc + "\n" + _table("calibration", cal)

    def write(self, path: str | Path) -> Path:
        """Write :meth:`to_toml` atomically to ``path``; checks that it reads back as the same spec."""
        text = self.to_toml()
        back = spec_from_dict(tomllib.loads(text), path)
        if back.spec_hash() != self.spec_hash():
            raise RuntimeError(f"{path}: the written engine file does not read back as the same spec "
                               f"({back.spec_hash()} != {self.spec_hash()})")
        return write_text(text, Path(path))


# --------------------------------------------------------------------------- TOML writing

def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write the non-finite value {v!r} to TOML")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write a {type(v).__name__} to TOML")


def _key(k: str) -> str:
    return k if k.replace("_", "").isalnum() else '"' + k + '"'


def _table(name: str, fields: Mapping) -> str:
    return f"[{name}]\n" + "".join(f"{_key(k)} = {_value(v)}\n" for k, v in fields.items())


def _valves(vs, side: str) -> dict:
    d = {"n_valves": vs.n_valves}
    if side == "intake":
        d["opens_deg_btdc"] = 360.0 - vs.open_deg
        d["closes_deg_abdc"] = vs.close_deg - 540.0
    else:
        d["opens_deg_bbdc"] = 180.0 - vs.open_deg
        d["closes_deg_atdc"] = vs.close_deg - 360.0
    for f in dataclasses.fields(vs):
        if f.name not in ("n_valves", "open_deg", "close_deg", "side"):
            d[f.name] = getattr(vs, f.name)
    return d


def spec_to_toml(spec: EngineSpec) -> str:
    """An :class:`EngineSpec` as the TOML text :func:`engine_model.spec.load_spec` reads (no comments)."""
    parts = [f"name = {_value(spec.name)}\n"]
    for f in dataclasses.fields(spec):
        if f.name in ("name", "sources"):
            continue
        sec = getattr(spec, f.name)
        if f.name == "intake_valves":
            fields = _valves(sec, "intake")
        elif f.name == "exhaust_valves":
            fields = _valves(sec, "exhaust")
        else:
            fields = {g.name: getattr(sec, g.name) for g in dataclasses.fields(sec)}
        parts.append(_table(f.name, fields))
    if spec.sources:
        parts.append(_table("sources", {str(k): str(v) for k, v in spec.sources.items()}))
    return "\n".join(parts)
