"""Library of candidate unmodelled effects for the sim-to-real gap diagnosis.

Each :class:`Effect` is a switchable sub-model of the simulator or of the
measurement chain with one or two physically meaningful parameters.  Every
parameter has a *neutral* value (the effect is off: the base model), a
documented physical range, a *realistic* magnitude (what the benchmark plants)
and a source.

Two hooks put effects into a simulation:

* :func:`apply_effects` (before ``simulate``) changes the operating-point table:
  it adds ``spec.<section>.<field>`` override columns (``simulate`` applies them
  per row) or changes inputs such as spark advance or the ambient state;
* :func:`post_effects` (after ``simulate``) changes what the bench would
  *measure*: transmission losses on the torque read behind the gearbox, the
  water vapour carried through the air-flow meter.

``post_effects`` expects the results of ``simulate`` on the table that
``apply_effects`` returned (it reads the echoed inputs), with the torque as the
dyno reads it, i.e. the base transmission efficiency ``ETA_TRANS_BASE``
already applied (the bench contract: torque behind the gearbox).

Example
-------
>>> from engine_model.effects import apply_effects, post_effects
>>> fx = {"heat_transfer": {"factor": 1.3}, "transmission_efficiency": {"eta": 0.92}}
>>> pts = apply_effects(points, fx)            # doctest: +SKIP
>>> res = post_effects(simulate(spec, pts), fx)  # doctest: +SKIP
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
import pandas as pd

from engine_model.spec import EngineSpec, default_spec

__all__ = ["EffectParam", "Effect", "EFFECTS", "ETA_TRANS_BASE", "get_effect", "check_effects",
           "apply_effects", "post_effects", "effect_names"]

#: Transmission efficiency the base model assumes between crank and dyno [-]
#: (the paper's assumption, reference paper sec. 4).
ETA_TRANS_BASE = 0.95


@dataclass(frozen=True)
class EffectParam:
    """One parameter of a candidate effect.

    Parameters
    ----------
    name : str
        Parameter name (key in the effects dict).
    unit : str
        Unit of the value ('-' for dimensionless).
    neutral : float
        Value meaning "no effect" (the base model).
    lo, hi : float
        Documented physical range (inclusive); values outside raise ValueError.
    realistic : float
        A realistic magnitude (what the gap benchmark plants).
    doc : str
        What the parameter means and where its range comes from.
    """

    name: str
    unit: str
    neutral: float
    lo: float
    hi: float
    realistic: float
    doc: str

    def __post_init__(self):
        if not (self.lo <= self.neutral <= self.hi and self.lo <= self.realistic <= self.hi):
            raise ValueError(f"EffectParam {self.name}: neutral {self.neutral} and realistic {self.realistic} "
                             f"must lie in [{self.lo}, {self.hi}]")
        if self.realistic == self.neutral:
            raise ValueError(f"EffectParam {self.name}: realistic magnitude equals the neutral value")


@dataclass(frozen=True)
class Effect:
    """A candidate unmodelled effect.

    Parameters
    ----------
    name : str
        Registry key.
    description : str
        What is physically missing from the base model.
    params : tuple of EffectParam
        One or two parameters.
    source : str
        Citation for the model form and the ranges.
    stage : str
        'model' (changes the simulation inputs, :func:`apply_effects`) or
        'measurement' (changes what the bench reads, :func:`post_effects`), or
        'both'.
    expect : tuple of (str, int)
        Documented direction of the change at the realistic magnitude: output
        column and sign (+1 up, -1 down, 0 changes with a sign that varies over
        the map) of the mean change over wide-open-throttle points at 6000,
        9000 and 12000 rpm with the MBT spark prior.
    """

    name: str
    description: str
    params: tuple[EffectParam, ...]
    source: str
    stage: str
    expect: tuple[tuple[str, int], ...] = ()

    def param(self, name: str) -> EffectParam:
        for p in self.params:
            if p.name == name:
                return p
        raise ValueError(f"effect {self.name!r}: no parameter {name!r}; valid: {[p.name for p in self.params]}")

    def neutral(self) -> dict[str, float]:
        """Parameter values of the switched-off effect."""
        return {p.name: p.neutral for p in self.params}

    def realistic(self) -> dict[str, float]:
        """Parameter values at the realistic magnitude."""
        return {p.name: p.realistic for p in self.params}

    def at_magnitude(self, scale: float) -> dict[str, float]:
        """Parameters at ``neutral + scale * (realistic - neutral)`` (scale 1 = realistic), clipped to the range."""
        return {p.name: float(np.clip(p.neutral + scale * (p.realistic - p.neutral), p.lo, p.hi))
                for p in self.params}


def _p(name, unit, neutral, lo, hi, realistic, doc):
    return EffectParam(name, unit, float(neutral), float(lo), float(hi), float(realistic), doc)


_HEYWOOD = "Heywood, Internal Combustion Engine Fundamentals, McGraw-Hill 1988"

EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect(
        "transmission_efficiency",
        "The gearbox/chain between crank and dyno loses a different fraction of the torque than the "
        "assumed eta_trans = 0.95 (constant efficiency).",
        (_p("eta", "-", ETA_TRANS_BASE, 0.85, 0.99, 0.91,
            "crank-to-dyno efficiency; 0.85-0.99 covers a wet multi-plate clutch, a sequential gearbox "
            "in one gear and a roller chain"),),
        "Reference paper sec. 4 (eta_trans assumed 0.95); gear mesh 0.98-0.99 per stage, chain 0.97-0.98: "
        "Naunheimer et al., Automotive Transmissions, Springer 2011, ch. 3.",
        "measurement", (("brake_torque_nm", -1),)),
    Effect(
        "transmission_speed_loss",
        "Speed-dependent transmission loss (oil churning, windage, chain): the efficiency falls "
        "linearly with engine speed, eta = eta_base (1 - k n/1000 rpm).",
        (_p("k_per_krpm", "1/krpm", 0.0, 0.0, 0.01, 0.004,
            "relative efficiency drop per 1000 rpm; 0.004 gives 4.8 % at 12000 rpm, the order of the "
            "churning losses of a splash-lubricated motorcycle gearbox"),),
        "Naunheimer et al., Automotive Transmissions, Springer 2011, ch. 3 (load-independent losses "
        "grow with speed).",
        "measurement", (("brake_torque_nm", -1),)),
    Effect(
        "runner_inertia",
        "Intake gas inertia / wave tuning: the model misjudges the acoustic length of the intake runner "
        "(end corrections, taper, the port's share), so the ram/tuning peak sits at another speed or height.",
        (_p("factor", "-", 1.0, 0.3, 2.0, 0.7,
            "multiplier on the runner's acoustic length (1D pipes) or gas inertance L/A (lumped runners), "
            "spec intake.runner_inertance_factor; 0.3-2 brackets end corrections and tapered runners"),),
        f"{_HEYWOOD}, sec. 7.6 (ram and tuning effects); Winterbone & Pearson, Design Techniques for "
        "Engine Manifolds, 1999, ch. 2 (effective length of a pipe).",
        "model", (("air_mass_flow_kg_h", 0), ("brake_torque_nm", 0))),
    Effect(
        "heat_transfer",
        "In-cylinder heat-transfer level differs from Woschni as published (combustion-chamber shape, "
        "squish, deposits).",
        (_p("factor", "-", 1.0, 0.5, 2.0, 1.3,
            "multiplier on the Woschni coefficient (spec heat_transfer.multiplier); Woschni scatters "
            "by a factor ~1.5 between engines"),),
        f"Woschni, SAE 670931 (1967); {_HEYWOOD}, sec. 12.4.",
        "model", (("brake_torque_nm", -1), ("exhaust_temp_k", -1))),
    Effect(
        "friction",
        "Friction level and speed slope differ from the Chen-Flynn constants of the spec "
        "(FMEP = A + B pmax + C Sp + D Sp^2).",
        (_p("delta_a_bar", "bar", 0.0, -0.3, 0.8, 0.2,
            "change of the constant FMEP term A; the base A is 0.40 bar"),
         _p("delta_c_bar_s_per_m", "bar s/m", 0.0, -0.05, 0.08, 0.02,
            "change of the mean-piston-speed term C; the base C is 0.09 bar/(m/s)")),
        f"Chen & Flynn, SAE 650733 (1965); {_HEYWOOD}, sec. 13.6 (FMEP of SI engines 1-3 bar at "
        "high speed).",
        "model", (("brake_torque_nm", -1),)),
    Effect(
        "combustion_efficiency",
        "Incomplete combustion: a fraction of the trapped fuel leaves unburned (HC, CO beyond "
        "the rich-mixture products the model accounts for).",
        (_p("eta", "-", 1.0, 0.85, 1.0, 0.96,
            "fraction of the fuel burned (spec losses.combustion_efficiency); SI engines 0.95-0.98"),),
        f"{_HEYWOOD}, sec. 3.5.5 and Fig. 3-9.",
        "model", (("brake_torque_nm", -1), ("exhaust_temp_k", -1))),
    Effect(
        "blowby",
        "Blow-by and crevice loss: charge escaping past the rings or hiding in crevices during "
        "combustion.  The leaked mass per cycle scales with the time available, i.e. 1/speed.  "
        "Approximation (no cylinder leak in the kernel): the leaked fraction of the charge energy "
        "is lost, modelled as a speed-dependent combustion efficiency 1 - f (6000 rpm / N); the "
        "lower compression pressure of a real leak is not modelled.",
        (_p("fraction_at_6000", "-", 0.0, 0.0, 0.05, 0.02,
            "blow-by/crevice fraction of the charge at 6000 rpm; normal engines 0.5-1.5 %, worn "
            "rings several %"),),
        f"{_HEYWOOD}, sec. 8.6 (crevice flow and blow-by: 0.5-1 % of the charge, more at low speed).",
        "model", (("brake_torque_nm", -1),)),
    Effect(
        "restrictor",
        "The 20 mm restrictor passes a different flow: discharge coefficient of the throat and "
        "pressure recovery of the diffuser differ from the spec.",
        (_p("cd_factor", "-", 1.0, 0.85, 1.03, 0.96,
            "multiplier on intake.restrictor_cd (base 0.97); the product must stay <= 1"),
         _p("recovery_delta", "-", 0.0, -0.4, 0.1, -0.15,
            "change of intake.restrictor_recovery (base 0.85); short or separated diffusers "
            "recover 0.5-0.7")),
        "ISO 5167-4 (venturi discharge coefficients 0.95-0.995); White, Fluid Mechanics, sec. 6.11 "
        "(diffuser recovery).",
        "model", (("air_mass_flow_kg_h", -1), ("brake_torque_nm", -1))),
    Effect(
        "exhaust_back_pressure",
        "The silencer/tailpipe restricts more (or less) than the spec's effective outlet area.",
        (_p("area_factor", "-", 1.0, 0.3, 2.0, 0.6,
            "multiplier on exhaust.tailpipe_cd (effective outlet area); 0.6 roughly triples the "
            "back pressure at a given flow"),),
        f"{_HEYWOOD}, sec. 6.5 (exhaust back pressure lowers volumetric efficiency via residuals); "
        "with 1D pipes the outlet restriction also changes the tailpipe reflection, so the airflow "
        "moves up at some speeds and down at others (tuning), while the pumping loss always grows.",
        "model", (("air_mass_flow_kg_h", 0), ("brake_torque_nm", -1))),
    Effect(
        "intake_air_temperature",
        "The air entering the throttle is warmer than the cell temperature the model uses (engine-bay "
        "or radiator heat pick-up, sensor placement).",
        (_p("delta_t_k", "K", 0.0, -10.0, 40.0, 12.0,
            "charge temperature minus the modelled ambient temperature; tens of K in a closed bay"),),
        f"{_HEYWOOD}, sec. 6.2.1 (volumetric efficiency ~ T^-1/2 for choked/quasi-steady flow).",
        "model", (("air_mass_flow_kg_h", -1), ("brake_torque_nm", -1))),
    Effect(
        "humidity",
        "Water vapour in the intake air displaces oxygen; the model assumes dry air.  Approximation "
        "through the ambient state: the engine breathes dry air at the dry-air partial pressure "
        "p - p_v (vapour treated as an inert that takes volume), and the air-flow meter reads the "
        "moist mass flow, dry flow x (1 + humidity ratio).",
        (_p("relative_humidity", "-", 0.0, 0.0, 1.0, 0.7,
            "relative humidity of the intake air at its temperature; p_v = RH p_sat(T), Magnus "
            "formula (Alduchov & Eskridge 1996)"),),
        "SAE J1349 (power correction uses the dry-air pressure); Alduchov & Eskridge, J. Appl. "
        "Meteor. 35 (1996) 601 (Magnus coefficients 17.625, 243.04 C, 610.94 Pa).",
        "both", (("brake_torque_nm", -1), ("fuel_mass_flow_kg_h", -1))),
    Effect(
        "knock_retard",
        "Non-MBT, knock-limited spark: the ECU (or the knock controller) retards spark at high load "
        "and low speed, so the spark the engine gets is later than the one logged.  Retard = R w_load "
        "w_speed, w_load rising 0->1 from 50 to 90 % throttle, w_speed = clip((11000 - N)/5000, 0.2, 1).",
        (_p("retard_deg", "deg", 0.0, 0.0, 12.0, 5.0,
            "maximal retard at WOT and low speed [deg CA]"),),
        f"{_HEYWOOD}, sec. 9.6 (knock limit at high load, low speed); Zhen et al., Appl. Energy 2012 "
        "(knock control retards 2-10 deg).",
        "model", (("exhaust_temp_k", 1),)),
)}


def effect_names() -> list[str]:
    """Names of all effects in the library."""
    return list(EFFECTS)


def get_effect(name: str) -> Effect:
    """The :class:`Effect` called ``name``; ValueError listing the valid names otherwise."""
    try:
        return EFFECTS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown effect {name!r}; valid effects: {sorted(EFFECTS)}") from None


def check_effects(effects: Mapping[str, Mapping[str, float]] | None) -> dict[str, dict[str, float]]:
    """Validate an effects dict ``{effect: {param: value}}``; return it complete (missing params neutral).

    Raises
    ------
    ValueError
        Unknown effect or parameter, a non-finite value, or a value outside the
        documented range (the message names effect, parameter, value and range).
    """
    out: dict[str, dict[str, float]] = {}
    for name, params in (effects or {}).items():
        eff = get_effect(name)
        if params is None:
            params = {}
        if not isinstance(params, Mapping):
            raise ValueError(f"effect {name!r}: parameters must be a dict {{name: value}}, got {params!r}")
        vals = eff.neutral()
        for pname, v in params.items():
            p = eff.param(pname)
            try:
                x = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"effect {name!r}, parameter {pname!r}: expected a number, got {v!r}") from None
            if not (math.isfinite(x) and p.lo <= x <= p.hi):
                raise ValueError(f"effect {name!r}, parameter {pname!r} = {v!r} [{p.unit}] is outside the "
                                 f"documented range [{p.lo:g}, {p.hi:g}]")
            vals[pname] = x
        out[name] = vals
    return out


# --------------------------------------------------------------------------- model-side hooks

def _spec_value(df: pd.DataFrame, spec: EngineSpec, key: str) -> np.ndarray:
    """Current value of spec field ``key`` per row: the override column if present, else the spec."""
    col = "spec." + key
    if col in df.columns:
        return pd.to_numeric(df[col], errors="coerce").to_numpy(float)
    section, _, field = key.partition(".")
    return np.full(len(df), float(getattr(getattr(spec, section), field)))


def _scale_spec(df, spec, key, factor):
    df["spec." + key] = _spec_value(df, spec, key) * factor


def _shift_spec(df, spec, key, delta):
    df["spec." + key] = _spec_value(df, spec, key) + delta


def _col(df: pd.DataFrame, name: str, default: float) -> np.ndarray:
    if name in df.columns:
        return pd.to_numeric(df[name], errors="coerce").to_numpy(float)
    return np.full(len(df), float(default))


def saturation_pressure_pa(t_k):
    """Saturation pressure of water vapour over water [Pa] (Magnus form, Alduchov & Eskridge 1996)."""
    tc = np.asarray(t_k, dtype=float) - 273.15
    return 610.94 * np.exp(17.625 * tc / (tc + 243.04))


def knock_retard_weight(speed_rpm, throttle_pct):
    """Weight 0..1 of the knock-limited spark retard over the map (see the ``knock_retard`` effect)."""
    w_load = np.clip((np.asarray(throttle_pct, float) - 50.0) / 40.0, 0.0, 1.0)
    w_speed = np.clip((11000.0 - np.asarray(speed_rpm, float)) / 5000.0, 0.2, 1.0)
    return w_load * w_speed


def _apply_runner_inertia(df, spec, v):
    _scale_spec(df, spec, "intake.runner_inertance_factor", v["factor"])


def _apply_heat_transfer(df, spec, v):
    _scale_spec(df, spec, "heat_transfer.multiplier", v["factor"])


def _apply_friction(df, spec, v):
    _shift_spec(df, spec, "friction.a_pa", 1e5 * v["delta_a_bar"])
    _shift_spec(df, spec, "friction.c_pa_s_per_m", 1e5 * v["delta_c_bar_s_per_m"])


def _apply_combustion_efficiency(df, spec, v):
    _scale_spec(df, spec, "losses.combustion_efficiency", v["eta"])


def _apply_blowby(df, spec, v):
    n = pd.to_numeric(df["speed_rpm"], errors="coerce").to_numpy(float)
    loss = np.clip(v["fraction_at_6000"] * 6000.0 / n, 0.0, 0.3)
    _scale_spec(df, spec, "losses.combustion_efficiency", 1.0 - loss)


def _apply_restrictor(df, spec, v):
    _scale_spec(df, spec, "intake.restrictor_cd", v["cd_factor"])
    _shift_spec(df, spec, "intake.restrictor_recovery", v["recovery_delta"])


def _apply_exhaust_back_pressure(df, spec, v):
    _scale_spec(df, spec, "exhaust.tailpipe_cd", v["area_factor"])


def _apply_intake_air_temperature(df, spec, v):
    df["t_amb_k"] = _col(df, "t_amb_k", spec.ambient.temperature_k) + v["delta_t_k"]


def _apply_humidity(df, spec, v):
    p = _col(df, "p_amb_pa", spec.ambient.pressure_pa)
    t = _col(df, "t_amb_k", spec.ambient.temperature_k)
    pv = v["relative_humidity"] * saturation_pressure_pa(t)
    df["p_amb_pa"] = p - pv
    df["gap_vapour_pressure_pa"] = _col(df, "gap_vapour_pressure_pa", 0.0) + pv


def _apply_knock_retard(df, spec, v):
    w = knock_retard_weight(df["speed_rpm"], df["throttle_pct"])
    df["spark_deg_btdc"] = pd.to_numeric(df["spark_deg_btdc"], errors="coerce").to_numpy(float) \
        - v["retard_deg"] * w


_APPLY: dict[str, Callable] = {
    "runner_inertia": _apply_runner_inertia,
    "heat_transfer": _apply_heat_transfer,
    "friction": _apply_friction,
    "combustion_efficiency": _apply_combustion_efficiency,
    "blowby": _apply_blowby,
    "restrictor": _apply_restrictor,
    "exhaust_back_pressure": _apply_exhaust_back_pressure,
    "intake_air_temperature": _apply_intake_air_temperature,
    "humidity": _apply_humidity,
    "knock_retard": _apply_knock_retard,
}


# --------------------------------------------------------------------------- measurement-side hooks

def _scale_torque(df: pd.DataFrame, factor: np.ndarray) -> None:
    for c in ("brake_torque_nm", "brake_power_kw"):
        if c in df.columns:
            df[c] = pd.to_numeric(df[c], errors="coerce").to_numpy(float) * factor
    if "bsfc_g_kwh" in df.columns:
        df["bsfc_g_kwh"] = pd.to_numeric(df["bsfc_g_kwh"], errors="coerce").to_numpy(float) / factor


def _post_transmission_efficiency(df, v, eta_base, spec):
    _scale_torque(df, np.full(len(df), v["eta"] / eta_base))


def _post_transmission_speed_loss(df, v, eta_base, spec):
    n = pd.to_numeric(df["speed_rpm"], errors="coerce").to_numpy(float)
    _scale_torque(df, 1.0 - v["k_per_krpm"] * n / 1000.0)


def _post_humidity(df, v, eta_base, spec):
    # the meter reads the moist mass: dry flow x (1 + humidity ratio), humidity
    # ratio = (M_w / M_a) p_v / p_dry = 0.622 p_v / p_dry.  Works on simulate's
    # output of the apply_effects table (vapour pressure column present) and on
    # a bench table built from the original plan (cell state from its columns
    # or the spec); the two differ only in second-order terms.
    if "gap_vapour_pressure_pa" in df.columns and "p_amb_pa" in df.columns:
        pv = pd.to_numeric(df["gap_vapour_pressure_pa"], errors="coerce").to_numpy(float)
        pdry = pd.to_numeric(df["p_amb_pa"], errors="coerce").to_numpy(float)
    else:
        t = _col(df, "t_amb_k", spec.ambient.temperature_k)
        pv = v["relative_humidity"] * saturation_pressure_pa(t)
        pdry = _col(df, "p_amb_pa", spec.ambient.pressure_pa) - pv
    if "air_mass_flow_kg_h" in df.columns:
        df["air_mass_flow_kg_h"] = pd.to_numeric(df["air_mass_flow_kg_h"], errors="coerce").to_numpy(float) \
            * (1.0 + 0.622 * pv / pdry)


_POST: dict[str, Callable] = {
    "transmission_efficiency": _post_transmission_efficiency,
    "transmission_speed_loss": _post_transmission_speed_loss,
    "humidity": _post_humidity,
}


def _is_neutral(name: str, vals: dict[str, float]) -> bool:
    eff = EFFECTS[name]
    return all(vals[p.name] == p.neutral for p in eff.params)


def apply_effects(points: pd.DataFrame, effects: Mapping[str, Mapping[str, float]] | None,
                  spec: EngineSpec | None = None) -> pd.DataFrame:
    """Put the model-side effects into an operating-point table.

    Parameters
    ----------
    points : DataFrame
        Operating points as for ``simulate`` (``speed_rpm, throttle_pct,
        spark_deg_btdc, ...``).  Existing ``spec.*`` override columns, ambient
        columns and spark are taken as the base the effects act on.
    effects : dict
        ``{effect_name: {param: value}}``; missing parameters are neutral.
    spec : EngineSpec, optional
        The engine the table is for (default: the embedded R6); spec values
        that an effect scales are read from it when the table has no override.

    Returns
    -------
    DataFrame
        A copy with ``spec.<section>.<field>`` columns, ``t_amb_k``,
        ``p_amb_pa`` or ``spark_deg_btdc`` changed; measurement-chain effects
        are left to :func:`post_effects`.

    Raises
    ------
    ValueError
        Unknown effect/parameter or a value out of its documented range.
    """
    vals = check_effects(effects)
    spec = default_spec() if spec is None else spec
    df = points.copy()
    # humidity first: its vapour pressure belongs to the cell temperature, before any intake heating
    for name in sorted(vals, key=lambda n: n != "humidity"):
        if name in _APPLY and not _is_neutral(name, vals[name]):
            _APPLY[name](df, spec, vals[name])
    return df


def post_effects(results: pd.DataFrame, effects: Mapping[str, Mapping[str, float]] | None,
                 eta_base: float = ETA_TRANS_BASE, spec: EngineSpec | None = None) -> pd.DataFrame:
    """Put the measurement-chain effects into simulated results.

    Parameters
    ----------
    results : DataFrame
        ``simulate`` output on the table :func:`apply_effects` returned, with
        ``brake_torque_nm`` as the dyno reads it (``eta_base`` applied).
    effects : dict
        ``{effect_name: {param: value}}``, the same dict given to apply_effects.
    eta_base : float
        Transmission efficiency already applied to the torque [-].
    spec : EngineSpec, optional
        For the cell state when the table has no ambient columns (default R6).

    Returns
    -------
    DataFrame
        A copy with torque, power and BSFC (transmission effects) and air flow
        (humidity) as measured.
    """
    vals = check_effects(effects)
    if any(name in _POST and not _is_neutral(name, v) for name, v in vals.items()):
        spec = default_spec() if spec is None else spec
    df = results.copy()
    for name, v in vals.items():
        if name in _POST and not _is_neutral(name, v):
            _POST[name](df, v, eta_base, spec)
    return df
