"""The model stage: the virtual-bench campaign and the global map-wide combustion model.

    calibrated engine --> engine_model.globalmodel.campaign.run_campaign (plan, virtual bench, identification,
                          global model, scores against the hidden law, learning curve)
                      --> virtual_bench/ (plan, measured rows, identification), model/ (model.json, CV,
                          learning curve, report)

No science here: the stage routes the campaign's simulations to Dask and writes its results.
"""

from __future__ import annotations

from flows.stages.context import StageContext

from engine_model.globalmodel.campaign import run_campaign  # noqa: E402
from engine_model.globalmodel.learning import plot_learning_curve  # noqa: E402
from engine_model.io import write_parquet  # noqa: E402
from engine_model.report import write_report  # noqa: E402
from engine_model.sim.prepare import SolverSettings  # noqa: E402


def run(ctx: StageContext) -> dict:
    """Run the campaign on the calibrated engine; write ``virtual_bench/`` and ``model/``; return the summary."""
    vdir, mdir = ctx.work / "virtual_bench", ctx.work / "model"
    vdir.mkdir(parents=True, exist_ok=True)
    mdir.mkdir(parents=True, exist_ok=True)
    st = ctx.settings.campaign()

    def make_evaluate(label: str, solver: SolverSettings):
        return ctx.evaluator(label, solver.step_deg, solver.tolerance)

    res = run_campaign(ctx.engine.spec, st, make_evaluate=make_evaluate)
    write_parquet(res.plan, vdir / "plan.parquet")
    write_parquet(res.measured, vdir / "measured.parquet")
    write_parquet(res.identified, vdir / "identified.parquet")
    write_parquet(res.holdout_status, vdir / "holdout_status.parquet")
    res.model.save(mdir / "model.json")
    cv = res.model.cv_table()
    write_parquet(cv, mdir / "cv.parquet")
    write_parquet(res.learning_curve, mdir / "learning_curve.parquet")
    plot_learning_curve(res.learning_curve, mdir / "learning_curve.png")
    write_parquet(res.learning_summary, mdir / "learning_summary.parquet")
    lines = res.lines(st)
    write_report(mdir, "model", "Virtual bench, identification and the global model",
                 [("Summary", lines), ("Cross-validation", [cv]),
                  ("Learning curve", [res.learning_summary, mdir / "learning_curve.png"])])
    meas = res.measured
    return {"doe_points": len(meas), "status": meas["status"].value_counts().to_dict(),
            "identification": res.identification_error, "model_chosen": dict(res.model.chosen_),
            "holdout": res.holdout_error, "model_path": "model/model.json", "lines": lines}   # relative to the run folder (renamed when complete)
