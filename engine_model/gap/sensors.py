"""Sensor faults as candidates of the gap diagnosis: an offset and a gain error on one measured channel.

A fault of one instrument changes what one channel reads and nothing else: the engine, and every other
channel, are untouched.  That is its signature, and it needs no simulation:

    reading = (1 + gain_pct / 100) * true value + offset,

so the sensitivity of the reading to the offset is 1 and to the gain is ``true value / 100`` (taken at
the model's reference).  :func:`with_sensor_faults` appends these columns to a
:class:`~engine_model.gap.linear.Linearisation`, and the diagnosis ranks ``sensor_<channel>`` beside
the physical effects of :mod:`engine_model.effects`.

Ranges and realistic sizes (1 sigma of the bench's own uncertainty is in
:data:`engine_model.gap.residuals.UNCERTAINTY`):

* exhaust temperature: offset +-60 K, realistic 20 K.  A class-2 type-K thermocouple may read 0.75 % of
  the temperature off (IEC 60584-1, ~8 K at 1050 K); radiation to the cooler port wall and a probe
  tip not in the core flow add tens of kelvin (Heywood 1988, sec. 6.6, on exhaust-temperature
  measurement).  Gain +-5 %.
* airflow: gain +-6 %, realistic 3 %; offset +-6 kg/h.  Hot-film and laminar-flow element meters are
  specified to 1-2 % of reading when clean and calibrated; pulsation from a single-cylinder-like
  intake of a restricted engine and contamination shift them by several percent.
* fuel flow: gain +-6 %, realistic 3 %; offset +-1 kg/h (Coriolis meters: 0.1-0.5 % of reading when
  zeroed; a stale zero or a return-line leak gives an offset).
* brake torque: no candidate.  A torque-meter offset reads exactly like a change of the friction level
  (a constant FMEP is a constant torque), and a gain error exactly like a change of the transmission
  efficiency (brake torque = eta x engine torque); both are in the library, and a second, identical
  candidate could only split the vote.  The verdict says so when it names either.

BSFC is derived from fuel flow and torque and gets no fault of its own.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from engine_model.effects import EFFECTS, Effect, EffectParam

__all__ = ["SENSOR_FAULTS", "SENSOR_PREFIX", "sensor_name", "is_sensor", "sensor_channel", "candidate",
           "with_sensor_faults", "SENSOR_STAGE"]

SENSOR_PREFIX = "sensor_"

#: Energy-chain stage label of the sensor candidates.
SENSOR_STAGE = "measurement (one channel)"

_SOURCE = ("IEC 60584-1 thermocouple tolerance classes; flow- and torque-meter accuracy classes of "
           "manufacturer data sheets; Heywood 1988 sec. 6.6 (exhaust temperature measurement)")

# channel: (offset unit, offset range, offset realistic, gain range [%] or None, gain realistic [%])
_CHANNELS = {
    "exhaust_temp_k": ("K", 60.0, 20.0, 5.0, 2.0),
    "air_mass_flow_kg_h": ("kg/h", 6.0, 2.0, 6.0, 3.0),
    "fuel_mass_flow_kg_h": ("kg/h", 1.0, 0.3, 6.0, 3.0),
}


def sensor_name(channel: str) -> str:
    """Candidate name of a fault on bench column ``channel``."""
    return SENSOR_PREFIX + channel


def is_sensor(name: str | None) -> bool:
    return bool(name) and str(name).startswith(SENSOR_PREFIX)


def sensor_channel(name: str) -> str:
    """Bench column of sensor candidate ``name``."""
    return str(name)[len(SENSOR_PREFIX):]


def _fault(channel: str) -> Effect:
    unit, o_rng, o_real, g_rng, g_real = _CHANNELS[channel]
    params = (EffectParam("offset", unit, 0.0, -o_rng, o_rng, o_real, f"reading minus true value at zero [{unit}]"),)
    if g_rng is not None:
        params += (EffectParam("gain_pct", "%", 0.0, -g_rng, g_rng, g_real, "reading / true value - 1 [%]"),)
    return Effect(
        name=sensor_name(channel),
        description=f"{'offset and gain' if g_rng else 'offset'} error of the {channel} reading (no change to "
                    "the engine)",
        params=params,
        source=_SOURCE, stage="measurement", expect=((channel, 0),))


#: One fault candidate per channel the bench contract measures directly.
SENSOR_FAULTS: dict[str, Effect] = {sensor_name(c): _fault(c) for c in _CHANNELS}


def candidate(name: str) -> Effect:
    """The effect or sensor fault called ``name``.

    Raises
    ------
    ValueError
        Naming the valid candidates.
    """
    if name in EFFECTS:
        return EFFECTS[name]
    if name in SENSOR_FAULTS:
        return SENSOR_FAULTS[name]
    raise ValueError(f"unknown effect {name!r} (nor a sensor fault); valid: {sorted(EFFECTS) + sorted(SENSOR_FAULTS)}")


def with_sensor_faults(lin, channels=None):
    """``lin`` with an offset and a gain column per measured channel appended (no simulation).

    Parameters
    ----------
    lin : Linearisation
    channels : sequence of str, optional
        Bench columns to give a fault candidate (default: every output of ``lin`` that has one).
        Channels already present are not added twice.

    Returns
    -------
    Linearisation
        Columns ``(sensor_<channel>, 'offset')`` [output unit] and ``(sensor_<channel>, 'gain_pct')``
        [%], finite-difference steps at their realistic sizes, sensitivities exact (the fault is linear).
    """
    chans = [c for c in (lin.outputs if channels is None else channels) if c in _CHANNELS and c in lin.outputs]
    have = set(lin.effect_names())
    chans = [c for c in chans if sensor_name(c) not in have]
    if not chans:
        return lin
    n, o, _ = lin.jac.shape
    cols, steps, extra = list(lin.columns), list(lin.steps), []
    for c in chans:
        k = lin.outputs.index(c)
        eff = SENSOR_FAULTS[sensor_name(c)]
        for prm in eff.params:
            col = np.zeros((n, o))
            col[:, k] = 1.0 if prm.name == "offset" else lin.y_ref[:, k] / 100.0
            extra.append(np.where(np.isfinite(col), col, 0.0))
            cols.append((eff.name, prm.name))
            steps.append(prm.realistic)
    jac = np.concatenate([lin.jac, np.stack(extra, axis=2)], axis=2)
    neutral = None if lin.neutral is None else np.concatenate([np.asarray(lin.neutral, float),
                                                                np.zeros(len(extra))])
    return replace(lin, columns=cols, steps=np.asarray(steps, float), jac=jac, neutral=neutral)
