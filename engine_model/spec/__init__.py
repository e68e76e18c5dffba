"""Engine specification: frozen, validated dataclasses in SI units, loaded from TOML engine files.

    machine      Geometry, ValveSet
    paths        IntakeSpec, ExhaustSpec, GasExchangeSpec (1D pipes or lumped runners)
    submodels    HeatTransferSpec, FrictionSpec, KnockSpec, InjectorSpec, AmbientSpec, ChargeSpec, LossSpec
    engine       EngineSpec, load_spec, default_spec, spec_from_dict

An :class:`EngineSpec` is built from a TOML file (see ``engine_model/engines/``) whose keys carry their unit
in the name (``bore_m``, ``volume_m3``, ``timing_deg``) and whose comments give the source of every constant.
All validation happens at construction and names the field, the value and the allowed range; an unknown
key or section is refused with the nearest valid name.

Crank-angle convention: degrees, 0 = firing TDC of the cylinder, ATDC positive, one cycle spans 720 deg.
Valve events are given as on a timing diagram (opening BTDC / closing ABDC and so on) and converted to
cycle angles in [0, 720).
"""

from engine_model.spec.engine import DEFAULT_ENGINE, SECTIONS, EngineSpec, default_spec, load_spec, spec_from_dict
from engine_model.spec.machine import Geometry, ValveSet
from engine_model.spec.paths import GAS_EXCHANGE_MODELS, ExhaustSpec, GasExchangeSpec, IntakeSpec
from engine_model.spec.submodels import (AmbientSpec, ChargeSpec, FrictionSpec, HeatTransferSpec, InjectorSpec,
                                         KnockSpec, LossSpec)

__all__ = ["DEFAULT_ENGINE", "SECTIONS", "EngineSpec", "default_spec", "load_spec", "spec_from_dict", "Geometry",
           "ValveSet", "GAS_EXCHANGE_MODELS", "ExhaustSpec", "GasExchangeSpec", "IntakeSpec", "AmbientSpec",
           "ChargeSpec", "FrictionSpec", "HeatTransferSpec", "InjectorSpec", "KnockSpec", "LossSpec"]
