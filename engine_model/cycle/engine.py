"""Converged-cycle driver of the multi-cylinder engine (numba).

The engine is a network of 0D volumes joined by flow elements and, in the 1D gas exchange (the
default), by pipes:

    ambient -throttle-> throttle body -restrictor-> plenum =intake runner k=> intake port k
    -intake valve k-> cylinder k -exhaust valve k-> exhaust port k =exhaust primary k=> merge
    =collector=> silencer =tailpipe=> ambient                                      (1D, ``P_GASX`` = 1)

    ... exhaust port k =runner k=> collector -tailpipe orifice-> ambient           (lumped, ``P_GASX`` = 0)

``=...=>`` are quasi-1D pipes (:mod:`.pipes`, advanced once per crank step by :func:`.pipenet.pipe_step`
in Courant-limited sub-steps; their end fluxes enter the volumes as constant rates over the step) or, in
the lumped option, runners with a lumped momentum equation (a mass-flow state per segment).  Every volume
holds the masses of three pseudo-species (air A, fresh mixture M = air + fuel vapour, products P) and its
total internal energy including enthalpies of formation; temperature follows from that energy, so the
heat released by combustion is the change of composition M -> P, not a separate source term.

Integration: fixed crank-angle step, Heun's method (explicit trapezoidal RK2) on the volume states (and
the lumped runner flows).  The orifice elements (throttle, restrictor, valves, the lumped tailpipe) are
evaluated, in each Heun stage, linearly implicitly: every flow is linearised in the two pressures and
solved together with the pressure changes of the volumes it joins over one step, including the known
pressure rates from the piston, wall heat, runner or pipe flows (``network.solve_one`` and
``solve_two``, closed forms; the coupled groups are [throttle body, plenum], [intake port k, cylinder k,
exhaust port k] and, lumped, [collector]).  Each flow leaves one volume or pipe end and enters another
with the same mass and enthalpy, so mass and energy are conserved by construction; the cycle-level
balances reported in ``out`` therefore measure how periodic the converged cycle is.
"""

import math

import numpy as np
from numba import njit

from engine_model.thermo import enthalpy_coeffs_into, mix_coeffs, s0_mass
from engine_model.cycle.accel import mpe, pack_state, state_weights, unpack_state
from engine_model.cycle.cylinder import (dilution_factor, end_gas_temperature, ignition_delay, wall_heat_rate,
                                         woschni_coefficient, woschni_velocity)
from engine_model.cycle.flow import gas_viscosity
from engine_model.cycle.layout import *  # noqa: F401,F403  (index constants)
from engine_model.cycle.network import add_rate, lin_between, orifice_between, solve_one, solve_two
from engine_model.cycle.pipenet import pipe_energy, pipe_step
from engine_model.cycle.pipes import NF, NPM, NQ, NWK, PM_P, Q_A, Q_M, Q_P
from engine_model.cycle.volumes import *  # noqa: F401,F403  (props columns, accumulator layout, volume kernels)
from engine_model.cycle.volumes import eval_props, iv_transfer, set_ambient, transfer

RHO_MIN = 0.5    # [-] smallest contraction ratio assumed by the convergence estimate
# [-] slowest cycle-to-cycle ratio assumed until an extrapolation has measured one:
# the plenum-composition mode of the R6 decays by 0.86-0.92 per cycle over the map
# (measured on 12 points, 250-cycle runs); a larger value only costs cycles.
RHO_START = 0.92
RHO_MAX = 0.97   # [-] ratios above this count as not contracting
PRANDTL_PORT = 0.7  # [-] Prandtl number of the port gas for the Dittus-Boelter heat transfer (air, 300-1000 K)
MBAL_SHARE = 0.25   # [-] the cycle's mass imbalance must be below this share of the tolerance (floor seen ~1.5e-4)


