"""The gap diagnosis on truths outside its library (``mbc gap-benchmark --suite outside``).

The in-library benchmark (:mod:`engine_model.gap.benchmark`) withholds the library's own effects through the
hooks the candidates use, so it cannot show what the diagnosis does with a gap that no candidate has the
form of.  Here the virtual bench (hidden burn law, knock back-off by the operator, the bench's noise model)
measures a truth the diagnosis' library does not contain:

* **functional forms** the library lacks, applied to the bench's noiseless readings: a torque-only loss
  growing with load, a VE dip localised between 9000 and 11000 rpm, a friction excess growing with speed
  squared, an exhaust-temperature-only loss in the port ahead of the thermocouple;
* **single-channel sensor faults** on the measured columns (offset or gain on one channel);
* **structural truths**: the bench simulates with another sub-model or calibration than the diagnosis
  (lumped gas exchange instead of 1D pipes, half the pipe cell length, a Chen-Flynn friction dominated by
  its peak-pressure term, another Woschni calibration), via ``dataclasses.replace`` on the spec;
* **the null** (nothing withheld), with many more noise seeds than the other cases.

Every case says which answers count as right (``accept``: a claimed candidate name; sensor-fault candidates
are ``sensor_<bench column>``) and whether an honest refusal is itself the right answer (``refusal_ok``).
Every trial is scored as ``right`` (a claim in ``accept``; for the null: no claim), ``refusal`` (no claim:
"partly explained", "not in the library" or "no significant gap" while something was withheld) or
``wrong_claim`` (a claim outside ``accept``); a wrong claim is ``confident_wrong`` when its fitted parameter
sits at its range edge or its held-out chi2 exceeds the pure-noise quantile the claim rule judged it by (with
the claimed candidate fitted, ``extra["remainder_chi2_q"]``; the base-only ``noise_chi2_q`` for diagnoses
without it).

Cost: the truths are noiseless and reused across seeds (only the noise is redrawn with the bench's noise
model, as in the in-library benchmark); reading-side cases cost no simulation, each structural truth one
noiseless bench run of the plan with its spec; the base calibration and one linearisation of the union of
the plans as run are shared with :func:`engine_model.gap.benchmark.base_and_linearisation`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import pandas as pd

from engine_model.effects import ETA_TRANS_BASE
from engine_model.gap.bench_procedure import BENCH_SOLVER, measure_with_backoff
from engine_model.gap.benchmark import base_and_linearisation, benchmark_plan
from engine_model.gap.covariance import DEFAULT_ERROR_MODEL
from engine_model.gap.diagnose import diagnose
from engine_model.sim.prepare import SolverSettings
from engine_model.spec import EngineSpec, default_spec

__all__ = ["OutsideCase", "outside_cases", "CASE_KINDS", "CATEGORIES", "CLAIM_CATEGORIES", "OUTSIDE_COLUMNS",
           "category_of", "score_diagnosis", "run_outside_benchmark", "summarise_outside", "overall_outside",
           "NULL_SEEDS", "prepared_of", "write_outside_report", "cases_table"]

#: Case kinds, in the order of the summary table.
CASE_KINDS = ("functional form", "sensor fault", "structural", "null")

#: Answer categories of the diagnosis; the first two are claims.  "indistinguishable" (a candidate fits, but so
#: does one of another kind: no name claimed, the set is in ``extra["indistinguishable"]``) scores as a refusal;
#: the trial table says whether the set holds an accepted name (``hedge_has_right``).
CATEGORIES = ("explained", "sensor fault", "indistinguishable", "partly explained", "not in the library",
              "no significant gap")
CLAIM_CATEGORIES = ("explained", "sensor fault")

#: Null trials per run by default (the issue's "null false claims <= 5 % over >= 60 null trials").
NULL_SEEDS = 60

#: Columns of outside_trials.csv.
OUTSIDE_COLUMNS = ("case", "kind", "seed", "category", "named", "best", "outcome", "acceptable", "confident_wrong",
                   "sensor_right_channel", "must_name", "accept", "gap_before", "gap_after", "gap_reduction_pct",
                   "named_heldout_chi2", "noise_chi2_q", "named_at_range_bound", "hedge_set", "hedge_has_right",
                   "n_points_used", "n_bench_backoff")

_MEASURED = ("brake_torque_nm", "air_mass_flow_kg_h", "fuel_mass_flow_kg_h", "exhaust_temp_k")


@dataclass(frozen=True)
class OutsideCase:
    """One withheld truth and the answers that count as right.

    Attributes
    ----------
    name, kind : str
        Case name and kind (:data:`CASE_KINDS`).
    description : str
        Functional form, magnitude and where the magnitude comes from.
    accept : frozenset of str
        Claimed candidate names that count as a right answer (empty: none in the library is right).
    refusal_ok : bool
        An honest refusal (no claim) is itself a right answer for this case.
    readings : callable(DataFrame) -> DataFrame, optional
        Applied to the bench's noiseless rows (measured columns; power and BSFC recomputed).
    spec_change : callable(EngineSpec) -> EngineSpec, optional
        The truth engine's spec (structural truths).
    channel : str, optional
        The faulty bench column (sensor faults).
    """

    name: str
    kind: str
    description: str
    accept: frozenset = frozenset()
    refusal_ok: bool = False
    readings: Callable | None = None
    spec_change: Callable | None = None
    channel: str | None = None

    @property
    def must_name(self) -> bool:
        """A sensor fault only its own sensor-fault candidate explains (the issue's >= 90 % naming rule)."""
        return self.kind == "sensor fault" and self.channel is not None and self.accept == {f"sensor_{self.channel}"}


# --------------------------------------------------------------------------- reading-side truths

def _recompute(out: pd.DataFrame) -> pd.DataFrame:
    """Brake power and BSFC from the (changed) torque and fuel readings, as the bench computes them."""
    if "brake_power_kw" in out.columns:
        out["brake_power_kw"] = out["brake_torque_nm"].to_numpy(float) * 2.0 * math.pi \
            * out["speed_rpm"].to_numpy(float) / 60.0 / 1e3
    if "bsfc_g_kwh" in out.columns:
        p = out["brake_power_kw"].to_numpy(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            out["bsfc_g_kwh"] = np.where(p > 0, out["fuel_mass_flow_kg_h"].to_numpy(float) * 1e3 / p, np.nan)
    return out


def _col(df: pd.DataFrame, c: str) -> np.ndarray:
    return pd.to_numeric(df[c], errors="coerce").to_numpy(float)


def torque_load_loss(m: pd.DataFrame, k: float = 0.03) -> pd.DataFrame:
    """Brake torque x (1 - k throttle/100): a torque-only loss whose share grows with load."""
    out = m.copy()
    out["brake_torque_nm"] = _col(out, "brake_torque_nm") * (1.0 - k * _col(out, "throttle_pct") / 100.0)
    return _recompute(out)


def ve_dip(m: pd.DataFrame, amplitude: float = -0.04, center_rpm: float = 10200.0,
           width_rpm: float = 450.0) -> pd.DataFrame:
    """Air, fuel and torque x (1 + amplitude exp(-((n - center)/width)^2 / 2)); exhaust T unchanged."""
    out = m.copy()
    f = 1.0 + amplitude * np.exp(-0.5 * ((_col(out, "speed_rpm") - center_rpm) / width_rpm) ** 2)
    for c in ("air_mass_flow_kg_h", "fuel_mass_flow_kg_h", "brake_torque_nm"):
        out[c] = _col(out, c) * f
    return _recompute(out)


def friction_speed_squared(m: pd.DataFrame, fmep_bar_at_ref: float = 0.35, ref_rpm: float = 12500.0,
                           displacement_m3: float | None = None, eta: float = ETA_TRANS_BASE) -> pd.DataFrame:
    """Brake torque minus eta FMEP Vd / (4 pi), FMEP = fmep_bar_at_ref (n / ref_rpm)^2 (four-stroke)."""
    out = m.copy()
    if displacement_m3 is None:
        g = default_spec().geometry
        displacement_m3 = math.pi / 4.0 * g.bore_m ** 2 * g.stroke_m * g.n_cylinders
    fmep = 1e5 * fmep_bar_at_ref * (_col(out, "speed_rpm") / ref_rpm) ** 2
    out["brake_torque_nm"] = _col(out, "brake_torque_nm") - eta * fmep * displacement_m3 / (4.0 * math.pi)
    return _recompute(out)


def exhaust_port_cooling(m: pd.DataFrame, dt_k_at_ref: float = 35.0, ref_air_kg_h: float = 200.0) -> pd.DataFrame:
    """Exhaust T reading minus dt (air / ref_air)^-0.2: heat lost between exhaust valve and thermocouple."""
    out = m.copy()
    air = np.clip(_col(out, "air_mass_flow_kg_h"), 1.0, None)
    out["exhaust_temp_k"] = _col(out, "exhaust_temp_k") - dt_k_at_ref * (air / ref_air_kg_h) ** -0.2
    return out


def sensor_offset(column: str, offset: float) -> Callable:
    """A reading transform adding ``offset`` to one bench column."""
    def f(m: pd.DataFrame) -> pd.DataFrame:
        out = m.copy()
        out[column] = _col(out, column) + offset
        return _recompute(out)
    f.__name__ = f"offset_{column}"
    return f


def sensor_gain(column: str, gain: float) -> Callable:
    """A reading transform multiplying one bench column by ``gain``."""
    def f(m: pd.DataFrame) -> pd.DataFrame:
        out = m.copy()
        out[column] = _col(out, column) * gain
        return _recompute(out)
    f.__name__ = f"gain_{column}"
    return f


# --------------------------------------------------------------------------- structural truths

def _replace(spec: EngineSpec, section: str, **values) -> EngineSpec:
    return dataclasses.replace(spec, **{section: dataclasses.replace(getattr(spec, section), **values)})


def lumped_gas_exchange(spec: EngineSpec) -> EngineSpec:
    return _replace(spec, "gas_exchange", model="lumped")


def finer_pipe_cells(spec: EngineSpec) -> EngineSpec:
    return _replace(spec, "gas_exchange", cell_length_m=spec.gas_exchange.cell_length_m / 2.0)


def friction_peak_pressure(spec: EngineSpec) -> EngineSpec:
    f = spec.friction
    return _replace(spec, "friction", b=3.0 * f.b, a_pa=max(0.0, f.a_pa - 2.0 * f.b * 40e5))


def woschni_recalibrated(spec: EngineSpec) -> EngineSpec:
    h = spec.heat_transfer
    return _replace(spec, "heat_transfer", c2_combustion=2.0 * h.c2_combustion, c1_closed=0.8 * h.c1_closed)


def outside_cases() -> list[OutsideCase]:
    """The outside-library cases (magnitudes and their sources in each description)."""
    sens = "sensor_"
    return [
        OutsideCase(
            "torque_load_loss", "functional form",
            "Brake torque x (1 - 0.03 throttle/100): 3 % at WOT, 0.9 % at 30 % throttle, no other channel. A "
            "load-dependent driveline/ring-pack loss; 3 % at full load is the order of one more gear or chain "
            "stage (0.97-0.99 each, Naunheimer et al. 2011 ch. 3). Accepted: the torque-proportional losses "
            "(constant or speed-dependent transmission efficiency, a torque gain error), which the data cannot "
            "tell from it; not blow-by or friction (changes exhaust T / does not grow with load).",
            frozenset({"transmission_efficiency", "transmission_speed_loss"}),
            refusal_ok=True, readings=torque_load_loss),
        OutsideCase(
            "ve_dip_10k", "functional form",
            "Volumetric-efficiency dip: air, fuel and torque x (1 - 0.04 exp(-((n - 10200)/450)^2/2)), i.e. "
            "-4 % at 10200 rpm, half-depth between ~9670 and ~10730 rpm; exhaust T unchanged. A wave-tuning "
            "trough of a few % (Heywood 1988 Fig. 7-22, ram-tuning swings of +-5 %); other centre, width and "
            "sign than the in-library suite's out-of-library bump. No library effect is localised in speed "
            "(runner_inertia moves the whole tuning curve): the right answer is a refusal.",
            frozenset(), refusal_ok=True, readings=ve_dip),
        OutsideCase(
            "friction_speed_squared", "functional form",
            "Friction excess growing with speed squared: FMEP + 0.35 bar (n/12500)^2 (1.6 Nm at 12500 rpm, "
            "0.26 Nm at 5000), torque only. The Chen-Flynn D Sp^2 term (windage, hydrodynamic oil shear) that "
            "the library's friction candidate (A and C) lacks; 0.35 bar is ~15 % of an SI engine's FMEP at "
            "high speed (1-3 bar, Heywood 1988 sec. 13.6). Accepted: friction (closest mechanism).",
            frozenset({"friction"}), refusal_ok=True, readings=friction_speed_squared),
        OutsideCase(
            "exhaust_port_cooling", "functional form",
            "Exhaust T reading - 35 K (air/200 kg/h)^-0.2 (40 K at 100 kg/h, 33 K at 250 kg/h): heat lost in "
            "the port/primary upstream of the thermocouple; per kg of gas it falls slowly with flow "
            "(h ~ Re^0.8 over m cp). Tens of K between port exit and a probe 100 mm downstream (Heywood 1988 "
            "sec. 14.2 - exhaust gas temperature drops along the port). To the data a fault of that channel: "
            "accepted sensor_exhaust_temp_k.",
            frozenset({sens + "exhaust_temp_k"}), refusal_ok=True, readings=exhaust_port_cooling),
        OutsideCase(
            "sensor_exhaust_t_offset", "sensor fault",
            "Exhaust-T offset +20 K: thermocouple radiation/conduction error or a cold-junction fault; type K "
            "class 2 alone allows +-0.75 % (+-9 K at 1200 K) and placement errors are tens of K.",
            frozenset({sens + "exhaust_temp_k"}), readings=sensor_offset("exhaust_temp_k", 20.0),
            channel="exhaust_temp_k"),
        OutsideCase(
            "sensor_airflow_gain", "sensor fault",
            "Airflow gain +3 %: a drifted or contaminated hot-film meter (accuracy class 2-3 % of reading).",
            frozenset({sens + "air_mass_flow_kg_h"}), readings=sensor_gain("air_mass_flow_kg_h", 1.03),
            channel="air_mass_flow_kg_h"),
        OutsideCase(
            "sensor_fuel_gain", "sensor fault",
            "Fuel-flow gain -3 %: a volumetric fuel meter with a wrong fuel density (EN 228 petrol "
            "720-775 kg/m3: +-3.5 %).",
            frozenset({sens + "fuel_mass_flow_kg_h"}), readings=sensor_gain("fuel_mass_flow_kg_h", 0.97),
            channel="fuel_mass_flow_kg_h"),
        OutsideCase(
            "sensor_torque_offset", "sensor fault",
            "Torque offset -1.5 Nm: load-cell zero drift / arm tare not zeroed (2.5 % at 60 Nm, 5 % at 30 Nm). "
            "To the data this is exactly a constant-FMEP friction change (brake torque = eta (indicated - "
            "FMEP Vd / 4 pi): -1.5 Nm = +0.31 bar on the Chen-Flynn A term, inside the friction candidate's "
            "range), so friction is the accepted answer (the diagnosis has no torque fault candidate for this "
            "reason) and the case is not a must-name sensor fault. (A torque GAIN "
            "fault is left out for the same reason: it is the transmission efficiency to the data.)",
            frozenset({"friction"}), readings=sensor_offset("brake_torque_nm", -1.5),
            channel="brake_torque_nm"),
        OutsideCase(
            "lumped_gas_exchange", "structural",
            "The bench runs the lumped gas exchange (runners as lumped inertances), the diagnosis the 1D pipes "
            "(2-3 % torque and airflow apart, speed-dependent). Accepted: runner_inertia (the one candidate "
            "acting on the intake wave dynamics); a refusal is right too.",
            frozenset({"runner_inertia"}), refusal_ok=True, spec_change=lumped_gas_exchange),
        OutsideCase(
            "finer_pipe_cells", "structural",
            "The bench's pipes have half the cell length (0.015 m vs 0.03 m): the diagnosis' spatial "
            "discretisation error (0.1-0.8 % torque). Nothing physical to name: the right answer is a refusal.",
            frozenset(), refusal_ok=True, spec_change=finer_pipe_cells),
        OutsideCase(
            "friction_peak_pressure", "structural",
            "Chen-Flynn friction dominated by its peak-pressure term: B tripled (0.005 -> 0.015), A lowered by "
            "2 B 40 bar (0.40 -> 0 bar), so FMEP is unchanged at p_max = 40 bar, higher above, lower below (a "
            "ring pack loaded by gas pressure; Heywood 1988 sec. 13.6). Accepted: friction (same sub-model).",
            frozenset({"friction"}), refusal_ok=True, spec_change=friction_peak_pressure),
        OutsideCase(
            "woschni_recalibrated", "structural",
            "Another Woschni calibration: combustion term C2 doubled, closed-cycle C1 x 0.8 (more heat loss "
            "during combustion, less in compression); Woschni's constants scatter by ~1.5x between engines "
            "(Heywood 1988 sec. 12.4). Accepted: heat_transfer (multiplier on the same correlation).",
            frozenset({"heat_transfer"}), refusal_ok=True, spec_change=woschni_recalibrated),
        OutsideCase("none", "null", "Nothing withheld.", frozenset(), refusal_ok=True),
    ]


# --------------------------------------------------------------------------- scoring

def category_of(d) -> str:
    """The diagnosis' answer category (:data:`CATEGORIES`).

    Uses ``d.category`` when the diagnosis has it; otherwise: a named ``sensor_*`` candidate -> "sensor
    fault", another named one -> "explained"; no claim -> "no significant gap" when the base's held-out chi2
    lies within the pure-noise quantile, else "not in the library".
    """
    cat = getattr(d, "category", None)
    if cat:
        return str(cat)
    if d.named:
        return "sensor fault" if str(d.named).startswith("sensor_") else "explained"
    ho0 = (d.extra or {}).get("heldout_chi2_base")
    if ho0 is None:
        ho0 = d.gap_before ** 2 * d.n_obs
    return "no significant gap" if ho0 <= d.noise_chi2_q else "not in the library"


def _named_row(d, name):
    r = d.ranking
    if name is None or r is None or not len(r) or "effect" not in r.columns:
        return None
    hit = r[r["effect"] == name]
    return hit.iloc[0] if len(hit) else None


def score_diagnosis(case: OutsideCase, d) -> dict:
    """Score one trial: ``outcome`` (right / refusal / wrong_claim), ``acceptable``, ``confident_wrong``, ...

    ``d`` is a :class:`~engine_model.gap.diagnose.GapDiagnosis` or anything with its fields ``named``,
    ``best``, ``ranking`` (``effect``, ``heldout_chi2``, ``at_range_bound``), ``noise_chi2_q``,
    ``gap_before``, ``gap_after``, ``n_obs``, ``extra`` (and ``category`` when the diagnosis has it).
    """
    cat = category_of(d)
    claimed = d.named if cat in CLAIM_CATEGORIES and d.named else None
    row = _named_row(d, claimed)
    at_bound = str(row["at_range_bound"]) if row is not None and "at_range_bound" in row.index \
        and isinstance(row["at_range_bound"], str) else ""
    if row is not None and "heldout_chi2" in row.index:
        ho = float(row["heldout_chi2"])
    elif claimed is not None and claimed == d.best:
        ho = float(d.gap_after) ** 2 * d.n_obs
    else:
        ho = float("nan")
    if case.kind == "null":
        outcome = "wrong_claim" if claimed else "right"
    elif claimed is None:
        outcome = "refusal"
    else:
        outcome = "right" if claimed in case.accept else "wrong_claim"
    # the quantile the claim rule judged the remainder by (the claimed candidate fitted beside the base on pure
    # noise, gap.noise); older diagnoses without it: the base-only quantile
    q_rem = float(((getattr(d, "extra", None) or {}).get("remainder_chi2_q")) or d.noise_chi2_q)
    confident = outcome == "wrong_claim" and (bool(at_bound) or (np.isfinite(ho) and ho > q_rem))
    acceptable = outcome == "right" or (outcome == "refusal" and case.refusal_ok)
    hedge = [str(x) for x in ((getattr(d, "extra", None) or {}).get("indistinguishable") or [])] \
        if cat == "indistinguishable" else []
    return {"category": cat, "named": claimed or "", "best": d.best or "", "outcome": outcome,
            "acceptable": bool(acceptable), "confident_wrong": bool(confident),
            "sensor_right_channel": bool(case.channel is not None and cat == "sensor fault"
                                         and claimed == f"sensor_{case.channel}"),
            "must_name": case.must_name, "hedge_set": ",".join(hedge),
            "hedge_has_right": bool(set(hedge) & set(case.accept)),
            "named_heldout_chi2": ho, "noise_chi2_q": float(d.noise_chi2_q), "remainder_chi2_q": q_rem,
            "named_at_range_bound": at_bound}


# --------------------------------------------------------------------------- the run

def _truths(cases, plan, spec, ev, evaluate_for, solver, say):
    """Noiseless bench rows and the plan as run, per case (structural truths simulated with their spec)."""
    from engine_model.bench.burnlaw import BurnLaw
    from engine_model.bench.virtual import NoiseModel, VirtualBench

    law = BurnLaw()
    plans, truth = {}, {}
    vb = VirtualBench(spec=spec, law=law, noise=NoiseModel.none(), solver=solver)
    null_plan, null = measure_with_backoff(vb, plan, ev)
    for c in cases:
        t = time.perf_counter()
        if c.spec_change is not None:
            sp = c.spec_change(spec)
            vb_c = VirtualBench(spec=sp, law=law, noise=NoiseModel.none(), solver=solver)
            p_c, m = measure_with_backoff(vb_c, plan, evaluate_for(sp))
            say(f"truth {c.name}: {len(p_c)} points ({time.perf_counter() - t:.0f} s)")
        else:
            p_c, m = null_plan, null
        if c.readings is not None:
            m = c.readings(m)
        plans[c.name], truth[c.name] = p_c, m
    return null_plan, null, plans, truth


def run_outside_benchmark(plan: pd.DataFrame | None = None, seeds: int = 3, seed_start: int = 0,
                          null_seeds: int = NULL_SEEDS, cases: Sequence[OutsideCase] | None = None,
                          spec: EngineSpec | None = None, evaluate_for: Callable | None = None,
                          solver: SolverSettings = BENCH_SOLVER, candidates: Sequence[str] | None = None,
                          base_iterations: int = 3, k_folds: int = 5, n_noise: int = 200, n_points: int = 32,
                          error_model: str = DEFAULT_ERROR_MODEL, prepared: dict | None = None,
                          progress: Callable[[str], None] | None = None) -> dict:
    """Run the outside-library benchmark.

    Parameters
    ----------
    plan : DataFrame, optional
        The bench DOE (e.g. ``mbc gap-plan``'s); default :func:`engine_model.gap.benchmark.benchmark_plan`
        with ``n_points`` (the discriminating plan: minutes of candidate-pool simulations).
    seeds, seed_start : int
        Noise seeds ``seed_start .. seed_start + seeds - 1`` for every non-null case (the bench noise
        generator is seeded with 1000 + seed, as in the in-library benchmark).
    null_seeds : int
        Noise seeds of the null case, ``seed_start .. seed_start + null_seeds - 1`` (at least ``seeds``).
    cases : sequence of OutsideCase, optional
        Default :func:`outside_cases`; the null case is added when missing.
    evaluate_for : callable(EngineSpec) -> callable(plan) -> results, optional
        The cycle model of a spec (default: in-process ``simulate`` with ``solver``); the diagnosis always
        uses ``evaluate_for(spec)``, a structural truth ``evaluate_for(its spec)``.
    candidates : sequence of str, optional
        Effects linearised and ranked (default: the whole library; ``diagnose`` adds its own sensor-fault
        candidates).
    prepared : dict, optional
        ``plan``, ``plans``, ``truth``, ``linearisations``, ``base``, ``base_theta`` of an earlier result (e.g.
        pickled by ``benchmarks/gap_outside.py --save-prepared``): re-diagnoses the same noiseless truths
        without any simulation (valid while the model and the linearisation code are unchanged).

    Returns
    -------
    dict
        ``table`` (one row per trial, :data:`OUTSIDE_COLUMNS` + detail), ``summary`` (per case kind),
        ``by_case``, ``overall`` (dict), ``timing``, ``plan``, ``plans``, ``truth``, ``diagnoses``.
    """
    from engine_model.bench.virtual import NoiseModel, apply_noise
    from engine_model.sim.simulate import simulate

    say = progress or (lambda s: None)
    spec = default_spec() if spec is None else spec
    evaluate_for = evaluate_for or (lambda sp: (lambda p: simulate(sp, p, solver)))
    n_sim = [0]
    ev0 = evaluate_for(spec)

    def ev(p):
        n_sim[0] += len(p)
        return ev0(p)

    cases = list(outside_cases() if cases is None else cases)
    if not any(c.kind == "null" for c in cases):
        cases.append(OutsideCase("none", "null", "Nothing withheld.", frozenset(), refusal_ok=True))
    t0 = time.perf_counter()
    if prepared is not None:
        missing = [c.name for c in cases if c.name not in prepared["truth"]]
        if missing:
            raise ValueError(f"run_outside_benchmark: prepared truths lack case(s) {missing}")
        plan, plans, truth = prepared["plan"], prepared["plans"], prepared["truth"]
        prep = {"base": prepared["base"], "theta": prepared["base_theta"], "calibration_s": 0.0,
                "linearisation_s": 0.0, "linearisations": prepared["linearisations"]}
        t_truth = 0.0
    else:
        if plan is None:
            plan = benchmark_plan(n_points, 0, spec, ev, solver)
        say(f"plan: {len(plan)} points ({time.perf_counter() - t0:.0f} s)")
        t1 = time.perf_counter()
        null_plan, null, plans, truth = _truths(cases, plan, spec, ev, evaluate_for, solver, say)
        t_truth = time.perf_counter() - t1
        say(f"truth: {len(cases)} cases ({t_truth:.0f} s)")
        all_plans = dict(plans)
        all_plans["__null__"], all_truth = null_plan, dict(truth, __null__=null)
        prep = base_and_linearisation(all_plans, all_truth, "__null__", ev, spec, base_iterations=base_iterations,
                                      candidates=candidates, progress=say)
    lins = prep["linearisations"]
    noise = NoiseModel()
    cache: dict = {}
    rows, diags = [], {}
    t2 = time.perf_counter()
    for c in cases:
        n_s = max(null_seeds, seeds) if c.kind == "null" else seeds
        n_back = int((plans[c.name]["bench_backoff_deg"] > 0).sum()) if "bench_backoff_deg" in plans[c.name] else 0
        for s in range(seed_start, seed_start + n_s):
            meas = apply_noise(truth[c.name], noise, 1000 + s)
            d = diagnose(lins[c.name], meas, k_folds=k_folds, n_noise=n_noise, seed=0, noise_cache=cache,
                         error_model=error_model)
            sc = score_diagnosis(c, d)
            rows.append({"case": c.name, "kind": c.kind, "seed": s, **sc,
                         "accept": ",".join(sorted(c.accept)), "gap_before": round(d.gap_before, 4),
                         "gap_after": round(d.gap_after, 4), "gap_reduction_pct": round(d.gap_reduction_pct, 2),
                         "n_points_used": d.n_points, "n_bench_backoff": n_back,
                         "top3": ",".join(d.top(3)), "statement": d.statement})
            diags[(c.name, s)] = d
        say(f"diagnosed {c.name}: {n_s} trials ({time.perf_counter() - t2:.0f} s so far)")
    table = pd.DataFrame(rows)
    t_diag = time.perf_counter() - t2
    timing = {"truth_s": round(t_truth, 1), "base_calibration_s": round(prep["calibration_s"], 1),
              "linearisation_s": round(prep["linearisation_s"], 1), "diagnosis_s": round(t_diag, 1),
              "total_s": round(time.perf_counter() - t0, 1), "simulations_default_spec": int(n_sim[0]),
              "base": list(prep["base"].params), "error_model": str(error_model), "seed_start": seed_start,
              "seeds": seeds, "null_seeds": max(null_seeds, seeds), "plan_points": len(plan)}
    return {"table": table, "summary": summarise_outside(table), "by_case": summarise_outside(table, by="case"),
            "overall": overall_outside(table), "timing": timing, "plan": plan, "plans": plans, "truth": truth,
            "diagnoses": diags, "base_theta": prep["theta"], "base": prep["base"], "cases": cases,
            "linearisations": prep["linearisations"]}


def prepared_of(result: dict) -> dict:
    """What :func:`run_outside_benchmark` needs to re-diagnose ``result``'s truths (``prepared=``)."""
    return {k: result[k] for k in ("plan", "plans", "truth", "linearisations", "base", "base_theta")}


# --------------------------------------------------------------------------- summaries

def summarise_outside(table: pd.DataFrame, by: str = "kind") -> pd.DataFrame:
    """Per case kind (or ``by="case"``): trials, right %, refusal %, wrong %, confident wrong count, ..."""
    rows = []
    keys = [k for k in CASE_KINDS if k in set(table["kind"])] if by == "kind" else list(dict.fromkeys(table["case"]))
    for k in keys:
        t = table[table[by] == k]
        o = t["outcome"]
        row = {by: k}
        if by == "case":
            row["kind"] = t["kind"].iloc[0]
        row.update({"trials": len(t), "right_pct": 100.0 * float((o == "right").mean()),
                    "refusal_pct": 100.0 * float((o == "refusal").mean()),
                    "wrong_pct": 100.0 * float((o == "wrong_claim").mean()),
                    "confident_wrong": int(t["confident_wrong"].sum()),
                    "right_or_refusal_pct": 100.0 * float(o.isin(["right", "refusal"]).mean()),
                    "acceptable_pct": 100.0 * float(t["acceptable"].mean()),
                    "wrong_names": ",".join(sorted(set(t.loc[o == "wrong_claim", "named"]))),
                    "categories": "; ".join(f"{c} {n}" for c, n in t["category"].value_counts().items())})
        rows.append(row)
    return pd.DataFrame(rows)


def overall_outside(table: pd.DataFrame) -> dict:
    """The issue's figures: right-or-refusal %, confident wrong claims, null false claims, sensor channel %."""
    o = table["outcome"]
    null = table[table["kind"] == "null"]
    sens = table[table["must_name"].astype(bool)] if "must_name" in table.columns else \
        table[table["kind"] == "sensor fault"]
    return {"trials": len(table),
            "right_or_refusal_pct": 100.0 * float(o.isin(["right", "refusal"]).mean()),
            "acceptable_pct": 100.0 * float(table["acceptable"].mean()),
            "confident_wrong": int(table["confident_wrong"].sum()),
            "null_trials": len(null), "null_false_claims": int((null["outcome"] == "wrong_claim").sum()),
            # null trials that report a significant gap without naming anything (e.g. "indistinguishable")
            "null_gap_reported": int((null["category"] != "no significant gap").sum()),
            "null_hedged": int((null["category"] == "indistinguishable").sum()),
            "null_false_claim_pct": 100.0 * float((null["outcome"] == "wrong_claim").mean()) if len(null) else
            float("nan"),
            "sensor_must_name_trials": len(sens),
            "sensor_right_channel_pct": 100.0 * float(sens["sensor_right_channel"].mean()) if len(sens) else
            float("nan")}


def cases_table(cases: Sequence[OutsideCase]) -> pd.DataFrame:
    """Case, kind, accepted answers, whether a refusal is right, description (for the report)."""
    return pd.DataFrame([{"case": c.name, "kind": c.kind, "accept": ", ".join(sorted(c.accept)) or "(none)",
                          "refusal_ok": c.refusal_ok, "description": c.description} for c in cases])


def write_outside_report(result: dict, out) -> dict:
    """``<out>/gap/outside_trials.csv``, ``outside_summary.csv``, ``outside_by_case.csv`` and a Markdown/HTML page."""
    import json
    from pathlib import Path

    from engine_model.io import write_csv
    from engine_model.report import write_report

    folder = (Path(out) / "gap").resolve()
    folder.mkdir(parents=True, exist_ok=True)
    table = result["table"]
    cols = list(OUTSIDE_COLUMNS) + [c for c in table.columns if c not in OUTSIDE_COLUMNS]
    paths = {"trials": write_csv(table[cols], folder / "outside_trials.csv"),
             "summary": write_csv(result["summary"], folder / "outside_summary.csv"),
             "by_case": write_csv(result["by_case"], folder / "outside_by_case.csv")}
    ov = result["overall"]
    sections = [
        ("Overall", [f"{ov['trials']} trials: right or honest refusal {ov['right_or_refusal_pct']:.1f} %, "
                     f"acceptable by the cases' own rule {ov['acceptable_pct']:.1f} %, confident wrong claims "
                     f"{ov['confident_wrong']}; null false claims {ov['null_false_claims']} of "
                     f"{ov['null_trials']} (a significant gap reported without a name in {ov['null_gap_reported']}, of them "
                     f"'indistinguishable' {ov['null_hedged']}); sensor faults named on the right channel "
                     f"{ov['sensor_right_channel_pct']:.1f} % of {ov['sensor_must_name_trials']} must-name trials."]),
        ("Per case kind", [result["summary"]]),
        ("Per case", [result["by_case"]]),
        ("Cases", [cases_table(result.get("cases") or outside_cases())]),
        ("Timing", [json.dumps(result.get("timing", {}))]),
    ]
    md, ht = write_report(folder, "outside", "Gap diagnosis on truths outside its library", sections)
    paths.update({"markdown": md, "html": ht})
    return paths
