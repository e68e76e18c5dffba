"""Prove the gap diagnosis on withheld effects (``mbc gap-benchmark``).

For every effect of the library, at a few magnitudes (fractions of its
realistic magnitude) and several noise seeds, the virtual bench
(:class:`engine_model.bench.virtual.VirtualBench`, hidden burn law) measures a
small realistic DOE with that effect present; the base model (without the
effect) is calibrated and the diagnosis names an effect or says that none
explains the gap.  Plus the null case (no effect withheld) and an
out-of-library case: a resonance-shaped bump of the volumetric efficiency over
speed, applied to the virtual bench's readings (defined here, not in the
library), which the tool must refuse to attribute while still localising it.

Affordability: the truth simulations are noiseless and reused across seeds
(noise is added afterwards with the bench's own noise model); the DOE is fixed
across trials except for the points the bench operator backs off for knock
(:func:`measure_with_backoff`), so the base calibration (on the null case's
noiseless data) and the Jacobian (on the union of the plans as run) are
computed once and every trial is linear algebra on its own rows.
Out of the trials, one per effect and magnitude 1 is verified by a nonlinear
re-simulation with the named effect at its fitted parameters.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import pandas as pd

from engine_model import doe
from engine_model.sim.prepare import SolverSettings
from engine_model.spec import EngineSpec, default_spec
from engine_model.gap.covariance import DEFAULT_ERROR_MODEL
from engine_model.gap.diagnose import diagnose
from engine_model.effects import EFFECTS, get_effect
from engine_model.gap.bench_procedure import BENCH_SOLVER, knock_backoff, measure_with_backoff
from engine_model.gap.design import discrimination_plan
from engine_model.gap.linear import BaseModel, calibrate_base, linearise

__all__ = ["BENCHMARK_COLUMNS", "benchmark_plan", "run_benchmark", "summarise_benchmark", "ool_bump",
           "BENCH_SOLVER", "OOL_EFFECT", "DEFAULT_DESIGN",
           "base_and_linearisation"]

#: Columns of gap_benchmark.csv (the issue's list, in its order).
BENCHMARK_COLUMNS = ("effect_withheld", "magnitude", "seed", "effect_named", "top1_correct", "top3_correct",
                     "gap_before", "gap_after", "gap_reduction_pct")


#: Design of ``run_benchmark`` and ``mbc gap-benchmark`` when none is given: the model-discrimination plan
#: (``mbc gap-plan``), chosen from the base model alone.  With the burn-scatter error model and the curved
#: base it names 91-93 % of the realistic-magnitude withheld effects on every seed block, where Sobol'
#: points with the diagonal error model named 80-85 % and claimed an effect in 26 % of null trials
#: (docs/sections/gap.md, "Structural error model").
DEFAULT_DESIGN = "discriminating"

#: Name of the out-of-library case in the benchmark table.
OOL_EFFECT = "ool_ve_resonance"

#: Out-of-library resonance: +4 % volumetric efficiency in a Gaussian bump at 9500 rpm, 700 rpm wide
#: (a pipe resonance a lumped runner cannot produce; amplitude of the ram-tuning peaks in Heywood
#: Fig. 7-22, width of one organ-pipe order at these speeds).
OOL_AMPLITUDE = 0.04
OOL_CENTER_RPM = 9500.0
OOL_WIDTH_RPM = 700.0


def ool_bump(measured: pd.DataFrame, amplitude: float = OOL_AMPLITUDE, center_rpm: float = OOL_CENTER_RPM,
             width_rpm: float = OOL_WIDTH_RPM) -> pd.DataFrame:
    """Apply the out-of-library VE resonance to bench rows: air, fuel and torque scale by the bump.

    More trapped air at fixed lambda and efficiency gives proportionally more fuel and torque; the
    exhaust temperature is left unchanged.
    """
    out = measured.copy()
    n = out["speed_rpm"].to_numpy(float)
    f = 1.0 + amplitude * np.exp(-0.5 * ((n - center_rpm) / width_rpm) ** 2)
    for c in ("air_mass_flow_kg_h", "fuel_mass_flow_kg_h", "brake_torque_nm", "brake_power_kw"):
        if c in out.columns:
            out[c] = out[c].to_numpy(float) * f
    if "bsfc_g_kwh" in out.columns:
        out["bsfc_g_kwh"] = out["bsfc_g_kwh"].to_numpy(float)   # fuel and power scale alike
    return out


#: Benchmark DOE designs: ``"discriminating"`` (the points of a candidate pool on which the library's effects
#: differ most, :func:`engine_model.gap.design.discrimination_plan`) and ``"sobol"`` (scattered points, one spark
#: each; cheaper to plan, used by the CI test).
DESIGNS = ("discriminating", "sobol")


def benchmark_plan(n: int = 32, seed: int = 0, spec: EngineSpec | None = None,
                   evaluate: Callable | None = None, solver: SolverSettings = BENCH_SOLVER,
                   knock_target: float = 0.85, retards: Sequence[float] = (0.0, 4.0, 8.0, 12.0, 16.0),
                   design: str = DEFAULT_DESIGN) -> pd.DataFrame:
    """A realistic small dyno DOE of ``n`` points.

    ``design="discriminating"`` (default): ``n`` points chosen from a 160-point candidate pool (5000-12500 rpm,
    spark 0-8 deg below the MBT prior, knock back-off) to minimise the misnaming bound between the
    library's effects, with no speed gap above 1000 rpm (:func:`engine_model.gap.design.discrimination_plan`;
    base model only, no bench data).

    ``design="sobol"``: ``n`` Sobol' points over 6000-12500 rpm x 30-100 % throttle, spark = MBT prior minus
    0-6 deg, retarded in 4 deg steps where the model (prior burn) predicts a knock index above ``knock_target``.

    Returns
    -------
    DataFrame
        ``point_id, speed_rpm, throttle_pct, spark_deg_btdc, lambda`` + ``op_id`` (operating point of the
        row), ``knock_retard_deg`` (back-off from the MBT prior's top of the sweep) and design columns.
    """
    from engine_model.sim.simulate import simulate

    if design not in DESIGNS:
        raise ValueError(f"benchmark_plan: design {design!r} unknown; valid: {list(DESIGNS)}")
    spec = default_spec() if spec is None else spec
    ev = evaluate or (lambda p: simulate(spec, p, solver))
    bounds = {"speed_rpm": (6000.0, 12500.0), "throttle_pct": (30.0, 100.0)}
    if design == "discriminating":
        plan, _ = discrimination_plan(n, spec, ev, seed=seed)
        return plan
    plan = doe.sobol(n, bounds=bounds, seed=seed)
    rng = np.random.default_rng(seed + 11)
    spark0 = plan["spark_deg_btdc"].to_numpy(float) - rng.uniform(0.0, 6.0, len(plan))
    chosen = knock_backoff(plan.assign(spark_deg_btdc=spark0), spark0, ev, knock_target, retards)
    plan["spark_deg_btdc"] = np.round(spark0 - chosen, 1)
    plan["knock_retard_deg"] = chosen
    plan["op_id"] = plan["point_id"]
    return plan

@dataclass
class _Case:
    effect: str
    magnitude: float
    effects: dict


def _cases(effects: Sequence[str], magnitudes: Sequence[float]) -> list[_Case]:
    cases = [_Case("none", 0.0, {})]
    for e in effects:
        eff = get_effect(e)
        for m in magnitudes:
            cases.append(_Case(e, float(m), {e: eff.at_magnitude(m)}))
    cases.append(_Case(OOL_EFFECT, 1.0, {}))
    return cases


def run_benchmark(seeds: int = 3, magnitudes: Sequence[float] = (0.25, 0.5, 1.0), effects: Sequence[str] | None = None,
                  n_points: int = 32, plan_seed: int = 0, spec: EngineSpec | None = None,
                  evaluate: Callable | None = None, solver: SolverSettings = BENCH_SOLVER,
                  base: BaseModel | None = None, base_iterations: int = 3, k_folds: int = 5, n_noise: int = 200,
                  verify: bool = True, candidates: Sequence[str] | None = None,
                  progress: Callable[[str], None] | None = None, design: str = DEFAULT_DESIGN,
                  seed_start: int = 0, plan: pd.DataFrame | None = None,
                  error_model: str = DEFAULT_ERROR_MODEL) -> dict:
    """Run the withheld-effect benchmark.

    Parameters
    ----------
    seeds : int
        Noise seeds per case: ``seed_start, ..., seed_start + seeds - 1`` (the bench noise generator is
        seeded with 1000 + seed).
    magnitudes : sequence of float
        Fractions of each effect's realistic magnitude (1 = realistic).
    effects : sequence of str, optional
        Effects to withhold (default: the whole library); the diagnosis always ranks all of them.
    n_points : int
        DOE size (simulated bench points).
    design : str
        ``"discriminating"`` (default) or ``"sobol"``, see :func:`benchmark_plan`.
    base : BaseModel, optional
        Default :func:`engine_model.gap.api.choose_base` of the null case's plan as run on the bench (the
        burn's speed curvature where the plan carries it).
    evaluate : callable(plan) -> results, optional
        Default: in-process ``simulate`` with ``solver``.
    verify : bool
        Re-simulate the named effect at its fitted parameters for the first seed, magnitude 1.
    seed_start : int
        First noise seed (fresh seeds for an independent check of rules chosen on earlier ones).
    candidates : sequence of str, optional
        The library the diagnosis ranks (default: all effects; a CI test passes a subset).
    plan : DataFrame, optional
        A DOE made beforehand (e.g. by :func:`engine_model.gap.design.discrimination_plan`); replaces
        ``benchmark_plan(n_points, plan_seed, design=design)``.
    error_model : str
        The diagnosis' structural error model (:data:`engine_model.gap.covariance.ERROR_MODELS`).

    Notes
    -----
    The bench operator re-runs points that knock 4 deg later (:func:`measure_with_backoff`); each trial is
    diagnosed on the plan as its engine ran it (one linearisation of the union of these plans).

    Returns
    -------
    dict
        ``table`` (DataFrame, :data:`BENCHMARK_COLUMNS` + detail columns), ``summary`` (DataFrame),
        ``plan``, ``base_theta``, ``verification`` (DataFrame), ``timing`` (dict), ``linearisation`` (of the
        union of the plans as run), per case (``(effect, magnitude)`` keys) ``plans`` as run, noiseless
        ``truth`` and ``linearisations``, and ``diagnoses`` per ``(effect, magnitude, seed)``.
    """
    from engine_model.sim.simulate import simulate
    from engine_model.bench.virtual import NoiseModel, VirtualBench, apply_noise
    from engine_model.bench.burnlaw import BurnLaw

    say = progress or (lambda s: None)
    spec = default_spec() if spec is None else spec
    ev0 = evaluate or (lambda p: simulate(spec, p, solver))
    n_sim = [0]

    def ev(p):
        n_sim[0] += len(p)
        return ev0(p)

    names = list(EFFECTS) if effects is None else [get_effect(e).name for e in effects]
    t0 = time.perf_counter()
    if plan is None:
        plan = benchmark_plan(n_points, plan_seed, spec, ev, solver, design=design)
    say(f"plan: {len(plan)} points, design {design} ({time.perf_counter() - t0:.0f} s)")
    cases = _cases(names, magnitudes)
    truth = {}
    plans = {}
    law = BurnLaw()
    for c in cases:
        vb = VirtualBench(spec=spec, law=law, effects=c.effects or None, noise=NoiseModel.none(), solver=solver)
        plan_c, m = measure_with_backoff(vb, plan, ev)
        if c.effect == OOL_EFFECT:
            m = ool_bump(m)
        truth[(c.effect, c.magnitude)] = m
        plans[(c.effect, c.magnitude)] = plan_c
    t_truth = time.perf_counter() - t0
    n_back = {k: int((p["bench_backoff_deg"] > 0).sum()) for k, p in plans.items() if "bench_backoff_deg" in p}
    say(f"truth: {len(cases)} noiseless bench runs ({t_truth:.0f} s); points backed off for knock on the "
        f"bench: {sorted(set(n_back.values()))}")
    prep = base_and_linearisation(plans, truth, ("none", 0.0), ev, spec, base=base, base_iterations=base_iterations,
                                  candidates=candidates, progress=say)
    base, theta, lin_all, lins = prep["base"], prep["theta"], prep["linearisation"], prep["linearisations"]
    t_cal, t_lin = prep["calibration_s"], prep["linearisation_s"]
    noise = NoiseModel()
    cache: dict = {}
    rows = []
    diags = {}
    seed_list = list(range(seed_start, seed_start + seeds))
    for c in cases:
        for s in seed_list:
            meas = apply_noise(truth[(c.effect, c.magnitude)], noise, 1000 + s)
            d = diagnose(lins[(c.effect, c.magnitude)], meas, k_folds=k_folds, n_noise=n_noise, seed=0,
                         noise_cache=cache, error_model=error_model)
            top = d.top(3)
            named = d.named or "none"
            if c.effect == "none" or c.effect == OOL_EFFECT:
                top1 = named == "none"
                top3 = top1
            else:
                top1 = named == c.effect
                top3 = c.effect in top
            rank_row = d.ranking[d.ranking["effect"] == d.best].iloc[0] if d.best else None
            rows.append({"effect_withheld": c.effect, "magnitude": c.magnitude, "seed": s,
                         "effect_named": named, "top1_correct": bool(top1), "top3_correct": bool(top3),
                         "category": d.category,
                         "gap_before": round(d.gap_before, 4), "gap_after": round(d.gap_after, 4),
                         "gap_reduction_pct": round(d.gap_reduction_pct, 2),
                         "best_candidate": d.best, "top3": ",".join(top), "confidence": round(d.confidence, 3),
                         "heldout_improvement": round(float(rank_row["heldout_improvement"]), 2) if rank_row is not None else 0.0,
                         "threshold": round(d.threshold, 2),
                         "localised_stage": d.stages["stage"].iloc[0] if len(d.stages) else "",
                         "shape": "; ".join(f"{r.output}: {r.shape}" for r in d.shape.itertuples()),
                         "fitted_params": rank_row["params"] if rank_row is not None else "",
                         "n_points_used": d.n_points,
                         "n_bench_backoff": n_back.get((c.effect, c.magnitude), 0)})
            diags[(c.effect, c.magnitude, s)] = d
    table = pd.DataFrame(rows)
    t_diag = time.perf_counter() - t0 - t_truth - t_cal - t_lin
    say(f"diagnosis: {len(table)} trials ({t_diag:.0f} s)")
    ver = []
    if verify:
        ver = _verify(plans, lins, truth, diags, names, seed_list[0], ev, spec)
    timing = {"truth_s": round(t_truth, 1), "base_calibration_s": round(t_cal, 1), "linearisation_s": round(t_lin, 1),
              "diagnosis_s": round(t_diag, 1), "total_s": round(time.perf_counter() - t0, 1),
              "simulations": int(n_sim[0]), "design": design, "base": list(base.params), "error_model": error_model,
              "seeds": seed_list}
    return {"table": table, "summary": summarise_benchmark(table), "plan": plan, "base_theta": theta,
            "verification": pd.DataFrame(ver), "timing": timing, "linearisation": lin_all, "diagnoses": diags,
            "plans": plans, "truth": truth, "linearisations": lins}


def base_and_linearisation(plans: dict, truth: dict, null_key, evaluate: Callable, spec: EngineSpec,
                           base: BaseModel | None = None, base_iterations: int = 3,
                           candidates: Sequence[str] | None = None,
                           progress: Callable[[str], None] | None = None) -> dict:
    """The diagnosis' side of a benchmark: base calibration on the null case, one linearisation of all plans.

    Shared by :func:`run_benchmark` and :func:`engine_model.gap.outside.run_outside_benchmark`.

    Parameters
    ----------
    plans, truth : dict {case key: DataFrame}
        Every case's plan as the bench ran it and its noiseless bench rows.
    null_key
        Key of the null case (no effect): the base is calibrated on its noiseless rows.
    evaluate : callable(plan) -> results
        The diagnosis' model (the default spec), never a truth's altered one.
    base : BaseModel, optional
        Default :func:`engine_model.gap.api.choose_base` of the null plan as run (speed curvature allowed).
    candidates : sequence of str, optional
        Effects to linearise (default: the whole library).

    Returns
    -------
    dict
        ``base``, ``theta``, ``linearisation`` (of the union of the plans as run), ``linearisations`` (per
        case key, rows of its plan), ``calibration_s``, ``linearisation_s``.
    """
    from engine_model.gap.api import choose_base

    say = progress or (lambda s: None)
    t0 = time.perf_counter()
    null, null_plan = truth[null_key], plans[null_key]
    # the base the data as run can carry (the bench back-off spreads the sparks)
    base = choose_base(null_plan, speed_curvature=True) if base is None else base
    say(f"base: {base.params}")
    theta, _, _ = calibrate_base(null_plan, null, evaluate, base, iterations=base_iterations, spec=spec)
    t_cal = time.perf_counter() - t0
    say(f"base calibration on the null case: {theta} ({t_cal:.0f} s)")
    cands = list(EFFECTS) if candidates is None else [get_effect(e).name for e in candidates]
    union = pd.concat(list(plans.values()), ignore_index=True, sort=False)
    union = union.drop_duplicates(subset="point_id", keep="first").reset_index(drop=True)
    lin_all = linearise(union, evaluate, base, effects=cands, theta=theta, spec=spec)
    lins = {k: lin_all.select(list(p["point_id"].astype(str))) for k, p in plans.items()}
    t_lin = time.perf_counter() - t0 - t_cal
    say(f"linearisation: {lin_all.n_simulations} simulations ({t_lin:.0f} s), {int(lin_all.ok.sum())} of "
        f"{len(union)} points ok")
    return {"base": base, "theta": theta, "linearisation": lin_all, "linearisations": lins,
            "calibration_s": t_cal, "linearisation_s": t_lin}


def _verify(plans, lins, truth, diags, names, seed, ev, spec) -> list[dict]:
    """Nonlinear re-simulation of the named effect at its fitted parameters (``seed``, magnitude 1)."""
    from engine_model.effects import apply_effects, check_effects, post_effects
    from engine_model.gap.linear import model_outputs

    jobs = []
    for e in names:
        d = diags.get((e, 1.0, seed))
        if d is None or d.named is None or d.named not in EFFECTS:      # a sensor fault needs no re-simulation
            continue
        plan, lin = plans[(e, 1.0)], lins[(e, 1.0)]
        row = d.ranking[d.ranking["effect"] == d.named].iloc[0]
        fx = {}
        eff = get_effect(d.named)
        for p, v in row["param_values"].items():
            prm = eff.param(p)
            fx[p] = float(np.clip(v, prm.lo, prm.hi))
        fx = check_effects({d.named: fx})
        pts = lin.base.plan(plan, d.base_theta_best, spec)
        jobs.append((e, d, fx, apply_effects(pts, fx, spec), plan, lin))
    if not jobs:
        return []
    frames = []
    for k, (_, _, _, p, _, _) in enumerate(jobs):
        f = p.copy()
        f["point_id"] = f["point_id"].astype(str) + f"#v{k}"
        frames.append(f)
    big = pd.concat(frames, ignore_index=True, sort=False)
    for c in big.columns:
        if c.startswith("spec."):
            sec, _, fld = c[5:].partition(".")
            big[c] = big[c].fillna(float(getattr(getattr(spec, sec), fld)))
    for c, dflt in (("t_amb_k", spec.ambient.temperature_k), ("p_amb_pa", spec.ambient.pressure_pa),
                    ("gap_vapour_pressure_pa", 0.0)):
        if c in big.columns:
            big[c] = big[c].fillna(dflt)
    res = ev(big.drop(columns=["gap_vapour_pressure_pa"], errors="ignore"))
    out = []
    start = 0
    for k, (e, d, fx, p, plan, lin) in enumerate(jobs):
        n = len(plan)
        r = res.iloc[start:start + n].reset_index(drop=True)
        start += n
        if "gap_vapour_pressure_pa" in p.columns:
            r["gap_vapour_pressure_pa"] = p["gap_vapour_pressure_pa"].to_numpy()
        r = post_effects(model_outputs(r, lin.eta_base), fx, lin.eta_base, spec)
        resid = d.residuals
        z_after = []
        for o in d.extra["outputs"]:
            rr = resid[(resid["output"] == o) & resid["used"]]
            idx = [list(plan["point_id"]).index(pid) for pid in rr["point_id"]]
            sim = pd.to_numeric(r[o], errors="coerce").to_numpy(float)[idx]
            z_after.append((rr["measured"].to_numpy() - sim) / rr["sigma"].to_numpy())
        z = np.concatenate(z_after)
        z0 = resid.loc[resid["used"], "z"].to_numpy()
        zl = resid.loc[resid["used"], "z_with_best"].to_numpy()
        out.append({"effect_withheld": e, "effect_named": d.named, "params": str(fx[d.named]),
                    "rms_before_sigma": float(np.sqrt(np.mean(z0**2))),
                    "rms_after_linear_sigma": float(np.sqrt(np.mean(zl**2))),
                    "rms_after_resimulated_sigma": float(np.sqrt(np.nanmean(z**2)))})
    return out


def summarise_benchmark(table: pd.DataFrame) -> pd.DataFrame:
    """Per withheld effect and magnitude: top-1/top-3 accuracy, claim rate, median gap reduction."""
    g = table.groupby(["effect_withheld", "magnitude"], sort=False)
    s = g.agg(trials=("seed", "size"), top1=("top1_correct", "mean"), top3=("top3_correct", "mean"),
              claimed=("effect_named", lambda x: float(np.mean(x != "none"))),
              gap_before=("gap_before", "median"), gap_after=("gap_after", "median"),
              gap_reduction_pct=("gap_reduction_pct", "median")).reset_index()
    return s