def n_volumes(ncyl, nseg_in=1, nseg_ex=1, pipes=False):
    """Number of gas volumes for ``ncyl`` cylinders.

    Cylinders, 2 ports each, plenum, throttle body, then the exhaust collector (lumped) or the merge
    volume and the silencer (1D, ``pipes``); the lumped model adds the inner joints of segmented runners
    (``nseg - 1`` per runner; intake runners first, runner by runner, then exhaust).
    """
    if pipes:
        return 3 * ncyl + 4
    return 3 * ncyl + 3 + ncyl * (nseg_in - 1) + ncyl * (nseg_ex - 1)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _port_heat(ip, m, props, area, diam, t_wall, mult):
    """Heat flow from the port wall into the port's gas [W]: Dittus-Boelter at the port's flow ``m`` [kg/s].

    h = 0.023 Re^0.8 Pr^0.4 k / D (Dittus and Boelter 1930, in Incropera et al., Fundamentals of Heat and
    Mass Transfer, eq. 8.60), Re = 4 |m| / (pi D mu), k = mu cp / Pr; the gas properties at the port gas
    temperature (Sutherland viscosity).  Fully developed turbulent pipe flow is a lower bound for a short,
    curved port with a valve at its end, hence the multiplier in the spec.
    """
    t = props[ip, PR_T]
    mu = gas_viscosity(t)
    g = props[ip, PR_G]
    cp = g * props[ip, PR_R] / (g - 1.0)
    re = 4.0 * abs(m) / (math.pi * diam * mu)
    if re < 1.0:
        return 0.0
    h = 0.023 * re ** 0.8 * PRANDTL_PORT ** 0.4 * mu * cp / PRANDTL_PORT / diam
    return mult * h * area * (t_wall - t)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _lumped_runners(vol, mr, par, props, vcur, nvol, ncyl, dt, dvol, dmr, rate):
    """Lumped runners (``P_GASX`` = 0): mass flows with a momentum equation per segment, or resistances.

    Intake runner k joins the plenum to port k, exhaust runner k port k to the collector.  Each runner is
    ``nseg`` lumped segments in series, a mass-flow state with its momentum equation per segment; the
    joints between segments are gas volumes (indices from the collector + 1 on, see ``n_volumes``).  The
    loss factor k_r (exit dump, minor losses and wall friction, see ``prepare``) is spread evenly over the
    segments, so in steady flow the runner's pressure drop is k_r * m^2 / (2 rho A^2) whatever ``nseg``.
    """
    ipl = 3 * ncyl
    icol = ipl + 2
    jnt = icol + 1
    for side in range(2):
        if side == 0:
            a_r = par[P_IR_A]
            l_r = par[P_IR_L]
            k_r = par[P_IR_K]
            inertia = par[P_IR_INERTIA] > 0.5
            nseg = int(par[P_IR_NSEG])
            m_first = 0
        else:
            a_r = par[P_ER_A]
            l_r = par[P_ER_L]
            k_r = par[P_ER_K]
            inertia = par[P_ER_INERTIA] > 0.5
            nseg = int(par[P_ER_NSEG])
            m_first = ncyl * int(par[P_IR_NSEG])
        l_s = l_r / nseg
        c_dp = a_r / l_s                       # [m]: d(mdot)/dt per unit pressure difference
        c_loss = k_r / (2.0 * a_r * l_r)       # [1/m^3]: loss term is c_loss * m|m| / rho
        for k in range(ncyl):
            if side == 0:
                up_end = ipl
                dn_end = ncyl + k
            else:
                up_end = 2 * ncyl + k
                dn_end = icol
            for j in range(nseg):
                up = up_end if j == 0 else jnt + j - 1
                dn = dn_end if j == nseg - 1 else jnt + j
                idx = m_first + k * nseg + j
                if inertia:
                    m = mr[idx]
                    rho = props[up, PR_RHO] if m >= 0.0 else props[dn, PR_RHO]
                    dmr[idx] = c_dp * (props[up, PR_P] - props[dn, PR_P]) - c_loss * m * abs(m) / rho
                else:
                    m = orifice_between(up, dn, a_r / math.sqrt(k_r), props, dt)
                    dmr[idx] = 0.0
                transfer(up, dn, m, nvol, props, dvol)
                add_rate(up, dn, m, nvol, props, vcur, rate)
            jnt += nseg - 1


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _derivs(vol, mr, s_step, stage, par, tab, offs, hcoeffs, rsp, fuel_c, ref, egc, egs, nvol, cbuf, props,
            vcur, dvol, dmr, acc, rate, E, xfer, xrate, have_props):
    """Time derivatives of all states at the start (stage 0) or end (stage 1) of step ``s_step``.

    ``xfer`` / ``xrate``: what the pipes bring each volume over the step (1D; see :func:`.pipenet.pipe_step`),
    added as constant rates in both stages.  ``have_props``: ``props`` already holds this state.
    ``egc`` / ``egs``: the end gas of each cylinder (see :func:`run_engine`).
    Returns a failure code (0 = ok).  ``acc`` receives the rates of the cycle integrals.
    """
    ncyl = int(par[P_NCYL])
    nstep = int(par[P_NSTEP])
    dt = par[P_DT]
    far = par[P_FAR]
    ipl = 3 * ncyl
    itb = ipl + 1
    icol = ipl + 2
    amb = nvol
    eps = par[P_NET_EPS]
    pipes_on = par[P_GASX] > 0.5
    # current volumes of the cylinders
    for k in range(ncyl):
        li = (s_step + stage - offs[k]) % nstep
        vcur[k] = tab[T_V, li]
    if not have_props:
        code = eval_props(vol, vcur, nvol, hcoeffs, rsp, cbuf, props)
        if code != 0:
            return code
    dvol[:, :] = 0.0
    acc[:] = 0.0
    rate[:] = 0.0

    # ---- runners: lumped flows, or the pipes' transfers over this step as constant rates
    if pipes_on:
        inv_dt = 1.0 / dt
        for i in range(ncyl, nvol):
            for c in range(NVCOL - 1):
                dvol[i, c] += xfer[i, c] * inv_dt
            rate[i] += xrate[i] * inv_dt
    else:
        _lumped_runners(vol, mr, par, props, vcur, nvol, ncyl, dt, dvol, dmr, rate)
        # exhaust collector -> ambient.  The tailpipe beyond the collector is full of exhaust gas, so gas
        # drawn back in has the collector's composition and temperature (pseudo-volume ``tpipe`` at
        # ambient pressure), not fresh air.
        tpipe = nvol + 1
        for c in range(NPR):
            props[tpipe, c] = props[icol, c]
        props[tpipe, PR_P] = par[P_PAMB]
        props[tpipe, PR_RHO] = par[P_PAMB] / (props[icol, PR_R] * props[icol, PR_T])
        props[tpipe, PR_S] = 0.0
        props[tpipe, PR_GV] = 0.0

    # ---- cylinders: combustion, wall heat, piston work, knock
    for k in range(ncyl):
        ls = (s_step - offs[k]) % nstep          # start of the step (burn increment, dV)
        ls1 = (ls + 1) % nstep
        le = ls1 if stage == 1 else ls           # evaluation point of this stage
        base = A_CYL0 + AC_N * k
        p = props[k, PR_P]
        t = props[k, PR_T]
        dvdt = (tab[T_V, ls1] - tab[T_V, ls]) / dt

        # combustion: the exact Wiebe increment of this step, spread evenly over it
        if par[P_COMBUSTION] > 0.5:
            dxb = tab[T_XB, ls1] - tab[T_XB, ls]
            if dxb > 0.0:
                mb = ref[k, 4] * dxb / dt
                cap = vol[k, V_MM] / dt
                if mb > cap:
                    mb = cap if cap > 0.0 else 0.0
                dvol[k, V_MM] -= mb
                dvol[k, V_MP] += mb
                acc[A_BURN] += mb * far / (1.0 + far)

        # Woschni wall heat transfer, phase-dependent constants
        phase = tab[T_PHASE, le]
        if phase < 0.5:
            c1 = par[P_C1_GE]
            c2 = 0.0
        elif phase < 1.5:
            c1 = par[P_C1_CL]
            c2 = 0.0
        else:
            c1 = par[P_C1_CL]
            c2 = par[P_C2]
        pmot = ref[k, 0] * tab[T_VMOT, le]
        w = woschni_velocity(c1, c2, par[P_SP], par[P_VD], ref[k, 1], ref[k, 0], ref[k, 2], p, pmot)
        h = woschni_coefficient(par[P_WOSCHNI], p, t, w)
        q = wall_heat_rate(h, t, par[P_A_HEAD], par[P_TW_HEAD], par[P_A_PISTON], par[P_TW_PISTON],
                           tab[T_ALINER, le], par[P_TW_LINER])
        dvol[k, V_U] -= q + p * dvdt
        acc[base + AC_WORK] += p * dvdt
        acc[base + AC_Q] += q
        g = props[k, PR_G]
        rate[k] -= (g * p * dvdt + (g - 1.0) * q) / vcur[k]

        # end-gas autoignition (Livengood-Wu integrand (1 - x_b)^d / tau).  Before the spark the whole charge
        # is end gas (its temperature is the cylinder's); from the spark on, the unburned gas follows the
        # variable-cp isentrope through the cylinder pressure from its state at the spark.
        # (both Heun stages of a step weighted by the step's share inside the window, so the integral ends
        # at the window's end angle, not at a grid node)
        kw = tab[T_KWIN, ls]
        if kw > 0.0:
            if phase > 1.5 and egs[k, 4] > 0.5:
                tu = end_gas_temperature(egc[k], egs[k, 0] + egs[k, 1] * math.log(p), egs[k, 2])
                egs[k, 2] = tu
            else:
                tu = t
            acc[base + AC_KNOCK] += kw * egs[k, 3] / ignition_delay(p, tu, par[P_KN_A], par[P_KN_N], par[P_KN_B])

    # ---- orifice elements.  Those outside the network first, so that their flows enter the network
    # solve as known pressure rates.
    # element rows: 0 throttle, 1 restrictor, 2 tailpipe (lumped), 3+2k intake valve k, 4+2k exhaust valve k
    lin_between(amb, itb, par[P_THR_CDA], 0.0, props, eps, E, 0)
    lin_between(itb, ipl, par[P_RES_CDA], par[P_RES_REC], props, eps, E, 1)
    # network solves: [throttle body, plenum], (lumped) [collector], [intake port, cylinder, exhaust port]
    solve_two(0, 1, E, props, rate, nvol, dt)
    if not pipes_on:
        lin_between(icol, nvol + 1, par[P_TP_CDA], 0.0, props, eps, E, 2)
        solve_one(2, E, props, rate, nvol, dt)
    for k in range(ncyl):
        le = (s_step + stage - offs[k]) % nstep
        e = 3 + 2 * k
        E[e, 6] = 0.0
        E[e + 1, 6] = 0.0
        aiv = tab[T_AIV, le]
        aev = tab[T_AEV, le]
        if aiv > 0.0:
            lin_between(ncyl + k, k, aiv, 0.0, props, eps, E, e)
        if aev > 0.0:
            lin_between(k, 2 * ncyl + k, aev, 0.0, props, eps, E, e + 1)
        if aiv > 0.0 and aev > 0.0:
            solve_two(e, e + 1, E, props, rate, nvol, dt)
        elif aiv > 0.0:
            solve_one(e, E, props, rate, nvol, dt)
        elif aev > 0.0:
            solve_one(e + 1, E, props, rate, nvol, dt)

    # ---- apply the flows (each leaves one volume and enters another, same mass and enthalpy)
    mth = E[0, 6]
    transfer(amb, itb, mth, nvol, props, dvol)
    acc[A_AIR] += mth * (1.0 if mth >= 0.0 else props[itb, PR_YA])   # air only: what an airflow meter sees
    acc[A_MIN] += mth                                                 # all species: for the mass balance
    acc[A_HAIR] += mth * (props[amb, PR_H] if mth >= 0.0 else props[itb, PR_H])
    transfer(itb, ipl, E[1, 6], nvol, props, dvol)
    if not pipes_on:
        mtp = E[2, 6]
        transfer(icol, nvol + 1, mtp, nvol, props, dvol)
        acc[A_OUT] += mtp
        acc[A_HOUT] += mtp * props[icol, PR_H]
    evap = par[P_EVAP]
    for k in range(ncyl):
        base = A_CYL0 + AC_N * k
        e = 3 + 2 * k
        m_in = E[e, 6]
        if m_in != 0.0:
            iv_transfer(ncyl + k, k, m_in, far, fuel_c, evap, nvol, props, dvol, acc)
        m_ex = E[e + 1, 6]
        if m_ex != 0.0:
            transfer(k, 2 * ncyl + k, m_ex, nvol, props, dvol)
            if m_ex > 0.0:
                acc[base + AC_EXM] += m_ex
                acc[base + AC_EXMT] += m_ex * props[k, PR_T]
        # port wall heat transfer at the flow through the port's valve
        if par[P_PHT_MULT] > 0.0:
            qi = _port_heat(ncyl + k, m_in, props, par[P_PHT_A_IN], par[P_PHT_D_IN], par[P_PHT_TW_IN],
                            par[P_PHT_MULT])
            qe = _port_heat(2 * ncyl + k, m_ex, props, par[P_PHT_A_EX], par[P_PHT_D_EX], par[P_PHT_TW_EX],
                            par[P_PHT_MULT])
            dvol[ncyl + k, V_U] += qi
            dvol[2 * ncyl + k, V_U] += qe
            acc[A_QPORT] += qi + qe
    return 0


