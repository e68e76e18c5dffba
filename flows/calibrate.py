"""The ``calibrate`` flow: airflow matching, then Wiebe combustion identification, on bench data.

    bench --validate--> airflow matching (global intake parameters, least squares on Ga_REL)
          --> identification sweep (BDUR10-90 x m at every bench point, airflow-matched spec)
          --> most probable (BDUR10-90, m) per point, eta_trans sensitivity, joint fit, report

Every simulation runs as a sweep on Dask (``flows.evaluate.SweepEvaluator``),
into ``<out>/sweeps/``; a re-run into the same folder reads finished batches
back.  Outputs in ``<out>/``: ``airflow_match.parquet``,
``combustion_params.parquet``, figures and ``calibration.md`` / ``.html``.
"""

from __future__ import annotations

import datetime as _dt
import json
import time
from pathlib import Path

import pandas as pd

from . import prefect_env
from .evaluate import SweepEvaluator, shared_cluster
from .sweep import DEFAULT_WORKERS

from prefect import flow  # noqa: E402

from engine_model import __version__, load_spec  # noqa: E402
from engine_model import calibrate as cal  # noqa: E402
from engine_model.bench import load_bench  # noqa: E402
from engine_model.io import write_json, write_parquet  # noqa: E402
from engine_model.report import write_report  # noqa: E402


def calibrate_into(out: Path, meas: pd.DataFrame, eng, spec: str | None, address: str, eta_trans: float,
                   step_deg: float, progress: bool) -> dict:
    """The calibration steps into folder ``out`` on the Dask scheduler ``address``; returns a summary dict."""
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    figs = out / "figures"
    figs.mkdir(exist_ok=True)

    def evaluator(label):
        return SweepEvaluator(out / "sweeps", address, spec=spec, step_deg=step_deg, label=label,
                              progress=progress)

    ev_air = evaluator("airflow")
    match = cal.match_airflow(meas, ev_air, spec=eng)
    write_parquet(match.table, out / "airflow_match.parquet")
    cal.plot_airflow_match(match, figs / "ga_rel_vs_speed.png")
    t_air = time.perf_counter() - t0

    ev_id = evaluator("identification")
    plan = cal.identification_plan(meas, overrides=match.spec_overrides())
    results = ev_id(plan)
    ident = cal.identify(meas, results, eta_trans=eta_trans)
    params = ident.table
    write_parquet(params, out / "combustion_params.parquet")
    for pid in params["point_id"]:
        cal.plot_identification(ident, results, pid, figs / f"plane_{pid}.png")
    eta = cal.eta_sensitivity(meas, results)
    relation = cal.fit_eta_relation(eta)
    write_parquet(eta, out / "eta_sensitivity.parquet")
    cal.plot_eta_relation(eta, relation, figs / "eta_relation.png")
    joint = cal.joint_fit(meas, results)
    summary = {
        "airflow": {"parameters": match.values, "ci95": match.ci95, "rms_ga_rel_pct": match.rms_ga_rel_pct,
                    "max_abs_ga_rel_pct": match.max_abs_ga_rel_pct, "simulations": ev_air.points,
                    "seconds": round(t_air, 1)},
        "identification": {"points": len(params), "simulations": ev_id.points,
                           "seconds": round(time.perf_counter() - t0 - t_air, 1)},
        "eta_relation": relation.coefficients if hasattr(relation, "coefficients") else relation,
        "joint_fit": joint.summary() if hasattr(joint, "summary") else str(joint),
        "eta_trans": eta_trans, "wall_s": round(time.perf_counter() - t0, 1),
    }
    sections = [
        ("Airflow matching", [match.summary(), match.table, figs / "ga_rel_vs_speed.png",
                              pd.DataFrame(match.correlation)]),
        ("Combustion identification", [ident.summary() if hasattr(ident, "summary") else "", params]
         + [figs / f"plane_{pid}.png" for pid in params["point_id"]]),
        ("Transmission efficiency", [eta, str(summary["eta_relation"]), figs / "eta_relation.png",
                                     str(summary["joint_fit"])]),
    ]
    write_report(out, "calibration", "Calibration on bench data", sections)
    write_json({"kind": "calibration", "package_version": __version__, "spec_hash": eng.spec_hash(),
                "created": _dt.datetime.now().isoformat(timespec="seconds"), **summary}, out / "summary.json")
    return summary


@flow(name="calibrate", log_prints=False, validate_parameters=False)
def calibrate_flow(out: str, bench: str | None = None, spec: str | None = None, eta_trans: float = 0.95,
                   step_deg: float = 0.5, workers: int = DEFAULT_WORKERS, dask_address: str | None = None,
                   progress: bool = True) -> dict:
    """Airflow matching and combustion identification of ``bench`` (packaged Table 2 by default) into ``out``."""
    eng = load_spec(spec)
    meas = load_bench(bench)
    with shared_cluster(workers, dask_address) as addr:
        return calibrate_into(Path(out), meas, eng, spec, addr, eta_trans, step_deg, progress)


def run_calibration(out, bench=None, spec=None, **kwargs) -> dict:
    """``mbc calibrate``: validate inputs, then run :func:`calibrate_flow` under one Prefect API."""
    load_spec(spec)
    load_bench(bench)
    with prefect_env.prefect_api(verbose=kwargs.get("progress", True)):
        res = calibrate_flow(out=str(out), bench=None if bench is None else str(bench), spec=spec, **kwargs)
    print(json.dumps(res, indent=1, default=str)[:3000])
    return res
