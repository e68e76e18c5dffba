"""What the table builder takes and gives: its settings, the combustion-model interface, the result."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import priors
from engine_model.io import write_json
from engine_model.spec import EngineSpec
from engine_model.tables.grid import EcuGrid

__all__ = ["MapSettings", "PriorModel", "MapResult", "load_model", "check_model"]


@dataclass(frozen=True)
class MapSettings:
    """How the tables are built (angles in deg crank angle, spark in deg BTDC).

    Attributes
    ----------
    knock_margin : float
        Table cells must satisfy ``knock index of the fastest cycles < 1 - knock_margin`` [-].
        Default 0: the safety is explicit elsewhere: the fastest cycles
        (``cycle_advance_deg``), the knock calibration's multiplier taken at its
        conservative quantile, and the combustion model's uncertainty
        (``knock_uncertainty_z``).
    cycle_advance_deg : float or None
        The fastest cycles burn this much earlier than the mean cycle [deg]; a
        spark is knock-free when the knock index at ``spark + cycle_advance_deg``
        stays below the limit.  None (default): the engine spec's
        ``knock.cycle_ca50_advance_deg``.
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
        (per breakpoint) among feasible cells not limited by knock [deg];
        knock-limited cells follow their border.  Default 10: on the default
        R6 map the MBT cells then need no shift at all (with the knock-limited
        cells inside the bound it moved MBT cells by up to 14 deg and cost
        0.8-1.3 % torque on average; docs/sections/tables.md).
    start_retard_deg : float
        Retard of the starting map from the built map [deg]; the paper
        recommends 10-15 deg [P].
    battery_v : float
        Battery voltage for the injector dead time [V].
    min_bmep_bar : float
        Near-zero-BMEP (zone 2) limit [bar], default :data:`engine_model.priors.MIN_BMEP_BAR`.
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
        measured per cell by two extra simulations (the burn 3 deg faster and
        slower; docs/sections/tables.md).  Default 1 (one-sided
        84 %): on the default pipeline's model it cut the cells where the truth
        engine knocks at the table spark from 25 to 6 of 80 at a 10 % mean
        torque cost; 1.64 removed them all at 25 % (measured with the earlier
        one-sided gain, docs/history/knock_uncertainty.md).
        0 ignores the uncertainty; models without ``*_std`` outputs get none.
    bench_offset_reach_rpm : float or None
        The bench's measured MBT error of the model (bench spark - model MBT in a cell the bench ran
        clean at MBT) is carried to the MBT target of every cell at that speed, linear in speed between
        measured speeds and faded to zero over this distance beyond them [rpm]
        (:mod:`engine_model.tables.bench_offset`).  Default 2000; None carries nothing (only the
        measured cells take the bench's spark).
    mbt_monotone_in_load : bool
        At each speed, fit the cells' MBT targets by least squares under the order "no less advance as the
        throttle closes" before the knock cap (a thinner charge with more residual burns more slowly:
        Heywood 1988, sec. 9.3); ``load_trend_shift_deg`` per cell says what moved.  Default True; False
        keeps each cell's own MBT estimate (the truth's own table in the benchmarks is built so).
    """

    knock_margin: float = 0.0
    cycle_advance_deg: float | None = None
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
    min_bmep_bar: float = priors.MIN_BMEP_BAR
    ca50_target_deg_atdc: float = priors.CA50_TARGET_DEG_ATDC
    knock_uncertainty_z: float = 1.0
    bench_offset_reach_rpm: float | None = 2000.0
    mbt_monotone_in_load: bool = True

    def __post_init__(self):
        def need(ok, name, rule):
            if not ok:
                raise ValueError(f"MapSettings.{name} = {getattr(self, name)!r}: {rule}")
        need(0 <= self.knock_margin < 1, "knock_margin", "must lie in [0, 1)")
        need(self.cycle_advance_deg is None or 0 <= self.cycle_advance_deg <= 15, "cycle_advance_deg",
             "must be None (the spec's value) or lie in [0, 15] deg")
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
        need(self.bench_offset_reach_rpm is None or 0 <= self.bench_offset_reach_rpm <= 20000,
             "bench_offset_reach_rpm", "must be None (carry nothing) or lie in [0, 20000] rpm")
        need(isinstance(self.mbt_monotone_in_load, bool), "mbt_monotone_in_load", "must be True or False")

    @property
    def cycle_advance(self) -> float:
        """``cycle_advance_deg`` resolved (0 when not set; :func:`build_maps` sets it from the spec) [deg]."""
        return 0.0 if self.cycle_advance_deg is None else float(self.cycle_advance_deg)

    @property
    def knock_limit(self) -> float:
        """Highest knock index a table cell may reach (exclusive) [-]."""
        return 1.0 - self.knock_margin


class PriorModel:
    """The DOE prior as a combustion model: :func:`engine_model.priors.combustion_estimate` (spark-independent).

    Parameters
    ----------
    spec_hash : str, optional
        Engine spec the model is meant for (None: any spec).
    """

    kind = "combustion_prior"

    def __init__(self, spec_hash: str | None = None):
        self.spec_hash = spec_hash

    def predict(self, points: pd.DataFrame) -> pd.DataFrame:
        b, m = priors.combustion_estimate(points["speed_rpm"].to_numpy(float), points["throttle_pct"].to_numpy(float))
        return pd.DataFrame({"bdur_10_90_deg": np.atleast_1d(b), "wiebe_m": np.atleast_1d(m)}, index=points.index)

    def check_spec(self, spec: EngineSpec) -> None:
        if self.spec_hash is not None and self.spec_hash != spec.spec_hash():
            raise ValueError(f"combustion model was built for engine spec {self.spec_hash}, not "
                             f"{spec.spec_hash()} ({spec.name}); refit it for this spec")

    def save(self, path) -> Path:
        return write_json({"model": self.kind, "spec_hash": self.spec_hash}, path)


def load_model(path):
    """Load a combustion model file: a :class:`PriorModel` JSON, else :func:`engine_model.globalmodel.mapmodel.load`."""
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
        from engine_model.globalmodel import mapmodel
    except ImportError:
        raise ValueError(f"{p}: not a combustion-prior file, and engine_model.globalmodel.mapmodel is not available") from None
    return mapmodel.load(p)


def check_model(model, spec: EngineSpec) -> None:
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
        ``spark_deg_btdc`` (table), ``smoothing_shift_deg``, ``load_trend_shift_deg`` (move of the
        MBT target by the load-trend fit, ``MapSettings.mbt_monotone_in_load``),
        ``phasing_std_deg`` (model's 1-sigma CA50-offset error at the knock border),
        ``knock_phasing_gain`` [deg spark / deg CA50] (the cell's own, or the median of the
        measured gains around it where the own is an outlier among them;
        ``knock_phasing_gain_cell`` the cell's own, ``knock_phasing_gain_measured``
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
