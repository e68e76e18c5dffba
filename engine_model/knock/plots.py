"""Figure of the knock calibration: the model's knock index at each bench point against the calibrated border."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from engine_model.io import write_figure

__all__ = ["plot_evidence"]


def plot_evidence(kcal, path: Path) -> Path:
    """Knock index of the fastest cycles at m = 1 per bench point (log scale) with the multiplier's posterior band:
    a point knocks in the calibrated model where its marker lies above the line."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ev = kcal.evidence
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    x = np.arange(len(ev))
    ki = ev["ki_cycle_m1"].to_numpy(float)
    kn = ev["knock"].to_numpy(bool)
    ax.axhspan(kcal.multiplier_lo68, kcal.multiplier_hi68, color="0.85", label="multiplier, 68 % band")
    ax.axhline(kcal.multiplier_median, color="k", lw=1, label=f"median {kcal.multiplier_median:.3g}")
    ax.axhline(kcal.multiplier_table, color="C3", lw=1.5, ls="--", label=f"table {kcal.multiplier_table:.3g}")
    ax.scatter(x[~kn], ki[~kn], marker="o", color="C0", zorder=3, label="ran knock-free")
    if kn.any():
        ax.scatter(x[kn], ki[kn], marker="x", color="C3", zorder=3, label="knocked")
    ax.set_yscale("log")
    ax.set_xticks(x, [str(p) for p in ev["point_id"]], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("knock index, fastest cycles, m = 1 [-]")
    ax.set_title(f"Knock calibration ({kcal.kind}): knock-free points must lie below the line", fontsize=10)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)
    return Path(path)
