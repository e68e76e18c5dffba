"""ECU look-up tables from the cycle model and a combustion model: spark advance and injection time.

    ECU grid (throttle % x rpm) + target-lambda table
      -> per cell: spark search on the cycle model, Wiebe parameters predicted per candidate spark
         (coarse sweep around the model's CA50 = 9 deg ATDC spark, then parabolic refinement of brake
          torque; knock border refined log-linearly), one batched ``evaluate`` call per search stage
      -> MBT, limited by knock (knock_index < 1 - knock_margin) and a safety retard
      -> MBT targets made non-decreasing as the throttle closes at each speed (the part-load trend [H])
      -> infeasible zones of the paper's Figure 1 flagged (``doe.feasibility``)
      -> smoothing with bounded second differences (only as much as needed; shifts reported)
      -> verification run of the final table (knock re-checked, trapped air) -> injection time
      -> the deliberately retarded starting map for the first bench session

A *combustion model* is any object with ``predict(points) -> DataFrame``
returning ``bdur_10_90_deg, wiebe_m`` for rows with ``throttle_pct,
speed_rpm, spark_deg_btdc, lambda``; a fitted model also has ``spec_hash``
and ``check_spec(spec)``.  :class:`PriorModel` wraps the DOE prior
:func:`engine_model.priors.combustion_estimate` (useful before any bench data).

Settings and the result type are in :mod:`engine_model.tables.settings`, the per-cell
search in :mod:`engine_model.tables.search`, the grid and lambda table in
:mod:`engine_model.tables.grid`, smoothing and injection in their own modules;
export (long-form Parquet, wide CSV, heatmaps) is in :mod:`engine_model.tables.export`.

References
----------
.. [P] Mrda et al., MVM2012-024: retarded initial spark map (10-15 deg), MBT or
   knock as the end of a spark sweep, Figure 1 (zones), Figures 3-4 (tables).
.. [H] J.B. Heywood, Internal Combustion Engine Fundamentals, 1988, sec.
   9.3 / 9.6 (MBT, knock-limited spark advance).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from engine_model import doe
from engine_model.spec import EngineSpec
from engine_model.tables.bench_offset import offset_at_speeds
from engine_model.tables.grid import EcuGrid, LambdaTable
from engine_model.tables.injection import injection_time_ms
from engine_model.tables.search import EVAL_COLUMNS, SparkRunner, decide_cell, model_spark, uncertainty_retard
from engine_model.tables.settings import MapResult, MapSettings, check_model
from engine_model.tables.smoothing import isotonic_nonincreasing, second_differences, smooth_table

__all__ = ["build_maps"]


def build_maps(spec: EngineSpec, model, grid: EcuGrid | None = None, lambda_table: LambdaTable | str | Path | None = None,
               evaluate: Callable[[pd.DataFrame], pd.DataFrame] | None = None, settings: MapSettings | None = None,
               step_deg: float = 0.5, progress: Callable[[str, int], None] | None = None,
               bench: pd.DataFrame | None = None) -> MapResult:
    """Build the spark-advance, injection-time and target-lambda tables on an ECU grid.

    Parameters
    ----------
    spec : EngineSpec
        The engine (injector, fuel, cylinders; the model's spec hash must match).
    model : combustion model
        ``predict(points) -> DataFrame`` with ``bdur_10_90_deg, wiebe_m``;
        ``check_spec(spec)`` or ``spec_hash`` if it has them (a mismatch raises).
    grid : EcuGrid, optional
        Default :class:`EcuGrid` () (11 throttle x 13 speed breakpoints).
    lambda_table : LambdaTable or CSV path, optional
        Target lambda; default :meth:`LambdaTable.default`.
    evaluate : callable(plan DataFrame) -> DataFrame, optional
        Runs the cycle model on a plan (contract columns + ``point_id``) and
        returns one row per plan row, same order.  Default: in-process
        :func:`engine_model.simulate` with ``step_deg``.  Called once per
        search stage with all cells' candidates (rows of a cell consecutive).
    settings : MapSettings, optional
    step_deg : float
        Crank-angle step of the default evaluator [deg].
    progress : callable(stage, n_points), optional
        Called after each batch.
    bench : DataFrame, optional
        Bench points (``speed_rpm, throttle_pct, spark_deg_btdc`` and optional ``at_mbt``, ``knock``).  A cell
        at a point's speed (within 1 rpm) and throttle (within 0.5 %) that the bench ran at MBT without knock
        takes the bench's spark (``spark_source`` "bench", ``limited_by`` "bench"): a measured clean MBT beats
        the model's extrapolation; smoothing keeps it and verification does not retard it (the model's knock
        index there is still reported, in ``knock_index_cycle``).  The difference between the bench's spark
        and the model's MBT there is carried to the MBT target of the cells at neighbouring speeds
        (``bench_mbt_offset_deg``; ``settings.bench_offset_reach_rpm``, :mod:`engine_model.tables.bench_offset`),
        still capped by the knock-safe border.

    Returns
    -------
    MapResult
    """
    t0 = time.perf_counter()
    grid = EcuGrid() if grid is None else grid
    st = MapSettings() if settings is None else settings
    if st.cycle_advance_deg is None:
        st = dataclasses.replace(st, cycle_advance_deg=spec.knock.cycle_ca50_advance_deg)
    if not isinstance(grid, EcuGrid):
        raise ValueError(f"grid must be an EcuGrid, got {type(grid).__name__}")
    grid.check_spec(spec)
    check_model(model, spec)
    if lambda_table is None:
        lam_tab = LambdaTable.default(grid)
    elif isinstance(lambda_table, LambdaTable):
        lam_tab = lambda_table
    else:
        lam_tab = LambdaTable.from_csv(lambda_table)
    if evaluate is None:
        evaluate = _in_process_evaluator(spec, step_deg)

    cells = grid.cells().set_index("cell", drop=False)
    cells["lambda"] = lam_tab.on_grid(grid).ravel()
    cells["spark_prior_deg_btdc"] = model_spark(model, cells, st)
    runner = SparkRunner(model, cells, evaluate, progress, st.cycle_advance)
    stages = _search(runner, cells, st)
    ev = runner.evaluations()
    _zones(cells, ev, st)
    border_safe = _knock_uncertainty(runner, ev, cells, st)
    border_safe = _honour_bench(cells, bench, border_safe)
    _carry_bench_offset(cells, border_safe, st)
    _load_trend(cells, border_safe, st)
    sinfo = _smooth_spark(cells, grid, st, border_safe)
    fixes = _verify(runner, ev, cells, st)
    inj, have = _injection(cells, grid, spec, st)
    applied = cells["knock_uncertainty_retard_deg"].to_numpy(float)    # as the bench offset left it
    stats = _stats(cells, grid, st, runner, stages, fixes, sinfo, inj, have, applied, time.perf_counter() - t0)
    return MapResult(grid=grid, settings=st, cells=cells.reset_index(drop=True), evaluations=runner.evaluations(),
                     stats=stats, spec_hash=spec.spec_hash(), model_name=type(model).__name__)


def _in_process_evaluator(spec: EngineSpec, step_deg: float):
    """``evaluate(plan)``: :func:`engine_model.simulate` in this process at ``step_deg``."""
    from engine_model.sim.prepare import SolverSettings
    from engine_model.sim.simulate import simulate
    solver = SolverSettings(step_deg=step_deg)

    def evaluate(plan):
        return simulate(spec, plan, solver)
    return evaluate


def _search(runner: SparkRunner, cells: pd.DataFrame, st: MapSettings) -> int:
    """Spark search in batched stages; fills the MBT / border / raw spark columns; returns the stages used."""
    lo, hi = st.spark_min_deg_btdc, st.spark_max_deg_btdc
    requests = {c: [min(hi, max(lo, s0 + o)) for o in st.coarse_offsets_deg]
                for c, s0 in cells["spark_prior_deg_btdc"].items()}
    resolved: dict[int, dict] = {}
    stages = 0
    for stage in range(1, st.max_stages + 1):
        if not requests:
            break
        runner.run(requests, f"s{stage}")
        stages = stage
        ev = runner.evaluations()
        requests = {}
        for c, grp in ev.groupby("cell"):
            if c in resolved:
                continue
            kind, what = decide_cell(grp, st)
            if kind == "done":
                resolved[c] = {**what, "search_converged": True}
            else:
                requests[c] = what
    ev = runner.evaluations()
    for c in cells["cell"]:
        if c not in resolved:   # out of stages: best safe point so far
            resolved[c] = {**_best_so_far(ev, c, st), "search_converged": False}
    res = pd.DataFrame([resolved[c] for c in cells["cell"]], index=cells.index)
    cells["spark_mbt_deg_btdc"] = res["mbt"].astype(float)
    cells["spark_border_deg_btdc"] = res["border"].astype(float)
    cells["spark_raw_deg_btdc"] = res["raw"].astype(float)
    cells["limited_by"] = res["limited_by"].astype(str)
    cells["search_converged"] = res["search_converged"].astype(bool)
    return stages


def _best_so_far(ev: pd.DataFrame, c: int, st: MapSettings) -> dict:
    """Resolution of a cell the search stages did not finish: its best knock-safe point so far."""
    lo, hi = st.spark_min_deg_btdc, st.spark_max_deg_btdc
    grp = ev[(ev["cell"] == c) & np.isfinite(ev["brake_torque_nm"]) & (ev["knock_index_cycle"] < st.knock_limit)]
    if grp.empty:
        kind, what = decide_cell(ev[ev["cell"] == c], st)
        return what if kind == "done" else {"status": "zone1" if len(ev[ev["cell"] == c]) else "failed",
                                            "mbt": math.nan, "border": lo, "raw": lo, "limited_by": "infeasible"}
    b = grp.loc[grp["brake_torque_nm"].idxmax()]
    knocked = ev[(ev["cell"] == c) & (ev["knock_index_cycle"] >= st.knock_limit)]
    border = float(grp["spark_deg_btdc"].max()) if len(knocked) else hi
    return {"status": "ok", "mbt": math.nan, "border": border, "raw": float(b["spark_deg_btdc"]),
            "limited_by": "knock" if float(b["spark_deg_btdc"]) >= border - 1e-6 else "mbt"}


def _zones(cells: pd.DataFrame, ev: pd.DataFrame, st: MapSettings) -> None:
    """Flag the paper's infeasible zones (``doe.feasibility`` on the evaluated point nearest the raw spark)."""
    best_rows = []
    for c in cells["cell"]:
        grp = ev[(ev["cell"] == c) & np.isfinite(ev["brake_torque_nm"])]
        raw = cells.at[c, "spark_raw_deg_btdc"]
        if grp.empty or not math.isfinite(raw):
            best_rows.append({"spark_deg_btdc": raw, "knock_index": math.nan, "bmep_bar": math.nan})
        else:
            r = grp.loc[(grp["spark_deg_btdc"] - raw).abs().idxmin()]
            best_rows.append({"spark_deg_btdc": raw, "knock_index": r["knock_index_cycle"], "bmep_bar": r["bmep_bar"]})
    best = pd.DataFrame(best_rows)
    plan = cells[["throttle_pct", "speed_rpm", "lambda"]].copy()
    plan["spark_deg_btdc"] = best["spark_deg_btdc"].to_numpy()
    flags = doe.feasibility(plan, evaluate=lambda _p: best[["knock_index", "bmep_bar"]].reset_index(drop=True),
                            knock_margin=st.knock_margin, min_bmep_bar=st.min_bmep_bar)
    cells["feasible"] = flags["feasible"].to_numpy(bool)
    cells["infeasible_reason"] = flags["infeasible_reason"].astype(str).to_numpy()
    cells.loc[~cells["feasible"], "limited_by"] = "infeasible"


