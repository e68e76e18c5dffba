"""How much of the uncalibrated Table 2 airflow gap is the lumping of the runners?  (prints figures)

The intake port is a perfectly mixed 0D volume, and a 1-segment runner has
no gas volume of its own (half of it is lumped with the port, half with the
plenum).  Gas pushed back from the cylinder during valve overlap and before
IVC therefore mixes into the port and is carried on into the plenum, where
in a real runner most of it would stay as a slug near the valve and be
drawn back in first.  This script measures that artefact and the backflow slug that removes it
(``intake.runner_backflow_slug``: the gas a port pushes back is held in its
runner's plenum-side share and drawn back first, see ``cycle/engine.py``):
for 1, 2, 4 and 8 segments per runner (intake and exhaust alike), with the
backflow mixed into the plenum and with the slug, at the seven Table 2 speeds
(WOT, measured spark, lambda 0.9, BDUR10-90 = 24 deg, m = 6.4) it prints

- the burned-gas and fresh-mixture mass fractions and the temperature of the
  plenum's bulk (end-of-cycle state of the converged cycle, the slugs held
  for the runners left out; the plenum barely moves within a cycle),
- the residual gas fraction, the volumetric efficiency (and the bench's,
  scaled from the measured airflow), the airflow error against the bench,
- the cycles to converge and the CPU time per cycle (more segments mean more
  volumes).

Run: ``.venv/bin/python benchmarks/runner_lumping.py [--spec-override KEY=VALUE ...]``.
Nothing is asserted; docs/sections/speed.md and the README (Known gaps) quote
the figures.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from engine_model import OperatingPoint, default_spec, simulate_point
from engine_model.bench import load_bench
from engine_model.cycle import layout as L


def _plenum(vol, mr, ncyl, nflow):
    """Burned-gas and fresh-mixture mass fractions of the plenum's bulk, and the plenum temperature.

    Volume order as in cycle/engine.py; the runners' backflow slugs (ledgers in
    ``mr`` after the ``nflow`` runner flows, empty when the slug is off) are
    taken out of the plenum node's masses.
    """
    i = 3 * ncyl
    slugs = mr[nflow:nflow + L.NSLUG * ncyl].reshape(ncyl, L.NSLUG)
    ma, mm, mp = (vol[i, c] - slugs[:, s].sum() for c, s in ((L.V_MA, L.SL_A), (L.V_MM, L.SL_M), (L.V_MP, L.SL_P)))
    m = ma + mm + mp
    return mp / m, mm / m, vol[i, L.V_T]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--segments", default="1,2,4,8", help="segment counts to compare (comma separated)")
    ap.add_argument("--backflow", default="mixed,slug", help="backflow models to compare: mixed, slug (comma separated)")
    ap.add_argument("--csv", help="also write the table to this CSV file")
    ap.add_argument("--spec-override", action="append", default=[], metavar="KEY=VALUE",
                    help="spec field to change for every run, e.g. exhaust.runner_length_m=0.275")
    args = ap.parse_args(argv)

    base = default_spec()
    if args.spec_override:
        base = base.with_values({k: float(v) for k, v in (o.split("=", 1) for o in args.spec_override)})
    ncyl = base.geometry.n_cylinders
    bench = load_bench()
    simulate_point(base, OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4))   # load the kernels before timing
    rows = []
    print(f"spec overrides: {args.spec_override or 'none'}")
    print(f"{'backflow':>8} {'seg':>3} {'rpm':>6} {'pl yP':>6} {'pl yM':>6} {'pl T K':>7} {'resid':>6} {'VE':>6} {'VE bench':>8} "
          f"{'air err':>8} {'cycles':>6} {'ms/cyc':>7}")
    runs = [(bf, int(s)) for bf in args.backflow.split(",") for s in args.segments.split(",")]
    for backflow, nseg in runs:
        if backflow not in ("mixed", "slug"):
            ap.error(f"--backflow: {backflow!r} is not one of mixed, slug")
        spec = base.with_values({"intake.runner_segments": nseg, "exhaust.runner_segments": nseg,
                                 "intake.runner_backflow_slug": backflow == "slug"})
        nflow = ncyl * 2 * nseg
        errs = []
        for _, b in bench.iterrows():
            op = OperatingPoint(float(b["speed_rpm"]), float(b["throttle_pct"]), float(b["spark_deg_btdc"]),
                                float(b["lambda"]), 24.0, 6.4)
            c0 = time.thread_time()
            row, state = simulate_point(spec, op)
            cpu = time.thread_time() - c0
            yp, ym, tpl = _plenum(state[0], state[1], ncyl, nflow)
            ve_bench = row["vol_eff"] * b["air_mass_flow_kg_h"] / row["air_mass_flow_kg_h"]
            err = row["air_mass_flow_kg_h"] / b["air_mass_flow_kg_h"] - 1.0
            errs.append(err)
            rows.append({"backflow": backflow, "segments": nseg, "speed_rpm": op.speed_rpm, "plenum_y_burned": yp, "plenum_y_mixture": ym,
                         "plenum_temp_k": tpl, "residual_fraction": row["residual_fraction"],
                         "vol_eff": row["vol_eff"], "vol_eff_bench": ve_bench, "airflow_error": err,
                         "converged": row["converged"], "cycles_run": row["cycles_run"],
                         "cpu_ms_per_cycle": cpu / row["cycles_run"] * 1e3})
            flag = "" if row["converged"] else "  NOT CONVERGED"
            print(f"{backflow:>8} {nseg:3d} {op.speed_rpm:6.0f} {yp:6.3f} {ym:6.3f} {tpl:7.1f} {row['residual_fraction']:6.3f} "
                  f"{row['vol_eff']:6.3f} {ve_bench:8.3f} {err * 100:+7.1f}% {row['cycles_run']:6d} "
                  f"{cpu / row['cycles_run'] * 1e3:7.2f}{flag}")
        errs = np.abs(errs)
        print(f"    {backflow}, {nseg} segment(s): airflow error max {errs.max() * 100:.1f} %, mean |err| {errs.mean() * 100:.1f} %")
    if args.csv:
        pd.DataFrame(rows).round(5).to_csv(args.csv, index=False)
        print(f"wrote {args.csv}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