@njit(cache=True, fastmath=FASTMATH)
def run_engine(par, tab, offs, coeffs, rsp, fuel_c, vol, mr, ref, vfix, out, trace, hist,
               pipes, geom, q, tcell, ends, endp):
    """Integrate whole cycles until the engine repeats itself.

    Parameters
    ----------
    par : (NPAR,) float64
        Scalar parameters, see :mod:`.layout` (``P_*``).
    tab : (NTAB, nstep) float64
        Per-local-angle tables (``T_*``), index 0 = firing TDC, step ``par[P_DT]`` in time.
    offs : (ncyl,) int64
        Firing-TDC step index of each cylinder in engine steps.
    coeffs : (3, 2, 7) float64
        Mass-based NASA coefficients of air, mixture, products (:mod:`engine_model.thermo`).
    rsp : (3,) float64
        Specific gas constants of the three species [J/(kg K)].
    fuel_c : (2, 7) float64
        Fuel-vapour coefficients.
    vol : (nvol, NVCOL) float64
        Initial state of every volume; overwritten with the final state.
    mr : (ncyl * (nseg_in + nseg_ex),) float64
        Lumped runner state: segment mass flows [kg/s] (intake runners, then exhaust, each runner's
        segments from its upstream end); empty in the 1D gas exchange; overwritten.
    ref : (ncyl, 5) float64
        Per-cylinder reference state of the closed period: pressure [Pa],
        temperature [K] and volume [m^3] at IVC, isentropic exponent
        (gamma-1)/gamma [-] and mixture mass at SOC [kg]; overwritten with the
        values at the end.  Rows with ``ref[k, 1] <= 0`` are unknown (cold
        start) and get defaults.  The mixture mass at SOC of a cylinder that is
        burning at the start is always re-derived from its state, so that the
        burn that straddles the start completes whatever the previous run's
        burn law (the remaining mixture over the remaining Wiebe fraction).
    vfix : (nvol,) float64
        Volumes [m^3] (cylinder entries ignored).
    out : (NOUT,) float64
        Cycle results of the last cycle (``O_*``).
    trace : (2*ncyl + NTR_EXTRA, nstep) float64
        Last-cycle traces: cylinder pressures, cylinder temperatures, plenum, collector, throttle-body,
        intake-port-1 and exhaust-port-1 pressures, then the pressures in intake runner 1 (middle, port
        end) and exhaust primary 1 (port end, middle) [Pa, K] (port pressures when lumped).
    hist : (nh, H_N0 + nvol*(NVCOL-1) + len(mr) + ncell*NQ) float64
        Per-cycle record (row = cycle - 1, up to ``nh`` cycles; ``nh`` may be 0):
        trapped mass [kg], net work [J], mass imbalance [-], then the end-of-cycle
        state (volume masses and energies, runner flows, pipe cells).
    pipes : (npipe, 2) int64; geom : (NG, ncell) float64
        Pipe layout and cell geometry (:func:`.pipes.build_pipes`); empty when lumped.
    q : (ncell, NQ) float64; tcell : (ncell,) float64
        Pipe cell state and temperatures (Newton start); overwritten with the final state.
    ends : (npipe, 2, NE) int64; endp : (npipe, 2, NEP) float64
        What is at each pipe end and its parameters (:mod:`.pipenet`).
    """
    ncyl = int(par[P_NCYL])
    nstep = int(par[P_NSTEP])
    dt = par[P_DT]
    nvol = vol.shape[0]
    ipl = 3 * ncyl
    itb = ipl + 1
    icol = ipl + 2
    nacc = A_CYL0 + AC_N * ncyl
    idx_ivc = int(par[P_IDX_IVC])
    idx_soc = int(par[P_IDX_SOC])
    maxcyc = int(par[P_MAXCYC])
    mincyc = int(par[P_MINCYC])
    tol = par[P_TOL]
    pipes_on = par[P_GASX] > 0.5
    ncell = q.shape[0]
    npipe = pipes.shape[0]

    cbuf = np.empty(4)
    t_start = np.zeros(nvol)            # start-of-step temperature of the previous step [K] (0 = none yet)
    hcoeffs = np.empty((3, 2, 6))      # enthalpy-polynomial form of ``coeffs`` for the property evaluation
    enthalpy_coeffs_into(coeffs, hcoeffs)
    props = np.zeros((nvol + 2, NPR))   # + ambient, + (lumped) tailpipe pseudo-volume
    set_ambient(props, nvol, par, coeffs, rsp)
    vcur = vfix.copy()
    vol1 = np.empty_like(vol)
    d0 = np.empty_like(vol)
    d1 = np.empty_like(vol)
    mr1 = np.empty_like(mr)
    dm0 = np.zeros_like(mr)
    dm1 = np.zeros_like(mr)
    rate = np.zeros(nvol)
    E = np.zeros((3 + 2 * ncyl, 7))
    a0 = np.zeros(nacc)
    a1 = np.zeros(nacc)
    cyc_acc = np.zeros(nacc)
    # pipe work arrays (1D)
    prim = np.zeros((NPM, ncell))
    fric = np.full((NF, ncell), np.nan)
    work = np.zeros((NWK, ncell))
    bflux = np.zeros((npipe, 2, NQ))
    wb = np.zeros((npipe, 2, 2))
    xfer = np.zeros((nvol + 1, NVCOL))
    xrate = np.zeros(nvol + 1)
    counter = np.zeros(1, dtype=np.int64)
    fric_every = max(int(par[P_FRIC_EVERY]), 1)
    cfl = par[P_CFL]
    # trace cells: intake runner 1 middle and port end, exhaust primary 1 port end and middle
    tr_cells = np.zeros(4, dtype=np.int64)
    if npipe > ncyl:
        tr_cells[0] = pipes[0, 0] + pipes[0, 1] // 2
        tr_cells[1] = pipes[0, 0] + pipes[0, 1] - 1
        tr_cells[2] = pipes[ncyl, 0]
        tr_cells[3] = pipes[ncyl, 0] + pipes[ncyl, 1] // 2
    # per-cylinder reference state: p_ivc, T_ivc, V_ivc, isentropic exponent, mixture mass at SOC
    for k in range(ncyl):
        if not (ref[k, 1] > 0.0):
            ref[k, 0] = par[P_PAMB]
            ref[k, 1] = 330.0
            ref[k, 2] = tab[T_V, idx_ivc]
            ref[k, 3] = 0.4 / 1.4
        ref[k, 4] = 0.0
        li0 = (nstep - offs[k]) % nstep
        if tab[T_PHASE, li0] > 1.5 and li0 != idx_soc:
            xb0 = tab[T_XB, li0]
            ref[k, 4] = vol[k, V_MM] / (1.0 - xb0) if xb0 < 1.0 - 1e-9 else vol[k, V_MM]
    # end gas per cylinder: mixed NASA block of its composition at the spark, and
    # [s0(T_soc) - R ln p_soc, R, last temperature (Newton start), dilution factor (1 - x_b)^d, isentrope set]
    egc = np.zeros((ncyl, 2, 7))
    egs = np.zeros((ncyl, 5))
    egs[:, 3] = 1.0
    knock_run = np.zeros(ncyl)       # running Livengood-Wu integral since IVC
    knock_cyc = np.zeros(ncyl)       # value reached in this cycle
    trapped = np.zeros(ncyl)
    trapped_fresh = np.zeros(ncyl)
    resid = np.zeros(ncyl)
    pmax = np.zeros(ncyl)
    pmax_ang = np.zeros(ncyl)
    wgross = np.zeros(ncyl)
    wpump = np.zeros(ncyl)
    ppl_sum = 0.0
    out_m = 0.0                      # 1D: mass and enthalpy out of the tailpipe this cycle
    out_h = 0.0
    pipe_e_in = 0.0                  # 1D: energy into the pipes through their ends this cycle
    pipe_e0 = 0.0
    max_sub = 0
    max_cour = 0.0

    prev_trap = -1.0
    prev_work = 0.0
    # MPE acceleration of the slow cycle-to-cycle modes (see ``accel``)
    acc_k = int(par[P_ACCEL_K])
    acc_warm = int(par[P_ACCEL_WARM])
    nx = nvol * (NVCOL - 1) + mr.shape[0] + ncell * NQ
    xs = np.zeros((max(acc_k, 1) + 2, nx))
    xw = np.zeros(nx)
    xe = np.zeros(nx)
    G = np.zeros((max(acc_k, 1), max(acc_k, 1)))
    grhs = np.zeros(max(acc_k, 1))
    n_x = 0
    d_prev = -1.0
    rho_slow = RHO_START   # contraction ratio of the slowest mode: assumed, then from the last MPE fit
    converged = 0
    fail = 0
    cyc = 0
    pref = par[P_PAMB] * par[P_VD] * ncyl   # work scale for the convergence floor [J]
    dtrap = 1.0
    dwork = 1.0
    for cyc in range(1, maxcyc + 1):
        cyc_acc[:] = 0.0
        pmax[:] = 0.0
        wgross[:] = 0.0
        wpump[:] = 0.0
        knock_cyc[:] = 0.0
        ppl_sum = 0.0
        out_m = 0.0
        out_h = 0.0
        pipe_e_in = 0.0
        pipe_e0 = pipe_energy(q)
        max_sub = 0
        max_cour = 0.0
        for s in range(nstep):
            # ---- crank-angle events at the start of the step
            for k in range(ncyl):
                li = (s - offs[k]) % nstep
                if li == idx_ivc:
                    m = vol[k, V_MA] + vol[k, V_MM] + vol[k, V_MP]
                    trapped[k] = m
                    trapped_fresh[k] = vol[k, V_MA] + vol[k, V_MM]
                    resid[k] = vol[k, V_MP] / m
                    knock_cyc[k] = max(knock_cyc[k], knock_run[k])
                    knock_run[k] = 0.0
                    egs[k, 3] = dilution_factor(resid[k], par[P_KN_D])
                    egs[k, 4] = 0.0
                if li == idx_soc:
                    ref[k, 4] = vol[k, V_MM]
            # ---- pipes: one crank step in sub-steps, against the volumes' start-of-step state
            have = False
            if pipes_on:
                for k in range(ncyl):
                    vcur[k] = tab[T_V, (s - offs[k]) % nstep]
                fail = eval_props(vol, vcur, nvol, hcoeffs, rsp, cbuf, props)
                if fail != 0:
                    break
                counter[0] = s     # friction refresh at fixed crank steps of the cycle
                fail, nsub, e_step, cour = pipe_step(q, tcell, geom, pipes, prim, fric, work, bflux, wb, ends, endp,
                                               props, nvol, hcoeffs, rsp, dt, cfl, fric_every, counter, xfer,
                                               xrate)
                if fail != 0:
                    break
                have = True
                pipe_e_in += e_step
                out_m += xfer[nvol, V_MA] + xfer[nvol, V_MM] + xfer[nvol, V_MP]
                out_h += xfer[nvol, V_U]
                if nsub > max_sub:
                    max_sub = nsub
                if cour > max_cour:
                    max_cour = cour
            # ---- stage 1
            fail = _derivs(vol, mr, s, 0, par, tab, offs, hcoeffs, rsp, fuel_c, ref, egc, egs, nvol, cbuf, props,
                           vcur, d0, dm0, a0, rate, E, xfer, xrate, have)
            if fail != 0:
                break
            # ---- record the state at the start of the step
            for k in range(ncyl):
                li = (s - offs[k]) % nstep
                p = props[k, PR_P]
                trace[k, s] = p
                trace[ncyl + k, s] = props[k, PR_T]
                if p > pmax[k]:
                    pmax[k] = p
                    ang = li * (720.0 / nstep)
                    pmax_ang[k] = ang if ang < 360.0 else ang - 720.0
                if li == idx_soc:    # end gas: composition and entropy at the spark
                    m = vol[k, V_MA] + vol[k, V_MM] + vol[k, V_MP]
                    if m > 0.0:
                        mix_coeffs(coeffs, vol[k, V_MA] / m, vol[k, V_MM] / m, vol[k, V_MP] / m, egc[k])
                        r_u = (vol[k, V_MA] * rsp[0] + vol[k, V_MM] * rsp[1] + vol[k, V_MP] * rsp[2]) / m
                        egs[k, 0] = s0_mass(egc[k], props[k, PR_T]) - r_u * math.log(p)
                        egs[k, 1] = r_u
                        egs[k, 2] = props[k, PR_T]
                        egs[k, 4] = 1.0
                if li == idx_ivc:
                    ref[k, 0] = p
                    ref[k, 1] = props[k, PR_T]
                    ref[k, 2] = vcur[k]
                    g = props[k, PR_G]
                    ref[k, 3] = (g - 1.0) / g
            trace[2 * ncyl, s] = props[ipl, PR_P]
            trace[2 * ncyl + 1, s] = props[icol, PR_P]
            trace[2 * ncyl + 2, s] = props[itb, PR_P]
            trace[2 * ncyl + 3, s] = props[ncyl, PR_P]
            trace[2 * ncyl + 4, s] = props[2 * ncyl, PR_P]
            for r in range(4):
                if pipes_on:
                    trace[2 * ncyl + 5 + r, s] = prim[PM_P, tr_cells[r]]
                else:
                    trace[2 * ncyl + 5 + r, s] = props[ncyl if r < 2 else 2 * ncyl, PR_P]
            ppl_sum += props[ipl, PR_P]
            # ---- stage 2 (predictor state at the end of the step)
            # Newton start for the end-of-step temperatures: linear extrapolation in
            # time from the last two start-of-step temperatures (leaves ~T'' dt^2
            # to iterate instead of ~T' dt; the answer does not depend on it)
            for i in range(nvol):
                for c in range(NVCOL - 1):
                    vol1[i, c] = vol[i, c] + dt * d0[i, c]
                t0 = vol[i, V_T]
                vol1[i, V_T] = 2.0 * t0 - t_start[i] if t_start[i] > 0.0 else t0
                t_start[i] = t0
            for i in range(mr.shape[0]):
                mr1[i] = mr[i] + dt * dm0[i]
            fail = _derivs(vol1, mr1, s, 1, par, tab, offs, hcoeffs, rsp, fuel_c, ref, egc, egs, nvol, cbuf, props,
                           vcur, d1, dm1, a1, rate, E, xfer, xrate, False)
            if fail != 0:
                break
            h2 = 0.5 * dt
            for i in range(nvol):
                for c in range(NVCOL - 1):
                    vol[i, c] += h2 * (d0[i, c] + d1[i, c])
                vol[i, V_T] = vol1[i, V_T]
            for i in range(mr.shape[0]):
                mr[i] += h2 * (dm0[i] + dm1[i])
            for i in range(nacc):
                cyc_acc[i] += h2 * (a0[i] + a1[i])
            for k in range(ncyl):
                base = A_CYL0 + AC_N * k
                wk = h2 * (a0[base + AC_WORK] + a1[base + AC_WORK])
                li = (s - offs[k]) % nstep
                if li < nstep // 4 or li >= 3 * nstep // 4:
                    wgross[k] += wk
                else:
                    wpump[k] += wk
                knock_run[k] += h2 * (a0[base + AC_KNOCK] + a1[base + AC_KNOCK])
        if fail != 0:
            break
        if pipes_on:
            cyc_acc[A_OUT] += out_m
            cyc_acc[A_HOUT] += out_h
        # ---- end of cycle: convergence on trapped mass, net work and mass balance
        mtrap = trapped.sum()
        wnet = wgross.sum() + wpump.sum()
        min_ = cyc_acc[A_MIN] + cyc_acc[A_FUEL]
        mbal = abs(min_ - cyc_acc[A_OUT]) / min_ if min_ > 0.0 else 1.0
        # Distance to the periodic solution, estimated from the change per cycle d
        # and the contraction ratio rho: the remaining geometric tail is
        # d*rho/(1 - rho).  rho is the larger of the ratio of the last two changes
        # and the slowest ratio known (RHO_START, then the last MPE fit), so a
        # slow mode hiding under a fast transient is not mistaken for convergence;
        # a growing change never converges.
        est = 1.0
        have_est = False
        if prev_trap > 0.0:
            dtrap = abs(mtrap - prev_trap) / mtrap
            dwork = abs(wnet - prev_work) / max(abs(wnet), 0.01 * pref)
            # the cycle's mass imbalance is a level with a floor set by the integration error, not a
            # change that decays geometrically: it is required below the tolerance on its own and kept out
            # of the tail estimate (inside it, a floor near 1e-4 blocked convergence at some points)
            dn = max(dtrap, dwork)
            rho = max(dn / d_prev, rho_slow) if d_prev > 0.0 else rho_slow
            est = dn * rho / (1.0 - rho) if rho < RHO_MAX else 1.0
            have_est = True
            if cyc >= mincyc and est < tol and dn < tol and mbal < MBAL_SHARE * tol:
                converged = 1
            d_prev = dn
        else:
            d_prev = -1.0
        out[O_EST] = est
        if cyc <= hist.shape[0]:
            hrow = cyc - 1
            hist[hrow, H_MTRAP] = mtrap
            hist[hrow, H_WNET] = wnet
            hist[hrow, H_MBAL] = mbal
            j = H_N0
            for i in range(nvol):
                for c in range(NVCOL - 1):
                    hist[hrow, j] = vol[i, c]
                    j += 1
            for i in range(mr.shape[0]):
                hist[hrow, j] = mr[i]
                j += 1
            for i in range(ncell):
                for c in range(NQ):
                    hist[hrow, j] = q[i, c]
                    j += 1
        prev_trap = mtrap
        prev_work = wnet
        if converged == 1:
            break
        # ---- acceleration: MPE over the last acc_k + 2 end-of-cycle states
        if acc_k > 0 and cyc >= acc_warm:
            pack_state(vol, mr, q, xs[n_x])
            n_x += 1
            if n_x == acc_k + 2:
                jumped = False
                if have_est and est > tol and cyc + 3 <= maxcyc:
                    state_weights(vol, mr, q, xw, ncyl)
                    ratio = mpe(xs, n_x, xw, xe, G, grhs)
                    if ratio >= 0.0:
                        # a species mass that the extrapolation would drive below zero
                        # (mixture left in the exhaust from the start, decaying to 0)
                        # drops to a tenth instead; likewise in the pipe cells
                        xl = xs[n_x - 1]
                        for j in range(nvol * (NVCOL - 1)):
                            if j % (NVCOL - 1) < V_U and xe[j] < 0.1 * xl[j]:
                                xe[j] = 0.1 * xl[j]
                        j0 = nvol * (NVCOL - 1) + mr.shape[0]
                        for i in range(ncell):
                            for c in (Q_A, Q_M, Q_P):
                                j = j0 + i * NQ + c
                                if xe[j] < 0.1 * xl[j]:
                                    xe[j] = 0.1 * xl[j]
                        unpack_state(xe, vol, mr, q)
                        jumped = True
                        rho_slow = min(max(ratio, RHO_START), RHO_MAX)
                        prev_trap = -1.0   # the next cycle starts a fresh comparison
                if jumped:
                    pack_state(vol, mr, q, xs[0])
                    n_x = 1
                else:
                    for r in range(n_x - 1):
                        xs[r, :] = xs[r + 1, :]
                    n_x -= 1

    est = out[O_EST]
    out[:] = 0.0
    out[O_EST] = est
    out[O_CYCLES] = cyc
    out[O_CONVERGED] = converged
    out[O_FAIL] = fail
    if fail != 0:
        out[O_CONVERGED] = 0
        return
    out[O_AIR] = cyc_acc[A_AIR]
    out[O_FUEL] = cyc_acc[A_FUEL]
    out[O_EXH] = cyc_acc[A_OUT]
    out[O_HAIR] = cyc_acc[A_HAIR]
    out[O_HFUEL] = cyc_acc[A_HFUEL]
    out[O_HOUT] = cyc_acc[A_HOUT]
    out[O_FUEL_BURNED] = cyc_acc[A_BURN]
    out[O_WGROSS] = wgross.sum()
    out[O_WPUMP] = wpump.sum()
    out[O_QPORT] = cyc_acc[A_QPORT]
    if pipes_on:
        # heat the pipes' gas took from their walls: the change of their energy minus what came in at the ends
        out[O_QPIPE] = (pipe_energy(q) - pipe_e0) - pipe_e_in
        out[O_SUBSTEPS] = max_sub
        out[O_COURANT] = max_cour
    exm = 0.0
    exmt = 0.0
    for k in range(ncyl):
        base = A_CYL0 + AC_N * k
        out[O_QWALL] += cyc_acc[base + AC_Q]
        exm += cyc_acc[base + AC_EXM]
        exmt += cyc_acc[base + AC_EXMT]
        out[O_PMAX] += pmax[k] / ncyl
        out[O_PMAX_ANG] += pmax_ang[k] / ncyl
        out[O_RES] += resid[k] / ncyl
        out[O_KNOCK] = max(out[O_KNOCK], knock_cyc[k])
    out[O_TEXH] = exmt / exm if exm > 0.0 else 0.0
    out[O_MTRAP] = trapped.sum()
    out[O_MAIR_TRAP] = trapped_fresh.sum()
    min_ = cyc_acc[A_MIN] + cyc_acc[A_FUEL]
    out[O_MBAL] = abs(min_ - cyc_acc[A_OUT]) / min_ if min_ > 0.0 else 1.0
    out[O_PPLENUM] = ppl_sum / nstep
    out[O_DTRAP] = dtrap
    out[O_DIMEP] = dwork
