"""Turn an :class:`EngineSpec` and one operating point into the plain arrays the kernels take."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from engine_model import thermo, wiebe
from engine_model.cycle import kinematics
from engine_model.cycle import layout as L
from engine_model.cycle import pipes as P
from engine_model.cycle.engine import n_volumes
from engine_model.cycle.flow import pipe_loss_factor, steady_plenum_pressure, throttle_open_area, valve_effective_area
from engine_model.spec import EngineSpec

GAMMA_MOTORED = 1.35       # polytropic exponent of the Woschni motored-pressure reference (Woschni 1967 uses a polytrope)
# MPE acceleration of the cycle iteration (``cycle/accel.py``): modes removed per
# extrapolation and the first cycle whose end state enters the window.  Chosen on
# 12 points spread over the map against their 250-cycle answers: median cycles
# for k = 2, 3, 4, 5 after 3 warm-up cycles were 24.5, 21, 17, 19 (all within
# 0.025 % of the periodic solution), and 19, 17, 16, 19 per row in the 7 x 7
# Wiebe sweep of benchmarks/bench_cycle.py.
ACCEL_MODES = 4
ACCEL_WARMUP = 3
# Runner wall friction is evaluated at the cycle-mean flow of one runner; the
# friction factor varies as Re^-0.2 or less, so these reference values move it
# by a few % at most (and the runner's loss by < 1 % of a dynamic head).
FRICTION_VE_REF = 0.85     # volumetric efficiency of the reference flow [-] (restricted WOT level)
FRICTION_T_EXH_REF = 1000.0  # exhaust-runner gas temperature for the viscosity [K]
MIN_CELLS = 2              # fewest cells of a pipe (the MUSCL reconstruction needs neighbours)
FRICTION_REFRESH = 8       # pipe friction factors every this many sub-steps (f varies as Re^-0.2; see pipes.py)
# [-]/[m/s] the crank step of the 1D model is refined below ``SolverSettings.step_deg`` where one step would take
# a pipe wave further than ``cfl`` cells: the largest |u| + c found in the pipes over 1000-14000 rpm x 5-100 %
# throttle was 1110 m/s (WOT above 8000 rpm, exhaust blowdown; 650-720 m/s at 1000 rpm), so the step is sized for
# WAVE_SPEED_MAX with a margin of ~12 %.  If a step still exceeds it, the pipes take sub-steps against the
# volumes' state at the start of the step (stable, but the coupling to the ports is then only first order; the
# result row reports it in ``pipe_substeps``).
WAVE_SPEED_MAX = 1250.0
TAILPIPE_ENTRY_K = 0.5     # [Id] sharp-edged pipe entrance from the silencer, 0.5 dynamic heads (Idelchik diagram 3-1)


@dataclass(frozen=True)
class SolverSettings:
    """Numerical settings of the cycle solver.

    Parameters
    ----------
    step_deg : float
        Crank-angle step [deg]; must divide 180 exactly.
    max_cycles : int
        Cycle cap; a point that has not converged by then is flagged, not dropped.
    min_cycles : int
        Cycles always run before convergence may be declared.
    tolerance : float
        A point counts as converged when the estimated relative distance of its
        last cycle to the periodic solution is below this [-].  The distance is
        estimated from the largest relative change per cycle d of trapped mass,
        net indicated work and the cycle's mass imbalance, and the contraction
        ratio rho of that change: d * rho / (1 - rho) (the geometric tail), with
        rho at least the slowest ratio seen by the last extrapolation, and d
        itself below the tolerance.
    accelerate : bool
        Extrapolate the slow cycle-to-cycle modes (minimal polynomial
        extrapolation over the last six end-of-cycle states, see
        ``cycle/accel.py``); the periodic solution is unchanged, only fewer
        cycles are needed.
    """

    step_deg: float = 0.5
    max_cycles: int = 100
    min_cycles: int = 3
    tolerance: float = 1e-3
    accelerate: bool = True

    def __post_init__(self):
        n = 180.0 / self.step_deg if self.step_deg > 0 else 0.0
        if not (self.step_deg > 0 and abs(n - round(n)) < 1e-9):
            raise ValueError(f"solver.step_deg = {self.step_deg!r} must be > 0 and divide 180 exactly")
        if not (1 <= self.min_cycles <= self.max_cycles <= 1000):
            raise ValueError(f"solver: need 1 <= min_cycles ({self.min_cycles}) <= max_cycles ({self.max_cycles}) <= 1000")
        if not (0 < self.tolerance < 0.1):
            raise ValueError(f"solver.tolerance = {self.tolerance!r} must lie in (0, 0.1)")


@dataclass(frozen=True)
class OperatingPoint:
    """One operating point in SI-friendly units (validated by :mod:`engine_model.simulate`)."""

    speed_rpm: float
    throttle_pct: float
    spark_deg_btdc: float
    lam: float
    bdur_10_90_deg: float
    wiebe_m: float
    wiebe_a: float = wiebe.WIEBE_A_999
    p_amb_pa: float = 101325.0
    t_amb_k: float = 298.15
    motored: bool = False


@dataclass
class KernelInputs:
    par: np.ndarray
    tab: np.ndarray
    offs: np.ndarray
    coeffs: np.ndarray
    rsp: np.ndarray
    fuel_c: np.ndarray
    vfix: np.ndarray
    gas: thermo.GasSet
    nstep: int
    ncyl: int
    nseg_in: int = 1      # lumped segments per intake runner
    nseg_ex: int = 1      # lumped segments per exhaust runner
    net: P.PipeNet | None = None          # 1D: the pipes (None when lumped)
    ends: np.ndarray | None = None        # 1D: what is at each pipe end (layout E_*)
    endp: np.ndarray | None = None        # 1D: end parameters

    @property
    def pipes_on(self) -> bool:
        return self.net is not None

    def pipe_arrays(self):
        """(pipes, geom, ends, endp) for ``run_engine``; empty arrays for the lumped model."""
        if self.net is None:
            return (np.zeros((0, 2), np.int64), np.zeros((P.NG, 0)), np.zeros((0, 2, L.NE), np.int64),
                    np.zeros((0, 2, L.NEP)))
        return self.net.pipes, self.net.geom, self.ends, self.endp


def _unwrapped_angles(nstep: int, ivc_deg: float) -> np.ndarray:
    """Local angles [deg ATDC] of the table indices, running continuously from IVC-720 to IVC."""
    ang = np.arange(nstep) * (720.0 / nstep)
    return np.where(ang >= ivc_deg, ang - 720.0, ang)


def angle_tables(spec: EngineSpec, op: OperatingPoint, nstep: int) -> np.ndarray:
    """Per-local-angle tables (see ``layout.T_*``), shape (NTAB, nstep)."""
    g = spec.geometry
    ang = np.arange(nstep) * (720.0 / nstep)
    ivc = spec.intake_valves.open_deg + spec.intake_valves.duration_deg
    evo = spec.exhaust_valves.open_deg
    a = _unwrapped_angles(nstep, ivc)
    tab = np.zeros((L.NTAB, nstep))
    vol = kinematics.cylinder_volume(ang, g.bore_m, g.stroke_m, g.conrod_m, g.compression_ratio)
    tab[L.T_V] = vol
    tab[L.T_ALINER] = kinematics.liner_area(ang, g.bore_m, g.stroke_m, g.conrod_m, g.compression_ratio)
    tab[L.T_AIV] = valve_effective_area(ang, spec.intake_valves)
    tab[L.T_AEV] = valve_effective_area(ang, spec.exhaust_valves)
    closed = a < evo
    soc_angle = -op.spark_deg_btdc
    if not op.motored:
        bdur = wiebe.bdur_10_90_to_bdur(op.bdur_10_90_deg, op.wiebe_m, op.wiebe_a)
        # Burning ends when the exhaust valve opens: a burn still going at EVO
        # leaves the rest of the mixture unburned (lost efficiency, not a failure).
        xb = wiebe.burn_fraction(a, op.spark_deg_btdc, bdur, op.wiebe_m, op.wiebe_a)
        xb_evo = wiebe.burn_fraction(evo, op.spark_deg_btdc, bdur, op.wiebe_m, op.wiebe_a)
        # combustion efficiency < 1: only that fraction of the charge ever burns (the rest leaves
        # unburned): the base model's curve in lambda (spec.charge) times the gap library's factor
        # (spec.losses, neutral 1)
        eta_c = spec.losses.combustion_efficiency * spec.charge.combustion_efficiency(op.lam)
        tab[L.T_XB] = eta_c * np.where(a < evo, xb, xb_evo)
        ca_end = wiebe.angle_at_fraction(spec.knock.end_burn_fraction, op.spark_deg_btdc, bdur, op.wiebe_m, op.wiebe_a)
        # share of each crank step [a, a + h] inside the window [IVC, min(ca_end, EVO)): the integral ends at
        # ca_end itself, not at the grid node after it (a whole-step end left a +-1.5 % ripple of the knock index
        # against spark at a 0.5 deg step, docs/sections/knock.md)
        h = 720.0 / nstep
        tab[L.T_KWIN] = np.clip((min(ca_end, evo) - a) / h, 0.0, 1.0)
    v_ivc = kinematics.cylinder_volume(ivc, g.bore_m, g.stroke_m, g.conrod_m, g.compression_ratio)
    tab[L.T_VMOT] = np.where(closed, (v_ivc / vol) ** GAMMA_MOTORED, 0.0)
    burning = closed & (a >= soc_angle) & (not op.motored)
    tab[L.T_PHASE] = np.where(burning, 2.0, np.where(closed, 1.0, 0.0))
    return tab


def kernel_inputs(spec: EngineSpec, op: OperatingPoint, solver: SolverSettings = SolverSettings(),
                  gas: thermo.GasSet | None = None) -> KernelInputs:
    """All arrays for :func:`engine_model.cycle.engine.run_engine` at one operating point."""
    g = spec.geometry
    ncyl = g.n_cylinders
    nstep = int(round(720.0 / crank_step_deg(spec, op.speed_rpm, solver.step_deg)))
    if gas is None:
        gas = thermo.gas_set(op.lam, spec.fuel)
    far = 0.0 if op.motored else gas.far
    step = 720.0 / nstep
    dt = step / (6.0 * op.speed_rpm)
    ivc = spec.intake_valves.open_deg + spec.intake_valves.duration_deg
    bore_area = math.pi / 4.0 * g.bore_m**2
    it, ex, ht, kn = spec.intake, spec.exhaust, spec.heat_transfer, spec.knock

    par = np.zeros(L.NPAR)
    par[L.P_DT] = dt
    par[L.P_NSTEP] = nstep
    par[L.P_NCYL] = ncyl
    par[L.P_PAMB] = op.p_amb_pa
    par[L.P_TAMB] = op.t_amb_k
    par[L.P_FAR] = far
    par[L.P_VD] = g.displacement_m3
    par[L.P_SP] = float(kinematics.mean_piston_speed(op.speed_rpm, g.stroke_m))
    par[L.P_WOSCHNI] = ht.woschni_coeff * g.bore_m ** -0.2 * ht.multiplier
    par[L.P_C1_GE] = ht.c1_gas_exchange
    par[L.P_C1_CL] = ht.c1_closed
    par[L.P_C2] = ht.c2_combustion
    par[L.P_TW_HEAD] = ht.head_temp_k
    par[L.P_TW_PISTON] = ht.piston_temp_k
    par[L.P_TW_LINER] = ht.liner_temp_k
    par[L.P_A_HEAD] = ht.head_area_factor * bore_area
    par[L.P_A_PISTON] = ht.piston_area_factor * bore_area
    par[L.P_THR_CDA] = it.throttle_cd * float(throttle_open_area(
        op.throttle_pct, it.throttle_bore_m, it.throttle_shaft_m, it.throttle_closed_deg, it.throttle_leak_area_m2))
    par[L.P_RES_CDA] = it.restrictor_cd * math.pi / 4.0 * it.restrictor_throat_m**2
    par[L.P_RES_REC] = it.restrictor_recovery
    par[L.P_IR_A] = math.pi / 4.0 * it.runner_diameter_m**2
    # The inertance factor scales both terms of the runner momentum equation
    # (A/L dp and k/(2 rho A L) m|m|), so the steady loss is unchanged and only
    # the gas inertia (wave tuning of the lumped runner) moves.
    par[L.P_IR_L] = it.runner_length_m * it.runner_inertance_factor
    # runner loss factor [dynamic heads]: exit (dump) loss of one dynamic head +
    # minor losses + Darcy wall friction f L/D at the cycle-mean runner flow
    m_ref = FRICTION_VE_REF * op.p_amb_pa / (float(gas.r_specific[L.SP_A]) * op.t_amb_k) \
        * g.displacement_m3 * op.speed_rpm / 120.0
    par[L.P_IR_K] = 1.0 + float(pipe_loss_factor(
        m_ref, op.t_amb_k, par[L.P_IR_A], it.runner_diameter_m, it.runner_length_m, it.runner_loss_k,
        it.runner_roughness_m / it.runner_diameter_m))
    par[L.P_IR_INERTIA] = 1.0 if it.runner_inertia else 0.0
    par[L.P_ER_A] = math.pi / 4.0 * ex.runner_diameter_m**2
    par[L.P_ER_L] = ex.runner_length_m
    par[L.P_ER_K] = 1.0 + float(pipe_loss_factor(
        m_ref * (1.0 + far), FRICTION_T_EXH_REF, par[L.P_ER_A], ex.runner_diameter_m, ex.runner_length_m,
        ex.runner_loss_k, ex.runner_roughness_m / ex.runner_diameter_m))
    par[L.P_ER_INERTIA] = 1.0 if ex.runner_inertia else 0.0
    # segments only exist with gas inertia; a quasi-steady runner is one resistance
    nsi = it.runner_segments if it.runner_inertia else 1
    nse = ex.runner_segments if ex.runner_inertia else 1
    par[L.P_IR_NSEG] = nsi
    par[L.P_ER_NSEG] = nse
    par[L.P_TP_CDA] = ex.tailpipe_cd * math.pi / 4.0 * ex.tailpipe_diameter_m**2
    par[L.P_KN_A] = kn.delay_coeff_effective_s
    par[L.P_KN_D] = kn.dilution_exponent
    par[L.P_KN_N] = kn.pressure_exponent
    par[L.P_KN_B] = kn.activation_temp_k
    par[L.P_COMBUSTION] = 0.0 if op.motored else 1.0
    par[L.P_MAXCYC] = solver.max_cycles
    par[L.P_MINCYC] = solver.min_cycles
    par[L.P_TOL] = solver.tolerance
    par[L.P_IDX_IVC] = int(round(ivc / step)) % nstep
    par[L.P_IDX_EVO] = int(round(spec.exhaust_valves.open_deg / step)) % nstep
    par[L.P_IDX_SOC] = int(math.floor(((-op.spark_deg_btdc) % 720.0) / step + 1e-9)) % nstep
    par[L.P_ACCEL_K] = ACCEL_MODES if solver.accelerate else 0
    par[L.P_ACCEL_WARM] = ACCEL_WARMUP
    par[L.P_NET_EPS] = 1e-4   # ~10 Pa at 1 bar; results change < 0.05 % between 1e-3 and 1e-6
    ch = spec.charge
    par[L.P_EVAP] = 0.0 if op.motored else ch.fuel_latent_heat_j_per_kg * ch.evaporation_from_charge
    # port wall heat transfer: each port a duct of the runner's diameter holding the port volume
    par[L.P_PHT_MULT] = ch.port_heat_transfer_multiplier
    par[L.P_PHT_D_IN] = it.runner_diameter_m
    par[L.P_PHT_A_IN] = 4.0 * it.port_volume_m3 / it.runner_diameter_m
    par[L.P_PHT_TW_IN] = it.port_wall_temp_k
    par[L.P_PHT_D_EX] = ex.runner_diameter_m
    par[L.P_PHT_A_EX] = 4.0 * ex.port_volume_m3 / ex.runner_diameter_m
    par[L.P_PHT_TW_EX] = ex.port_wall_temp_k
    pipes_on = spec.gas_exchange.model == "1d"
    par[L.P_GASX] = 1.0 if pipes_on else 0.0
    par[L.P_CFL] = spec.gas_exchange.cfl
    par[L.P_FRIC_EVERY] = FRICTION_REFRESH

    offs = np.array([int(round(ph / step)) for ph in g.phase_deg()], dtype=np.int64)
    coeffs = np.ascontiguousarray(gas.coeffs, dtype=np.float64)
    if op.motored:  # no fuel: the "mixture" is air
        coeffs = coeffs.copy()
        coeffs[L.SP_M] = coeffs[L.SP_A]
    rsp = np.ascontiguousarray(gas.r_specific, dtype=np.float64).copy()
    if op.motored:
        rsp[L.SP_M] = rsp[L.SP_A]
    common = dict(par=par, tab=angle_tables(spec, op, nstep), offs=offs, coeffs=coeffs, rsp=rsp,
                  fuel_c=np.ascontiguousarray(gas.fuel_coeffs, dtype=np.float64), gas=gas, nstep=nstep, ncyl=ncyl)
    if pipes_on:
        net, ends, endp = pipe_network(spec)
        vfix = np.zeros(n_volumes(ncyl, pipes=True))
        vfix[ncyl:2 * ncyl] = it.port_volume_m3
        vfix[2 * ncyl:3 * ncyl] = ex.port_volume_m3
        vfix[3 * ncyl] = it.plenum_volume_m3
        vfix[3 * ncyl + 1] = it.throttle_body_volume_m3
        vfix[3 * ncyl + 2] = ex.merge_volume_m3
        vfix[3 * ncyl + 3] = ex.silencer_volume_m3
        return KernelInputs(vfix=vfix, nseg_in=1, nseg_ex=1, net=net, ends=ends, endp=endp, **common)
    nvol = n_volumes(ncyl, nsi, nse)
    vfix = np.zeros(nvol)
    # Lumped runner: each of its nseg segments is an inertance whose gas volume
    # A*L/nseg is shared by the capacitances at its two ends (pi lumping).  Inner
    # joints get half of each neighbouring segment; at the ends the fraction
    # ``runner_volume_at_port`` of the end segment's volume goes with the port at
    # the valve end, the rest with the plenum / collector.
    v_is = par[L.P_IR_A] * it.runner_length_m / nsi
    v_es = par[L.P_ER_A] * ex.runner_length_m / nse
    fi, fe = it.runner_volume_at_port, ex.runner_volume_at_port
    vfix[ncyl:2 * ncyl] = it.port_volume_m3 + fi * v_is
    vfix[2 * ncyl:3 * ncyl] = ex.port_volume_m3 + fe * v_es
    vfix[3 * ncyl] = it.plenum_volume_m3 + (1.0 - fi) * ncyl * v_is
    vfix[3 * ncyl + 1] = it.throttle_body_volume_m3
    vfix[3 * ncyl + 2] = ex.collector_volume_m3 + (1.0 - fe) * ncyl * v_es
    j0 = 3 * ncyl + 3
    vfix[j0:j0 + ncyl * (nsi - 1)] = v_is
    vfix[j0 + ncyl * (nsi - 1):] = v_es
    return KernelInputs(vfix=vfix, nseg_in=nsi, nseg_ex=nse, **common)


def crank_step_deg(spec: EngineSpec, speed_rpm: float, step_deg: float) -> float:
    """The crank step [deg] the model runs at: ``step_deg``, or for the 1D gas exchange the largest 180/n (n whole)
    not above it at which a wave of ``WAVE_SPEED_MAX`` crosses at most ``gas_exchange.cfl`` of the shortest cell."""
    gx = spec.gas_exchange
    if gx.model != "1d":
        return step_deg
    dx = min(length / _cells(length, gx.cell_length_m) for length in _pipe_lengths(spec))
    step_cfl = gx.cfl * dx / WAVE_SPEED_MAX * 6.0 * speed_rpm
    if step_cfl >= step_deg:
        return step_deg
    return 180.0 / math.ceil(180.0 / step_cfl - 1e-9)


def _pipe_lengths(spec: EngineSpec) -> tuple:
    it, ex = spec.intake, spec.exhaust
    return it.runner_length_m * it.runner_inertance_factor, ex.runner_length_m, ex.collector_length_m, \
        ex.tailpipe_length_m


def _cells(length: float, cell: float) -> int:
    return max(MIN_CELLS, int(round(length / cell)))


def pipe_network(spec: EngineSpec):
    """The 1D gas exchange's pipes and what is at their ends.

    Pipes (in this order): intake runner k (plenum -> intake port k), exhaust primary k (exhaust port
    k -> merge), collector (merge -> silencer), tailpipe (silencer -> ambient).  Ends:

    * runner at the plenum: open end, a bellmouth (its small entry loss is in ``runner_loss_k``);
    * runner at the port: orifice of A / sqrt(1 + k) both ways, k = ``intake.runner_loss_k`` (bend and
      guide boss in the head), so flow into the port loses 1 + k dynamic heads (jet dump + minor losses),
      as the lumped runner's loss;
    * primary at the exhaust port: the same with ``exhaust.runner_loss_k``;
    * primary, collector and tailpipe at the merge and the silencer: open ends (the tailpipe's entry from
      the silencer with a sharp-edged entry loss);
    * tailpipe at the ambient: orifice of ``tailpipe_cd`` times its area (the silencer outlet).

    Returns
    -------
    PipeNet, ends (npipe, 2, NE) int64, endp (npipe, 2, NEP) float64
    """
    g, it, ex, gx = spec.geometry, spec.intake, spec.exhaust, spec.gas_exchange
    ncyl = g.n_cylinders
    ipl, imerge, isil = 3 * ncyl, 3 * ncyl + 2, 3 * ncyl + 3
    nvol = n_volumes(ncyl, pipes=True)
    h = gx.cell_length_m
    specs = []
    l_in = it.runner_length_m * it.runner_inertance_factor      # 1 unless a study changes the acoustic length
    for _ in range(ncyl):
        specs.append(P.PipeSpec(l_in, _cells(l_in, h), it.runner_diameter_m,
                                wall_temperature=it.wall_temp_k, roughness=it.runner_roughness_m))
    for _ in range(ncyl):
        specs.append(P.PipeSpec(ex.runner_length_m, _cells(ex.runner_length_m, h), ex.runner_diameter_m,
                                wall_temperature=ex.wall_temp_k, roughness=ex.runner_roughness_m))
    specs.append(P.PipeSpec(ex.collector_length_m, _cells(ex.collector_length_m, h), ex.collector_diameter_m,
                            wall_temperature=ex.wall_temp_k, roughness=ex.runner_roughness_m))
    specs.append(P.PipeSpec(ex.tailpipe_length_m, _cells(ex.tailpipe_length_m, h), ex.tailpipe_diameter_m,
                            wall_temperature=ex.wall_temp_k, roughness=ex.runner_roughness_m))
    net = P.build_pipes(specs)
    npipe = net.npipe
    ends = np.zeros((npipe, 2, L.NE), dtype=np.int64)
    endp = np.zeros((npipe, 2, L.NEP))
    a_in = math.pi / 4.0 * it.runner_diameter_m ** 2
    a_ex = math.pi / 4.0 * ex.runner_diameter_m ** 2
    a_tp = math.pi / 4.0 * ex.tailpipe_diameter_m ** 2

    def put(ip, side, kind, kv, p0=0.0, p1=0.0):
        ends[ip, side] = kind, kv
        endp[ip, side] = p0, p1

    for k in range(ncyl):
        put(k, 0, L.BC_OPEN, ipl)
        c = a_in / math.sqrt(1.0 + it.runner_loss_k)
        put(k, 1, L.BC_ORIFICE, ncyl + k, c, c)
        c = a_ex / math.sqrt(1.0 + ex.runner_loss_k)
        put(ncyl + k, 0, L.BC_ORIFICE, 2 * ncyl + k, c, c)
        put(ncyl + k, 1, L.BC_OPEN, imerge)
    put(2 * ncyl, 0, L.BC_OPEN, imerge)
    put(2 * ncyl, 1, L.BC_OPEN, isil)
    put(2 * ncyl + 1, 0, L.BC_OPEN, isil, TAILPIPE_ENTRY_K)
    put(2 * ncyl + 1, 1, L.BC_ORIFICE, nvol, ex.tailpipe_cd * a_tp, ex.tailpipe_cd * a_tp)
    return net, ends, endp


def estimate_plenum_pressure(spec: EngineSpec, ki: KernelInputs, ve_guess: float = 0.95) -> float:
    """Plenum pressure [Pa] at which throttle + restrictor pass what the cylinders draw (steady estimate).

    Used only to start the cycle iteration close to the answer; the bisections
    run in the compiled :func:`~engine_model.cycle.flow.steady_plenum_pressure`
    (as a Python loop they cost ~4 ms per cold start, 7 % of a converged point).
    """
    par = ki.par
    p_amb, t_amb = par[L.P_PAMB], par[L.P_TAMB]
    r, gam = float(ki.rsp[L.SP_A]), 1.4
    speed_rpm = (720.0 / ki.nstep) / (6.0 * par[L.P_DT])
    vd_tot = spec.geometry.total_displacement_m3
    return float(steady_plenum_pressure(par[L.P_THR_CDA], par[L.P_RES_CDA], par[L.P_RES_REC], p_amb, t_amb, r, gam,
                                        ve_guess, vd_tot, speed_rpm))


def initial_state(spec: EngineSpec, ki: KernelInputs):
    """A cold-start state ``(vol, mr, q, tcell)``: intake at the estimated plenum pressure, exhaust hot and full
    of products (``q``, ``tcell``: pipe cells, empty when lumped; ``mr``: lumped runner flows, empty in 1D)."""
    ncyl, nstep = ki.ncyl, ki.nstep
    nsi, nse = ki.nseg_in, ki.nseg_ex
    nvol = len(ki.vfix)
    par = ki.par
    p_amb, t_amb = par[L.P_PAMB], par[L.P_TAMB]
    p_pl = estimate_plenum_pressure(spec, ki)
    p_ex, t_ex = 1.03 * p_amb, 900.0
    vol = np.zeros((nvol, L.NVCOL))
    v = ki.vfix.copy()
    for k in range(ncyl):
        v[k] = ki.tab[L.T_V, (0 - ki.offs[k]) % nstep]

    def fill(i, p, t, ya, ym, yp):
        c = ya * ki.coeffs[0] + ym * ki.coeffs[1] + yp * ki.coeffs[2]
        r = ya * ki.rsp[0] + ym * ki.rsp[1] + yp * ki.rsp[2]
        m = p * v[i] / (r * t)
        vol[i, L.V_MA], vol[i, L.V_MM], vol[i, L.V_MP] = m * ya, m * ym, m * yp
        vol[i, L.V_U] = m * (thermo.h_mass(c, t) - r * t)
        vol[i, L.V_T] = t

    # cylinders: in their closed period, a motored-like state compressed from IVC;
    # otherwise at plenum pressure (fresh charge with a little residual)
    ivc = int(par[L.P_IDX_IVC])
    evo = int(par[L.P_IDX_EVO])
    v_ivc = ki.tab[L.T_V, ivc]
    for k in range(ncyl):
        li = (0 - ki.offs[k]) % nstep
        closed = li >= ivc or li < evo
        ratio = v_ivc / v[k] if closed else 1.0
        fill(k, p_pl * ratio**1.35, 340.0 * ratio**0.35, 0.0, 0.93, 0.07)
        fill(ncyl + k, p_pl, t_amb, 1.0, 0.0, 0.0)
        fill(2 * ncyl + k, p_ex, t_ex, 0.0, 0.0, 1.0)
    fill(3 * ncyl, p_pl, t_amb, 1.0, 0.0, 0.0)
    fill(3 * ncyl + 1, 0.5 * (p_pl + p_amb), t_amb, 1.0, 0.0, 0.0)
    fill(3 * ncyl + 2, p_ex, t_ex, 0.0, 0.0, 1.0)
    if ki.pipes_on:
        fill(3 * ncyl + 3, p_ex, t_ex, 0.0, 0.0, 1.0)     # silencer
        net = ki.net
        q = np.zeros((net.ncell, P.NQ))
        tcell = np.full(net.ncell, 300.0)
        hc = thermo.enthalpy_coeffs(ki.coeffs)
        for ip in range(net.npipe):
            i0, i1 = net.first_cell(ip), net.last_cell(ip) + 1
            if ip < ncyl:
                P.fill_cells(q, tcell, net.geom, i0, i1, p_pl, t_amb, 0.0, 1.0, 0.0, 0.0, hc, ki.rsp)
            else:
                P.fill_cells(q, tcell, net.geom, i0, i1, p_ex, t_ex, 0.0, 0.0, 0.0, 1.0, hc, ki.rsp)
        return vol, np.zeros(0), q, tcell
    j0 = 3 * ncyl + 3
    for i in range(j0, j0 + ncyl * (nsi - 1)):          # intake runner joints: plenum gas
        fill(i, p_pl, t_amb, 1.0, 0.0, 0.0)
    for i in range(j0 + ncyl * (nsi - 1), nvol):        # exhaust runner joints: hot products
        fill(i, p_ex, t_ex, 0.0, 0.0, 1.0)
    mr = np.zeros(ncyl * (nsi + nse))   # runner flows at rest
    return vol, mr, np.zeros((0, P.NQ)), np.zeros(0)
