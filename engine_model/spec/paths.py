"""The gas paths: intake and exhaust geometry, and how the gas exchange is modelled."""

from __future__ import annotations

from dataclasses import dataclass

from engine_model.spec.checks import check, check_segments

__all__ = ["IntakeSpec", "ExhaustSpec", "GasExchangeSpec", "GAS_EXCHANGE_MODELS"]


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
    ``runner_inertia``, ``runner_volume_at_port`` and ``runner_segments`` are
    settings of the lumped gas exchange only; the 1D model resolves the runner as
    a pipe (``GasExchangeSpec``).  ``runner_inertance_factor`` (1 = as built) is a
    model-error multiplier for studies of unmodelled wave action: on the lumped
    runner's gas inertance L/A, and on the 1D runner's acoustic length (its
    pipe is that much longer or shorter than ``runner_length_m``).
    ``wall_temp_k`` is the runner wall temperature (1D wall heat transfer) and
    ``port_wall_temp_k`` the intake port's (port heat transfer, both models).
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
    port_wall_temp_k: float = 380.0

    def __post_init__(self):
        o = "intake"
        check(o, "throttle_bore_m", self.throttle_bore_m, 0.0, 0.2, lo_open=True)
        check(o, "throttle_shaft_m", self.throttle_shaft_m, 0.0, self.throttle_bore_m / 2, hi_open=True)
        check(o, "throttle_closed_deg", self.throttle_closed_deg, 0.0, 20.0)
        check(o, "throttle_cd", self.throttle_cd, 0.0, 1.0, lo_open=True)
        check(o, "throttle_body_volume_m3", self.throttle_body_volume_m3, 0.0, 0.05, lo_open=True)
        check(o, "restrictor_throat_m", self.restrictor_throat_m, 0.0, 0.2, lo_open=True)
        check(o, "restrictor_cd", self.restrictor_cd, 0.0, 1.0, lo_open=True)
        check(o, "restrictor_recovery", self.restrictor_recovery, 0.0, 0.98)
        check(o, "plenum_volume_m3", self.plenum_volume_m3, 0.0, 0.1, lo_open=True)
        check(o, "runner_length_m", self.runner_length_m, 0.0, 2.0, lo_open=True)
        check(o, "runner_diameter_m", self.runner_diameter_m, 0.0, 0.2, lo_open=True)
        check(o, "runner_loss_k", self.runner_loss_k, 0.0, 50.0)
        check(o, "port_volume_m3", self.port_volume_m3, 0.0, 0.01, lo_open=True)
        check(o, "wall_temp_k", self.wall_temp_k, 200.0, 600.0)
        check(o, "throttle_leak_area_m2", self.throttle_leak_area_m2, 0.0, 1e-3)
        check(o, "runner_volume_at_port", self.runner_volume_at_port, 0.0, 1.0)
        check_segments(o, self.runner_segments)
        check(o, "runner_roughness_m", self.runner_roughness_m, 0.0, 0.1 * self.runner_diameter_m)
        check(o, "runner_inertance_factor", self.runner_inertance_factor, 0.05, 5.0)
        check(o, "port_wall_temp_k", self.port_wall_temp_k, 250.0, 700.0)


@dataclass(frozen=True)
class ExhaustSpec:
    """Exhaust path: ports -> primaries (runners) -> merge -> collector -> silencer -> tailpipe -> ambient.

    ``runner_*`` describe the primaries (length to the merge, diameter, minor
    losses in dynamic heads, wall roughness).  In the 1D model the primaries end
    in a small merge volume (``merge_volume_m3``), a collector pipe
    (``collector_length_m``, ``collector_diameter_m``) leads to the silencer
    (``silencer_volume_m3``) and a tailpipe (``tailpipe_length_m``,
    ``tailpipe_diameter_m``) to the ambient, with ``tailpipe_cd`` the discharge
    coefficient of its outlet; the pipes' walls are at ``wall_temp_k`` and the
    exhaust ports' at ``port_wall_temp_k``.  The lumped model instead ends the
    runners in one ``collector_volume_m3`` and a tailpipe orifice of
    ``tailpipe_diameter_m`` and ``tailpipe_cd``; ``runner_inertia``,
    ``runner_volume_at_port`` and ``runner_segments`` are its settings.
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
    merge_volume_m3: float = 0.0002
    collector_length_m: float = 0.35
    collector_diameter_m: float = 0.05
    silencer_volume_m3: float = 0.003
    tailpipe_length_m: float = 0.25
    wall_temp_k: float = 700.0
    port_wall_temp_k: float = 450.0

    def __post_init__(self):
        o = "exhaust"
        check(o, "port_volume_m3", self.port_volume_m3, 0.0, 0.01, lo_open=True)
        check(o, "runner_length_m", self.runner_length_m, 0.0, 3.0, lo_open=True)
        check(o, "runner_diameter_m", self.runner_diameter_m, 0.0, 0.2, lo_open=True)
        check(o, "runner_loss_k", self.runner_loss_k, 0.0, 50.0)
        check(o, "collector_volume_m3", self.collector_volume_m3, 0.0, 0.1, lo_open=True)
        check(o, "tailpipe_diameter_m", self.tailpipe_diameter_m, 0.0, 0.3, lo_open=True)
        check(o, "tailpipe_cd", self.tailpipe_cd, 0.0, 1.0, lo_open=True)
        check(o, "runner_volume_at_port", self.runner_volume_at_port, 0.0, 1.0)
        check_segments(o, self.runner_segments)
        check(o, "runner_roughness_m", self.runner_roughness_m, 0.0, 0.1 * self.runner_diameter_m)


#: Gas-exchange models: quasi-1D pipes (the default) or lumped runners (a fast option).
GAS_EXCHANGE_MODELS = ("1d", "lumped")


@dataclass(frozen=True)
class GasExchangeSpec:
    """How the intake and exhaust pipes are modelled.

    Parameters
    ----------
    model : {"1d", "lumped"}
        "1d": intake runners, exhaust primaries, collector and tailpipe are quasi-1D pipes solved by finite
        volumes (:mod:`engine_model.cycle.pipes`), the default.  "lumped": runners are lumped inertances
        between 0D volumes (faster; not converged in space: see docs/sections/gas_exchange.md).
    cell_length_m : float
        Target cell length of the pipes [m]; each pipe gets round(length / cell_length) cells, at least 2.
    cfl : float
        Courant number the pipe sub-steps are held to [-] (stable up to 1 for the MUSCL-Hancock scheme).
    """

    model: str = "1d"
    cell_length_m: float = 0.03
    cfl: float = 0.9

    def __post_init__(self):
        if self.model not in GAS_EXCHANGE_MODELS:
            raise ValueError(f"gas_exchange.model = {self.model!r}: choose one of {list(GAS_EXCHANGE_MODELS)}")
        check("gas_exchange", "cell_length_m", self.cell_length_m, 0.002, 0.2)
        check("gas_exchange", "cfl", self.cfl, 0.1, 1.0)
