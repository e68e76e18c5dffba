"""Two effects withheld at once: does the best-pair search name both? (prints figures; not a test).

The virtual bench (hidden burn law, gearbox, noise, the operator's knock back-off) runs the gap
benchmark's 32-point Sobol' plan with two library effects present at their realistic magnitudes;
the base model is calibrated on the null case, as in ``mbc gap-benchmark``; each noise seed is
diagnosed (single effects) and then searched for the best pair (:func:`engine_model.gap.best_pair`).
One-effect cases and the null case count false pair claims.

Run: ``.venv/bin/python benchmarks/gap_pairs.py [--seeds 10] [--out docs/data/gap_pairs_benchmark.csv]``
"""

from __future__ import annotations

import argparse
import time

import pandas as pd

PAIRS = (("transmission_efficiency", "runner_inertia"), ("heat_transfer", "exhaust_back_pressure"),
         ("friction", "intake_air_temperature"), ("combustion_efficiency", "restrictor"))
SINGLES = ("transmission_efficiency", "heat_transfer", "friction", "restrictor", "runner_inertia")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10, help="noise seeds per case (0 .. seeds-1)")
    ap.add_argument("--out", default=None, help="CSV with one row per trial")
    args = ap.parse_args(argv)

    from engine_model import default_spec

    from engine_model.sim import simulate
    from engine_model.bench.burnlaw import BurnLaw
    from engine_model.gap import EFFECTS, best_pair, calibrate_base, choose_base, diagnose, get_effect, linearise
    from engine_model.gap.bench_procedure import BENCH_SOLVER, measure_with_backoff
    from engine_model.gap.benchmark import benchmark_plan
    from engine_model.bench.virtual import NoiseModel, VirtualBench, apply_noise

    t0 = time.perf_counter()
    spec = default_spec()

    def ev(p):
        return simulate(spec, p, BENCH_SOLVER)

    plan = benchmark_plan(32, 0, spec, ev, BENCH_SOLVER)
    cases = {("none",): {}}
    for e in SINGLES:
        cases[(e,)] = {e: get_effect(e).at_magnitude(1.0)}
    for a, b in PAIRS:
        cases[(a, b)] = {a: get_effect(a).at_magnitude(1.0), b: get_effect(b).at_magnitude(1.0)}
    truth, plans = {}, {}
    for key, eff in cases.items():
        vb = VirtualBench(spec=spec, law=BurnLaw(), effects=eff or None, noise=NoiseModel.none(), solver=BENCH_SOLVER)
        plans[key], truth[key] = measure_with_backoff(vb, plan, ev)
    print(f"truth: {len(cases)} cases ({time.perf_counter() - t0:.0f} s)", flush=True)
    base = choose_base(plans[("none",)])
    theta, _, _ = calibrate_base(plans[("none",)], truth[("none",)], ev, base, iterations=3, spec=spec)
    union = pd.concat(list(plans.values()), ignore_index=True).drop_duplicates("point_id").reset_index(drop=True)
    lin_all = linearise(union, ev, base, effects=list(EFFECTS), theta=theta, spec=spec)
    print(f"base {theta}; linearisation {lin_all.n_simulations} simulations ({time.perf_counter() - t0:.0f} s)",
          flush=True)

    rows, cache, pcache = [], {}, {}
    for key in cases:
        lin = lin_all.select(list(plans[key]["point_id"].astype(str)))
        for s in range(args.seeds):
            meas = apply_noise(truth[key], NoiseModel(), 1000 + s)
            d = diagnose(lin, meas, n_noise=200, seed=0, noise_cache=cache)
            p = best_pair(d, n_noise=200, seed=0, noise_cache=pcache)
            top = p.table.iloc[0]
            named = tuple(sorted(p.named)) if p.named else ()
            rows.append({"effects_withheld": "+".join(key), "n_withheld": 0 if key == ("none",) else len(key),
                         "seed": s, "single_named": d.named or "none",
                         "pair_named": "+".join(named) if named else "none",
                         "pair_correct": named == tuple(sorted(key)) if len(key) == 2 else not named,
                         "pair_contains_one": bool(set(named) & set(key)) if len(key) == 2 else None,
                         "best_pair": f"{top['effect_a']}+{top['effect_b']}",
                         "gap_before": round(d.gap_before, 4), "gap_after_single": round(d.gap_after, 4),
                         "gap_after_pair": round(float(top["heldout_gap_rms"]), 4),
                         "pair_reduction_pct": round(float(top["reduction_pct"]), 1),
                         "pair_excess": round(float(top["improvement_over_best_single"]), 2),
                         "pair_excess_threshold": round(p.excess_threshold, 2), "pair_params": top["params"]})
    table = pd.DataFrame(rows)
    print(f"diagnosis + pair search: {len(table)} trials ({time.perf_counter() - t0:.0f} s)\n")
    summ = table.groupby("effects_withheld", sort=False).agg(
        trials=("seed", "size"), pair_correct=("pair_correct", "mean"), any_pair_claim=("pair_named", lambda v: (v != "none").mean()),
        single_named=("single_named", lambda v: v.value_counts().to_dict()),
        gap_before=("gap_before", "median"), gap_single=("gap_after_single", "median"),
        gap_pair=("gap_after_pair", "median"))
    with pd.option_context("display.width", 200, "display.max_colwidth", 80):
        print(summ.to_string())
        two = table[table["n_withheld"] == 2]
        print("\npairs named when two effects are withheld:")
        print(two.groupby("effects_withheld", sort=False)["pair_named"].value_counts().to_string())
    if args.out:
        table.to_csv(args.out, index=False)
        print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
