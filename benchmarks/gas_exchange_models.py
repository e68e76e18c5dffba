"""The 1D pipes against the lumped runners on Table 2's operating points (prints figures, asserts nothing).

The lumped option (``gas_exchange.model = "lumped"``) replaces every runner by ``runner_segments`` lumped
inertances with the gas volumes between them; its intake port is a perfectly mixed volume, so gas pushed
back from the cylinder during overlap is mixed into the port and carried on into the plenum, where in a
pipe it stays as a slug near the valve and is drawn back first.  For the 1D default and for 1, 2, 4 and 8
lumped segments per runner, at the seven Table 2 speeds (WOT, the measured spark, lambda 0.9, BDUR10-90 =
24 deg, m = 6.4), it prints

- the burned-gas mass fraction and the temperature of the plenum at the end of the converged cycle,
- the residual gas fraction, the volumetric efficiency and the airflow error against the bench,
- the cycles to converge and the CPU time per cycle.

Run: ``.venv/bin/python benchmarks/gas_exchange_models.py [--models 1d,lumped:1,lumped:8] [--csv F]
[--spec-override KEY=VALUE ...]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from engine_model import OperatingPoint, default_spec, simulate_point
from engine_model.bench import load_bench
from engine_model.cycle import layout as L


def _model_spec(base, name: str):
    if name == "1d":
        return base.with_values({"gas_exchange.model": "1d"})
    kind, _, nseg = name.partition(":")
    if kind != "lumped" or not nseg.isdigit():
        raise ValueError(f"--models: {name!r} is not '1d' or 'lumped:<segments>'")
    return base.with_values({"gas_exchange.model": "lumped", "intake.runner_segments": int(nseg),
                             "exhaust.runner_segments": int(nseg)})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="1d,lumped:1,lumped:2,lumped:4,lumped:8",
                    help="models to compare: 1d, lumped:<segments> (comma separated)")
    ap.add_argument("--csv", help="also write the table to this CSV file")
    ap.add_argument("--spec-override", action="append", default=[], metavar="KEY=VALUE",
                    help="spec field to change for every run, e.g. exhaust.runner_length_m=0.275")
    args = ap.parse_args(argv)

    base = default_spec()
    if args.spec_override:
        base = base.with_values({k: float(v) for k, v in (o.split("=", 1) for o in args.spec_override)})
    ncyl = base.geometry.n_cylinders
    bench = load_bench()
    rows = []
    print(f"spec overrides: {args.spec_override or 'none'}")
    print(f"{'model':>9} {'rpm':>6} {'pl yP':>6} {'pl T K':>7} {'resid':>6} {'VE':>6} {'VE bench':>8} "
          f"{'air err':>8} {'cycles':>6} {'ms/cyc':>7}")
    for name in args.models.split(","):
        spec = _model_spec(base, name)
        simulate_point(spec, OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4))   # compile before timing
        errs = []
        for _, b in bench.iterrows():
            op = OperatingPoint(float(b["speed_rpm"]), float(b["throttle_pct"]), float(b["spark_deg_btdc"]),
                                float(b["lambda"]), 24.0, 6.4)
            c0 = time.thread_time()
            row, state = simulate_point(spec, op)
            cpu = time.thread_time() - c0
            vol = state[0]
            i = 3 * ncyl
            m = vol[i, L.V_MA] + vol[i, L.V_MM] + vol[i, L.V_MP]
            yp, tpl = vol[i, L.V_MP] / m, vol[i, L.V_T]
            ve_bench = row["vol_eff"] * b["air_mass_flow_kg_h"] / row["air_mass_flow_kg_h"]
            err = row["air_mass_flow_kg_h"] / b["air_mass_flow_kg_h"] - 1.0
            errs.append(err)
            rows.append({"model": name, "speed_rpm": op.speed_rpm, "plenum_y_burned": yp, "plenum_temp_k": tpl,
                         "residual_fraction": row["residual_fraction"], "vol_eff": row["vol_eff"],
                         "vol_eff_bench": ve_bench, "airflow_error": err, "converged": row["converged"],
                         "cycles_run": row["cycles_run"], "cpu_ms_per_cycle": cpu / row["cycles_run"] * 1e3})
            flag = "" if row["converged"] else "  NOT CONVERGED"
            print(f"{name:>9} {op.speed_rpm:6.0f} {yp:6.3f} {tpl:7.1f} {row['residual_fraction']:6.3f} "
                  f"{row['vol_eff']:6.3f} {ve_bench:8.3f} {err * 100:+7.1f}% {row['cycles_run']:6d} "
                  f"{cpu / row['cycles_run'] * 1e3:7.2f}{flag}")
        errs = np.abs(errs)
        print(f"    {name}: airflow error max {errs.max() * 100:.1f} %, mean |err| {errs.mean() * 100:.1f} %")
    if args.csv:
        pd.DataFrame(rows).round(5).to_csv(args.csv, index=False)
        print(f"wrote {args.csv}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
