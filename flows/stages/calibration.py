"""The calibration stage (and the ``mbc calibrate`` flow): airflow matching, then Wiebe combustion identification, on bench data.

    bench --validate--> airflow matching (global intake/exhaust parameters, least squares on Ga_REL)
          --> identification sweep (BDUR10-90 x m at every bench point, airflow-matched spec)
          --> most probable (BDUR10-90, m) per point, eta_trans sensitivity + eq-6 relation,
              joint fit of a shared eta_trans, report

Every simulation runs as a sweep on Dask (``flows.evaluate.SweepEvaluator``),
into ``<out>/sweeps/``; a re-run into the same folder reads finished batches
back.  Outputs in ``<out>/calibration/``: ``airflow_match.parquet``,
``combustion_params.parquet`` (at the given eta_trans, default 0.95),
``combustion_params_joint_eta.parquet`` (at the jointly fitted shared eta_trans), ``eta_sensitivity.parquet``,
``eta_relation.parquet``, ``summary.json``, figures (Ga_REL, identification planes, eta relation, the
pressures over the cycle at the point nearest 9000 rpm) and ``calibration.md`` / ``.html``.
"""

from __future__ import annotations

import datetime as _dt
import time
from pathlib import Path

import numpy as np
import pandas as pd

from flows import prefect_env
from flows.evaluate import shared_cluster
from flows.settings import RunSettings
from flows.stages.context import StageContext
from flows.sweep import DEFAULT_WORKERS

from prefect import flow  # noqa: E402

from engine_model import calibration as cal  # noqa: E402
from engine_model.bench import load_bench  # noqa: E402
from engine_model import knock  # noqa: E402
from engine_model.calibrated import CalibratedEngine  # noqa: E402
from engine_model.io import write_json, write_parquet  # noqa: E402
from engine_model.report import plot_traces, write_report  # noqa: E402
from engine_model.sim.prepare import SolverSettings  # noqa: E402
from engine_model.version import package_version  # noqa: E402

#: The knock multiplier the tables use: the predictive quantile at which a cell called knock-free knocks with
#: this probability (the issue's bar for the tables: <= 2 % of cells knocking on the engine).
KNOCK_PROBABILITY = 0.02
#: Speed step of the speed term's table multipliers in the summary [rpm] (the maps interpolate in ln n).
SPEED_TERM_STEP_RPM = 500.0
AIRFLOW_COLUMNS = ["point_id", "speed_rpm", "air_mass_flow_kg_h_meas", "air_mass_flow_kg_h_sim", "ga_rel_pct"]