def _knock_uncertainty(runner: SparkRunner, ev: pd.DataFrame, cells: pd.DataFrame,
                       st: MapSettings) -> np.ndarray:
    """Knock safety against the model's burn uncertainty: the border moved back by z * sigma_CA50 * gain.

    Sets ``knock_uncertainty_retard_deg`` (the retard applied per cell [deg]); returns the knock-safe border
    [deg BTDC].
    """
    lo = st.spark_min_deg_btdc
    unc = uncertainty_retard(runner, ev, cells, st)
    for col in ("phasing_std_deg", "knock_phasing_gain", "knock_phasing_gain_cell"):
        cells[col] = unc[col].to_numpy(float)
    cells["knock_phasing_gain_measured"] = unc["knock_phasing_gain_measured"].to_numpy(bool)
    feas = cells["feasible"].to_numpy()
    border_safe = np.maximum(lo, cells["spark_border_deg_btdc"].to_numpy(float)
                             - unc["knock_uncertainty_border_retard_deg"].to_numpy(float))
    raw0 = cells["spark_raw_deg_btdc"].to_numpy(float)
    raw1 = np.where(feas & np.isfinite(border_safe), np.minimum(raw0, border_safe), raw0)
    applied = np.where(feas, np.nan_to_num(raw0 - raw1), 0.0)
    cells["knock_uncertainty_retard_deg"] = applied
    cells["spark_raw_deg_btdc"] = raw1
    cells.loc[applied > 0, "limited_by"] = "knock"
    return border_safe


