"""Figures of the calibration (matplotlib, Agg backend): Ga_REL vs speed, identification planes, eta relation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from engine_model.io import write_figure


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_airflow_match(match, path: Path) -> Path:
    """Ga_REL [%] vs speed with the +-1 % band, and measured vs simulated air mass flow."""
    plt = _plt()
    t = match.table.sort_values("speed_rpm")
    fig, ax = plt.subplots(1, 2, figsize=(12, 4))
    ax[0].axhspan(-1, 1, color="g", alpha=0.15, label="+-1 % (paper's target)")
    ax[0].plot(t["speed_rpm"], t["ga_rel_pct"], "bo-", label="after matching")
    g0 = match.grid
    ax[0].axhline(0, color="k", lw=0.5)
    ax[0].set_ylabel("Ga_REL = (Ga_sim - Ga_meas) / Ga_sim [%]")
    ax[1].plot(t["speed_rpm"], t["air_mass_flow_kg_h_meas"], "ko-", label="measured")
    ax[1].plot(t["speed_rpm"], t["air_mass_flow_kg_h_sim"], "bs--", label="simulated (matched)")
    ax[1].set_ylabel("air mass flow [kg/h]")
    for a in ax:
        a.set_xlabel("speed [rpm]")
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    vals = ", ".join(f"{k.split('.')[-1]}={v:.3g}" for k, v in match.values.items())
    fig.suptitle(f"Airflow match ({vals}); coarse grid of {len(g0)} sets, rms {match.rms_ga_rel_pct:.2f} %")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)
    return Path(path)


#: Upper end of the BSFC colour scale [g/kWh]: above any running SI engine's BSFC (best ~230, part load
#: ~400-500); cells above it are near-zero-power corners of the plane, where BSFC runs off to 10^5 and
#: would flatten the rest of the scale to one colour.
BSFC_PLOT_MAX_G_KWH = 600.0


def bsfc_scale(z, top: float = BSFC_PLOT_MAX_G_KWH) -> tuple[np.ndarray, np.ndarray]:
    """Contour levels of a BSFC field [g/kWh] clipped at ``top``, and the mask of cells shown as "> top"
    (above it, or without positive power: BSFC <= 0 or not finite)."""
    z = np.asarray(z, dtype=float)
    over = ~np.isfinite(z) | (z <= 0.0) | (z > top)
    ok = z[~over]
    lo = float(np.min(ok)) if ok.size else 0.0
    return np.linspace(min(lo, top - 1.0), top, 21), over


def _bsfc_panel(ax, M, B, z, label: str):
    """BSFC contours on a scale clipped at :data:`BSFC_PLOT_MAX_G_KWH`; cells above it (or with no positive
    power, BSFC <= 0) are hatched grey and counted in the label."""
    z = np.asarray(z, dtype=float)
    levels, over = bsfc_scale(z)
    cs = ax.contourf(M, B, np.where(over, np.nan, z), levels=levels, cmap="viridis")
    if over.any():
        ax.contourf(M, B, over.astype(float), levels=[0.5, 1.5], colors=["0.85"], hatches=["xx"])
        label = f"{label}; hatched: > {BSFC_PLOT_MAX_G_KWH:.0f} ({100 * over.mean():.0f} % of the plane)"
    return cs, label


def plot_identification(ident, point_id: str, path: Path) -> Path:
    """Six panels over the (BDUR10-90, m) plane of one point, with the chosen point and its ridge mirror.

    Brake power (measured isoline P_meas/eta and +-1 %), CA50 (8-10 deg band), Pmax (plausibility
    limit), exhaust temperature and BSFC (measured isolines when measured), chi2 with the 95 % region.
    """
    from engine_model.calibration.identify import CHI2_95_2DOF, chi2_terms, terms_used

    plt = _plt()
    ps = ident.surfaces[point_id]
    r = ident.table.set_index("point_id").loc[point_id]
    eta, tol = ident.eta_trans, ident.tol
    M, B = np.meshgrid(ps.fine_m, ps.fine_b)
    f = ps.fine
    target = float(ps.row["brake_power_kw"]) / eta
    chi2 = sum(chi2_terms(ps, eta, tol, terms_used(ps.row)).values())
    panels = [
        ("brake_power_kw", "brake power at crank [kW]", [target * 0.99, target, target * 1.01]),
        ("ca50_deg_atdc", "CA50 [deg ATDC]", [tol.ca50_target_deg - tol.ca50_sigma_deg,
                                               tol.ca50_target_deg + tol.ca50_sigma_deg]),
        ("pmax_bar", "peak pressure [bar]", [tol.pmax_max_bar]),
        ("exhaust_temp_k", "exhaust temperature [K]", [float(ps.row["exhaust_temp_k"])]
         if "exhaust_temp_k" in ps.row.index and pd.notna(ps.row["exhaust_temp_k"]) else []),
        ("bsfc_g_kwh", "BSFC at crank [g/kWh]", [float(ps.row["bsfc_g_kwh"]) * eta]
         if "bsfc_g_kwh" in ps.row.index and pd.notna(ps.row["bsfc_g_kwh"]) else []),
    ]
    fig, axes = plt.subplots(2, 3, figsize=(15, 8.5))
    for ax, (col, label, lines) in zip(axes.ravel(), panels):
        z = f[col]
        if col == "bsfc_g_kwh":
            cs, bar_label = _bsfc_panel(ax, M, B, z, label)
        else:
            cs, bar_label = ax.contourf(M, B, z, levels=20, cmap="viridis"), label
        fig.colorbar(cs, ax=ax, label=bar_label)
        if col == "ca50_deg_atdc" and lines:
            ax.contourf(M, B, z, levels=lines, colors="w", alpha=0.35)
        if lines:
            ax.contour(M, B, z, levels=sorted(lines), colors="r", linewidths=[1, 2, 1][:len(lines)] if
                       col == "brake_power_kw" else 1.5)
        ax.set_title(label + ("  (red: measured)" if col in ("brake_power_kw", "exhaust_temp_k", "bsfc_g_kwh")
                              and lines else ""), fontsize=9)
    ax = axes.ravel()[5]
    c = np.log10(1e-3 + chi2 - np.nanmin(chi2))
    cs = ax.contourf(M, B, c, levels=20, cmap="magma_r")
    fig.colorbar(cs, ax=ax, label="log10(chi2 - chi2_min)")
    ax.contour(M, B, chi2 - np.nanmin(chi2), levels=[CHI2_95_2DOF], colors="c", linewidths=2)
    ax.set_title(f"chi2 ({r['terms']}); cyan: 95 % region", fontsize=9)
    # the ridge of maximum power (dP/dm = 0) on every panel
    dpdm = np.gradient(f["brake_power_kw"], ps.fine_m, axis=1)
    for ax in axes.ravel():
        ax.contour(M, B, dpdm, levels=[0.0], colors="k", linestyles="--", linewidths=1)
        ax.plot(r["wiebe_m"], r["bdur_10_90_deg"], "r*", ms=14, mec="w", label="chosen")
        if pd.notna(r.get("mirror_wiebe_m", np.nan)):
            ax.plot(r["mirror_wiebe_m"], r["bdur_10_90_deg"], "wx", ms=10, mew=2, label="ridge mirror")
        ax.set_xlabel("Wiebe m [-]")
        ax.set_ylabel("BDUR10-90 [deg]")
    axes.ravel()[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{point_id}: {ps.row['speed_rpm']:.0f} rpm, throttle {ps.row['throttle_pct']:g} %, spark "
                 f"{ps.row['spark_deg_btdc']:g} deg BTDC, eta_trans {eta:g}: BDUR10-90 {r['bdur_10_90_deg']:.1f} deg "
                 f"({r['bdur_10_90_deg_lo']:.1f}-{r['bdur_10_90_deg_hi']:.1f}), m {r['wiebe_m']:.2f} "
                 f"({r['wiebe_m_lo']:.2f}-{r['wiebe_m_hi']:.2f}); dashed: power ridge; x: mirror rejected by "
                 f"{r.get('mirror_rejected_by', '')}", fontsize=9)
    fig.tight_layout()
    write_figure(fig, path, dpi=90)
    plt.close(fig)
    return Path(path)


def plot_eta_relation(eta: pd.DataFrame, isolines: pd.DataFrame, relation: pd.DataFrame, path: Path,
                      point_id: str | None = None) -> Path:
    """Identified BDUR10-90 and m vs eta_trans per point; the isolines with the fitted eq-6 relation."""
    plt = _plt()
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    for pid, g in eta.groupby("point_id", sort=False):
        ax[0].plot(g["eta_trans"], g["bdur_10_90_deg"], "o-", ms=3, label=pid)
        ax[1].plot(g["eta_trans"], g["wiebe_m"], "o-", ms=3, label=pid)
    ax[0].set_ylabel("identified BDUR10-90 [deg]")
    ax[1].set_ylabel("identified m [-]")
    for a in ax[:2]:
        a.set_xlabel("eta_trans [-]")
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=7)
    pid = point_id or (relation["point_id"].iloc[len(relation) // 2] if len(relation) else None)
    if pid is not None and len(isolines):
        g = isolines[isolines["point_id"] == pid]
        rel = relation.set_index("point_id").loc[pid]
        for e, gg in g.groupby("eta_trans"):
            line, = ax[2].plot(gg["wiebe_m"], gg["bdur_10_90_deg"], ".", ms=3)
            if rel.get("status", "ok") == "ok":
                m = np.linspace(gg["wiebe_m"].min(), gg["wiebe_m"].max(), 50)
                b = rel["c_1"] + rel["c_eta"] * e + rel["c_m"] * m + rel["c_m*eta"] * m * e + rel["c_m^2"] * m * m
                ax[2].plot(m, b, "-", color=line.get_color(), lw=1, label=f"eta {e:.2f}")
        ax[2].set_xlabel("Wiebe m [-]")
        ax[2].set_ylabel("BDUR10-90 on the measured-power isoline [deg]")
        ax[2].set_title(f"{pid}: isolines (dots) and fitted eq-6 relation (lines)", fontsize=9)
        ax[2].legend(fontsize=6, ncol=2)
        ax[2].grid(alpha=0.3)
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)
    return Path(path)
