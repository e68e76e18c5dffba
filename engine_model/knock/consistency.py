"""Real-data consistency of a built spark table: at each bench point, what the bench ran against what the
model and the table say (model MBT at the identified burn, knock index at the bench's spark, the table there)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.interpolate import RegularGridInterpolator

from engine_model.io import write_figure

__all__ = ["FULL_CHARGE", "LIGHT_LOAD_CHARGE", "bench_consistency", "consistency_summary", "plot_consistency",
           "table_trends"]


def bench_consistency(evidence: pd.DataFrame, cells: pd.DataFrame, multiplier) -> pd.DataFrame:
    """One row per bench point of the knock evidence (:func:`engine_model.knock.point_evidence`).

    ``cells``: the built table's cells (``throttle_pct, speed_rpm, spark_deg_btdc``); the table's value at a
    point is bilinear in (throttle, speed), held at the grid's edges.  ``multiplier``: the delay multiplier of
    the engine the table was built with (knock index = index at m = 1 / multiplier): one value, or one per
    evidence row (the speed-dependent multiplier at each point's speed).
    """
    multiplier = np.broadcast_to(np.asarray(multiplier, dtype=float), (len(evidence),))
    th = np.unique(cells["throttle_pct"].to_numpy(float))
    sp = np.unique(cells["speed_rpm"].to_numpy(float))
    def table(col):
        vals = cells.pivot_table(index="throttle_pct", columns="speed_rpm", values=col, dropna=False).reindex(
            index=th, columns=sp).to_numpy(float)
        return RegularGridInterpolator((th, sp), vals) if th.size > 1 and sp.size > 1 else None
    f = table("spark_deg_btdc")
    f_mbt = table("spark_mbt_deg_btdc") if "spark_mbt_deg_btdc" in cells.columns else None
    out = evidence[["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "at_mbt", "knock"]].copy()
    out = out.rename(columns={"spark_deg_btdc": "bench_spark_deg_btdc", "knock": "bench_knock"})
    out["model_mbt_deg_btdc"] = evidence["mbt_model_deg_btdc"].to_numpy(float)
    out["model_mbt_minus_bench_deg"] = out["model_mbt_deg_btdc"] - out["bench_spark_deg_btdc"]
    out["knock_index_at_bench_spark"] = evidence["ki_m1"].to_numpy(float) / multiplier
    out["knock_index_fastest_cycles"] = evidence["ki_cycle_m1"].to_numpy(float) / multiplier
    if f is not None:
        q = np.column_stack([np.clip(out["throttle_pct"], th.min(), th.max()),
                             np.clip(out["speed_rpm"], sp.min(), sp.max())])
        out["table_spark_deg_btdc"] = f(q)
        # the map's own MBT there (global combustion model, no bench data): how far the model alone would be
        out["map_mbt_deg_btdc"] = f_mbt(q) if f_mbt is not None else math.nan
    else:
        out["table_spark_deg_btdc"] = math.nan
        out["map_mbt_deg_btdc"] = math.nan
    out["map_mbt_minus_bench_deg"] = out["map_mbt_deg_btdc"] - out["bench_spark_deg_btdc"]
    out["table_minus_bench_deg"] = out["table_spark_deg_btdc"] - out["bench_spark_deg_btdc"]
    return out


def consistency_summary(tab: pd.DataFrame) -> dict:
    """Counts a reader checks first: MBT within 2 deg, knock index < 1 at the clean points, table within 3 deg."""
    clean = ~tab["bench_knock"].astype(bool)
    mbt = tab["at_mbt"].astype(bool)
    d_mbt = tab.loc[mbt, "model_mbt_minus_bench_deg"].abs()
    return {"points": int(len(tab)),
            "mbt_within_2deg": f"{int((d_mbt <= 2).sum())} of {int(mbt.sum())}",
            "knock_free_points_below_1": f"{int((tab.loc[clean, 'knock_index_fastest_cycles'] < 1).sum())} of "
                                         f"{int(clean.sum())}",
            "table_within_3deg": f"{int((tab['table_minus_bench_deg'].abs() <= 3).sum())} of {int(len(tab))}",
            "max_abs_table_minus_bench_deg": round(float(tab["table_minus_bench_deg"].abs().max()), 2)
            if len(tab) else None}


def plot_consistency(tab: pd.DataFrame, path: Path) -> Path:
    """Bench spark, model MBT and table spark per bench point (top); knock index of the fastest cycles (bottom)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7.5, 5.6), sharex=True)
    x = np.arange(len(tab))
    a1.plot(x, tab["bench_spark_deg_btdc"], "ks", label="bench ran (clean, MBT)")
    a1.plot(x, tab["model_mbt_deg_btdc"], "o", color="C0", mfc="none", label="model MBT at the identified burn")
    a1.plot(x, tab["table_spark_deg_btdc"], "x", color="C3", label="spark table")
    a1.plot(x, tab["map_mbt_deg_btdc"], "^", color="0.5", mfc="none", label="map's MBT (global model, no bench)")
    a1.set_ylabel("spark [deg BTDC]")
    a1.legend(fontsize=7)
    a1.set_title("Spark table and model against the real bench", fontsize=10)
    a2.bar(x, tab["knock_index_fastest_cycles"], color=np.where(tab["bench_knock"], "C3", "C0"))
    a2.axhline(1.0, color="k", lw=1)
    a2.set_ylabel("knock index, fastest\ncycles, at bench spark")
    a2.set_xticks(x, [str(p) for p in tab["point_id"]], rotation=60, ha="right", fontsize=7)
    fig.tight_layout()
    write_figure(fig, path, dpi=100)
    plt.close(fig)
    return Path(path)


