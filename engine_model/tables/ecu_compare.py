"""A proposed ECU table against the one in the car: cell by cell on the current table's breakpoints, and a heatmap."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ..io import write_figure
from .ecu_table import LOAD_KINDS, EcuTable, resample

__all__ = ["compare", "plot_difference"]


def _norm_unit(u: str) -> str:
    u = u.strip().lower().replace("°", "deg")
    return {"lambda": "-", "": "-", "deg btdc": "deg", "degbtdc": "deg"}.get(u, u)


def compare(current: EcuTable, proposed: EcuTable) -> pd.DataFrame:
    """The proposed table on the current table's breakpoints, cell by cell.

    Returns one row per cell of ``current`` (row-major):
    ``i, j, <load column>, speed_rpm, current, proposed, difference``
    (proposed - current), ``outside`` (the current cell lies outside the
    proposed table's breakpoints: edge value held, see :func:`resample`), and
    where given ``proposed_flag``, ``proposed_uncertainty`` and
    ``within_uncertainty`` (``|difference| <= proposed_uncertainty``), and
    ``current_flag``.  ``attrs`` hold name, unit, load kind and unit.
    Different load kinds or units are a ValueError (convert first).
    """
    if current.load_kind != proposed.load_kind:
        raise ValueError(f"compare: current table {current.name!r} has load axis {current.load_kind}, proposed "
                         f"{proposed.name!r} {proposed.load_kind}; convert one (to_map_kpa) first")
    if _norm_unit(current.unit) != _norm_unit(proposed.unit):
        raise ValueError(f"compare: current table {current.name!r} is in {current.unit!r}, proposed "
                         f"{proposed.name!r} in {proposed.unit!r}")
    on, outside = resample(proposed, current.rpm, current.load)
    df = current.to_frame().rename(columns={"value": "current"})
    df = df.drop(columns=[c for c in ("flag", "uncertainty") if c in df.columns])
    df["proposed"] = on.values.ravel()
    df["difference"] = df["proposed"] - df["current"]
    df["outside"] = outside.ravel()
    if on.flags is not None:
        df["proposed_flag"] = on.flags.ravel()
    if on.uncertainty is not None:
        df["proposed_uncertainty"] = on.uncertainty.ravel()
        df["within_uncertainty"] = df["difference"].abs() <= df["proposed_uncertainty"]
    if current.flags is not None:
        df["current_flag"] = current.flags.ravel()
    df.attrs.update(name=current.name, proposed=proposed.name, unit=current.unit, load_kind=current.load_kind,
                    load_unit=current.load_unit, decimals=current.decimals)
    return df


def plot_difference(diff: pd.DataFrame, path, title: str | None = None) -> Path:
    """Heatmap of :func:`compare`'s ``difference`` (rows load, columns rpm), matplotlib Agg; returns the path.

    Diverging colours centred on 0; cells outside the proposed table hatched;
    flagged proposed cells marked '*'; cells within the proposed uncertainty
    drawn with grey text.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    load_col = next(c for c in (v[0] for v in LOAD_KINDS.values()) if c in diff.columns)
    loads = np.unique(diff[load_col].to_numpy(float))
    rpms = np.unique(diff["speed_rpm"].to_numpy(float))
    nl, nr = loads.size, rpms.size
    d = diff.sort_values(["i", "j"])
    vals = d["difference"].to_numpy(float).reshape(nl, nr)

    def grid(col, default=False):
        return d[col].to_numpy().reshape(nl, nr) if col in d.columns else np.full((nl, nr), default)

    outside, flagged, within = grid("outside"), grid("proposed_flag"), grid("within_uncertainty")
    lim = float(np.max(np.abs(vals))) or 1.0
    fig, ax = plt.subplots(figsize=(1.2 + 0.62 * nr, 1.3 + 0.42 * nl))
    im = ax.imshow(vals, origin="lower", aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim)
    dec = int(diff.attrs.get("decimals", 2))
    for i in range(nl):
        for j in range(nr):
            if outside[i, j]:
                ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="///", edgecolor="0.4",
                                           linewidth=0))
            ax.text(j, i, f"{vals[i, j]:+.{dec}f}" + ("*" if flagged[i, j] else ""), ha="center", va="center",
                    fontsize=6.5, color="0.55" if within[i, j] else "black")
    ax.set_xticks(range(nr), [f"{n:g}" for n in rpms], fontsize=7, rotation=90)
    ax.set_yticks(range(nl), [f"{t:g}" for t in loads], fontsize=7)
    ax.set_xlabel("engine speed [rpm]")
    ax.set_ylabel(f"{load_col} [{diff.attrs.get('load_unit', '')}]")
    unit = diff.attrs.get("unit", "")
    ax.set_title(title or f"{diff.attrs.get('proposed', 'proposed')} - {diff.attrs.get('name', 'current')} [{unit}]"
                 "\nhatched: outside proposed table; *: flagged; grey: within uncertainty", fontsize=8)
    fig.colorbar(im, ax=ax, label=f"difference [{unit}]", fraction=0.04, pad=0.02)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_figure(fig, path, dpi=110)
    plt.close(fig)
    return path
