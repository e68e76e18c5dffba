"""Speed of the cycle kernel (prints figures; not part of the test run).

Figures printed, for the 1D gas exchange (the default) and the lumped runners (the fast option) in the
same run:
- numba compile time, cold (fresh cache folder, in a subprocess) and cached;
- microseconds per cylinder-cycle and milliseconds per 4-cylinder cycle;
- milliseconds per converged operating point from a cold start, median over
  >= 50 points spread over throttle, speed and spark;
- milliseconds per point inside a Wiebe sweep at one operating point, where
  consecutive points start from the previous converged gas-exchange state;
- cycles to converge, and the largest deviation of the converged answer
  (trapped mass, net IMEP) from the long-run periodic solution (150 plain
  cycles) on a subset of the points of both parts.

Run: ``make bench`` or ``.venv/bin/python benchmarks/bench_cycle.py [--points N]``.
Single core: numba kernels are serial; set NUMBA_NUM_THREADS=1 for certainty.
Times are wall clock and, in brackets, the thread's CPU time (``time.thread_time``),
which does not count the time the process waits for a core on a shared machine.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import textwrap
import time

import numpy as np
import pandas as pd

COMPILE_SNIPPET = textwrap.dedent("""
    import time
    t0 = time.perf_counter()
    from engine_model import OperatingPoint, default_spec, simulate_point
    t1 = time.perf_counter()
    simulate_point(default_spec(), OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4))
    t2 = time.perf_counter()
    print(f"{t1 - t0:.3f} {t2 - t1:.3f}")
