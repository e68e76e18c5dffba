"""The ``plan`` flow: generate a DOE test plan and save it under ``doe_plans/`` (Parquet + CSV + metadata).

A thin layer over :mod:`engine_model.doe`: the generators, feasibility
filter, bench run order and Wiebe grid all live there; this module only maps
command-line options onto them and runs the generation as a Prefect flow.
"""

from __future__ import annotations

import argparse

import numpy as np

from flows import prefect_env

from prefect import flow  # noqa: E402

from engine_model import load_spec  # noqa: E402

from engine_model import doe
from engine_model import priors
from engine_model.knock import knock_sweep_plan

KINDS = ("full-factorial", "lhs", "sobol", "d-optimal", "spark-sweep", "knock-sweeps")
KNOCK_THROTTLES = "60,80,100"
KNOCK_POINTS = 40
DEFAULT_SPEEDS = "3000:13000:1000"
DEFAULT_THROTTLES = "10,20,30,40,60,80,100"


def parse_values(text: str, what: str) -> np.ndarray:
    """'a,b,c' or 'start:stop:step' (stop included) -> array; ValueError naming the option."""
    try:
        if ":" in text:
            a, b, s = (float(x) for x in text.split(":"))
            if s <= 0 or b < a:
                raise ValueError
            return np.round(np.arange(a, b + 0.5 * s, s), 9)
        return np.array([float(x) for x in text.split(",") if x.strip()])
    except ValueError:
        raise ValueError(f"--{what} = {text!r}: expected 'a,b,c' or 'start:stop:step' with step > 0") from None


def parse_bounds(items: list[str] | None) -> dict:
    """['speed_rpm=3000:13000', ...] -> {'speed_rpm': (3000.0, 13000.0), ...}."""
    out = {}
    for it in items or []:
        try:
            name, rng = it.split("=")
            lo, hi = (float(x) for x in rng.split(":"))
        except ValueError:
            raise ValueError(f"--bound {it!r}: expected COLUMN=LOW:HIGH, e.g. speed_rpm=3000:13000") from None
        out[name.strip()] = (lo, hi)
    return out


@flow(name="plan", log_prints=False, validate_parameters=False)
def plan_flow(kind: str, name: str, out_dir: str = "doe_plans", n: int = 64, seed: int = 0,
              speeds: str = DEFAULT_SPEEDS, throttles: str = DEFAULT_THROTTLES, bounds: dict | None = None,
              model: str = "quadratic", feasibility: str = "flag", wiebe_grid: bool = False,
              spec: str | None = None, run: str | None = None) -> dict:
    """Generate a plan of kind ``kind`` and save it as ``out_dir``/``name``.{parquet,csv,meta.json}.

    Returns the saved paths and the plan's metadata.
    """
    if kind not in KINDS:
        raise ValueError(f"plan kind {kind!r} unknown; choose one of {', '.join(KINDS)}")
    if feasibility not in ("flag", "drop", "off"):
        raise ValueError(f"--feasibility {feasibility!r}: choose flag, drop or off")
    eng = load_spec(spec)
    sp, th = parse_values(speeds, "speeds"), parse_values(throttles, "throttles")
    bnds = bounds or {"speed_rpm": (float(sp.min()), float(sp.max())),
                      "throttle_pct": (float(th.min()), float(th.max()))}
    meta = {"generator": kind, "seed": seed, "bounds": bnds}
    if kind == "full-factorial":
        plan = doe.full_factorial(speed_rpm=sp, throttle_pct=th)
        meta.update(speeds=sp.tolist(), throttles=th.tolist())
    elif kind == "lhs":
        plan = doe.latin_hypercube(n, bnds, seed=seed)
    elif kind == "sobol":
        plan = doe.sobol(n, bnds, seed=seed)
    elif kind == "d-optimal":
        plan = doe.d_optimal(n, model=model, bounds=bnds, seed=seed)
        meta.update(model=model, d_efficiency=plan.attrs.get("d_efficiency"))
    elif kind == "knock-sweeps":
        start, source = _start_map(run)
        plan = knock_sweep_plan(start, sp, th, max_points=n)
        meta.update(speeds=sp.tolist(), throttles=th.tolist(), start_map=source, step_deg=3.0, retard_deg=12.0,
                    procedure="per sweep_id, run the steps in order from the retarded start; log knock 0/1 at "
                              "every step run; stop at the first knocking step or when torque stops rising (MBT); "
                              "if the first step already knocks, retard in the same 3 deg steps until it runs "
                              "clean and log those too; rows not reached stay out of the bench file")
    else:
        pairs = [(float(t), float(s)) for t in th for s in sp]
        plan = doe.spark_sweeps(pairs, spec=eng)
        meta.update(speeds=sp.tolist(), throttles=th.tolist())
    if feasibility != "off" and kind not in ("spark-sweep", "knock-sweeps"):
        plan = doe.feasibility(plan, spec=eng, drop=feasibility == "drop")
        meta["feasibility"] = feasibility
    if kind != "knock-sweeps":     # a sweep's steps run in their own order
        plan = doe.bench_order(plan)
    plan = priors.with_combustion(plan)
    if wiebe_grid:
        plan = doe.wiebe_grid(plan)
        meta["wiebe_grid"] = True
    saved = doe.save_plan(plan, name, directory=out_dir, metadata=meta)
    return {"paths": [str(saved[k]) for k in ("parquet", "csv", "meta")], "points": len(plan),
            "metadata": saved["metadata"]}