def run(ctx: StageContext) -> dict:
    """The calibration stage into ``ctx.work/calibration``: airflow match, identification, eta_trans study.

    Returns the summary (also written as ``calibration/summary.json``); its ``airflow.parameters`` are the
    values the calibrated engine takes (:func:`calibrated_engine`).
    """
    out = (ctx.work / "calibration").resolve()   # absolute, so the report links its figures relative to itself
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    figs = out / "figures"
    figs.mkdir(exist_ok=True)
    s = ctx.settings.calibration_settings()
    meas, eng = ctx.bench, ctx.engine.spec

    ev_air = ctx.evaluator("airflow", s.airflow_step_deg)
    match = cal.match_airflow(meas, ev_air, spec=eng, grid=s.airflow_grid, starts=s.airflow_starts,
                              max_nfev=s.airflow_max_nfev)
    air_tab = match.table
    write_parquet(air_tab[AIRFLOW_COLUMNS + [c for c in air_tab.columns if c not in AIRFLOW_COLUMNS]],
                  out / "airflow_match.parquet")
    write_parquet(match.grid, out / "airflow_grid.parquet")
    cal.plot_airflow_match(match, figs / "ga_rel_vs_speed.png")
    t_air = time.perf_counter() - t0

    ev_id = ctx.evaluator("identification", s.step_deg)
    plan = cal.identification_plan(meas, overrides=match.spec_overrides(), n_bdur=s.n_bdur, n_m=s.n_m)
    results = ev_id(plan) if len(plan) else pd.DataFrame()
    ident = cal.identify(meas, results, eta_trans=s.eta_trans, surface=s.surface)
    params = ident.table
    write_parquet(params, out / "combustion_params.parquet")
    planes = [cal.plot_identification(ident, pid, figs / f"plane_{pid}.png") for pid in ident.surfaces]
    eta = cal.eta_sensitivity(ident)
    iso = cal.power_isolines(ident)
    relation = cal.fit_eta_relation(iso)
    write_parquet(eta, out / "eta_sensitivity.parquet")
    write_parquet(relation, out / "eta_relation.parquet")
    cal.plot_eta_relation(eta, iso, relation, figs / "eta_relation.png")
    traces = _pressure_traces(eng.with_values(match.values), meas, params, s, figs)
    t_kn = time.perf_counter()
    kcal, kplan, kspeed = _knock_calibration(ctx, meas, params, match, s.step_deg, out, figs)
    joint = cal.joint_fit(ident)
    ident_joint = cal.identify_at_eta(ident, joint.eta_by_throttle())
    params_joint = ident_joint.table
    write_parquet(params_joint, out / "combustion_params_joint_eta.parquet")
    t_id = time.perf_counter() - t0 - t_air
    rel_text = {r["point_id"]: cal.relation_text(r) for _, r in relation.iterrows() if r.get("status") == "ok"}
    summary = {
        "airflow": {"parameters": match.values, "ci95_assumed_noise": match.ci95,
                    "ci95_residual_variance": match.ci95_residual, "correlation": match.correlation,
                    "rms_ga_rel_pct": round(match.rms_ga_rel_pct, 3),
                    "max_abs_ga_rel_pct": round(match.max_abs_ga_rel_pct, 3),
                    "misses_1pct": {r.point_id: round(r.ga_rel_pct, 2) for r in match.misses().itertuples()},
                    "at_bound": match.at_bound, "simulations": ev_air.points, "seconds": round(t_air, 1),
                    "bounds": {p.name: [p.low, p.high] for p in cal.DEFAULT_PARAMETERS if p.name in match.values}},
        "identification": {"points": len(params), "fit_ok": int(params["fit_ok"].sum()),
                           "grid": [s.n_bdur, s.n_m], "surface": s.surface,
                           "simulations": ev_id.points, "seconds": round(t_id, 1),
                           "eta_trans": s.eta_trans, "per_point": _per_point(params),
                           "search_range": {"bdur_10_90_deg": list(cal.BDUR_RANGE_DEG), "wiebe_m": list(cal.M_RANGE)}},
        "knock": {**kcal.summary(), "text": kcal.text() + _speed_term_text(kspeed), "speed_term": kspeed,
                  "simulations": len(kplan),
                  "seconds": round(time.perf_counter() - t_kn, 1),
                  "cycle_ca50_advance_deg": eng.knock.cycle_ca50_advance_deg,
                  "octane_index": round(eng.knock.octane_index, 2)},
        "eta_relation": rel_text,
        "joint_fit": joint.summary(),
        "joint_eta": _joint_summary(joint, params_joint),
        "eta_trans": s.eta_trans, "step_deg": s.step_deg, "airflow_step_deg": s.airflow_step_deg,
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    show = ["point_id", "speed_rpm", "spark_deg_btdc", "bdur_10_90_deg", "bdur_10_90_deg_lo", "bdur_10_90_deg_hi",
            "wiebe_m", "wiebe_m_lo", "wiebe_m_hi", "ca50_deg_atdc", "brake_power_kw_meas", "brake_power_kw_sim",
            "brake_power_err_pct", "power_ok", "ca50_ok", "pmax_bar", "mirror_wiebe_m", "mirror_rejected_by", "status"]
    sections = [
        ("Airflow matching", [match.summary(), air_tab, figs / "ga_rel_vs_speed.png",
                              "Parameter correlation matrix (rows/columns in the order "
                              + ", ".join(match.names) + "):",
                              pd.DataFrame(match.correlation, columns=list(match.names))]),
        ("Combustion identification", [ident.summary(), params[[c for c in show if c in params.columns]]] + planes),
        ("Knock calibration", [kcal.text(), kcal.evidence, figs / "knock_evidence.png"]),
        ("Pressures over the cycle", ["At the bench point nearest 9000 rpm, with the matched engine and the identified "
                                      "burn: cylinders, manifold volumes and the waves in the pipes of cylinder 1."]
         + traces),
        ("Identification at the jointly fitted eta_trans", [
            joint.summary(), joint.table, ident_joint.summary(),
            params_joint[[c for c in show[:3] + ["eta_trans"] + show[3:] if c in params_joint.columns]]]),
        ("Transmission efficiency", [
            "Identified parameters versus the assumed eta_trans (post-processing: eta only scales the target):",
            eta[["point_id", "eta_trans", "bdur_10_90_deg", "wiebe_m", "ca50_deg_atdc", "brake_power_err_pct",
                 "status"]],
            "Fitted relation BDUR10-90 = f(m, eta_trans) on the measured-power isoline (paper eq 6 form):",
            relation, figs / "eta_relation.png", joint.summary(), joint.table]),
    ]
    write_report(out, "calibration", "Calibration on bench data", sections)
    write_json({"kind": "calibration", "package_version": package_version(), "spec_hash": eng.spec_hash(),
                "created": _dt.datetime.now().isoformat(timespec="seconds"), **summary}, out / "summary.json")
    return summary


def _pressure_traces(spec, meas, params, s, figs) -> list:
    """The pressure-trace figure at the identified bench point nearest 9000 rpm (empty if none identified)."""
    ok = params[np.isfinite(params["bdur_10_90_deg"].to_numpy(float))] if len(params) else params
    if not len(ok):
        return []
    pid = ok.iloc[int(np.argmin(np.abs(ok["speed_rpm"].to_numpy(float) - 9000.0)))]
    bench_row = meas.set_index("point_id").loc[pid["point_id"]]
    path = figs / f"pressure_traces_{pid['point_id']}.png"
    plot_traces(spec, bench_row, float(pid["bdur_10_90_deg"]), float(pid["wiebe_m"]),
                SolverSettings(step_deg=s.step_deg), path)
    return [path]


def calibrated_engine(engine: CalibratedEngine, summary: dict) -> CalibratedEngine:
    """The engine with the airflow-matched values and the knock multiplier (knock-prone quantile) of a summary."""
    values = {k: float(v) for k, v in summary["airflow"]["parameters"].items()}
    if "knock" in summary:
        values["knock.delay_multiplier"] = float(summary["knock"]["delay_multiplier_table"])
    return engine.calibrated(values)


def _knock_calibration(ctx, meas, params, match, step_deg, out, figs):
    """Spark sweeps at the identified burns -> knock evidence per bench point -> delay multiplier; writes
    ``knock_evidence.parquet`` and ``figures/knock_evidence.png``."""
    eng = ctx.engine.spec
    plan = knock.bench_sweep_plan(params, overrides=match.spec_overrides())
    res = ctx.evaluator("knock", step_deg)(plan) if len(plan) else pd.DataFrame(
        columns=["knock_index", "brake_torque_nm"])
    evidence = knock.point_evidence(meas, plan, res, eng.knock.delay_multiplier, eng.knock.cycle_ca50_advance_deg)
    kcal = knock.calibrate_knock(evidence, knock_probability=KNOCK_PROBABILITY)
    kspeed = None
    if np.isfinite(evidence["ln_ki_cycle_m1"].to_numpy(float)).any():
        speeds = np.arange(1000.0, eng.geometry.max_speed_rpm + 1.0, SPEED_TERM_STEP_RPM)
        kspeed = knock.calibrate_knock_speed(evidence).summary(speeds, KNOCK_PROBABILITY)
    write_parquet(evidence, out / "knock_evidence.parquet")
    knock.plot_evidence(kcal, figs / "knock_evidence.png")
    return kcal, plan, kspeed


def _speed_term_text(term: dict | None) -> str:
    """One sentence on the speed-dependent multiplier: used by the tables or not, and why."""
    if not term:
        return ""
    lo, hi = term["slope_68"]
    head = (f"  Speed term ln m = a + b ln(n/{term['reference_speed_rpm']:g} rpm): b = {term['slope_median']:.3g} "
            f"(68 % {lo:.3g} to {hi:.3g}, posterior sd {term['slope_sd']:.2g} against the prior's "
            f"{term['slope_prior_sd']:g})")
    if term["used"]:
        return head + "; the data inform b, so the tables take the multiplier at each cell's speed."
    return head + "; the data do not inform b, so the tables keep the one multiplier."


_POINT_KEYS = ("point_id", "speed_rpm", "eta_trans", "bdur_10_90_deg", "bdur_10_90_deg_lo", "bdur_10_90_deg_hi",
               "wiebe_m", "wiebe_m_lo", "wiebe_m_hi", "ca50_deg_atdc", "brake_power_err_pct", "power_ok", "ca50_ok",
               "fit_ok", "region_at_edge", "status")


def _per_point(table: pd.DataFrame) -> list[dict]:
    """Plain-JSON rows of an identification table (the keys the summary and the console show)."""
    out = []
    for _, r in table.iterrows():
        d = {}
        for k in _POINT_KEYS:
            v = r.get(k)
            if v is None or (isinstance(v, float) and v != v):
                d[k] = None
            elif isinstance(v, (bool, str)) or hasattr(v, "dtype") and v.dtype == bool:
                d[k] = v if isinstance(v, str) else bool(v)
            else:
                d[k] = round(float(v), 3)
        out.append(d)
    return out


def _joint_summary(joint, table: pd.DataFrame) -> dict:
    """The shared eta_trans per throttle with its interval, and the identification at it."""
    groups = [{"throttle_pct": float(r.throttle_pct), "eta_trans": float(r.eta_best),
               "ci95": [float(r.eta_lo), float(r.eta_hi)], "identifiable": bool(r.identifiable),
               "note": str(r.note), "points": int(r.points)} for r in joint.table.itertuples()]
    return {"groups": groups, "fit_ok": int(table["fit_ok"].sum()), "points": len(table),
            "per_point": _per_point(table)}


def _point_lines(rows: list[dict]) -> list[str]:
    lines = [f"  {'point':<10} {'eta':>5} {'BDUR10-90 deg (95 %)':>22} {'m (95 %)':>18} {'CA50':>6} "
             f"{'P err %':>8}  pass"]
    for r in rows:
        if r["bdur_10_90_deg"] is None:
            lines.append(f"  {r['point_id']:<10} {r['status']}")
            continue
        flags = ("ok" if r["fit_ok"] else "MISS: " + ", ".join(
            [k for k, v in (("power", r["power_ok"]), ("CA50", r["ca50_ok"])) if not v] or ["other term"]))
        edge = " (region at the plane edge)" if r.get("region_at_edge") else ""
        lines.append(f"  {r['point_id']:<10} {r['eta_trans']:>5.3f} {r['bdur_10_90_deg']:>6.1f} "
                     f"({r['bdur_10_90_deg_lo']:>4.1f}-{r['bdur_10_90_deg_hi']:>4.1f}){'':>4} "
                     f"{r['wiebe_m']:>5.2f} ({r['wiebe_m_lo']:.2f}-{r['wiebe_m_hi']:.2f}) "
                     f"{r['ca50_deg_atdc']:>6.1f} {r['brake_power_err_pct']:>+8.2f}  {flags}{edge}")
    return lines


def summary_text(summary: dict) -> str:
    """Console summary of :func:`calibrate_into`'s result: airflow, identification at the default and
    at the jointly fitted eta_trans (per point, with CA50/power pass flags)."""
    air = summary["airflow"]
    idn = summary["identification"]
    lines = ["Airflow match: " + ", ".join(f"{k} = {v:.4g} +- {air['ci95_assumed_noise'][k]:.2g}"
                                         for k, v in air["parameters"].items()),
             f"  max |Ga_REL| {air['max_abs_ga_rel_pct']:.2f} %, rms {air['rms_ga_rel_pct']:.2f} %; outside +-1 %: "
             + (", ".join(f"{k} {v:+.2f} %" for k, v in air["misses_1pct"].items()) or "none"),
             f"Identification at eta_trans = {idn['eta_trans']:g} (default): {idn['fit_ok']} of {idn['points']} "
             "points meet brake power +-1 % and CA50 8-10 deg ATDC"]
    lines += _point_lines(idn["per_point"])
    je = summary["joint_eta"]
    for g in je["groups"]:
        lines.append(f"Joint fit, throttle {g['throttle_pct']:g} %: shared eta_trans = {g['eta_trans']:.3f} "
                     f"(95 % {g['ci95'][0]:.3f}-{g['ci95'][1]:.3f}, {g['points']} points)"
                     + ("" if g["identifiable"] else f"; NOT identified by the data: {g['note']}"))
    lines.append(f"Identification at the joint eta_trans: {je['fit_ok']} of {je['points']} points meet power and CA50")
    lines += _point_lines(je["per_point"])
    if "knock" in summary:
        lines.append(summary["knock"]["text"])
    lines.append(f"wall time {summary['wall_s']:.0f} s (airflow {air['seconds']:.0f} s, {air['simulations']} "
                 f"simulations; identification {idn['seconds']:.0f} s, {idn['simulations']} simulations)")
    return "\n".join(lines)


@flow(name="calibrate", log_prints=False, validate_parameters=False)
def calibrate_flow(out: str, bench: str | None = None, spec: str | None = None, eta_trans: float = 0.95,
                   step_deg: float = 0.5, workers: int = DEFAULT_WORKERS, dask_address: str | None = None,
                   n_bdur: int = 11, n_m: int = 13, airflow_grid: tuple = (6, 6, 1), airflow_max_nfev: int = 12,
                   airflow_step_deg: float = 1.0, progress: bool = True, throttle_unit: str = "pct") -> dict:
    """Airflow matching and combustion identification of ``bench`` (packaged Table 2 by default) into ``out``.

    ``throttle_unit`` "fraction" reads the bench file's ``throttle_pct`` as 0-1 and converts it to percent.

    Writes ``out/calibration/`` and the calibrated engine ``out/engine.toml`` (``--spec`` of later commands).
    """
    engine = CalibratedEngine.from_spec(spec)
    settings = RunSettings(eta_trans=eta_trans, step_deg=step_deg, stages=("calibration",),
                           calibration=cal.CalibrationSettings(airflow_grid=tuple(airflow_grid),
                                                               airflow_max_nfev=airflow_max_nfev, n_bdur=n_bdur,
                                                               n_m=n_m, airflow_step_deg=airflow_step_deg))
    with shared_cluster(workers, dask_address) as addr:
        ctx = StageContext(work=Path(out), engine=engine, engine_file=spec, address=addr, settings=settings,
                           bench=load_bench(bench, throttle_unit), bench_source=str(bench or "packaged Table 2"),
                           progress=progress)
        summary = run(ctx)
    ctx.with_engine(calibrated_engine(engine, summary))
    return summary


def run_calibration(out, bench=None, spec=None, **kwargs) -> dict:
    """``mbc calibrate``: validate inputs, then run :func:`calibrate_flow` under one Prefect API."""
    CalibratedEngine.from_spec(spec)
    load_bench(bench, kwargs.get("throttle_unit", "pct"))
    cal.grid_axes(kwargs.get("n_bdur", 11), kwargs.get("n_m", 13))   # bad grid sizes fail before any work
    with prefect_env.prefect_api(verbose=kwargs.get("progress", True)):
        res = calibrate_flow(out=str(out), bench=None if bench is None else str(bench), spec=spec, **kwargs)
    print(summary_text(res))
    print(f"(full summary: {Path(out) / 'calibration' / 'summary.json'}; calibrated engine: {Path(out) / 'engine.toml'})")
    return res