def _honour_bench(cells: pd.DataFrame, bench: pd.DataFrame | None, border_safe: np.ndarray) -> np.ndarray:
    """Pin the cells the bench ran clean at MBT to the bench's spark (``bench_spark_deg_btdc``); returns the
    knock-safe border with the pinned cells at exactly that spark (the smoothing's upper bound; its lower bound
    there is the same spark, so smoothing leaves them)."""
    cells["bench_spark_deg_btdc"] = np.nan
    if bench is None or not len(bench):
        return border_safe
    knock = bench["knock"].fillna(False).astype(bool).to_numpy() if "knock" in bench.columns else np.zeros(len(bench), bool)
    at_mbt = bench["at_mbt"].fillna(True).astype(bool).to_numpy() if "at_mbt" in bench.columns else ~knock
    th, sp = cells["throttle_pct"].to_numpy(float), cells["speed_rpm"].to_numpy(float)
    for (_, r), clean in zip(bench.iterrows(), at_mbt & ~knock):
        hit = np.flatnonzero((np.abs(th - float(r["throttle_pct"])) < 0.5) & (np.abs(sp - float(r["speed_rpm"])) < 1.0))
        if clean and hit.size:
            cells.iloc[hit[0], cells.columns.get_loc("bench_spark_deg_btdc")] = float(r["spark_deg_btdc"])
    pinned = np.isfinite(cells["bench_spark_deg_btdc"].to_numpy(float))
    if not pinned.any():
        return border_safe
    spark = cells["bench_spark_deg_btdc"].to_numpy(float)
    cells.loc[pinned, "spark_raw_deg_btdc"] = spark[pinned]
    cells.loc[pinned, "feasible"] = True
    cells.loc[pinned, "infeasible_reason"] = ""
    cells.loc[pinned, "limited_by"] = "bench"
    return np.where(pinned, spark, border_safe)      # pinned: lower and upper bound of the smoothing


