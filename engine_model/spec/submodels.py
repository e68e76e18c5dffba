"""Constants of the sub-models: wall heat transfer, friction, knock, injector, ambient state, losses."""

from __future__ import annotations

from dataclasses import dataclass

from engine_model.spec.checks import check

__all__ = ["HeatTransferSpec", "FrictionSpec", "KnockSpec", "InjectorSpec", "AmbientSpec", "LossSpec", "ChargeSpec"]


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
        check(o, "woschni_coeff", self.woschni_coeff, 0.0, 20.0, lo_open=True)
        check(o, "c1_gas_exchange", self.c1_gas_exchange, 0.0, 20.0)
        check(o, "c1_closed", self.c1_closed, 0.0, 20.0)
        check(o, "c2_combustion", self.c2_combustion, 0.0, 0.05)
        check(o, "multiplier", self.multiplier, 0.0, 5.0)
        for n in ("head_temp_k", "piston_temp_k", "liner_temp_k"):
            check(o, n, getattr(self, n), 250.0, 900.0)
        check(o, "head_area_factor", self.head_area_factor, 1.0, 3.0)
        check(o, "piston_area_factor", self.piston_area_factor, 1.0, 3.0)


@dataclass(frozen=True)
class FrictionSpec:
    """Chen-Flynn friction: FMEP = A + B*p_max + C*Sp + D*Sp^2 (SI: Pa, -, Pa s/m, Pa s^2/m^2)."""

    a_pa: float
    b: float
    c_pa_s_per_m: float
    d_pa_s2_per_m2: float

    def __post_init__(self):
        o = "friction"
        check(o, "a_pa", self.a_pa, 0.0, 5e5)
        check(o, "b", self.b, 0.0, 0.1)
        check(o, "c_pa_s_per_m", self.c_pa_s_per_m, 0.0, 1e5)
        check(o, "d_pa_s2_per_m2", self.d_pa_s2_per_m2, 0.0, 1e4)


@dataclass(frozen=True)
class KnockSpec:
    """End-gas autoignition: Douaud-Eyzat ignition delay with dilution, integrated as a Livengood-Wu integral.

    tau = m_cal * A * (OI/100)^a * (p / 1 atm)^-n * exp(B / T_u) / (1 - x_b)^d; the knock index is
    the integral of 1/tau [1/s] over time from IVC until ``end_burn_fraction`` of the charge has
    burned (1 = autoignition before the end gas is consumed).  T_u: the cylinder temperature
    before the spark, then the variable-cp isentrope through the cylinder pressure from the
    state at the spark; x_b: burned-gas (residual and EGR) mass fraction of the charge at IVC.

    Attributes
    ----------
    research_octane, motor_octane : float
        RON and MON of the fuel [-]; their mean is the anti-knock index (R+M)/2.
    octane_sensitivity_k : float
        K of the octane index OI = RON - K (RON - MON) that enters the correlation
        (Kalghatgi 2001, SAE 2001-01-3584); K = 0.5 makes OI the anti-knock index,
        K = 0 the RON, K = 1 the MON.
    delay_coeff_s, octane_exponent, pressure_exponent, activation_temp_k : float
        A [s], a, n and B [K] of Douaud and Eyzat (1978, SAE 780080).
    dilution_exponent : float
        d [-]; 0 ignores burned gas in the end gas.
    end_burn_fraction : float
        Burned fraction at which the integral stops [-].
    delay_multiplier : float
        m_cal [-]: 1 for the literature constants; the knock calibration on bench data
        (:mod:`engine_model.knock`) writes its estimate here.
    cycle_ca50_advance_deg : float
        How much earlier than the mean cycle the fastest cycles that matter for knock
        burn [deg crank]: a spark is knock-free when the knock index stays below 1 with
        the burn advanced by this much (the calibration reads the bench the same way).
    """

    research_octane: float
    motor_octane: float
    octane_sensitivity_k: float
    delay_coeff_s: float
    octane_exponent: float
    pressure_exponent: float
    activation_temp_k: float
    dilution_exponent: float = 1.0
    end_burn_fraction: float = 0.9
    delay_multiplier: float = 1.0
    cycle_ca50_advance_deg: float = 3.0

    def __post_init__(self):
        o = "knock"
        check(o, "research_octane", self.research_octane, 40.0, 130.0)
        check(o, "motor_octane", self.motor_octane, 40.0, 130.0)
        if self.motor_octane > self.research_octane:
            raise ValueError(f"knock.motor_octane = {self.motor_octane!r} exceeds knock.research_octane = "
                             f"{self.research_octane!r}; a fuel's MON is not above its RON")
        check(o, "octane_sensitivity_k", self.octane_sensitivity_k, -2.0, 2.0)
        check(o, "delay_coeff_s", self.delay_coeff_s, 0.0, 1.0, lo_open=True)
        check(o, "octane_exponent", self.octane_exponent, 0.0, 10.0)
        check(o, "pressure_exponent", self.pressure_exponent, 0.0, 5.0)
        check(o, "activation_temp_k", self.activation_temp_k, 0.0, 20000.0)
        check(o, "dilution_exponent", self.dilution_exponent, 0.0, 5.0)
        check(o, "end_burn_fraction", self.end_burn_fraction, 0.5, 0.999)
        check(o, "delay_multiplier", self.delay_multiplier, 1e-3, 1e3)
        check(o, "cycle_ca50_advance_deg", self.cycle_ca50_advance_deg, 0.0, 15.0)

    @property
    def octane_index(self) -> float:
        """OI = RON - K (RON - MON) [-], the octane number the correlation uses."""
        return self.research_octane - self.octane_sensitivity_k * (self.research_octane - self.motor_octane)

    @property
    def anti_knock_index(self) -> float:
        """(RON + MON) / 2 [-]."""
        return 0.5 * (self.research_octane + self.motor_octane)

    @property
    def delay_coeff_effective_s(self) -> float:
        """m_cal * A * (OI/100)^a [s]: the pre-factor of the delay at 1 atm, 1/T = 0, no dilution."""
        return self.delay_multiplier * self.delay_coeff_s * (self.octane_index / 100.0) ** self.octane_exponent


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
        check(o, "static_flow_kg_s", self.static_flow_kg_s, 0.0, 0.1, lo_open=True)
        check(o, "dead_time_s", self.dead_time_s, 0.0, 0.01)
        check(o, "dead_time_ref_v", self.dead_time_ref_v, 6.0, 30.0)
        check(o, "dead_time_slope_s_per_v", self.dead_time_slope_s_per_v, -0.01, 0.0)


