"""The gap diagnosis on truths outside its library: per-category table (``engine_model.gap.outside``).

Usage::

    python benchmarks/gap_outside.py [--plan PLAN.csv] [--seeds 3] [--seed-start 0] [--null-seeds 60]
                                     [--out DIR] [--save-prepared P.pkl | --prepared P.pkl]

Without ``--plan`` the 32-point discriminating plan is computed first (its 160-point candidate pool and
linearisation: ~20 min on 2 cores); ``mbc gap-plan --points 32 --out PLAN.csv`` makes one to reuse.
Prints the per-kind and per-case tables and the issue's overall figures; ``--out`` also writes
``<out>/gap/outside_*.csv`` and ``outside.md``.
"""

from __future__ import annotations

import argparse
import json
import pickle
import time

import pandas as pd

from engine_model.gap.outside import prepared_of, run_outside_benchmark, write_outside_report


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plan", default=None, help="plan CSV (point_id, speed_rpm, throttle_pct, spark_deg_btdc, lambda)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--null-seeds", type=int, default=60)
    ap.add_argument("--out", default=None)
    ap.add_argument("--save-prepared", default=None, help="pickle the truths and linearisations here")
    ap.add_argument("--prepared", default=None, help="re-diagnose a pickle of --save-prepared (no simulation)")
    a = ap.parse_args(argv)
    plan = pd.read_csv(a.plan) if a.plan else None
    if plan is not None:
        plan["point_id"] = plan["point_id"].astype(str)
    prepared = None
    if a.prepared:
        with open(a.prepared, "rb") as f:
            prepared = pickle.load(f)
    t0 = time.perf_counter()
    res = run_outside_benchmark(plan=plan, seeds=a.seeds, seed_start=a.seed_start, null_seeds=a.null_seeds,
                                prepared=prepared,
                                progress=lambda s: print(f"[{time.perf_counter() - t0:6.0f} s] {s}", flush=True))
    pd.set_option("display.width", 200)
    pd.set_option("display.max_colwidth", 60)
    cols = ["trials", "right_pct", "refusal_pct", "wrong_pct", "confident_wrong", "right_or_refusal_pct",
            "acceptable_pct"]
    print(res["summary"][["kind"] + cols].round(1).to_string(index=False))
    print(res["by_case"][["case"] + cols + ["wrong_names", "categories"]].round(1).to_string(index=False))
    print(json.dumps(res["overall"], indent=1))
    print(json.dumps(res["timing"]))
    if a.save_prepared:
        with open(a.save_prepared, "wb") as f:
            pickle.dump(prepared_of(res), f)
    if a.out:
        paths = write_outside_report(res, a.out)
        print({k: str(v) for k, v in paths.items()})
    return res


if __name__ == "__main__":
    main()