""")


def _compile_time(cache_dir: str) -> tuple[float, float]:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    out = subprocess.run([sys.executable, "-c", COMPILE_SNIPPET], env=env, capture_output=True, text=True, check=True)
    imp, first = (float(x) for x in out.stdout.split())
    return imp, first


def _deviation(spec, solver, ops, rows) -> tuple[float, float]:
    """Largest relative deviation of trapped mass and net IMEP from 150 plain cycles (the periodic solution)."""
    from engine_model import SolverSettings, simulate_point
    long = SolverSettings(step_deg=solver.step_deg, max_cycles=150, min_cycles=150, accelerate=False)
    dm = dw = 0.0
    for op, row in zip(ops, rows):
        ref, _ = simulate_point(spec, op, long)
        dm = max(dm, abs(row["trapped_mass_mg"] / ref["trapped_mass_mg"] - 1.0))
        dw = max(dw, abs(row["imep_net_bar"] / ref["imep_net_bar"] - 1.0))
    return dm, dw


def _wiebe_sweep(spec, solver, grid, check, label) -> None:
    """Time a Wiebe sweep at 9000 rpm WOT (consecutive rows reuse the converged state) and check it."""
    from engine_model import OperatingPoint
    from engine_model.sim import simulate

    sweep = pd.DataFrame({"speed_rpm": 9000.0, "throttle_pct": 100.0, "spark_deg_btdc": 50.0, "lambda": 0.9,
                          "bdur_10_90_deg": [g[0] for g in grid], "wiebe_m": [g[1] for g in grid]})
    t0, c0 = time.perf_counter(), time.thread_time()
    res = simulate(spec, sweep, solver)
    el = time.perf_counter() - t0
    cel = time.thread_time() - c0
    print(f"\nWiebe sweep at 9000 rpm WOT, {len(sweep)} points (BDUR10-90 20..50 x m 2..8), warm state reused{label}:")
    print(f"  per point:                    mean {el / len(sweep) * 1e3:7.1f} ms   (CPU {cel / len(sweep) * 1e3:.1f} ms)"
          f"   median cycles {res['cycles_run'].median():.0f}   max {res['cycles_run'].max()}"
          f"   not converged {int((~res['converged']).sum())}")
    sops = [OperatingPoint(9000.0, 100.0, 50.0, 0.9, float(b), float(m)) for b, m in grid]
    idx = np.linspace(0, len(sops) - 1, min(check, len(sops))).astype(int)
    dev = _deviation(spec, solver, [sops[i] for i in idx], [res.iloc[i] for i in idx])
    print(f"  max deviation from the 150-cycle answer ({len(idx)} points): "
          f"trapped mass {dev[0] * 100:.3f} %, net IMEP {dev[1] * 100:.3f} %")


def _cells(spec) -> int:
    from engine_model.sim.prepare import pipe_network
    return pipe_network(spec)[0].ncell


def _measure(spec, args) -> None:
    """Cold points and a Wiebe sweep of one gas-exchange model."""
    from engine_model import OperatingPoint, SolverSettings, simulate_point

    solver = SolverSettings()
    simulate_point(spec, OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4), solver)  # warm this process

    rng = np.random.default_rng(20261122)
    n = max(args.points, 50)
    speeds = rng.uniform(3000.0, 13000.0, n)
    throttles = rng.uniform(20.0, 100.0, n)
    sparks = rng.uniform(20.0, 50.0, n)
    t_point, c_point, cycles, n_bad, ops, rows = [], [], [], 0, [], []
    for sp, th, sa in zip(speeds, throttles, sparks):
        op = OperatingPoint(float(sp), float(th), float(sa), 0.9 if th > 90 else 1.0, 24.0, 6.4)
        t0, c0 = time.perf_counter(), time.thread_time()
        row, _ = simulate_point(spec, op, solver)
        t_point.append(time.perf_counter() - t0)
        c_point.append(time.thread_time() - c0)
        cycles.append(row["cycles_run"])
        n_bad += not row["converged"]
        ops.append(op)
        rows.append(row)
    t_point = np.array(t_point)
    c_point = np.array(c_point)
    cycles = np.array(cycles)
    per_cycle = t_point / cycles
    cpu_cycle = c_point / cycles
    ncyl = spec.geometry.n_cylinders
    print(f"\nstep {solver.step_deg} deg (1D: refined where a pipe wave would cross more than cfl cells), "
          f"tolerance {solver.tolerance:g}, {n} points (3000-13000 rpm, 20-100 % throttle, spark 20-50 deg BTDC)")
    print(f"  per 4-cylinder cycle:         median {np.median(per_cycle) * 1e3:7.2f} ms"
          f"   (CPU {np.median(cpu_cycle) * 1e3:.2f} ms)")
    print(f"  per cylinder-cycle:           median {np.median(per_cycle) / ncyl * 1e6:7.0f} us"
          f"   (CPU {np.median(cpu_cycle) / ncyl * 1e6:.0f} us)")
    print(f"  cycles to converge:           median {np.median(cycles):5.0f}   max {cycles.max()}"
          f"   not converged {n_bad}")
    print(f"  per converged point (cold):   median {np.median(t_point) * 1e3:7.1f} ms"
          f"   p90 {np.percentile(t_point, 90) * 1e3:.1f} ms   (CPU median {np.median(c_point) * 1e3:.1f} ms)")
    dev = _deviation(spec, solver, ops[:args.check], rows[:args.check])
    print(f"  max deviation from the 150-cycle answer ({args.check} points): "
          f"trapped mass {dev[0] * 100:.3f} %, net IMEP {dev[1] * 100:.3f} %")

    k = int(round(np.sqrt(args.sweep)))
    grid = [(b, m) for b in np.linspace(20.0, 50.0, k) for m in np.linspace(2.0, 8.0, k)]
    _wiebe_sweep(spec, solver, grid, args.check, "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=60, help="operating points for the cold-start median (>= 50)")
    ap.add_argument("--sweep", type=int, default=49, help="points of the Wiebe sweep (7 x 7 by default)")
    ap.add_argument("--check", type=int, default=12, help="points of each part checked against a 150-cycle run")
    ap.add_argument("--no-compile", action="store_true", help="skip the compile-time measurement")
    ap.add_argument("--models", default="1d,lumped", help="gas-exchange models to measure (comma separated)")
    args = ap.parse_args(argv)

    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    if not args.no_compile:
        with tempfile.TemporaryDirectory() as cache:
            imp_c, cold = _compile_time(cache)
            imp_w, warm = _compile_time(cache)
        print("numba compile + first point (subprocess, fresh cache):  "
              f"{cold:6.2f} s   (import {imp_c:.2f} s)")
        print("cached load + first point   (subprocess, warm cache):   "
              f"{warm:6.2f} s   (import {imp_w:.2f} s)")

    from engine_model import default_spec

    models = args.models.split(",")
    for model in models:
        spec = default_spec().with_values({"gas_exchange.model": model})
        print(f"\n===== gas_exchange.model = {model!r}" + (
            f" (cells of {spec.gas_exchange.cell_length_m * 1e3:.0f} mm, "
            f"{_cells(spec)} cells in all)" if model == "1d" else ""))
        _measure(spec, args)
    print(f"load average at end: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
