"""Export of ECU tables: long-form Parquet (data contract), wide CSV per table, heatmap PNGs.

``write_maps(result, out_dir)`` writes, into ``out_dir`` (normally ``<run>/maps``)::

    ecu_tables.parquet        long form: table, throttle_pct, speed_rpm, value, unit, source, limited_by
    spark_advance.csv         wide: rows throttle %, columns rpm [deg BTDC]
    injection_time.csv        [ms]
    lambda_target.csv         [-]
    spark_start_retarded.csv  the first-bench-session map [deg BTDC]
    cells.parquet             every per-cell quantity of the build (search, verification, injection)
    evaluations.parquet       every simulated point of the build
    maps.json                 settings, statistics, spec hash, model, the ECU files and their notes
    *.png                     heatmaps (rows throttle, columns rpm, like the paper's Figures 3-4)
    ecu/                      ECU files on the build's grid, throttle % load axis
                              (:mod:`engine_model.tables.ecu_export`): TunerStudio .table, DCM 2.0 and
                              units-header CSV of spark, injection time and lambda; Speeduino and rusEFI
                              .msq of spark, VE (when the engine is given) and lambda, resampled to the
                              firmware's 16 x 16; README.txt says what was resampled or skipped and why

The whole folder is assembled next to ``out_dir`` and swapped in by renames,
so a reader sees the old complete set or the new complete set, never a mix.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model.io import make_temp_dir, write_figure
from engine_model.spec import EngineSpec
from engine_model.tables.ecu_export import ExportOptions, export_tables, write_exports
from engine_model.tables.settings import MapResult

__all__ = ["TABLES", "long_form", "wide_table", "plot_table", "cell_label", "write_ecu_files", "write_maps"]

#: table name -> (cell column, unit, decimals in the CSV, source column or fixed source, title)
TABLES = {
    "spark_advance": ("spark_deg_btdc", "deg BTDC", 1, "spark_source", "Spark advance [deg BTDC]"),
    "injection_time": ("injection_time_ms", "ms", 3, "injection_source", "Injection time [ms]"),
    "lambda_target": ("lambda", "-", 3, "input", "Target lambda [-]"),
    "spark_start_retarded": ("spark_start_deg_btdc", "deg BTDC", 1, "retarded",
                             "Starting spark map, retarded [deg BTDC]"),
}


def long_form(result: MapResult) -> pd.DataFrame:
    """All tables in the contract's long form: ``table, throttle_pct, speed_rpm, value, unit, source, limited_by``.

    ``limited_by`` is the spark reason (mbt / knock / retard / spark_max /
    infeasible) for the spark tables, and 'infeasible' or '' for the others.
    """
    c = result.cells
    frames = []
    for name, (col, unit, _dec, src, _title) in TABLES.items():
        source = c[src].astype(str).to_numpy() if src in c.columns else np.full(len(c), src, dtype=object)
        limited = c["limited_by"].astype(str).to_numpy() if name.startswith("spark") else \
            np.where(c["feasible"].to_numpy(bool), "", "infeasible")
        frames.append(pd.DataFrame({"table": name, "throttle_pct": c["throttle_pct"].to_numpy(float),
                                    "speed_rpm": c["speed_rpm"].to_numpy(float),
                                    "value": c[col].to_numpy(float), "unit": unit,
                                    "source": source.astype(str), "limited_by": limited.astype(str)}))
    return pd.concat(frames, ignore_index=True)


def wide_table(result: MapResult, name: str) -> pd.DataFrame:
    """One table wide: first column ``throttle_pct``, then one column per speed (header = rpm as integer text)."""
    col, _unit, dec, _src, _title = TABLES[name]
    vals = np.round(result.table(col), dec)
    heads = [f"{n:g}" for n in result.grid.speed_rpm]
    wide = pd.DataFrame(vals, columns=heads)
    wide.insert(0, "throttle_pct", [float(t) for t in result.grid.throttle_pct])
    return wide


def cell_label(name: str, value: float, dec: int, limited_by: str) -> str:
    """Text of one heatmap cell: the value (one decimal less than the CSV from 2 decimals on), with an
    asterisk on a knock-limited cell of a spark table and a dagger on a cell pinned to the bench's measured clean
    MBT spark (no letter suffix, which would read as a unit)."""
    txt = f"{value:.{max(dec - 1, 0) if dec > 1 else dec}f}"
    if name.startswith("spark") and limited_by == "knock":
        return txt + "*"
    return txt + "\u2020" if name.startswith("spark") and limited_by == "bench" else txt


def plot_table(result: MapResult, name: str, path, annotate: bool = True) -> Path:
    """Heatmap of one table (rows throttle %, columns rpm), values written in the cells, infeasible cells hatched.

    Spark tables mark knock-limited cells with an asterisk after the value and an orange outline
    (MBT-limited ones with nothing); infeasible cells (paper's Figure 1 zones) are hatched.  Speed ticks
    are in 1000 rpm, so no cell value carries a unit-like suffix.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    col, unit, dec, _src, title = TABLES[name]
    vals = result.table(col)
    nt, ns = result.grid.shape
    feas = result.cells["feasible"].to_numpy(bool).reshape(nt, ns)
    lim = result.cells["limited_by"].astype(str).to_numpy().reshape(nt, ns)
    fig, ax = plt.subplots(figsize=(1.0 + 0.62 * ns, 1.2 + 0.42 * nt))
    im = ax.imshow(vals, origin="lower", aspect="auto", cmap="viridis" if name != "lambda_target" else "coolwarm_r")
    for i in range(nt):
        for j in range(ns):
            if not feas[i, j]:
                ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="///", edgecolor="white",
                                           linewidth=0))
            if name.startswith("spark") and lim[i, j] == "knock":
                ax.add_patch(plt.Rectangle((j - 0.46, i - 0.46), 0.92, 0.92, fill=False, edgecolor="tab:orange",
                                           linewidth=1.2))
            if annotate and np.isfinite(vals[i, j]):
                ax.text(j, i, cell_label(name, vals[i, j], dec, lim[i, j]), ha="center", va="center", fontsize=6.5,
                        color="white" if im.norm(vals[i, j]) < 0.6 else "black")
    ax.set_xticks(range(ns), [f"{n / 1000:g}" for n in result.grid.speed_rpm], fontsize=8)
    ax.set_yticks(range(nt), [f"{t:g}" for t in result.grid.throttle_pct], fontsize=8)
    ax.set_xlabel("engine speed [1000 rpm]")
    ax.set_ylabel("throttle [%]")
    note = "hatched: infeasible"
    if name.startswith("spark"):
        note += "; *: knock-limited (outlined)"
        if (lim == "bench").any():
            note += "; \u2020: bench's clean MBT spark"
    ax.set_title(f"{title}\n{note}", fontsize=8)
    fig.colorbar(im, ax=ax, label=unit, fraction=0.04, pad=0.02)
    fig.tight_layout()
    path = Path(path)
    write_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


