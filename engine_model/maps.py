"""ECU look-up tables from the cycle model and a combustion model: spark advance and injection time.

    ECU grid (throttle % x rpm) + target-lambda table
      -> per cell: spark search on the cycle model, Wiebe parameters predicted per candidate spark
         (coarse sweep around the model's CA50 = 9 deg ATDC spark, then parabolic refinement of brake
          torque; knock border refined log-linearly), one batched ``evaluate`` call per search stage
      -> MBT, limited by knock (knock_index < 1 - knock_margin) and a safety retard
      -> infeasible zones of the paper's Figure 1 flagged (``doe.feasibility``)
      -> smoothing with bounded second differences (only as much as needed; shifts reported)
      -> verification run of the final table (knock re-checked, trapped air) -> injection time
      -> the deliberately retarded starting map for the first bench session

A *combustion model* is any object with ``predict(points) -> DataFrame``
returning ``bdur_10_90_deg, wiebe_m`` for rows with ``throttle_pct,
speed_rpm, spark_deg_btdc, lambda``; a fitted model also has ``spec_hash``
and ``check_spec(spec)``.  :class:`PriorModel` wraps the DOE prior
:func:`engine_model.doe.combustion_estimate` (useful before any bench data).

The grid, lambda table, injection formula and smoothing are in :mod:`engine_model.maps_tables`;
export (long-form Parquet, wide CSV, heatmaps) is in :mod:`engine_model.maps_io`.

References
----------
.. [P] Mrda et al., MVM2012-024: retarded initial spark map (10-15 deg), MBT or
   knock as the end of a spark sweep, Figure 1 (zones), Figures 3-4 (tables).
.. [H] J.B. Heywood, Internal Combustion Engine Fundamentals, 1988, sec.
   9.3 / 9.6 (MBT, knock-limited spark advance).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from . import doe
from .maps_search import _EVAL_KEEP, _Runner, _decide, _model_spark, _uncertainty_retard  # noqa: F401  (_decide: tests)
from .maps_tables import (DEFAULT_SPEED_RPM, DEFAULT_THROTTLE_PCT, LAMBDA_RANGE, EcuGrid, LambdaTable,  # noqa: F401
                          injection_time_ms, parse_breakpoints, second_differences, smooth_table)
from .spec import EngineSpec

__all__ = [
    "EcuGrid", "LambdaTable", "MapSettings", "MapResult", "PriorModel", "build_maps", "injection_time_ms",
    "load_model", "parse_breakpoints", "smooth_table", "second_differences", "write_maps",
]

# --------------------------------------------------------------------------- settings and models

@dataclass(frozen=True)
class MapSettings:
    """How the tables are built (angles in deg crank angle, spark in deg BTDC).

    Attributes
    ----------
    knock_margin : float
        Table cells must satisfy ``knock_index < 1 - knock_margin`` [-]
        (default 0.15: limit 0.85; the knock model is a Livengood-Wu integral
        with uncertain constants, so the border is kept away from 1).
    safety_retard_deg : float
        Retard from MBT applied where MBT (not knock) sets the spark [deg]
        (default 0: the torque plateau near MBT is flat, 2 deg cost < 0.5 %).
    spark_min_deg_btdc, spark_max_deg_btdc : float
        Search range [deg BTDC]; a cell that knocks at ``spark_min`` is the
        knock-limited infeasible zone 1.
    coarse_offsets_deg : tuple of float
        First-stage candidates relative to the model's CA50 = 9 deg ATDC spark.
    refine_step_deg : float
        Spacing of the refinement points around the torque peak [deg].
    mbt_window_deg : float
        MBT = vertex of a least-squares parabola through the points within
        this distance of the best point [deg] (averages torque noise).
    knock_tol_deg : float
        Knock border resolved when the highest knock-safe evaluated spark is
        within this of the interpolated border [deg].
    max_stages : int
        Search stages (batched evaluate calls) at most, verification excluded.
    max_fix_rounds : int
        Verification rounds that retard cells found knocking.
    max_second_diff_deg : float
        Bound on |second difference| of the spark table along either axis
        (per breakpoint, feasible cells) [deg].  Default 10: on the default R6
        map it moves feasible cells by 2.8 deg RMS (7.6 max) at a mean torque
        cost of 1.1 %; 6 deg costs 1.4 % (measured, docs/sections/maps.md).
    start_retard_deg : float
        Retard of the starting map from the built map [deg]; the paper
        recommends 10-15 deg [P].
    battery_v : float
        Battery voltage for the injector dead time [V].
    min_bmep_bar : float
        Near-zero-BMEP (zone 2) limit [bar], default :data:`engine_model.doe.MIN_BMEP_BAR`.
    ca50_target_deg_atdc : float
        Centre of the first-stage sweep: the spark at which the model puts
        CA50 here [deg ATDC] (paper: MBT at CA50 8-10 deg ATDC).
    knock_uncertainty_z : float
        Knock safety against the combustion model's own uncertainty [-, number
        of standard deviations], in [0, 4].  In every cell where knock was met,
        the knock border is moved back by ``z * sigma_ca50_offset * g`` [deg]:
        ``sigma_ca50_offset`` the model's 1-sigma error of the ignition-to-CA50
        angle at the border (its ``ca50_offset_deg_std``, else the delta method
        on ``bdur_10_90_deg_std`` and ``wiebe_m_std``, errors independent), ``g``
        the spark retard that offsets a 1 deg earlier CA50 at equal knock index,
        measured per cell by one extra simulation (a faster burn raises the
        knock index: docs/sections/knock_uncertainty.md).  Default 1 (one-sided
        84 %): on the default pipeline's model it cut the cells where the truth
        engine knocks at the table spark from 25 to 6 of 80 at a 10 % mean
        torque cost; 1.64 removed them all at 25 % (measured, same section).
        0 ignores the uncertainty; models without ``*_std`` outputs get none.
    """

    knock_margin: float = 0.15
    safety_retard_deg: float = 0.0
    spark_min_deg_btdc: float = 0.0
    spark_max_deg_btdc: float = 70.0
    coarse_offsets_deg: tuple[float, ...] = (-12.0, -8.0, -4.0, 0.0, 4.0, 8.0)
    refine_step_deg: float = 2.0
    mbt_window_deg: float = 6.0
    knock_tol_deg: float = 0.5
    max_stages: int = 5
    max_fix_rounds: int = 3
    max_second_diff_deg: float = 10.0
    start_retard_deg: float = 12.0
    battery_v: float = 14.0
    min_bmep_bar: float = doe.MIN_BMEP_BAR
    ca50_target_deg_atdc: float = doe.CA50_TARGET_DEG_ATDC
    knock_uncertainty_z: float = 1.0

    def __post_init__(self):
        def need(ok, name, rule):
            if not ok:
                raise ValueError(f"MapSettings.{name} = {getattr(self, name)!r}: {rule}")
        need(0 <= self.knock_margin < 1, "knock_margin", "must lie in [0, 1)")
        need(0 <= self.safety_retard_deg <= 20, "safety_retard_deg", "must lie in [0, 20] deg")
        need(-30 <= self.spark_min_deg_btdc < self.spark_max_deg_btdc <= 90, "spark_min_deg_btdc",
             "need -30 <= spark_min < spark_max <= 90 deg BTDC")
        offs = tuple(float(o) for o in self.coarse_offsets_deg)
        object.__setattr__(self, "coarse_offsets_deg", offs)
        need(len(offs) >= 3 and len(set(offs)) == len(offs), "coarse_offsets_deg", "needs >= 3 distinct offsets")
        need(0.1 <= self.refine_step_deg <= 5, "refine_step_deg", "must lie in [0.1, 5] deg")
        need(1 <= self.mbt_window_deg <= 20, "mbt_window_deg", "must lie in [1, 20] deg")
        need(0.05 <= self.knock_tol_deg <= 5, "knock_tol_deg", "must lie in [0.05, 5] deg")
        need(isinstance(self.max_stages, int) and 1 <= self.max_stages <= 20, "max_stages", "integer 1-20")
        need(isinstance(self.max_fix_rounds, int) and 0 <= self.max_fix_rounds <= 10, "max_fix_rounds",
             "integer 0-10")
        need(self.max_second_diff_deg > 0, "max_second_diff_deg", "must be > 0 deg")
        need(0 <= self.start_retard_deg <= 40, "start_retard_deg", "must lie in [0, 40] deg")
        need(6 <= self.battery_v <= 30, "battery_v", "must lie in [6, 30] V")
        need(self.min_bmep_bar >= 0, "min_bmep_bar", "must be >= 0 bar")
        need(isinstance(self.knock_uncertainty_z, (int, float)) and not isinstance(self.knock_uncertainty_z, bool)
             and 0 <= self.knock_uncertainty_z <= 4, "knock_uncertainty_z", "must be a number in [0, 4] (sigmas)")

    @property
    def knock_limit(self) -> float:
        """Highest knock index a table cell may reach (exclusive) [-]."""
        return 1.0 - self.knock_margin


class PriorModel:
    """The DOE prior as a combustion model: :func:`engine_model.doe.combustion_estimate` (spark-independent).

    Parameters
    ----------
    spec_hash : str, optional
        Engine spec the model is meant for (None: any spec).
    """

    kind = "combustion_prior"

    def __init__(self, spec_hash: str | None = None):
        self.spec_hash = spec_hash

    def predict(self, points: pd.DataFrame) -> pd.DataFrame:
        b, m = doe.combustion_estimate(points["speed_rpm"].to_numpy(float), points["throttle_pct"].to_numpy(float))
        return pd.DataFrame({"bdur_10_90_deg": np.atleast_1d(b), "wiebe_m": np.atleast_1d(m)}, index=points.index)

    def check_spec(self, spec: EngineSpec) -> None:
        if self.spec_hash is not None and self.spec_hash != spec.spec_hash():
            raise ValueError(f"combustion model was built for engine spec {self.spec_hash}, not "
                             f"{spec.spec_hash()} ({spec.name}); refit it for this spec")

    def save(self, path) -> Path:
        from .io import write_json
        return write_json({"model": self.kind, "spec_hash": self.spec_hash}, path)


def load_model(path):
    """Load a combustion model file: a :class:`PriorModel` JSON, else :func:`engine_model.mapmodel.load`."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: model file not found")
    if p.suffix.lower() == ".json":
        try:
            doc = json.loads(p.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"{p}: not a readable JSON model file: {exc}") from None
        if isinstance(doc, dict) and doc.get("model") == PriorModel.kind:
            return PriorModel(doc.get("spec_hash"))
    try:
        from . import mapmodel
    except ImportError:
        raise ValueError(f"{p}: not a combustion-prior file, and engine_model.mapmodel is not available") from None
    return mapmodel.load(p)