def _carry_bench_offset(cells: pd.DataFrame, border_safe: np.ndarray, st: MapSettings) -> None:
    """Move the MBT target of the unmeasured feasible cells by the bench's MBT offset at their speed
    (:mod:`engine_model.tables.bench_offset`); the knock-safe border still caps it (then ``limited_by`` "knock").

    ``bench_mbt_offset_deg`` holds the offset at every cell's speed (0 where nothing is carried; in a pinned cell
    its own bench spark - model MBT), ``bench_mbt_offset_applied`` whether the cell's target moved by it.
    """
    cells["bench_mbt_offset_deg"] = 0.0
    cells["bench_mbt_offset_applied"] = False
    pinned = np.isfinite(cells["bench_spark_deg_btdc"].to_numpy(float))
    if st.bench_offset_reach_rpm is None or not pinned.any():
        return
    lo, hi = st.spark_min_deg_btdc, st.spark_max_deg_btdc
    mbt = cells["spark_mbt_deg_btdc"].to_numpy(float)
    speed = cells["speed_rpm"].to_numpy(float)
    # a cell at the end of the spark range has no MBT inside it: its offset is not measured
    measured = pinned & np.isfinite(mbt) & (mbt > lo + 1e-6) & (mbt < hi - 1e-6)
    off = cells["bench_spark_deg_btdc"].to_numpy(float) - mbt
    d = offset_at_speeds(speed[measured], off[measured], speed, float(st.bench_offset_reach_rpm))
    cells["bench_mbt_offset_deg"] = np.where(measured, off, d)
    limited = cells["limited_by"].to_numpy(object)
    move = (cells["feasible"].to_numpy(bool) & ~pinned & np.isfinite(mbt) & (np.abs(d) > 1e-9)
            & np.isin(limited, ["mbt", "retard", "knock"]))
    if not move.any():
        return
    _set_target(cells, move, np.clip(mbt + d - st.safety_retard_deg, lo, hi), border_safe, st)
    cells.loc[move, "bench_mbt_offset_applied"] = True


