"""Injector pulse width from airflow, speed and target lambda (sequential port injection)."""

from __future__ import annotations

import numpy as np

from engine_model import thermo
from engine_model.spec import EngineSpec

__all__ = ["injection_time_ms"]


def injection_time_ms(air_mass_flow_kg_h, speed_rpm, lam, spec: EngineSpec, battery_v: float = 14.0):
    """Injector pulse width [ms] for one injection per cylinder per cycle (sequential injection).

    Parameters
    ----------
    air_mass_flow_kg_h : array_like
        Engine air mass flow [kg/h].
    speed_rpm : array_like
        Engine speed [rpm].
    lam : array_like
        Target excess-air ratio [-].
    spec : EngineSpec
        ``geometry.n_cylinders``, ``fuel`` (stoichiometric AFR), ``injector``.
    battery_v : float
        Battery voltage [V].

    Returns
    -------
    dict of ndarray
        ``air_mg`` (per cylinder per cycle), ``fuel_mg``, ``dead_time_ms``,
        ``injection_time_ms``, ``duty_pct`` (of the 720 deg cycle).

    Notes
    -----
    ``m_air = Ga / (N/120) / z``, ``m_fuel = m_air / (lambda AFR_st)``,
    ``t = m_fuel / (k q_static) + t_dead(U)``, ``t_dead(U) = t_dead,ref +
    s (U - U_ref)`` (clipped at 0), with ``k`` injectors per cylinder.
    """
    inj = spec.injector
    ga = np.asarray(air_mass_flow_kg_h, float) / 3600.0
    n = np.asarray(speed_rpm, float)
    cycles_per_s = n / 120.0
    air = ga / cycles_per_s / spec.geometry.n_cylinders
    fuel = air / (np.asarray(lam, float) * thermo.stoich_afr(spec.fuel))
    dead = max(0.0, inj.dead_time_s + inj.dead_time_slope_s_per_v * (battery_v - inj.dead_time_ref_v))
    t = fuel / (inj.per_cylinder * inj.static_flow_kg_s) + dead
    return {"air_mg": air * 1e6, "fuel_mg": fuel * 1e6, "dead_time_ms": np.full_like(t, dead * 1e3),
            "injection_time_ms": t * 1e3, "duty_pct": t * cycles_per_s * 100.0}