def _check_model(model, spec: EngineSpec) -> None:
    if not callable(getattr(model, "predict", None)):
        raise ValueError(f"combustion model {type(model).__name__} has no predict(points) method")
    if callable(getattr(model, "check_spec", None)):
        model.check_spec(spec)
    elif getattr(model, "spec_hash", None) not in (None, spec.spec_hash()):
        raise ValueError(f"combustion model was fitted for engine spec {model.spec_hash}, not "
                         f"{spec.spec_hash()} ({spec.name})")


@dataclass(frozen=True)
class MapResult:
    """ECU tables and how they were found.

    Attributes
    ----------
    grid : EcuGrid
    settings : MapSettings
    cells : DataFrame
        One row per cell (row-major, throttle outer): ``throttle_pct, speed_rpm,
        lambda, spark_prior_deg_btdc`` (model's CA50 spark), ``spark_mbt_deg_btdc``
        (NaN where not found), ``spark_border_deg_btdc`` (highest knock-safe
        spark evaluated; spark_max if no knock met), ``spark_raw_deg_btdc``,
        ``spark_deg_btdc`` (table), ``smoothing_shift_deg``,
        ``phasing_std_deg`` (model's 1-sigma CA50-offset error at the knock border),
        ``knock_phasing_gain`` [deg spark / deg CA50] (``knock_phasing_gain_measured``
        False where the fallback 1 was used), ``knock_uncertainty_retard_deg``
        (retard of the raw spark for that uncertainty, ``MapSettings.knock_uncertainty_z``),
        ``spark_start_deg_btdc`` (retarded starting map), ``limited_by``
        (mbt / knock / retard / spark_max / infeasible), ``feasible``,
        ``infeasible_reason`` (doe.feasibility words), ``search_converged``,
        verification results at the table spark (``brake_torque_nm,
        knock_index, bmep_bar, air_mass_flow_kg_h, ...``), ``air_mg, fuel_mg,
        injection_time_ms, duty_pct``, ``spark_source, injection_source``.
    evaluations : DataFrame
        Every evaluated point (``stage`` s1.. for the search, v1.. for verification).
    stats : dict
        Counts, timings, smoothing report.
    spec_hash, model_name : str
    """

    grid: EcuGrid
    settings: MapSettings
    cells: pd.DataFrame
    evaluations: pd.DataFrame
    stats: dict
    spec_hash: str
    model_name: str

    def table(self, column: str) -> np.ndarray:
        """A cell column as an array of shape (n_throttle, n_speed)."""
        return self.cells[column].to_numpy(float).reshape(self.grid.shape)