def _set_target(cells: pd.DataFrame, move: np.ndarray, target: np.ndarray, border_safe: np.ndarray,
                st: MapSettings) -> None:
    """Give the ``move`` cells a new spark target, capped by the knock-safe border: ``spark_raw_deg_btdc``,
    ``limited_by`` ("knock" where the cap binds) and the uncertainty retard the cap takes off the target."""
    capped = target > border_safe
    at_mbt = "retard" if st.safety_retard_deg > 0 else "mbt"
    unc = np.maximum(0.0, np.minimum(target, cells["spark_border_deg_btdc"].to_numpy(float)) - border_safe)
    cells.loc[move, "spark_raw_deg_btdc"] = np.where(capped, border_safe, target)[move]
    cells.loc[move, "limited_by"] = np.where(capped, "knock", at_mbt)[move]
    cells.loc[move, "knock_uncertainty_retard_deg"] = np.nan_to_num(unc)[move]


def _load_trend(cells: pd.DataFrame, border_safe: np.ndarray, st: MapSettings) -> None:
    """Make the MBT targets of each speed non-decreasing as the throttle closes, still capped by the knock border.

    At one speed a smaller throttle means a thinner charge with more residual gas, which burns more slowly,
    so MBT moves to more advance [H, sec. 9.3]; the model's MBT estimates, each with its identification error
    (1-3 deg hold-out), can break that order, and a part-load cell then runs behind WOT.  The targets (MBT +
    carried bench offset - safety retard; a cell whose MBT lies beyond ``spark_max`` is held there, a
    bench-pinned cell at its bench spark) are replaced by their least-squares fit under the order, per speed
    (:func:`isotonic_nonincreasing` along throttle, equal weights, held values weighted 1e6): only runs of
    cells that break the order move, each run to its mean.  Knock-limited cells take part with their MBT
    estimate (the border still caps them); cells without an MBT estimate and infeasible cells do not.
    ``load_trend_shift_deg`` records each cell's move of its target (0 where nothing moved).
    """
    cells["load_trend_shift_deg"] = 0.0
    if not st.mbt_monotone_in_load:
        return
    lo, hi = st.spark_min_deg_btdc, st.spark_max_deg_btdc
    limited = cells["limited_by"].to_numpy(object)
    bench = cells["bench_spark_deg_btdc"].to_numpy(float)
    pinned = np.isfinite(bench)
    offset = np.where(cells["bench_mbt_offset_applied"].to_numpy(bool),
                      cells["bench_mbt_offset_deg"].to_numpy(float), 0.0)
    target = np.clip(cells["spark_mbt_deg_btdc"].to_numpy(float) + offset - st.safety_retard_deg, lo, hi)
    target = np.where(pinned, bench, np.where(limited == "spark_max", hi, target))
    use = (cells["feasible"].to_numpy(bool) & np.isfinite(target)
           & (pinned | np.isin(limited, ["mbt", "retard", "knock", "spark_max"])))
    # held: the bench's spark, and a cell whose MBT lies beyond spark_max (its target is spark_max exactly)
    held = pinned | (limited == "spark_max")
    speed, th = cells["speed_rpm"].to_numpy(float), cells["throttle_pct"].to_numpy(float)
    fitted = target.copy()
    for n in np.unique(speed[use]):
        idx = np.flatnonzero(use & (speed == n))
        idx = idx[np.argsort(th[idx])]          # throttle ascending: the target must not rise
        fitted[idx] = isotonic_nonincreasing(target[idx], np.where(held[idx], 1e6, 1.0))
    move = use & ~held & (np.abs(fitted - target) > 1e-9)
    _set_target(cells, move, fitted, border_safe, st)
    cells.loc[move, "load_trend_shift_deg"] = (fitted - target)[move]


