"""Speed of the pipe kernel per engine cycle (prints figures, asserts nothing).

An R6-like pipe set: 4 intake runners (0.2 m, 36 mm, 8 cells), 4 exhaust primaries (0.30, 0.35,
0.40, 0.45 m, 32 mm, 12-18 cells), a collector (0.1 m, 50 mm, 4 cells) and a tailpipe (0.15 m,
45 mm, 6 cells): 102 cells of ~25 mm in 10 pipes.  Every pipe end is joined to a 0D volume through
an orifice (``pipe_bc.bc_orifice``): plenum -> throttle-sized orifice -> runner -> intake valve ->
cylinder -> exhaust valve -> primary -> collector volume -> collector pipe -> silencer volume ->
tailpipe -> ambient.  The volumes are held fixed (cylinders at an intake-stroke and a blowdown
state); the valve effective areas follow sin^2 lift curves with the R6 firing order phasing, so
every valve end opens, reverses flow and closes once per cycle.  One cycle = 1440 steps of
0.5 deg at 9000 rpm (dt = 9.26e-6 s); the Courant number stays below ~0.5 (``--deg 1`` times
pipe steps of 1 deg instead, Courant ~0.8: what a driver could do at this speed).

Printed: CPU time per cycle (best of ``--repeat``, thread CPU time), its split into the property pass (u -> T Newton),
the end fluxes and the MUSCL-Hancock/HLLC advance, the cost per cell-step, and the accuracy of the
temperature inversion.  Run: ``.venv/bin/python benchmarks/pipe_kernel.py [--cycles N] [--repeat N]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from numba import njit

from engine_model.cycle import pipe_bc as B
from engine_model.cycle import pipes as P
from engine_model.cycle.pipe_scheme import advance
from engine_model.cycle import volumes as VOL
from engine_model.thermo import enthalpy_coeffs, gas_set

RPM = 9000.0
# The njit drivers here are compiled uncached on purpose: numba links the machine code of the
# kernels they call into their own cache entry without tracking the kernels' sources, so a cached
# driver could keep running an old kernel after pipes.py changes (the cache guard in
# engine_model/cycle/__init__.py covers only that package's own cache).
DEG = 0.5           # crank angle per pipe step [deg] (--deg changes it)
NSTEP = int(round(720.0 / DEG))
DT = DEG / (RPM * 6.0)
FRIC_EVERY = 8      # steps between friction-factor refreshes (4 deg)

# volumes: 0 plenum, 1-4 cylinders (intake side state), 5-8 cylinders (exhaust side state),
# 9 collector, 10 silencer, 11 ambient
PLENUM, CYL_IN, CYL_EX, COLLECTOR, SILENCER, AMBIENT = 0, 1, 5, 9, 10, 11
NVOL = 12


def layout():
    specs = []
    for _ in range(4):
        specs.append(P.PipeSpec(0.2, 8, 0.036, wall_temperature=320.0, roughness=2e-5))
    for length, n in ((0.30, 12), (0.35, 14), (0.40, 16), (0.45, 18)):
        specs.append(P.PipeSpec(length, n, 0.032, wall_temperature=700.0, roughness=5e-5))
    specs.append(P.PipeSpec(0.10, 4, 0.050, wall_temperature=650.0, roughness=5e-5))
    specs.append(P.PipeSpec(0.15, 6, 0.045, wall_temperature=550.0, roughness=5e-5))
    return P.build_pipes(specs)


def volume_props(hc, rsp, gs):
    """Fixed property rows of the 12 volumes (layout of volumes.eval_props)."""
    states = [(0.95e5, 305.0, (1.0, 0.0, 0.0))]                       # plenum: air
    states += [(0.90e5, 340.0, (0.0, 0.92, 0.08))] * 4                  # cylinders, intake stroke
    states += [(3.0e5, 1150.0, (0.0, 0.0, 1.0))] * 4                    # cylinders, blowdown
    states += [(1.15e5, 900.0, (0.0, 0.0, 1.0)), (1.05e5, 800.0, (0.0, 0.0, 1.0)),
               (1.0e5, 300.0, (1.0, 0.0, 0.0))]
    props = np.zeros((NVOL, VOL.NPR))
    for k, (p, t, y) in enumerate(states):
        kr = 0 if t < 1000.0 else 1
        h = sum(ys * (t * (c[0] + t * (c[1] + t * (c[2] + t * (c[3] + t * c[4])))) + c[5])
                for ys, c in zip(y, hc[:, kr]))
        cp = sum(ys * (c[0] + t * (2 * c[1] + t * (3 * c[2] + t * (4 * c[3] + t * 5 * c[4]))))
                 for ys, c in zip(y, hc[:, kr]))
        r = float(np.dot(y, rsp))
        props[k, VOL.PR_P], props[k, VOL.PR_T], props[k, VOL.PR_R] = p, t, r
        props[k, VOL.PR_G], props[k, VOL.PR_H] = cp / (cp - r), h
        props[k, VOL.PR_YA:VOL.PR_YP + 1] = y
        props[k, VOL.PR_RHO] = p / (r * t)
    return props


def valve_tables(net, nstep=None):
    """Effective areas per step [m2]: ends table (npipe, 2, nstep) and the volume of each end (npipe, 2)."""
    nstep = NSTEP if nstep is None else nstep
    cda = np.zeros((net.npipe, 2, nstep))
    kv = np.zeros((net.npipe, 2), dtype=np.int64)
    ang = np.arange(nstep) * (720.0 / nstep)
    fire = (0.0, 180.0, 540.0, 360.0)          # R6 firing order 1-2-4-3: TDC of each cylinder [deg]

    def lift(open_deg, dur):
        x = np.mod(ang - open_deg, 720.0) / dur
        return np.where(x < 1.0, np.sin(np.pi * np.clip(x, 0.0, 1.0)) ** 2, 0.0)

    for k in range(4):
        a_in = net.geom[P.G_AR, net.last_cell(k)]
        a_ex = net.geom[P.G_AL, net.first_cell(4 + k)]
        cda[k, 0] = 0.8 * net.geom[P.G_AL, net.first_cell(k)]          # plenum bellmouth-ish
        cda[k, 1] = 0.7 * a_in * lift(fire[k] - 30.0, 250.0)            # intake valve
        cda[4 + k, 0] = 0.6 * a_ex * lift(fire[k] + 130.0, 250.0)       # exhaust valve
        cda[4 + k, 1] = 0.9 * net.geom[P.G_AR, net.last_cell(4 + k)]    # into the collector
        kv[k] = PLENUM, CYL_IN + k
        kv[4 + k] = CYL_EX + k, COLLECTOR
    cda[8, 0] = 0.9 * net.geom[P.G_AL, net.first_cell(8)]
    cda[8, 1] = 0.9 * net.geom[P.G_AR, net.last_cell(8)]
    cda[9, 0] = 0.9 * net.geom[P.G_AL, net.first_cell(9)]
    cda[9, 1] = 0.9 * net.geom[P.G_AR, net.last_cell(9)]
    kv[8] = COLLECTOR, SILENCER
    kv[9] = SILENCER, AMBIENT
    return cda, kv


@njit(cache=False)
def run_cycles(ncyc, q, tc, prim, fric, work, geom, pipes, bflux, wb, props, kv, cda, hc, rsp, dt):
    """Full steps: properties, end fluxes, advance; friction factors every FRIC_EVERY steps.
    Returns the largest Courant number seen."""
    ncell = q.shape[0]
    npipe = pipes.shape[0]
    cmax = 0.0
    for _ in range(ncyc):
        for k in range(cda.shape[2]):
            if P.pipe_props(q, tc, geom, ncell, hc, rsp, prim) != 0:
                return -1.0
            if k % FRIC_EVERY == 0:
                P.friction_factors(prim, geom, ncell, fric)
            for ip in range(npipe):
                for side in range(2):
                    c = cda[ip, side, k]
                    B.bc_orifice(prim, pipes, geom, ip, side, c, c, props, kv[ip, side], wb, bflux)
            cmax = max(cmax, dt / P.max_stable_dt(prim, geom, ncell, 1.0))
            advance(q, prim, geom, pipes, bflux, fric, dt, work)
    return cmax


@njit(cache=False)
def record_cycle(q, tc, prim, fric, work, geom, pipes, bflux, wb, props, kv, cda, hc, rsp, dt, qrec, trec, prec,
                 brec, wrec):
    """One cycle as run_cycles, recording the inputs of every part at every step."""
    ncell = q.shape[0]
    for k in range(cda.shape[2]):
        qrec[k] = q
        trec[k] = tc
        wrec[k] = wb
        P.pipe_props(q, tc, geom, ncell, hc, rsp, prim)
        if k % FRIC_EVERY == 0:
            P.friction_factors(prim, geom, ncell, fric)
        prec[k] = prim
        for ip in range(pipes.shape[0]):
            for side in range(2):
                c = cda[ip, side, k]
                B.bc_orifice(prim, pipes, geom, ip, side, c, c, props, kv[ip, side], wb, bflux)
        brec[k] = bflux
        advance(q, prim, geom, pipes, bflux, fric, dt, work)


@njit(cache=False)
def replay(part, nstep, qrec, trec, prec, brec, wrec, crec, q, tc, prim, fric, work, geom, pipes, bflux, wb, props,
           kv, hc, rsp, dt):
    """Run one part (1 properties, 2 end fluxes, 3 advance, 4 friction factors; 0 none) ``nstep``
    times, cycling through the recorded snapshots; each call first restores the inputs it saw
    (part 0 measures the restoring alone).  The snapshots are few enough to stay in cache."""
    ncell = q.shape[0]
    nsnap = qrec.shape[0]
    for k in range(nstep):
        j = k % nsnap
        q[:] = qrec[j]
        tc[:] = trec[j]
        prim[:] = prec[j]
        bflux[:] = brec[j]
        wb[:] = wrec[j]
        if part == 1:
            P.pipe_props(q, tc, geom, ncell, hc, rsp, prim)
        elif part == 2:
            for ip in range(pipes.shape[0]):
                for side in range(2):
                    c = crec[j, ip, side]
                    B.bc_orifice(prim, pipes, geom, ip, side, c, c, props, kv[ip, side], wb, bflux)
        elif part == 3:
            advance(q, prim, geom, pipes, bflux, fric, dt, work)
        elif part == 4:
            P.friction_factors(prim, geom, ncell, fric)


def best(f, *args, repeat=5):
    """Smallest CPU time of the calling thread [s] over ``repeat`` calls (preemption by other
    processes on a shared machine does not count; cache interference still does)."""
    ts = []
    for _ in range(repeat):
        t = time.thread_time()
        f(*args)
        ts.append(time.thread_time() - t)
    return min(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=3, help="cycles per timed run")
    ap.add_argument("--repeat", type=int, default=5, help="timed runs (best is reported)")
    ap.add_argument("--deg", type=float, default=0.5, help="crank angle per pipe step [deg] (default 0.5)")
    args = ap.parse_args(argv)
    global DEG, NSTEP, DT
    DEG = args.deg
    NSTEP = int(round(720.0 / DEG))
    DT = DEG / (RPM * 6.0)

    gs = gas_set(0.9)
    hc, rsp = enthalpy_coeffs(gs.coeffs), np.array(gs.r_specific)
    net = layout()
    props = volume_props(hc, rsp, gs)
    cda, kv = valve_tables(net)
    q, tc, prim, fric, work, bflux, wb = net.new_arrays()
    for ip in range(net.npipe):
        i0, n = net.pipes[ip]
        exhaust = ip >= 4
        t = 850.0 if exhaust else 310.0
        y = (0.0, 0.0, 1.0) if exhaust else (1.0, 0.0, 0.0)
        P.fill_cells(q, tc, net.geom, i0, i0 + n, 1.05e5 if exhaust else 0.95e5, t, 0.0, *y, hc, rsp)
    # settle into the periodic pattern (and compile)
    cmax = run_cycles(5, q, tc, prim, fric, work, net.geom, net.pipes, bflux, wb, props, kv, cda, hc, rsp, DT)
    assert cmax > 0.0, "property failure"
    t_cyc = best(run_cycles, args.cycles, q, tc, prim, fric, work, net.geom, net.pipes, bflux, wb, props, kv, cda,
                 hc, rsp, DT, repeat=args.repeat) / args.cycles
    # split (approximate): each part alone, on 16 snapshots of a cycle taken in turn
    qrec = np.zeros((NSTEP,) + q.shape)
    trec = np.zeros((NSTEP,) + tc.shape)
    prec = np.zeros((NSTEP,) + prim.shape)
    brec = np.zeros((NSTEP,) + bflux.shape)
    wrec = np.zeros((NSTEP,) + wb.shape)
    record_cycle(q, tc, prim, fric, work, net.geom, net.pipes, bflux, wb, props, kv, cda, hc, rsp, DT,
                 qrec, trec, prec, brec, wrec)
    snap = np.arange(0, NSTEP, NSTEP // 16) + 1
    crec = np.ascontiguousarray(np.moveaxis(cda[:, :, snap], 2, 0))
    recs = [np.ascontiguousarray(r[snap]) for r in (qrec, trec, prec, brec, wrec)]
    q0, tc0 = q.copy(), tc.copy()
    t_part = []
    for part in range(5):
        t_part.append(best(replay, part, NSTEP, *recs, crec, q.copy(), tc.copy(), prim, fric.copy(), work,
                           net.geom, net.pipes, bflux, wb.copy(), props, kv, hc, rsp, DT, repeat=args.repeat))
    t_props, t_bc, t_adv, t_fric = (t - t_part[0] for t in t_part[1:])
    t_fric /= FRIC_EVERY
    cellsteps = net.ncell * NSTEP
    print(f"pipes {net.npipe}, cells {net.ncell}, ends {2 * net.npipe}; {NSTEP} steps of {DT:.3e} s "
          f"({DEG:g} deg at {RPM:.0f} rpm); max Courant number {cmax:.2f}")
    print(f"time per cycle:       {1e3 * t_cyc:7.3f} ms  ({1e9 * t_cyc / cellsteps:5.1f} ns per cell-step)")
    print("split (each part alone on snapshots of the cycle; approximate):")
    print(f"  property pass:      {1e3 * t_props:7.3f} ms  ({1e9 * t_props / cellsteps:5.1f} ns per cell-step)")
    print(f"  end fluxes:         {1e3 * t_bc:7.3f} ms  ({1e9 * t_bc / (NSTEP * 2 * net.npipe):5.1f} ns per end-step)")
    print(f"  advance:            {1e3 * t_adv:7.3f} ms  ({1e9 * t_adv / cellsteps:5.1f} ns per cell-step)")
    print(f"  friction factors:   {1e3 * t_fric:7.3f} ms  (every {FRIC_EVERY} steps)")

    # accuracy of the temperature inversion: compare with a fully converged Newton
    from engine_model.thermo import mixture_tcphr
    P.pipe_props(q0, tc0, net.geom, net.ncell, hc, rsp, prim)
    err = 0.0
    for i in range(net.ncell):
        m = q0[i, :3].sum()
        y = q0[i, :3] / m
        u = q0[i, P.Q_MOM] / m
        e = q0[i, P.Q_E] / m - 0.5 * u * u
        t_ref = mixture_tcphr.py_func(hc, rsp, y[0], y[1], y[2], e, 1000.0)[0]
        err = max(err, abs(prim[P.PM_T, i] - t_ref))
    print(f"temperature inversion: max |T - T_converged| = {err:.2e} K over the cells")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
