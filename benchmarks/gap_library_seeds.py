"""The gap diagnosis on its own library over many noise seeds, without re-simulating the truths.

Usage::

    python benchmarks/gap_library_seeds.py --plan PLAN.csv --save-prepared P.pkl      # simulate once (~15 min)
    python benchmarks/gap_library_seeds.py --prepared P.pkl --seeds 30-89 [--csv OUT.csv]

The first form runs ``run_benchmark`` (12 effects at realistic magnitude, the null and the
out-of-library VE bump, on the given plan; ``mbc gap-plan --points 32 --out PLAN.csv`` makes the
default one) and pickles its noiseless truths and linearisations.  The second re-diagnoses them with the
noise the benchmark draws for seed ``s`` (``apply_noise(truth, NoiseModel(), 1000 + s)``), ~1 min per 20
seeds, and prints top-1, wrong claims, null and bump claims, per effect and per category.
"""

from __future__ import annotations

import argparse
import pickle
import time

import pandas as pd

from engine_model.bench.virtual import NoiseModel, apply_noise
from engine_model.gap.benchmark import OOL_EFFECT, run_benchmark
from engine_model.gap.diagnose import diagnose


def seed_range(text: str) -> range:
    a, _, b = text.partition("-")
    try:
        lo, hi = int(a), int(b or a)
    except ValueError:
        raise SystemExit(f"--seeds {text!r}: expected A-B (e.g. 30-89) or one seed") from None
    if hi < lo:
        raise SystemExit(f"--seeds {text!r}: the end is before the start")
    return range(lo, hi + 1)


def rediagnose(prepared: dict, seeds: range) -> pd.DataFrame:
    cache: dict = {}
    rows = []
    for (eff, mag), truth in prepared["truth"].items():
        lin = prepared["linearisations"][(eff, mag)]
        for s in seeds:
            d = diagnose(lin, apply_noise(truth, NoiseModel(), 1000 + s), k_folds=5, n_noise=200, seed=0,
                         noise_cache=cache)
            rows.append({"effect": eff, "seed": s, "category": d.category, "named": d.named, "best": d.best})
    return pd.DataFrame(rows)


def main(argv=None) -> pd.DataFrame | None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plan", default=None, help="plan CSV for --save-prepared")
    ap.add_argument("--save-prepared", default=None, help="simulate the truths on --plan and pickle them here")
    ap.add_argument("--prepared", default=None, help="re-diagnose this pickle")
    ap.add_argument("--seeds", default="30-49", help="noise seeds A-B (default 30-49)")
    ap.add_argument("--csv", default=None, help="write the per-trial table here")
    a = ap.parse_args(argv)
    if a.save_prepared:
        if not a.plan:
            raise SystemExit("--save-prepared needs --plan")
        plan = pd.read_csv(a.plan)
        plan["point_id"] = plan["point_id"].astype(str)
        res = run_benchmark(seeds=1, magnitudes=(1.0,), plan=plan, verify=False, progress=print)
        with open(a.save_prepared, "wb") as f:
            pickle.dump({k: res[k] for k in ("truth", "linearisations", "plan")}, f)
        print(f"saved {a.save_prepared}")
        return None
    if not a.prepared:
        raise SystemExit("give --prepared P.pkl (or --plan and --save-prepared to make one)")
    with open(a.prepared, "rb") as f:
        prepared = pickle.load(f)
    seeds = seed_range(a.seeds)
    t0 = time.perf_counter()
    t = rediagnose(prepared, seeds)
    if a.csv:
        t.to_csv(a.csv, index=False)
    lib = t[~t["effect"].isin(["none", OOL_EFFECT])]
    ok = lib["named"] == lib["effect"]
    print(f"seeds {seeds.start}-{seeds.stop - 1}, {time.perf_counter() - t0:.0f} s")
    print(f"top-1 {100 * ok.mean():.1f} % ({ok.sum()} of {len(lib)}); wrong claims "
          f"{int((lib['named'].notna() & ~ok).sum())}; null claims {int(t[t.effect == 'none'].named.notna().sum())} "
          f"of {int((t.effect == 'none').sum())}; bump claims {int(t[t.effect == OOL_EFFECT].named.notna().sum())}")
    pd.set_option("display.width", 200)
    print((100 * lib.assign(ok=ok).groupby("effect")["ok"].mean()).round(1).to_string())
    print(pd.crosstab(t["effect"], t["category"]).to_string())
    return t


if __name__ == "__main__":
    main()