@dataclass(frozen=True)
class AmbientSpec:
    """Default test-cell state: pressure [Pa] and temperature [K]."""

    pressure_pa: float
    temperature_k: float

    def __post_init__(self):
        check("ambient", "pressure_pa", self.pressure_pa, 5e4, 1.2e5)
        check("ambient", "temperature_k", self.temperature_k, 230.0, 340.0)


@dataclass(frozen=True)
class LossSpec:
    """Extra losses on top of the base model; neutral defaults (the gap-diagnosis library switches them on).

    Parameters
    ----------
    combustion_efficiency : float
        Multiplier on the base model's combustion efficiency (``ChargeSpec``) [-]:
        the Wiebe burned fraction is scaled by it, the rest of the fresh mixture
        leaves unburned with the exhaust.  1 = the base model as calibrated.
    """

    combustion_efficiency: float = 1.0

    def __post_init__(self):
        check("losses", "combustion_efficiency", self.combustion_efficiency, 0.5, 1.0)


@dataclass(frozen=True)
class ChargeSpec:
    """What happens to the charge between the injector and the end of combustion (the base model's losses).

    Parameters
    ----------
    combustion_efficiency_lean : float
        Fraction of the fuel that burns at lambda >= 1 [-]: unburned hydrocarbons from crevices, oil-film
        absorption and wall quenching leave the rest unburned (Heywood 1988, sec. 4.9.4 and Fig. 4-22:
        0.95-0.98 for SI engines at stoichiometric and lean mixtures).
    combustion_efficiency_rich : float
        The same at lambda = 0.8 [-]; linear in lambda between 0.8 and 1, constant beyond.  The chemical
        loss of a rich mixture (CO and H2 in the products) is in the gas model already (water-gas shift
        products), so this is only what is left of the incomplete-combustion loss (Heywood Fig. 4-22: the
        gap below equilibrium grows by a few % from stoichiometric to phi = 1.25).
    fuel_latent_heat_j_per_kg : float
        Heat of vaporisation of the fuel [J/kg] (Heywood 1988, Table D.4: gasoline 350 kJ/kg).
    evaporation_from_charge : float
        Share of the latent heat that the evaporating port-injected fuel takes from the charge [-]; the rest
        comes from the port walls and the back of the intake valve, where most port-injected fuel lands
        (Heywood 1988, ch. 7, liquid fuel behaviour in the intake); the share is an assumption of this
        project within the 0.2-0.5 that charge-cooling estimates for port injection give.
    port_heat_transfer_multiplier : float
        Multiplier on the port wall heat-transfer coefficient (Dittus-Boelter at the port's flow) [-].
    """

    combustion_efficiency_lean: float = 0.975
    combustion_efficiency_rich: float = 0.955
    fuel_latent_heat_j_per_kg: float = 350.0e3
    evaporation_from_charge: float = 0.3
    port_heat_transfer_multiplier: float = 1.0

    def __post_init__(self):
        o = "charge"
        check(o, "combustion_efficiency_lean", self.combustion_efficiency_lean, 0.5, 1.0)
        check(o, "combustion_efficiency_rich", self.combustion_efficiency_rich, 0.5, 1.0)
        check(o, "fuel_latent_heat_j_per_kg", self.fuel_latent_heat_j_per_kg, 0.0, 2.0e6)
        check(o, "evaporation_from_charge", self.evaporation_from_charge, 0.0, 1.0)
        check(o, "port_heat_transfer_multiplier", self.port_heat_transfer_multiplier, 0.0, 10.0)

    def combustion_efficiency(self, lam: float) -> float:
        """Fraction of the trapped fuel that burns at excess-air ratio ``lam`` [-]."""
        if lam >= 1.0:
            return self.combustion_efficiency_lean
        x = max(lam, 0.8)
        return self.combustion_efficiency_rich + (self.combustion_efficiency_lean - self.combustion_efficiency_rich) \
            * (x - 0.8) / 0.2
