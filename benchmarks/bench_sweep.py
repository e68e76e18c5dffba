"""Throughput, overhead and driver memory of the sweep pipeline (prints figures; not part of the tests).

Figures printed, for a plan of >= 10,000 points (operating points x the
paper's Wiebe grid, consecutive rows of one operating point, as a real
identification sweep is):

- throughput of ``run_sweep`` on 1 and on 2 local Dask workers, and the ratio
  (target: 2 workers >= 1.8 x one);
- orchestration overhead: the 1-worker sweep against calling
  ``engine_model.simulate`` directly on the same points in one process
  (target <= 10 %);
- time to first result;
- peak memory of the driver process (RSS high-water mark of the process that
  runs the flow; the Prefect server and the Dask workers are other processes)
  against the number of points, up to 100,000 (target: flat, < 1 GiB).

Every measurement runs in a fresh subprocess so that peaks do not leak from
one to the next.  The solver settings are options: the defaults (1 deg,
1 % tolerance) keep the whole benchmark near half an hour on 2 cores; the
100,000-point memory run uses a 2 deg step and 5 % tolerance, since it
measures the driver, not the physics.

Run: ``.venv/bin/python benchmarks/bench_sweep.py [--points 10000] [--memory-points 1000,10000,100000]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd

WIEBE_BDUR = np.arange(20, 51, 2)
WIEBE_M = np.arange(2, 9, 1)


def make_plan(n_points: int) -> pd.DataFrame:
    """Operating points (speed x throttle) crossed with the Wiebe grid, first ``n_points`` rows."""
    rows = []
    speeds = np.arange(3000, 13001, 500)
    throttles = [30.0, 50.0, 70.0, 100.0]
    k = 0
    for rep in range(1000):
        for th in throttles:
            for n in speeds:
                spark = 25.0 + 0.0015 * n + 0.1 * (100 - th) + rep * 0.5
                for b in WIEBE_BDUR:
                    for m in WIEBE_M:
                        rows.append((f"b{k:06d}", float(n), th, round(spark, 2), 0.9 if th == 100 else 1.0,
                                     float(b), float(m)))
                        k += 1
                        if k >= n_points:
                            return pd.DataFrame(rows, columns=["point_id", "speed_rpm", "throttle_pct",
                                                               "spark_deg_btdc", "lambda", "bdur_10_90_deg",
                                                               "wiebe_m"])
    raise ValueError("plan too large")


DIRECT = textwrap.dedent("""
    import json, resource, sys, time
    import pandas as pd
    from engine_model import SolverSettings, default_spec
    from engine_model.sim import simulate
    plan = pd.read_parquet(sys.argv[1])
    solver = SolverSettings(step_deg=float(sys.argv[2]), tolerance=float(sys.argv[3]))
    spec = default_spec()
    simulate(spec, plan.iloc[:1], solver)            # load kernels (cached) before timing
    t0 = time.perf_counter()
    res = simulate(spec, plan, solver)
    wall = time.perf_counter() - t0
    print(json.dumps({"wall_s": wall, "points": len(res),
                      "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
""")

SWEEP = textwrap.dedent("""
    import json, resource, sys, time
    t0 = time.perf_counter()
    from flows.sweep import run_sweep
    man = run_sweep(sys.argv[1], sys.argv[2], workers=int(sys.argv[3]), step_deg=float(sys.argv[4]),
                    tolerance=float(sys.argv[5]), progress=False)
    print(json.dumps({"total_s": time.perf_counter() - t0, "manifest": man,
                      "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
""")


def _py(code: str, *args) -> dict:
    res = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(res.stderr[-3000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=10000)
    ap.add_argument("--step-deg", type=float, default=1.0)
    ap.add_argument("--tolerance", type=float, default=1e-2)
    ap.add_argument("--memory-points", default="1000,10000,100000")
    ap.add_argument("--direct-s", type=float, default=None,
                    help="reuse the direct-call wall time of an earlier run on the same plan and solver [s]")
    ap.add_argument("--memory-step-deg", type=float, default=2.0)
    ap.add_argument("--memory-tolerance", type=float, default=5e-2)
    args = ap.parse_args(argv)
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    tmp = Path(tempfile.mkdtemp(prefix="bench_sweep_"))
    plan = make_plan(args.points)
    plan_path = tmp / "plan.parquet"
    plan.to_parquet(plan_path, index=False)
    print(f"plan: {len(plan)} points ({len(plan) // (len(WIEBE_BDUR) * len(WIEBE_M)) + 1} operating points x "
          f"Wiebe grid), solver step {args.step_deg:g} deg, tolerance {args.tolerance:g}; scratch {tmp}")

    if args.direct_s is None:
        direct = _py(DIRECT, plan_path, args.step_deg, args.tolerance)
        print(f"direct, one process:        {direct['wall_s']:8.1f} s  {len(plan) / direct['wall_s']:7.1f} pt/s")
    else:
        direct = {"wall_s": args.direct_s}
        print(f"direct, one process:        {direct['wall_s']:8.1f} s  (given with --direct-s, not measured)")
    runs = {}
    for w in (1, 2):
        r = _py(SWEEP, plan_path, tmp / f"sweep_w{w}", w, args.step_deg, args.tolerance)
        m = r["manifest"]
        runs[w] = r
        print(f"sweep, {w} worker(s):        {m['timings']['wall_s']:8.1f} s in the flow "
              f"({r['total_s']:.1f} s with Prefect server and cluster start-up)  "
              f"{len(plan) / m['timings']['wall_s']:7.1f} pt/s; first result after {m['timings']['first_result_s']} s; "
              f"chunk {m['chunk_size']} points; driver peak RSS {r['peak_rss_mib']:.0f} MiB")
    w1, w2 = runs[1]["manifest"]["timings"]["wall_s"], runs[2]["manifest"]["timings"]["wall_s"]
    print(f"\nspeed-up 2 workers / 1 worker: {w1 / w2:.2f}x   (target >= 1.8x)")
    print(f"orchestration overhead, 1 worker vs direct: {100 * (w1 / direct['wall_s'] - 1):+.1f} % in the flow, "
          f"{100 * (runs[1]['total_s'] / direct['wall_s'] - 1):+.1f} % including start-up   (target <= 10 %)")

    print(f"\ndriver memory (2 workers, step {args.memory_step_deg:g} deg, tolerance {args.memory_tolerance:g}):")
    for n in [int(x) for x in args.memory_points.split(",") if x]:
        p = tmp / f"plan_{n}.parquet"
        make_plan(n).to_parquet(p, index=False)
        r = _py(SWEEP, p, tmp / f"mem_{n}", 2, args.memory_step_deg, args.memory_tolerance)
        m = r["manifest"]
        print(f"  {n:7d} points: driver peak RSS {r['peak_rss_mib']:6.0f} MiB, {m['timings']['wall_s']:7.1f} s, "
              f"{m['chunks']} chunks, all points: {m['counts']['points'] == n}")


if __name__ == "__main__":
    main()