#: Light load, for the trend checks: a cell whose fresh-air charge is below this fraction of the WOT cell's at the
#: same speed [-].  [A] a definition (half of full load), not a fitted value: at <= 20 % throttle the single
#: butterfly ahead of the restrictor already passes 55-85 % of the WOT charge at 2000-3000 rpm (default R6 run), so
#: the throttle position alone does not say whether a cell is at light load.
LIGHT_LOAD_CHARGE = 0.5
#: Near full load, for the trend checks: a charge of at least this fraction of the WOT cell's at the same speed
#: [-].  [A] a definition, not a fitted value: at 2000-4000 rpm 30-60 % throttle holds 0.90-0.99 of it (default run).
FULL_CHARGE = 0.9


def _charge_vs_wot(c: pd.DataFrame) -> pd.Series:
    """Each cell's fresh-air charge (``vol_eff``) over the WOT (100 %) cell's at its speed; NaN where either is
    missing."""
    if "vol_eff" not in c.columns:
        return pd.Series(np.nan, index=c.index)
    ve = pd.to_numeric(c["vol_eff"], errors="coerce")
    wot = ve.where(c["throttle_pct"] == 100.0).groupby(c["speed_rpm"]).transform("max")
    return ve / wot


def table_trends(cells: pd.DataFrame, min_speed_rpm: float = 3000.0, bench: pd.DataFrame | None = None) -> dict:
    """Physical-trend checks of a spark table (the cells of a :class:`engine_model.tables.MapResult`).

    * ``small_throttle_knock``: knock-limited or knock-infeasible cells at <= 20 % throttle and >= 2000 rpm, each
      with its plenum pressure and its charge relative to WOT at that speed (a butterfly at 20 % passes most of
      full load at low speed on a restricted engine);
    * ``light_load_knock``: those of them at light load, charge below ``LIGHT_LOAD_CHARGE`` of WOT's, or not
      known (no ``vol_eff``, or no 100 % cell at that speed) (expected: none; knock belongs to high load);
    * ``part_load_drops``: per speed >= ``min_speed_rpm``, cells outside knock-limited and bench cells whose
      spark lies more than 2 deg below the WOT cell's model spark (when the bench pinned the WOT cell: its model
      MBT plus the bench offset the table carried at that speed, ``bench_mbt_offset_deg``, i.e. the bench's spark
      when the offset is carried, the model's MBT when it is not);
    * ``load_trend_moves``: cells whose MBT target the table's load-trend fit moved by more than 2 deg
      (``load_trend_shift_deg``; where the model's own MBT estimates broke the order "no less advance as the
      throttle closes" by that much), each with its shift;
    * ``zone1``: where knock survives full retard (expected at high throttle and low speed), with the charge;
    * ``full_charge_lean_knock``: knock-limited or knock-infeasible cells below 100 % throttle that hold at least
      ``FULL_CHARGE`` of WOT's charge at their speed but run a leaner target lambda than the WOT cell there (with
      ``lambda`` in ``cells``): full load without the WOT cell's enrichment, a knock limit the lambda table sets;
    * with ``bench`` (bench points, ``speed_rpm, throttle_pct``): ``knock_evidence``, the speed and throttle span
      of the bench's points and the knock-limited or knock-infeasible cells outside its speed span (there the
      border is the calibrated model's extrapolation).
    """
    c = cells
    kl = c["limited_by"].astype(str).eq("knock") | c["infeasible_reason"].astype(str).eq("knock-limited")
    charge = _charge_vs_wot(c)
    small = c[kl & (c["throttle_pct"] <= 20) & (c["speed_rpm"] >= 2000)]
    drops = []
    for n, g in c[c["speed_rpm"] >= min_speed_rpm].groupby("speed_rpm"):
        g = g.set_index("throttle_pct").sort_index()
        if 100.0 not in g.index:
            continue
        w = g.loc[100.0]
        carried = float(w["bench_mbt_offset_deg"]) if "bench_mbt_offset_deg" in g.columns else 0.0
        ref = float(w["spark_mbt_deg_btdc"]) + carried if w["limited_by"] == "bench" else float(w["spark_deg_btdc"])
        for t, r in g.iterrows():
            if 20 <= t < 100 and r["limited_by"] not in ("knock", "bench", "infeasible") and \
                    r["spark_deg_btdc"] < ref - 2.0:
                drops.append({"speed_rpm": float(n), "throttle_pct": float(t), "spark": float(r["spark_deg_btdc"]),
                              "wot_reference": ref})
    moves = []
    if "load_trend_shift_deg" in c.columns:
        sh = pd.to_numeric(c["load_trend_shift_deg"], errors="coerce").fillna(0.0)
        moves = [{"speed_rpm": float(c.at[i, "speed_rpm"]), "throttle_pct": float(c.at[i, "throttle_pct"]),
                  "shift_deg": round(float(sh[i]), 2)} for i in c.index[sh.abs() > 2.0]]
    z1 = c[c["infeasible_reason"].astype(str).eq("knock-limited")]
    pp = "plenum_pressure_bar" if "plenum_pressure_bar" in c.columns else None

    def cell(i, r):
        q = float(charge.at[i])
        return {"speed_rpm": float(r.speed_rpm), "throttle_pct": float(r.throttle_pct),
                "plenum_pressure_bar": round(float(r[pp]), 3) if pp else None,
                "charge_vs_wot": round(q, 3) if math.isfinite(q) else None}

    small_rows = [cell(i, r) for i, r in small.iterrows()]
    lean = []
    if "lambda" in c.columns:
        lam = pd.to_numeric(c["lambda"], errors="coerce")
        lam_wot = lam.where(c["throttle_pct"] == 100.0).groupby(c["speed_rpm"]).transform("min")
        full = c[kl & (c["throttle_pct"] < 100.0) & (charge >= FULL_CHARGE) & (lam > lam_wot + 1e-3)]
        lean = [{**cell(i, r), "lambda": float(lam[i]), "wot_lambda": float(lam_wot[i])} for i, r in full.iterrows()]
    extra = {}
    if bench is not None and len(bench):
        bs, bt = bench["speed_rpm"].to_numpy(float), bench["throttle_pct"].to_numpy(float)
        out = c[kl & ((c["speed_rpm"] < bs.min() - 1.0) | (c["speed_rpm"] > bs.max() + 1.0))]
        extra["knock_evidence"] = {"points": int(len(bench)), "speed_rpm": [float(bs.min()), float(bs.max())],
                                   "throttle_pct": [float(bt.min()), float(bt.max())],
                                   "knock_cells": int(kl.sum()), "knock_cells_outside_speeds": int(len(out)),
                                   "outside_speeds_rpm": sorted({float(n) for n in out["speed_rpm"]})}
    return {**extra, "small_throttle_knock": small_rows,
            "light_load_knock": [d for d in small_rows
                                 if d["charge_vs_wot"] is None or d["charge_vs_wot"] < LIGHT_LOAD_CHARGE],
            "part_load_drops": drops,
            "load_trend_moves": moves,
            "zone1": [cell(i, r) for i, r in z1.iterrows()],
            "full_charge_lean_knock": lean}