def _start_map(run: str | None):
    """(spark(speed, throttle) of the map the knock sweeps start from, its description): a run's spark table
    (bilinear, held at the edges) or the prior's MBT estimate."""
    if run is None:
        return (lambda n, t: float(priors.spark_estimate(n, t))), "prior MBT estimate (engine_model.priors)"
    from pathlib import Path

    import pandas as pd
    from scipy.interpolate import RegularGridInterpolator
    path = Path(run) / "maps" / "spark_advance.csv"
    if not path.is_file():
        raise ValueError(f"--run {run}: no spark table at {path} (run the maps stage first)")
    tab = pd.read_csv(path, index_col=0)
    th = tab.index.to_numpy(float)
    sp = np.array([float(c) for c in tab.columns])
    f = RegularGridInterpolator((th, sp), tab.to_numpy(float))
    return (lambda n, t: float(f([[np.clip(t, th.min(), th.max()), np.clip(n, sp.min(), sp.max())]])[0])), str(path)


def add_plan_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("kind", choices=KINDS, help="design")
    p.add_argument("--name", required=True, help="plan name (files doe_plans/NAME.parquet, .csv, .meta.json)")
    p.add_argument("--out-dir", default="doe_plans", help="folder for the plan files (default doe_plans/)")
    p.add_argument("--n", type=int, default=None, help=f"points (lhs, sobol, d-optimal: default 64; knock-sweeps: "
                                                     f"at most this many, default {KNOCK_POINTS})")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--speeds", default=DEFAULT_SPEEDS, help=f"rpm values 'a,b' or 'start:stop:step' "
                                                            f"(default {DEFAULT_SPEEDS})")
    p.add_argument("--throttles", default=None, help=f"throttle %% values (default {DEFAULT_THROTTLES}; "
                                                   f"knock-sweeps {KNOCK_THROTTLES})")
    p.add_argument("--bound", action="append", help="COLUMN=LOW:HIGH for lhs/sobol/d-optimal (repeatable)")
    p.add_argument("--model", default="quadratic", choices=("linear", "interaction", "quadratic"),
                   help="response-surface model of the D-optimal design (default quadratic)")
    p.add_argument("--feasibility", default="flag", choices=("flag", "drop", "off"),
                   help="quick-model check of the knock-limited and near-zero-BMEP zones (default flag)")
    p.add_argument("--wiebe-grid", action="store_true",
                   help="cross every point with the paper's grid BDUR10-90 20..50 deg x m 2..8")
    p.add_argument("--spec", default=None, help="engine spec TOML (default: embedded Yamaha R6 FS)")
    p.add_argument("--run", default=None, help="knock-sweeps: start from this run's spark table (maps/), retarded "
                                             "12 deg (default: the prior's MBT estimate)")


def plan_from_args(args) -> dict:
    """``mbc plan``: run :func:`plan_flow` under one Prefect API; print where the plan went."""
    bounds = parse_bounds(args.bound)
    knock = args.kind == "knock-sweeps"
    throttles = args.throttles or (KNOCK_THROTTLES if knock else DEFAULT_THROTTLES)
    n = args.n if args.n is not None else (KNOCK_POINTS if knock else 64)
    parse_values(args.speeds, "speeds")
    parse_values(throttles, "throttles")
    if args.run is not None and not knock:
        raise ValueError("--run applies to knock-sweeps plans only")
    if knock:
        _start_map(args.run)      # a missing table is refused before any work
    with prefect_env.prefect_api():
        res = plan_flow(kind=args.kind, name=args.name, out_dir=args.out_dir, n=n, seed=args.seed,
                        speeds=args.speeds, throttles=throttles, bounds=bounds or None, model=args.model,
                        feasibility=args.feasibility, wiebe_grid=args.wiebe_grid, spec=args.spec, run=args.run)
    print(f"{args.kind} plan, {res['points']} points -> " + ", ".join(res["paths"]))
    return res