def _smooth_spark(cells: pd.DataFrame, grid: EcuGrid, st: MapSettings, border_safe: np.ndarray) -> dict:
    """Smooth the spark table (feasible cells are data; others are filled; zone 1 pinned to spark_min)."""
    lo, hi = st.spark_min_deg_btdc, st.spark_max_deg_btdc
    feas = cells["feasible"].to_numpy()
    zone1 = (cells["infeasible_reason"] == "knock-limited").to_numpy()
    border = np.where(feas, border_safe, cells["spark_border_deg_btdc"].to_numpy(float))
    upper = np.where(feas, border, np.where(np.isfinite(border), np.maximum(border, lo), hi))
    upper = np.where(zone1, lo, upper)
    shape = grid.shape
    # uniform weights: measured on the default R6 map, torque-curvature weights cost more torque (mean 1.3 % vs
    # 1.1 %, max 8.2 % both at a 10 deg bound), because most forced moves are knock-limited cells that can only retard
    pinned = np.isfinite(cells["bench_spark_deg_btdc"].to_numpy(float))
    lower = np.where(pinned, cells["bench_spark_deg_btdc"].to_numpy(float), lo)
    # knock-limited cells follow the knock border (a physical limit, steep at low speed) and stay out of the
    # curvature bound, which is there for the MBT cells' search noise on a flat torque plateau: kept in, the
    # bound pulled MBT cells next to the border 9-14 deg below MBT on the default map (docs/sections/tables.md)
    knock_limited = feas & (cells["limited_by"] == "knock").to_numpy()
    spark, sinfo = smooth_table(cells["spark_raw_deg_btdc"].to_numpy(float).reshape(shape),
                                feas.astype(float).reshape(shape), lower.reshape(shape), upper.reshape(shape),
                                st.max_second_diff_deg, stencil=~(zone1 | knock_limited).reshape(shape))
    # ECU resolution 0.1 deg, rounded down (towards retard: never past the knock border); this exact value is verified
    cells["spark_deg_btdc"] = np.floor(spark.ravel() * 10.0 + 1e-6) / 10.0
    cells["smoothing_shift_deg"] = np.where(feas, cells["spark_deg_btdc"] - cells["spark_raw_deg_btdc"], np.nan)
    cells["spark_source"] = np.where(pinned, "bench", np.where(feas, "simulation", np.where(zone1, "spark_min", "fill")))
    return sinfo


