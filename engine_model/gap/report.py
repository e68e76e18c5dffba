"""Gap report: PNG figures, Parquet score tables and a Markdown/HTML page under ``<out>/gap/``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model.io import write_figure, write_parquet, write_text
from engine_model.report import write_report
from engine_model.gap.diagnose import GapDiagnosis

__all__ = ["write_gap_report", "plot_residual_map", "plot_chain", "plot_ranking", "plot_before_after",
           "write_benchmark_report"]

_LABEL = {"air_mass_flow_kg_h": "airflow", "brake_torque_nm": "torque", "exhaust_temp_k": "exhaust T",
          "fuel_mass_flow_kg_h": "fuel flow", "bsfc_g_kwh": "BSFC"}


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_residual_map(d: GapDiagnosis, path: Path) -> Path:
    """Normalised residuals (sigma units) of each output over speed x throttle, after the base calibration."""
    plt = _plt()
    res = d.residuals[d.residuals["used"]]
    outs = list(dict.fromkeys(res["output"]))
    fig, axes = plt.subplots(1, len(outs), figsize=(4.2 * len(outs), 3.8), squeeze=False)
    one_load = res["throttle_pct"].nunique() == 1
    for ax, o in zip(axes[0], outs):
        r = res[res["output"] == o].sort_values("speed_rpm")
        if one_load:
            ax.errorbar(r["speed_rpm"], r["z"], yerr=1.0, fmt="ko", capsize=3, label="measured - model")
            ax.axhspan(-1, 1, color="0.9", zorder=0, label="+-1 sigma")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_ylabel("residual [sigma]")
        else:
            lim = max(2.0, float(np.nanmax(np.abs(r["z"]))))
            sc = ax.scatter(r["speed_rpm"], r["throttle_pct"], c=r["z"], cmap="RdBu_r", vmin=-lim, vmax=lim,
                            s=60, edgecolors="k")
            fig.colorbar(sc, ax=ax, label="residual [sigma]")
            ax.set_ylabel("throttle [%]")
        ax.set_xlabel("speed [rpm]")
        ax.set_title(_LABEL.get(o, o))
        ax.grid(alpha=0.3)
    fig.suptitle("Residual map after the base calibration (measured - model, in measurement sigmas)")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def plot_chain(d: GapDiagnosis, path: Path) -> Path:
    """Waterfall of the mean relative torque gap along the energy chain."""
    plt = _plt()
    ch = d.chain
    steps = ch[ch["stage"] != "brake at dyno (total)"]
    total = ch[ch["stage"] == "brake at dyno (total)"].iloc[0]
    fig, ax = plt.subplots(figsize=(8, 4))
    cum = 0.0
    booked = ch["booked"] if "booked" in ch.columns else pd.Series(True, index=ch.index)
    for i, r in enumerate(steps.itertuples()):
        v = 0.0 if not np.isfinite(r.mean_pct) else r.mean_pct
        if booked[r.Index]:
            ax.bar(i, v, bottom=cum, color="tab:red" if v < 0 else "tab:green",
                   yerr=r.se_pct if np.isfinite(r.se_pct) else None, capsize=4, alpha=0.8)
            cum += v
        else:               # not significant: drawn as an outline, not added to the waterfall
            ax.bar(i, v, bottom=cum, fill=False, edgecolor="0.5", linestyle="--",
                   yerr=r.se_pct if np.isfinite(r.se_pct) else None, capsize=4)
    ax.bar(len(steps), total["mean_pct"], color="tab:blue", yerr=total["se_pct"], capsize=4)
    ax.set_xticks(range(len(steps) + 1), list(steps["stage"]) + ["brake at dyno"], rotation=15, fontsize=8)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_ylabel("measured vs model torque [%]")
    ax.set_title("Energy chain: where the torque gap arises (mean +- s.e.; dashed: not significant, not booked)")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def plot_ranking(d: GapDiagnosis, path: Path) -> Path:
    """Held-out chi2 improvement per candidate against the noise threshold, in the ranking's order (best on
    top: the lead within the noise threshold ordered by AIC), Akaike weights of 1 % or more at the bars."""
    plt = _plt()
    r = d.ranking.iloc[::-1]
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(r) + 1.5))
    colors = ["tab:green" if e == d.named else ("tab:orange" if b else "0.6")
              for e, b in zip(r["effect"], r["beats_noise"])]
    edge = r["at_range_bound"].astype(bool).to_numpy() if "at_range_bound" in r.columns else np.zeros(len(r), bool)
    bars = ax.barh(r["effect"], r["heldout_improvement"], color=colors)
    for bar, e in zip(bars, edge):
        if e:
            bar.set_hatch("//")
    if "weight" in r.columns:
        for bar, w in zip(bars, r["weight"].to_numpy(float)):
            if w >= 0.01:
                ax.annotate(f"w {w:.2f}", (max(bar.get_width(), 0.0), bar.get_y() + bar.get_height() / 2),
                            xytext=(3, 0), textcoords="offset points", va="center", fontsize=7)
    handles = [ax.axvline(d.threshold, color="k", ls="--", label=f"noise threshold {d.threshold:.1f}")]
    if edge.any():
        from matplotlib.patches import Patch

        handles.append(Patch(facecolor="white", edgecolor="k", hatch="//", label="a parameter at its range edge"))
    ax.set_xlabel("held-out chi2 improvement over the base model")
    ax.legend(handles=handles, fontsize=8)
    ax.set_title(f"Candidate ranking (K-fold held-out, lead by AIC): {d.category}")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def plot_before_after(d: GapDiagnosis, path: Path) -> Path:
    """RMS normalised residual per output before and after the best candidate (all points)."""
    plt = _plt()
    res = d.residuals[d.residuals["used"]]
    g = res.groupby("output", sort=False)
    before = g["z"].apply(lambda z: float(np.sqrt(np.mean(z**2))))
    after = g["z_with_best"].apply(lambda z: float(np.sqrt(np.mean(z**2))))
    x = np.arange(len(before))
    fig, ax = plt.subplots(figsize=(7, 3.8))
    ax.bar(x - 0.2, before.to_numpy(), 0.4, label="base calibration")
    ax.bar(x + 0.2, after.to_numpy(), 0.4, label=f"+ {d.best}" if d.best else "after")
    ax.axhline(1.0, color="k", ls="--", lw=0.8, label="noise level")
    ax.set_xticks(x, [_LABEL.get(o, o) for o in before.index])
    ax.set_ylabel("rms residual [sigma]")
    ax.legend(fontsize=8)
    ax.set_title(f"Before/after (held-out overall: {d.gap_before:.2f} -> {d.gap_after:.2f} sigma)")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def write_gap_report(d: GapDiagnosis, out, title: str = "Sim-to-real gap diagnosis", notes: list[str] | None = None) -> dict:
    """Write the gap report into ``<out>/gap/``; returns the paths written.

    Files: ``residual_map.png, energy_chain.png, ranking.png, before_after.png``, ``scores.parquet``
    (candidate ranking), ``residuals.parquet``, ``shape.parquet``, ``chain.parquet``, ``field.parquet``,
    ``regions.parquet`` (localisation per channel and region),
    ``gap.md`` / ``gap.html`` and ``gap_summary.json``.
    """
    folder = (Path(out) / "gap").resolve()
    folder.mkdir(parents=True, exist_ok=True)
    figs = {"residual_map": plot_residual_map(d, folder / "residual_map.png"),
            "energy_chain": plot_chain(d, folder / "energy_chain.png"),
            "ranking": plot_ranking(d, folder / "ranking.png"),
            "before_after": plot_before_after(d, folder / "before_after.png")}
    rank = d.ranking.drop(columns=["param_values"]).copy()
    rank["param_values"] = d.ranking["param_values"].map(json.dumps)
    paths = {k: write_parquet(v, folder / f"{k}.parquet") for k, v in
             (("scores", rank), ("residuals", d.residuals), ("shape", d.shape), ("chain", d.chain),
              ("field", d.field), ("stages", d.stages), ("regions", d.regions))}
    summary = {"category": d.category, "named": d.named, "best": d.best, "confidence": d.confidence, "statement": d.statement,
               "gap_before_sigma": d.gap_before, "gap_after_sigma": d.gap_after,
               "gap_reduction_pct": d.gap_reduction_pct, "threshold": d.threshold, "n_points": d.n_points,
               "n_obs": d.n_obs, "base_theta": d.base_theta, "excluded": d.excluded.to_dict("records")}
    pairs = d.extra.get("pairs")
    if pairs is not None:
        paths["pairs"] = write_parquet(pairs.table, folder / "pairs.parquet")
        summary["pair_named"] = list(pairs.named) if pairs.named else None
        summary["pair_statement"] = pairs.statement
    paths["summary"] = write_text(json.dumps(summary, indent=1, default=float), folder / "gap_summary.json")
    show = ["rank", "effect", "stage", "params", "heldout_chi2", "heldout_improvement", "delta_aic", "delta_bic",
            "signature_match", "weight", "beats_noise"]
    sections = [
        ("Verdict", [d.statement] + list(notes or [])),
        ("Residuals after the base calibration", [
            "Measured minus model, in units of the measurement uncertainty (airflow 1 %, torque 0.5 %, exhaust "
            "temperature 5 K, fuel flow 1 %), after the base calibration (refitted on all points).",
            figs["residual_map"], d.shape]),
        ("Where: channels and operating regions", [
            "Mean residual per measured channel and operating region (speed terciles x load halves of the plan), "
            "in sigma units. A cell is significant when its standardised mean exceeds what the largest cell "
            "reaches in 95 % of pure-noise data sets on this plan (base refitted to each).", d.regions]),
        ("Energy chain", ["A share is booked (drawn solid) only when it is at least 3 standard errors from zero "
                          "and the torque gap itself is.", figs["energy_chain"], d.chain]),
        ("Which effect", [f"Noise threshold of the held-out chi2 improvement: {d.threshold:.2f} (95 % of pure-noise "
                          f"trials on this design stay below it). {d.n_points} points, {d.n_obs} observations.",
                          figs["ranking"], d.ranking[show]]),
        ("How far it shrinks", [figs["before_after"]]),
    ]
    if pairs is not None:
        show_p = ["effect_a", "effect_b", "params", "heldout_chi2", "improvement_over_base",
                  "improvement_over_best_single", "reduction_pct", "at_range_bound"]
        sections.append(("Best pair of effects", [
            pairs.statement,
            f"Noise thresholds: improvement over the base {pairs.threshold:.2f}, over the best single candidate "
            f"{pairs.excess_threshold:.2f} (95 % of pure-noise trials on this design stay below each). Top 10 of "
            f"{len(pairs.table)} pairs:", pairs.table[show_p].head(10)]))
    sections += [
        ("Smooth residual field", [d.field]),
    ]
    if len(d.excluded):
        sections.append(("Excluded points", [d.excluded]))
    md, ht = write_report(folder, "gap", title, sections)
    paths.update(figs)
    paths.update({"markdown": md, "html": ht})
    return paths


def write_benchmark_report(result: dict, out) -> dict:
    """``gap_benchmark.csv`` (the issue's columns), details, summary and a Markdown/HTML page in ``<out>/gap/``."""
    from engine_model.io import write_csv
    from engine_model.gap.benchmark import BENCHMARK_COLUMNS

    folder = (Path(out) / "gap").resolve()
    folder.mkdir(parents=True, exist_ok=True)
    table = result["table"]
    paths = {"csv": write_csv(table[list(BENCHMARK_COLUMNS)], folder / "gap_benchmark.csv"),
             "details": write_parquet(table, folder / "gap_benchmark_details.parquet"),
             "summary": write_parquet(result["summary"], folder / "gap_benchmark_summary.parquet")}
    if len(result.get("verification", [])):
        paths["verification"] = write_parquet(result["verification"], folder / "gap_benchmark_verification.parquet")
    if result.get("plans"):
        # the plan of every case as the bench ran it (knocking points backed off on the bench)
        runs = pd.concat([p.assign(effect_withheld=k[0], magnitude=k[1]) for k, p in result["plans"].items()],
                         ignore_index=True, sort=False)
        paths["plans"] = write_parquet(runs, folder / "gap_benchmark_plans.parquet")
    plt = _plt()
    s = result["summary"]
    fig, ax = plt.subplots(figsize=(10, 4))
    lib = s[~s["effect_withheld"].isin(["none", "ool_ve_resonance"])]
    for m, grp in lib.groupby("magnitude"):
        ax.plot(grp["effect_withheld"], grp["top1"] * 100, "o-", label=f"magnitude {m:g} x realistic")
    ax.set_ylabel("top-1 accuracy [%]")
    ax.tick_params(axis="x", rotation=35, labelsize=8)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    write_figure(fig, folder / "benchmark_top1.png", dpi=100)
    plt.close(fig)
    paths["figure"] = folder / "benchmark_top1.png"
    sections = [("Summary", [s]), ("Timing", [json.dumps(result.get("timing", {}))]),
                ("Top-1 by effect", [paths["figure"]])]
    if len(result.get("verification", [])):
        sections.append(("Nonlinear verification", [result["verification"]]))
    md, ht = write_report(folder, "gap_benchmark", "Gap diagnosis benchmark on withheld effects", sections)
    paths.update({"markdown": md, "html": ht})
    return paths
