"""The gap stage (sim-to-real gap diagnosis of bench data), and the ``gap`` and ``gap-benchmark`` flows.

    bench --validate--> base calibration (smooth combustion law, Gauss-Newton, sweeps on Dask)
          --> one linearisation batch (reference + FD step per base and effect parameter)
          --> diagnosis (residuals, where, which effect, how far it shrinks) --> <out>/gap/

Every simulation runs as a sweep subflow on one shared Dask cluster
(``flows.evaluate.SweepEvaluator``) into ``<out>/sweeps/``; a re-run into the same
folder reads finished batches back.  No physics here: it all lives in
``engine_model.gap``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import time
from pathlib import Path

from flows import prefect_env
from flows.evaluate import SweepEvaluator, shared_cluster
from flows.settings import RunSettings
from flows.stages.context import StageContext
from flows.sweep import DEFAULT_WORKERS

from prefect import flow  # noqa: E402

from engine_model.bench import load_bench  # noqa: E402
from engine_model.calibrated import CalibratedEngine  # noqa: E402
from engine_model.gap.api import diagnose_bench  # noqa: E402
from engine_model.gap.bench_procedure import LINEARISATION_TOLERANCE  # noqa: E402
from engine_model.gap.report import write_gap_report  # noqa: E402
from engine_model.contracts import throttle_to_pct  # noqa: E402
from engine_model.gap.residuals import check_gap_bench  # noqa: E402
from engine_model.io import read_table, write_json  # noqa: E402
from engine_model.report import format_parameters  # noqa: E402
from engine_model.version import package_version  # noqa: E402


def _read_bench(bench: str | None, throttle_unit: str = "pct"):
    """Packaged Table 2 by default; any bench-contract file otherwise (virtual-bench output included).

    Every column the diagnosis needs is checked here, so a bad bench file fails before any server,
    cluster or folder; ``throttle_unit`` "fraction" converts a 0-1 throttle column to percent.
    """
    if bench is None:
        return load_bench(None), "engine_model/data/r6_wot_table2.csv (paper Table 2)"
    p = Path(bench)
    if not p.is_file():
        raise ValueError(f"bench file not found: {p}")
    try:
        df = read_table(p)
    except ValueError as exc:
        raise ValueError(f"bench file {exc}") from None
    df = throttle_to_pct(df, f"bench file {p}", throttle_unit)
    check_gap_bench(df, f"bench file {p}")
    return df, str(p)


def run(ctx: StageContext, n_noise: int = 200) -> dict:
    """The diagnosis of ``ctx.bench`` with the calibrated engine into ``ctx.work/gap``; returns a summary dict."""
    t0 = time.perf_counter()
    ctx.work.mkdir(parents=True, exist_ok=True)
    spec = ctx.engine.spec
    ev = ctx.evaluator("gap", tolerance=LINEARISATION_TOLERANCE)
    d, info = diagnose_bench(ctx.bench, ev, spec=spec, n_noise=n_noise, source=ctx.bench_source)
    notes = [f"Bench: {ctx.bench_source}. Engine: {ctx.engine.source}, calibrated values "
             f"{format_parameters(ctx.engine.overrides) or 'none'}. Base calibration parameters: "
             f"{format_parameters(info['theta']) if isinstance(info['theta'], dict) else info['theta']} "
             f"(base: {info['base']}). "
             f"{ev.points} simulations in {ev.calls} sweep batches."]
    paths = write_gap_report(d, ctx.work, notes=notes)
    summary = {"kind": "gap", "package_version": package_version(), "spec_hash": spec.spec_hash(),
               "bench": ctx.bench_source, "created": _dt.datetime.now().isoformat(timespec="seconds"),
               "category": d.category, "named": d.named, "best": d.best, "confidence": d.confidence,
               "statement": d.statement,
               "gap_before_sigma": d.gap_before, "gap_after_sigma": d.gap_after,
               "gap_reduction_pct": d.gap_reduction_pct, "base_theta": info["theta"],
               "overrides": dict(ctx.engine.overrides), "simulations": ev.points,
               "wall_s": round(time.perf_counter() - t0, 1), "report": os.path.relpath(paths["markdown"], ctx.work)}   # relative: the folder is renamed
    pairs = d.extra.get("pairs")
    if pairs is not None:
        summary["pair_named"] = list(pairs.named) if pairs.named else None
        summary["pair_statement"] = pairs.statement
    write_json(summary, ctx.work / "gap" / "run.json")
    return summary


@flow(name="gap", log_prints=False, validate_parameters=False)
def gap_flow(out: str, bench: str | None = None, spec: str | None = None, step_deg: float = 0.5,
             workers: int = DEFAULT_WORKERS, dask_address: str | None = None, progress: bool = True,
             n_noise: int = 200, overrides: dict | None = None, throttle_unit: str = "pct") -> dict:
    """Gap diagnosis of ``bench`` (packaged Table 2 by default) into ``<out>/gap/``.

    ``overrides`` ({"section.field": value}) fixes spec values from an earlier calibration step
    (e.g. the airflow match) for every simulation.
    """
    df, source = _read_bench(bench, throttle_unit)
    engine = CalibratedEngine.from_spec(spec).calibrated(overrides or {})
    with shared_cluster(workers, dask_address) as addr:
        ctx = StageContext(work=Path(out), engine=engine, engine_file=spec, address=addr,
                           settings=RunSettings(step_deg=step_deg, stages=("gap",)), bench=df, bench_source=source,
                           progress=progress)
        if overrides:
            ctx = ctx.with_engine(engine)
        return run(ctx, n_noise=n_noise)


@flow(name="gap-benchmark", log_prints=False, validate_parameters=False)
def gap_benchmark_flow(out: str, seeds: int = 3, small: bool = False, spec: str | None = None,
                       workers: int = DEFAULT_WORKERS, dask_address: str | None = None,
                       progress: bool = False, seed_start: int = 0, design: str = "discriminating") -> dict:
    """The withheld-effect benchmark into ``<out>/gap/`` (``gap_benchmark.csv`` and a report).

    Noise seeds ``seed_start .. seed_start + seeds - 1`` (fresh seeds check rules chosen on earlier ones);
    ``design`` 'discriminating' (default) or 'sobol' (see ``engine_model.gap.benchmark.benchmark_plan``).
    """
    from engine_model import load_spec
    from engine_model.gap.bench_procedure import BENCH_SOLVER
    from engine_model.gap.benchmark import run_benchmark
    from engine_model.gap.report import write_benchmark_report

    kw = small_settings() if small else {}
    with shared_cluster(workers, dask_address) as addr:
        ev = SweepEvaluator(Path(out) / "sweeps", addr, spec=spec, step_deg=BENCH_SOLVER.step_deg,
                            tolerance=BENCH_SOLVER.tolerance, label="bench", progress=progress)
        res = run_benchmark(seeds=seeds, spec=load_spec(spec), evaluate=ev, progress=print, seed_start=seed_start,
                            design=design, **kw)
    paths = write_benchmark_report(res, out)
    s = res["summary"]
    return {"csv": str(paths["csv"]), "trials": len(res["table"]), "timing": res["timing"],
            "summary": s.to_dict("records")}


@flow(name="gap-benchmark-outside", log_prints=False, validate_parameters=False)
def gap_outside_flow(out: str, seeds: int = 3, seed_start: int = 0, null_seeds: int = 60, plan: str | None = None,
                     spec: str | None = None, workers: int = DEFAULT_WORKERS, dask_address: str | None = None,
                     progress: bool = False) -> dict:
    """The outside-library benchmark (``engine_model.gap.outside``) into ``<out>/gap/outside_*``.

    The diagnosis' simulations (plan, base calibration, linearisation) run as sweeps on Dask; a structural
    truth's (another spec than the diagnosis') run in-process, one noiseless bench run of the plan each.
    ``plan``: a plan CSV (e.g. ``mbc gap-plan``'s); default the 32-point discriminating plan.
    """
    from engine_model import load_spec
    from engine_model.gap.bench_procedure import BENCH_SOLVER
    from engine_model.gap.outside import run_outside_benchmark, write_outside_report
    from engine_model.sim.simulate import simulate

    base_spec = load_spec(spec)
    plan_df = None
    if plan is not None:
        plan_df = read_table(Path(plan))
        plan_df["point_id"] = plan_df["point_id"].astype(str)
    with shared_cluster(workers, dask_address) as addr:
        ev = SweepEvaluator(Path(out) / "sweeps", addr, spec=spec, step_deg=BENCH_SOLVER.step_deg,
                            tolerance=BENCH_SOLVER.tolerance, label="bench", progress=progress)

        def evaluate_for(sp):
            return ev if sp is base_spec else (lambda p: simulate(sp, p, BENCH_SOLVER))

        res = run_outside_benchmark(plan=plan_df, seeds=seeds, seed_start=seed_start, null_seeds=null_seeds,
                                    spec=base_spec, evaluate_for=evaluate_for, progress=print)
    paths = write_outside_report(res, out)
    return {"csv": str(paths["trials"]), "summary_csv": str(paths["summary"]), "report": str(paths["markdown"]),
            "trials": len(res["table"]), "timing": res["timing"], "overall": res["overall"],
            "summary": res["summary"].to_dict("records")}


def small_settings() -> dict:
    """``--small``: a few effects, one magnitude, a 20-point DOE (minutes, not tens of minutes)."""
    return {"effects": ["transmission_efficiency", "heat_transfer", "restrictor", "combustion_efficiency"],
            "magnitudes": (1.0,), "n_points": 20, "n_noise": 100}


def run_gap(out, bench=None, spec=None, **kwargs) -> dict:
    """``mbc gap``: validate inputs (before any server, cluster or folder), then run :func:`gap_flow` under one
    Prefect API."""
    _read_bench(bench, kwargs.get("throttle_unit", "pct"))
    CalibratedEngine.from_spec(spec).calibrated(kwargs.get("overrides") or {})   # bad spec or override: fails here
    with prefect_env.prefect_api(verbose=kwargs.get("progress", True)):
        res = gap_flow(out=str(out), bench=None if bench is None else str(bench), spec=spec, **kwargs)
    print(res["statement"])
    if res.get("pair_statement"):
        print(res["pair_statement"])
    print(f"report: {res['report']}")
    return res


def run_gap_benchmark(out, seeds=3, small=False, spec=None, suite="library", **kwargs) -> dict:
    """``mbc gap-benchmark``: run :func:`gap_benchmark_flow` (``suite="library"``, default) or
    :func:`gap_outside_flow` (``suite="outside"``; takes ``seed_start``, ``null_seeds``, ``plan``, ``workers``,
    ``dask_address``) under one Prefect API."""
    CalibratedEngine.from_spec(spec)
    if suite not in ("library", "outside"):
        raise ValueError(f"gap-benchmark: suite {suite!r} unknown; valid: ['library', 'outside']")
    if suite == "outside" and kwargs.get("plan") is not None and not Path(kwargs["plan"]).is_file():
        raise ValueError(f"plan file not found: {kwargs['plan']}")
    with prefect_env.prefect_api(verbose=kwargs.get("progress", False)):
        if suite == "outside":
            res = gap_outside_flow(out=str(out), seeds=seeds, spec=spec, **kwargs)
        else:
            res = gap_benchmark_flow(out=str(out), seeds=seeds, small=small, spec=spec, **kwargs)
    print(json.dumps(res, indent=1, default=str)[:4000])
    return res