def _verify(runner: SparkRunner, ev: pd.DataFrame, cells: pd.DataFrame, st: MapSettings) -> int:
    """Run the final table (knock re-checked, trapped air for the injection); retard cells found knocking.

    Returns the number of knock fixes.
    """
    lo = st.spark_min_deg_btdc
    feas = cells["feasible"].to_numpy()
    pinned = np.isfinite(cells["bench_spark_deg_btdc"].to_numpy(float))
    ver = {}
    for c in cells["cell"][~feas]:   # not verified: nearest searched point (air flow for the injection fill)
        grp = ev[(ev["cell"] == c) & np.isfinite(ev["brake_torque_nm"])]
        if grp.empty:
            grp = ev[ev["cell"] == c] if (ev["cell"] == c).any() else None
        if grp is None:
            ver[c] = pd.Series({"status": "not evaluated", **{k: math.nan for k in EVAL_COLUMNS if k != "status"},
                                "bdur_10_90_deg": math.nan, "wiebe_m": math.nan})
            continue
        r = grp.loc[(grp["spark_deg_btdc"] - cells.at[c, "spark_deg_btdc"]).abs().idxmin()].copy()
        r["status"] = f"not verified (infeasible; nearest searched point {r['spark_deg_btdc']:g} deg)"
        ver[c] = r
    todo = {int(c): [float(s)] for c, s in cells["spark_deg_btdc"][feas].items()}
    fixes = 0
    for rnd in range(1, st.max_fix_rounds + 2):
        if not todo:
            break
        out = runner.run(todo, f"v{rnd}")
        evc = runner.evaluations()
        out = evc.iloc[len(evc) - len(out):].reset_index(drop=True)
        todo = {}
        for _, r in out.iterrows():
            c = int(r["cell"])
            ver[c] = r
            k = r["knock_index_cycle"]
            if feas[c] and np.isfinite(k) and k >= st.knock_limit and rnd <= st.max_fix_rounds and not pinned[c]:
                new = _knock_fix(ev, c, float(r["spark_deg_btdc"]), k, st, lo)
                cells.at[c, "spark_deg_btdc"] = new
                cells.at[c, "limited_by"] = "knock"
                todo[c] = [new]
                fixes += 1
        if not todo:
            break
    vt = pd.DataFrame([ver[c] for c in cells["cell"]], index=cells.index)
    # plenum pressure (cycle mean), trapped mass and volumetric efficiency: the MAP axis and VE of the ECU exports
    for col in ("brake_torque_nm", "knock_index", "knock_index_cycle", "bmep_bar", "ca50_deg_atdc",
                "air_mass_flow_kg_h", "fuel_mass_flow_kg_h", "exhaust_temp_k", "plenum_pressure_bar",
                "trapped_mass_mg", "vol_eff", "bdur_10_90_deg", "wiebe_m"):
        cells[col] = pd.to_numeric(vt[col], errors="coerce").astype(float).to_numpy()
    cells["verify_status"] = vt["status"].astype(str).to_numpy()
    cells["verified"] = ~(feas & ~pinned & ~(cells["knock_index_cycle"].to_numpy(float) < st.knock_limit))
    cells["smoothing_shift_deg"] = np.where(feas, cells["spark_deg_btdc"] - cells["spark_raw_deg_btdc"], np.nan)
    best_safe = ev[np.isfinite(ev["brake_torque_nm"]) & (ev["knock_index_cycle"] < st.knock_limit)] \
        .groupby("cell")["brake_torque_nm"].max()
    ref = cells["cell"].map(best_safe).astype(float).to_numpy()
    cells["torque_best_searched_nm"] = ref
    cells["torque_loss_pct"] = np.where(feas, 100.0 * (1.0 - cells["brake_torque_nm"].to_numpy(float) / ref), np.nan)
    return fixes


def _knock_fix(ev: pd.DataFrame, c: int, spark: float, k: float, st: MapSettings, lo: float) -> float:
    """Retarded spark [deg BTDC] for a cell that knocked at ``spark`` in verification (log-linear in the knock index)."""
    grp = ev[(ev["cell"] == c) & np.isfinite(ev["knock_index"]) & (ev["knock_index"] > 0)]
    slope = 0.05   # d ln(knock)/d spark [1/deg] fallback (typical of the search data)
    if len(grp) >= 2:
        g = grp.sort_values("spark_deg_btdc")
        fit = np.polyfit(g["spark_deg_btdc"], np.log(g["knock_index"]), 1)[0]
        slope = fit if fit > 1e-3 else slope
    new = max(lo, spark - max(0.5, math.log(k / st.knock_limit) / slope + 0.2))
    return math.floor(new * 10.0 + 1e-6) / 10.0