def _summary(result: MapResult, ecu: dict) -> dict:
    return {"ecu_files": ecu, "kind": "ecu_tables", "spec_hash": result.spec_hash, "model": result.model_name,
            "grid": {"throttle_pct": list(result.grid.throttle_pct), "speed_rpm": list(result.grid.speed_rpm)},
            "settings": dataclasses.asdict(result.settings), "stats": result.stats,
            "files": {name: f"{name}.csv" for name in TABLES} | {"long_form": "ecu_tables.parquet"}}


def write_ecu_files(result: MapResult, out_dir, spec: EngineSpec | None = None) -> dict:
    """The ECU files of the build into ``out_dir`` (see the module docstring); returns files and notes.

    A table the files cannot hold (e.g. a non-finite cell) is not an error of the build: the
    reason is returned under ``error`` and no ECU file is written.
    """
    try:
        es = export_tables(result.cells, spec, ExportOptions(), source="map cells")
        ve = export_tables(result.cells, spec, ExportOptions(fuel="ve"), source="map cells") if spec else None
        res = write_exports(es, out_dir, msq_set=ve)
    except ValueError as exc:
        return {"error": str(exc), "files": [], "notes": []}
    notes = res["notes"] + ([] if spec else ["no engine given: the msq files hold spark and lambda, no VE"])
    return {"files": sorted(res["files"]), "notes": notes}


def write_maps(result: MapResult, out_dir, figures: bool = True, spec: EngineSpec | None = None) -> dict:
    """Write all table files into ``out_dir`` (replaced as a whole; see module docstring).

    Parameters
    ----------
    result : MapResult
    out_dir : path
        Target folder, e.g. ``<run>/maps``; an existing folder of that name is replaced.
    figures : bool
        Also write the heatmap PNGs.
    spec : EngineSpec, optional
        The engine of the build: with it the msq files carry a VE table as well.

    Returns
    -------
    dict
        name -> final Path of every file written.
    """
    out = Path(out_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(out.parent, f".{out.name}.")   # the umask's folder mode, not mkdtemp's 0700
    names = {}
    try:
        long_form(result).to_parquet(tmp / "ecu_tables.parquet", index=False)
        names["ecu_tables"] = "ecu_tables.parquet"
        for name in TABLES:
            wide_table(result, name).to_csv(tmp / f"{name}.csv", index=False, lineterminator="\n")
            names[f"{name}_csv"] = f"{name}.csv"
            if figures:
                plot_table(result, name, tmp / f"{name}.png")
                names[f"{name}_png"] = f"{name}.png"
        result.cells.to_parquet(tmp / "cells.parquet", index=False)
        ev = result.evaluations.copy()
        ev["status"] = ev["status"].astype(str)
        ev.to_parquet(tmp / "evaluations.parquet", index=False)
        names["cells"], names["evaluations"] = "cells.parquet", "evaluations.parquet"
        ecu = write_ecu_files(result, tmp / "ecu", spec)
        for name in ecu["files"]:
            names[f"ecu/{name}"] = f"ecu/{name}"
        (tmp / "maps.json").write_text(json.dumps(_summary(result, ecu), indent=2, sort_keys=True, default=str) + "\n")
        names["summary"] = "maps.json"
        old = None
        if out.exists():
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {k: out / v for k, v in names.items()}