def _feasibility(cells: pd.DataFrame, best: pd.DataFrame, st: MapSettings) -> pd.DataFrame:
    plan = cells[["throttle_pct", "speed_rpm", "lambda"]].copy()
    plan["spark_deg_btdc"] = best["spark_deg_btdc"].to_numpy()
    return doe.feasibility(plan, evaluate=lambda _p: best[["knock_index", "bmep_bar"]].reset_index(drop=True),
                           knock_margin=st.knock_margin, min_bmep_bar=st.min_bmep_bar)


def build_maps(spec: EngineSpec, model, grid: EcuGrid | None = None, lambda_table: LambdaTable | str | Path | None = None,
               evaluate: Callable[[pd.DataFrame], pd.DataFrame] | None = None, settings: MapSettings | None = None,
               step_deg: float = 0.5, progress: Callable[[str, int], None] | None = None) -> MapResult:
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

    Returns
    -------
    MapResult
    """
    t0 = time.perf_counter()
    grid = EcuGrid() if grid is None else grid
    st = MapSettings() if settings is None else settings
    if not isinstance(grid, EcuGrid):
        raise ValueError(f"grid must be an EcuGrid, got {type(grid).__name__}")
    grid.check_spec(spec)
    _check_model(model, spec)
    if lambda_table is None:
        lam_tab = LambdaTable.default(grid)
    elif isinstance(lambda_table, LambdaTable):
        lam_tab = lambda_table
    else:
        lam_tab = LambdaTable.from_csv(lambda_table)
    if evaluate is None:
        from .prepare import SolverSettings
        from .simulate import simulate
        solver = SolverSettings(step_deg=step_deg)

        def evaluate(plan):
            return simulate(spec, plan, solver)

    cells = grid.cells().set_index("cell", drop=False)
    cells["lambda"] = lam_tab.on_grid(grid).ravel()
    lo, hi = st.spark_min_deg_btdc, st.spark_max_deg_btdc
    cells["spark_prior_deg_btdc"] = _model_spark(model, cells, st)
    runner = _Runner(model, cells, evaluate, progress)

    # ---- search stages
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
            kind, what = _decide(grp, st)
            if kind == "done":
                resolved[c] = {**what, "search_converged": True}
            else:
                requests[c] = what
    ev = runner.evaluations()
    for c in cells["cell"]:
        if c not in resolved:   # out of stages: best safe point so far
            grp = ev[(ev["cell"] == c) & np.isfinite(ev["brake_torque_nm"]) & (ev["knock_index"] < st.knock_limit)]
            if grp.empty:
                kind, what = _decide(ev[ev["cell"] == c], st)
                what = what if kind == "done" else {"status": "zone1" if len(ev[ev["cell"] == c]) else "failed",
                                                    "mbt": math.nan, "border": lo, "raw": lo,
                                                    "limited_by": "infeasible"}
            else:
                b = grp.loc[grp["brake_torque_nm"].idxmax()]
                knocked = ev[(ev["cell"] == c) & (ev["knock_index"] >= st.knock_limit)]
                border = float(grp["spark_deg_btdc"].max()) if len(knocked) else hi
                what = {"status": "ok", "mbt": math.nan, "border": border, "raw": float(b["spark_deg_btdc"]),
                        "limited_by": "knock" if float(b["spark_deg_btdc"]) >= border - 1e-6 else "mbt"}
            resolved[c] = {**what, "search_converged": False}
    res = pd.DataFrame([resolved[c] for c in cells["cell"]], index=cells.index)
    cells["spark_mbt_deg_btdc"] = res["mbt"].astype(float)
    cells["spark_border_deg_btdc"] = res["border"].astype(float)
    cells["spark_raw_deg_btdc"] = res["raw"].astype(float)
    cells["limited_by"] = res["limited_by"].astype(str)
    cells["search_converged"] = res["search_converged"].astype(bool)

    # ---- zones (doe.feasibility on the evaluated point nearest the raw spark)
    best_rows = []
    for c in cells["cell"]:
        grp = ev[(ev["cell"] == c) & np.isfinite(ev["brake_torque_nm"])]
        raw = cells.at[c, "spark_raw_deg_btdc"]
        if grp.empty or not math.isfinite(raw):
            best_rows.append({"spark_deg_btdc": raw, "knock_index": math.nan, "bmep_bar": math.nan})
        else:
            r = grp.loc[(grp["spark_deg_btdc"] - raw).abs().idxmin()]
            best_rows.append({"spark_deg_btdc": raw, "knock_index": r["knock_index"], "bmep_bar": r["bmep_bar"]})
    flags = _feasibility(cells, pd.DataFrame(best_rows), st)
    cells["feasible"] = flags["feasible"].to_numpy(bool)
    cells["infeasible_reason"] = flags["infeasible_reason"].astype(str).to_numpy()
    cells.loc[~cells["feasible"], "limited_by"] = "infeasible"

    # ---- knock safety against the model's burn uncertainty: the border moved back by z * sigma_CA50 * gain
    unc = _uncertainty_retard(runner, ev, cells, st)
    for col in ("phasing_std_deg", "knock_phasing_gain"):
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

    # ---- smoothing (feasible cells are data; others are filled; zone 1 pinned to spark_min)
    zone1 = (cells["infeasible_reason"] == "knock-limited").to_numpy()
    border = np.where(feas, border_safe, cells["spark_border_deg_btdc"].to_numpy(float))
    upper = np.where(feas, border, np.where(np.isfinite(border), np.maximum(border, lo), hi))
    upper = np.where(zone1, lo, upper)
    shape = grid.shape
    # uniform weights: measured on the default R6 map, torque-curvature weights cost more torque (mean 1.3 % vs
    # 1.1 %, max 8.2 % both at a 10 deg bound), because most forced moves are knock-limited cells that can only retard
    spark, sinfo = smooth_table(cells["spark_raw_deg_btdc"].to_numpy(float).reshape(shape),
                                feas.astype(float).reshape(shape), np.full(shape, lo), upper.reshape(shape),
                                st.max_second_diff_deg, stencil=~zone1.reshape(shape))
    # ECU resolution 0.1 deg, rounded down (towards retard: never past the knock border); this exact value is verified
    cells["spark_deg_btdc"] = np.floor(spark.ravel() * 10.0 + 1e-6) / 10.0
    cells["smoothing_shift_deg"] = np.where(feas, cells["spark_deg_btdc"] - cells["spark_raw_deg_btdc"], np.nan)
    cells["spark_source"] = np.where(feas, "simulation", np.where(zone1, "spark_min", "fill"))

    # ---- verification of the final table (knock re-checked; trapped air for the injection time)
    ver = {}
    for c in cells["cell"][~feas]:   # not verified: nearest searched point (air flow for the injection fill)
        grp = ev[(ev["cell"] == c) & np.isfinite(ev["brake_torque_nm"])]
        if grp.empty:
            grp = ev[ev["cell"] == c] if (ev["cell"] == c).any() else None
        if grp is None:
            ver[c] = pd.Series({"status": "not evaluated", **{k: math.nan for k in _EVAL_KEEP if k != "status"},
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
        todo = {}
        for _, r in out.iterrows():
            c = int(r["cell"])
            ver[c] = r
            k = r["knock_index"]
            if feas[c] and np.isfinite(k) and k >= st.knock_limit and rnd <= st.max_fix_rounds:
                grp = ev[(ev["cell"] == c) & np.isfinite(ev["knock_index"]) & (ev["knock_index"] > 0)]
                slope = 0.05   # d ln(knock)/d spark [1/deg] fallback (typical of the search data)
                if len(grp) >= 2:
                    g = grp.sort_values("spark_deg_btdc")
                    fit = np.polyfit(g["spark_deg_btdc"], np.log(g["knock_index"]), 1)[0]
                    slope = fit if fit > 1e-3 else slope
                new = max(lo, float(r["spark_deg_btdc"]) - max(0.5, math.log(k / st.knock_limit) / slope + 0.2))
                new = math.floor(new * 10.0 + 1e-6) / 10.0
                cells.at[c, "spark_deg_btdc"] = new
                cells.at[c, "limited_by"] = "knock"
                todo[c] = [new]
                fixes += 1
        if not todo:
            break
    vt = pd.DataFrame([ver[c] for c in cells["cell"]], index=cells.index)
    for col in ("brake_torque_nm", "knock_index", "bmep_bar", "ca50_deg_atdc", "air_mass_flow_kg_h",
                "fuel_mass_flow_kg_h", "exhaust_temp_k", "bdur_10_90_deg", "wiebe_m"):
        cells[col] = pd.to_numeric(vt[col], errors="coerce").astype(float).to_numpy()
    cells["verify_status"] = vt["status"].astype(str).to_numpy()
    cells["verified"] = ~(feas & ~(cells["knock_index"].to_numpy(float) < st.knock_limit))
    cells["smoothing_shift_deg"] = np.where(feas, cells["spark_deg_btdc"] - cells["spark_raw_deg_btdc"], np.nan)
    best_safe = ev[np.isfinite(ev["brake_torque_nm"]) & (ev["knock_index"] < st.knock_limit)] \
        .groupby("cell")["brake_torque_nm"].max()
    ref = cells["cell"].map(best_safe).astype(float).to_numpy()
    cells["torque_best_searched_nm"] = ref
    cells["torque_loss_pct"] = np.where(feas, 100.0 * (1.0 - cells["brake_torque_nm"].to_numpy(float) / ref), np.nan)

    # ---- injection time from the verified air flow; cells without it are filled
    inj = injection_time_ms(cells["air_mass_flow_kg_h"], cells["speed_rpm"], cells["lambda"], spec, st.battery_v)
    have = np.isfinite(inj["injection_time_ms"])
    t_inj, iinfo = smooth_table(np.where(have, inj["injection_time_ms"], np.nan).reshape(shape),
                                have.astype(float).reshape(shape), np.full(shape, inj["dead_time_ms"][0]),
                                np.full(shape, 1e3 * 120.0 / grid.speed_rpm[0]), None)
    for key in ("air_mg", "fuel_mg", "dead_time_ms", "duty_pct"):
        cells[key] = inj[key]
    cells["injection_time_ms"] = t_inj.ravel()
    cells["injection_source"] = np.where(have, "simulation", "fill")
    cells["spark_start_deg_btdc"] = np.maximum(cells["spark_deg_btdc"] - st.start_retard_deg, -30.0)

    wall = time.perf_counter() - t0
    d2t, d2n = second_differences(np.where(feas, cells["spark_deg_btdc"].to_numpy(float), np.nan).reshape(shape))
    d2 = np.concatenate([d2t.ravel(), d2n.ravel()])
    d2 = d2[np.isfinite(d2)]
    stats = {
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
        "battery_v": st.battery_v, "seconds": round(wall, 2),
    }
    return MapResult(grid=grid, settings=st, cells=cells.reset_index(drop=True), evaluations=runner.evaluations(),
                     stats=stats, spec_hash=spec.spec_hash(), model_name=type(model).__name__)


def write_maps(result: MapResult, out_dir, figures: bool = True) -> dict:
    """Write the tables (long Parquet, wide CSVs, PNGs, summary) into ``out_dir``; see :mod:`engine_model.maps_io`."""
    from .maps_io import write_maps as _write

    return _write(result, out_dir, figures=figures)