def _injection(cells: pd.DataFrame, grid: EcuGrid, spec: EngineSpec, st: MapSettings) -> tuple[dict, np.ndarray]:
    """Injection time from the verified air flow; cells without it are filled by the smoother."""
    shape = grid.shape
    inj = injection_time_ms(cells["air_mass_flow_kg_h"], cells["speed_rpm"], cells["lambda"], spec, st.battery_v)
    have = np.isfinite(inj["injection_time_ms"])
    t_inj, _info = smooth_table(np.where(have, inj["injection_time_ms"], np.nan).reshape(shape),
                                have.astype(float).reshape(shape), np.full(shape, inj["dead_time_ms"][0]),
                                np.full(shape, 1e3 * 120.0 / grid.speed_rpm[0]), None)
    for key in ("air_mg", "fuel_mg", "dead_time_ms", "duty_pct"):
        cells[key] = inj[key]
    cells["injection_time_ms"] = t_inj.ravel()
    cells["injection_source"] = np.where(have, "simulation", "fill")
    cells["spark_start_deg_btdc"] = np.maximum(cells["spark_deg_btdc"] - st.start_retard_deg, -30.0)
    return inj, have


def _stats(cells, grid, st, runner, stages, fixes, sinfo, inj, have, applied, wall) -> dict:
    """Counts, smoothing report, torque cost and timing of a build."""
    feas = cells["feasible"].to_numpy()
    d2t, d2n = second_differences(np.where(feas, cells["spark_deg_btdc"].to_numpy(float), np.nan).reshape(grid.shape))
    d2 = np.concatenate([d2t.ravel(), d2n.ravel()])
    d2 = d2[np.isfinite(d2)]
    return {
        "cells": len(cells), "feasible": int(feas.sum()),
        "infeasible": {str(k): int(v) for k, v in cells.loc[~cells["feasible"], "infeasible_reason"]
                       .value_counts().items()},
        "limited_by": {str(k): int(v) for k, v in cells["limited_by"].value_counts().items()},
        "search_stages": stages, "search_unconverged": int((~cells["search_converged"]).sum()),
        "evaluate_calls": runner.calls, "simulated_points": runner.points,
        "points_per_cell": round(runner.points / len(cells), 2), "knock_fixes": fixes,
        "unverified_cells": int((~cells["verified"]).sum()),
        "smoothing": {"lambda": sinfo["lam"], "bound_deg": st.max_second_diff_deg,
                      "bound_met": sinfo["bound_met"], "max_shift_deg": sinfo["max_shift"],
                      "rms_shift_deg": sinfo["rms_shift"],
                      "max_second_diff_feasible_deg": float(np.max(np.abs(d2))) if d2.size else 0.0},
        "torque_loss_pct": {"max": float(np.nanmax(cells["torque_loss_pct"])) if feas.any() else math.nan,
                            "mean": float(np.nanmean(cells["torque_loss_pct"])) if feas.any() else math.nan},
        "injection_fill_cells": int((~have).sum()),
        "max_duty_pct": float(np.nanmax(inj["duty_pct"])) if have.any() else math.nan,
        "knock_uncertainty": {"z": st.knock_uncertainty_z, "cells_retarded": int((applied > 0).sum()),
                              "mean_retard_deg": float(applied[applied > 0].mean()) if (applied > 0).any() else 0.0,
                              "max_retard_deg": float(applied.max()) if applied.size else 0.0},
        "bench_mbt_offset": {"reach_rpm": st.bench_offset_reach_rpm,
                             "cells_moved": int(cells["bench_mbt_offset_applied"].sum()),
                             "max_abs_deg": float(cells["bench_mbt_offset_deg"].abs().max())},
        "load_trend": {"on": st.mbt_monotone_in_load,
                       "cells_raised": int((cells["load_trend_shift_deg"] > 0).sum()),
                       "cells_lowered": int((cells["load_trend_shift_deg"] < 0).sum()),
                       "max_abs_shift_deg": float(cells["load_trend_shift_deg"].abs().max())},
        "battery_v": st.battery_v, "seconds": round(wall, 2),
    }
