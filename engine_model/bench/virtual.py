"""The virtual test bench: a truth engine that answers a DOE plan with measured-like rows.

Real dyno time is scarce; the virtual bench stands in for it.  It is the cycle
model run with a *hidden* combustion law (:class:`engine_model.bench.burnlaw.BurnLaw`),
optional extra physical effects switched on by name (the gap-analysis effects
library, :mod:`engine_model.effects`), the measurement chain of a bench
(gearbox losses between crank and brake, noise, quantisation) and the bench's
limits (knocking points are aborted, as in the paper's zone 1; points below a
holdable load are aborted, zone 2).  Its rows follow the bench contract, so a
real bench file and the virtual bench feed the same downstream code.

Chain per point::

    plan row -> BurnLaw.predict (hidden BDUR10-90, m) -> apply_effects
             -> evaluate (cycle model) -> limits (knock, load, convergence)
             -> crank -> brake (x eta_trans) -> post_effects -> noise -> quantisation

Noise is drawn from a :class:`numpy.random.Generator` seeded with
``(seed, sha256(point_id))``: the same point id gives the same reading in any
plan, any order and any chunking, and the same plan gives the same data.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np
import pandas as pd

from engine_model import effects as effects_lib
from engine_model.bench.burnlaw import BurnLaw
from engine_model.contracts import (COMBUSTION_INPUTS, COMBUSTION_OUTPUTS, MEASURED_COLUMNS,
                                    check_combustion_inputs)
from engine_model.priors import MIN_BMEP_BAR
from engine_model.sim.prepare import SolverSettings
from engine_model.spec import EngineSpec, default_spec

__all__ = ["NoiseModel", "VirtualBench", "run_virtual_bench"]


# Columns the bench never takes from the plan: its combustion is its own.
_HIDDEN = ("bdur_10_90_deg", "wiebe_m", "wiebe_a")


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise and quantisation of the bench instruments.

    Noise terms are one standard deviation of a normal error, independent per
    point and channel.  The defaults are the accuracy classes the issue states
    for a Formula Student bench (torque +-0.5 %, airflow +-1 %, exhaust
    temperature +-5 K), taken as 1 sigma; fuel flow +-1 % (gravimetric or
    Coriolis fuel meter class, engineering assumption).

    Attributes
    ----------
    torque_rel : float
        Relative torque noise [-] (load-cell brake).
    airflow_rel : float
        Relative air mass flow noise [-] (hot-film / laminar-flow meter).
    fuel_rel : float
        Relative fuel mass flow noise [-].
    exhaust_t_k : float
        Absolute exhaust temperature noise [K] (thermocouple).
    torque_step_nm, airflow_step_kg_h, fuel_step_kg_h, exhaust_t_step_k : float
        Quantisation steps of the logged values [N m, kg/h, kg/h, K]
        (a 0.1 N m / 0.1 kg/h / 0.01 kg/h / 1 K display resolution); 0 = none.
    """

    torque_rel: float = 0.005
    airflow_rel: float = 0.01
    fuel_rel: float = 0.01
    exhaust_t_k: float = 5.0
    torque_step_nm: float = 0.1
    airflow_step_kg_h: float = 0.1
    fuel_step_kg_h: float = 0.01
    exhaust_t_step_k: float = 1.0

    def __post_init__(self):
        for name, v in self.__dict__.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"NoiseModel.{name} = {v!r} must be a finite number >= 0")
        for name in ("torque_rel", "airflow_rel", "fuel_rel"):
            if getattr(self, name) > 0.2:
                raise ValueError(f"NoiseModel.{name} = {getattr(self, name)!r} > 0.2: a relative error of "
                                 "more than 20 % is not a measurement")

    @classmethod
    def none(cls) -> "NoiseModel":
        """A perfect bench: no noise, no quantisation."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def point_rng(seed: int, point_id) -> np.random.Generator:
    """Generator for one point: seeded by ``seed`` and the sha256 of ``str(point_id)``."""
    h = int.from_bytes(hashlib.sha256(str(point_id).encode("utf-8")).digest()[:8], "little")
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, h])


def _quantise(x: np.ndarray, step: float) -> np.ndarray:
    return np.round(x / step) * step if step > 0 else x


def apply_noise(rows: pd.DataFrame, noise: NoiseModel, seed: int) -> pd.DataFrame:
    """Add instrument noise and quantisation to bench rows (a copy).

    Parameters
    ----------
    rows : DataFrame
        ``point_id, speed_rpm, brake_torque_nm, air_mass_flow_kg_h,
        fuel_mass_flow_kg_h, exhaust_temp_k`` (noise-free, brake side).
    noise : NoiseModel
    seed : int

    Returns
    -------
    DataFrame
        Torque, airflow, fuel flow and exhaust temperature with noise and
        quantisation; ``brake_power_kw`` and ``bsfc_g_kwh`` recomputed from the
        noisy readings, as a bench computes them.  NaN stays NaN.
    """
    out = rows.copy()
    n = len(out)
    z = np.empty((n, 4))
    for i, pid in enumerate(out["point_id"]):
        z[i] = point_rng(seed, pid).standard_normal(4)
    tq = out["brake_torque_nm"].to_numpy(float) * (1.0 + noise.torque_rel * z[:, 0])
    air = out["air_mass_flow_kg_h"].to_numpy(float) * (1.0 + noise.airflow_rel * z[:, 1])
    fuel = out["fuel_mass_flow_kg_h"].to_numpy(float) * (1.0 + noise.fuel_rel * z[:, 2])
    tex = out["exhaust_temp_k"].to_numpy(float) + noise.exhaust_t_k * z[:, 3]
    tq = _quantise(tq, noise.torque_step_nm)
    air = _quantise(air, noise.airflow_step_kg_h)
    fuel = _quantise(fuel, noise.fuel_step_kg_h)
    tex = _quantise(tex, noise.exhaust_t_step_k)
    power = tq * 2.0 * math.pi * out["speed_rpm"].to_numpy(float) / 60.0 / 1e3
    with np.errstate(invalid="ignore", divide="ignore"):
        bsfc = np.where(power > 0, fuel * 1e3 / power, np.nan)
    out["brake_torque_nm"], out["air_mass_flow_kg_h"] = tq, air
    out["fuel_mass_flow_kg_h"], out["exhaust_temp_k"] = fuel, tex
    out["brake_power_kw"], out["bsfc_g_kwh"] = power, bsfc
    return out


def _check_effects(effects) -> dict:
    if effects is None or (isinstance(effects, Mapping) and not effects):
        return {}
    if not isinstance(effects, Mapping):
        raise ValueError(f"VirtualBench: effects must be a dict {{name: {{param: value}}}}, got "
                         f"{type(effects).__name__}")
    # names, parameters and ranges are checked by the effects library (ValueError listing valid names)
    return effects_lib.check_effects(effects)


@dataclass(frozen=True)
class VirtualBench:
    """Truth engine + bench: answers a plan with measured-like rows.

    Parameters
    ----------
    spec : EngineSpec, optional
        The truth engine; default :func:`engine_model.default_spec`.
    law : BurnLaw
        Hidden combustion law (anything with ``predict(points)`` returning
        ``bdur_10_90_deg, wiebe_m`` works, e.g. a fitted map model).
    effects : dict {name: {param: value}}, optional
        Extra physical / measurement effects by name, applied through
        :mod:`engine_model.effects` (``apply_effects`` before the
        simulation, ``post_effects`` on the measured rows).
    noise : NoiseModel
        Instrument noise and quantisation; :meth:`NoiseModel.none` for a
        perfect bench.
    eta_trans : float
        Transmission efficiency between crank and brake [-] (the paper assumes
        ~0.95; the torque is measured behind the gearbox [P]).
    knock_limit : float
        The bench aborts a point whose knock index reaches this value [-]
        (Livengood-Wu integral of the cycle model; 1 = autoignition).
    min_bmep_bar : float
        A manually controlled brake cannot hold a point below this BMEP [bar]
        (zone 2 of the paper's Figure 1); default
        :data:`engine_model.priors.MIN_BMEP_BAR`.  0 disables the limit.
    solver : SolverSettings
        Solver of the default in-process evaluator.
    seed : int
        Noise seed.
    """

    spec: EngineSpec | None = None
    law: object = field(default_factory=BurnLaw)
    effects: dict | None = None
    noise: NoiseModel = field(default_factory=NoiseModel)
    eta_trans: float = 0.95
    knock_limit: float = 1.0
    min_bmep_bar: float = MIN_BMEP_BAR
    solver: SolverSettings = field(default_factory=SolverSettings)
    seed: int = 0

    def __post_init__(self):
        if self.spec is None:
            object.__setattr__(self, "spec", default_spec())
        if not isinstance(self.spec, EngineSpec):
            raise ValueError(f"VirtualBench.spec must be an EngineSpec, got {type(self.spec).__name__}")
        if not callable(getattr(self.law, "predict", None)):
            raise ValueError("VirtualBench.law needs a predict(points) -> DataFrame method")
        object.__setattr__(self, "effects", _check_effects(self.effects))
        if not (0.5 <= self.eta_trans <= 1.0):
            raise ValueError(f"VirtualBench.eta_trans = {self.eta_trans!r} must lie in [0.5, 1]")
        if not (0 < self.knock_limit <= 10):
            raise ValueError(f"VirtualBench.knock_limit = {self.knock_limit!r} must lie in (0, 10]")
        if not (0 <= self.min_bmep_bar < 20):
            raise ValueError(f"VirtualBench.min_bmep_bar = {self.min_bmep_bar!r} must lie in [0, 20)")
        if not isinstance(self.seed, (int, np.integer)):
            raise ValueError(f"VirtualBench.seed = {self.seed!r} must be an integer")
        if not isinstance(self.noise, NoiseModel):
            raise ValueError(f"VirtualBench.noise must be a NoiseModel, got {type(self.noise).__name__}")

    # ------------------------------------------------------------------ pieces
    def _plan(self, plan: pd.DataFrame) -> pd.DataFrame:
        check_combustion_inputs(plan, "VirtualBench.measure", "plan")
        p = plan.reset_index(drop=True).copy()
        if "point_id" not in p.columns:
            width = max(4, len(str(len(p))))
            p.insert(0, "point_id", [f"vb-{i + 1:0{width}d}" for i in range(len(p))])
        ids = p["point_id"].astype(str)
        dup = ids.duplicated().to_numpy()
        if dup.any():
            i = int(np.flatnonzero(dup)[0])
            raise ValueError(f"VirtualBench.measure: plan row {i}, column 'point_id': value {ids.iloc[i]!r} "
                             "is a duplicate (the noise is seeded per point id)")
        return p.drop(columns=[c for c in _HIDDEN if c in p.columns])

    def hidden_law(self, plan: pd.DataFrame) -> pd.DataFrame:
        """The truth's combustion parameters at the plan's points (what identification should find).

        Returns
        -------
        DataFrame
            The plan (``point_id`` added if missing) with ``bdur_10_90_deg``
            [deg] and ``wiebe_m`` [-] of the hidden law at the plan's logged
            inputs.  (With a spark-changing effect such as ``knock_retard`` the
            engine burns at the spark it actually gets: see
            :meth:`simulation_points`.)
        """
        p = self._plan(plan)
        return self._with_law(p)

    def _with_law(self, p: pd.DataFrame) -> pd.DataFrame:
        law = self.law.predict(p[list(COMBUSTION_INPUTS)])
        if len(law) != len(p) or not set(COMBUSTION_OUTPUTS) <= set(law.columns):
            raise ValueError(f"VirtualBench: law.predict returned {len(law)} rows / columns {list(law.columns)}; "
                             f"expected {len(p)} rows with {list(COMBUSTION_OUTPUTS)}")
        p = p.copy()
        p["bdur_10_90_deg"] = law["bdur_10_90_deg"].to_numpy(float)
        p["wiebe_m"] = law["wiebe_m"].to_numpy(float)
        return p

    def simulation_points(self, plan: pd.DataFrame) -> pd.DataFrame:
        """What the truth engine simulates: plan -> model-side effects -> hidden law at the resulting inputs."""
        pts = self._plan(plan)
        if self.effects:
            pts = effects_lib.apply_effects(pts, self.effects, spec=self.spec)
        return self._with_law(pts)

    def default_evaluate(self, points: pd.DataFrame) -> pd.DataFrame:
        """In-process cycle model; rows that fail at a step above 0.5 deg are re-run once at 0.5 deg.

        (A 1 deg step is unstable below ~10 % throttle, see ``doe.QUICK_SOLVER``;
        a real engine does not 'fail' there, so the truth engine retries finer.)
        """
        from engine_model.sim.simulate import simulate  # late import: keeps `import engine_model.bench` light

        res = simulate(self.spec, points, solver=self.solver)
        failed = res["status"].astype(str).str.startswith("failed").to_numpy()
        if failed.any() and self.solver.step_deg > 0.5:
            finer = dataclasses.replace(self.solver, step_deg=0.5)
            redo = simulate(self.spec, points[failed].reset_index(drop=True), solver=finer)
            redo.index = np.flatnonzero(failed)
            res.loc[redo.index, redo.columns] = redo
        return res

    # ------------------------------------------------------------------ the bench
    def measure(self, plan: pd.DataFrame,
                evaluate: Callable[[pd.DataFrame], pd.DataFrame] | None = None) -> pd.DataFrame:
        """Run a plan on the virtual bench.

        Parameters
        ----------
        plan : DataFrame, n rows
            ``speed_rpm`` [rpm], ``throttle_pct`` [%], ``spark_deg_btdc`` [deg
            BTDC], ``lambda`` [-], optional ``point_id`` (unique; generated
            'vb-0001'... if absent) and any other columns (echoed).  Wiebe
            columns of the plan are ignored: the bench burns by its own law.
        evaluate : callable(points DataFrame) -> DataFrame, optional
            The cycle model: one result row per point, same order, with the
            simulation-result columns of the data contract (``simulate``'s
            output).  Default: in-process :func:`engine_model.simulate` with
            ``self.solver``; the flow layer passes a Dask-backed one.

        Returns
        -------
        DataFrame, n rows (never fewer: failed points are flagged, not dropped)
            ``point_id, speed_rpm, throttle_pct, spark_deg_btdc, lambda,
            brake_torque_nm`` (behind the gearbox: crank torque x eta_trans),
            ``brake_power_kw, air_mass_flow_kg_h, exhaust_temp_k, bsfc_g_kwh,
            fuel_mass_flow_kg_h, knock`` (bool: aborted for knock), ``status``
            (one of :data:`BENCH_STATUSES`), ``status_detail`` (the simulator's
            status or the limit that was hit) and the plan's other columns.
            Measured columns are NaN where ``status != 'ok'``.  ``attrs`` holds
            the bench settings (seed, eta_trans, limits, effects, noise).
        """
        pts = self.simulation_points(plan)
        res = self.default_evaluate(pts) if evaluate is None else evaluate(pts)
        if not isinstance(res, pd.DataFrame) or len(res) != len(pts):
            raise ValueError(f"VirtualBench.measure: evaluate returned {len(res) if hasattr(res, '__len__') else res!r} "
                             f"rows for {len(pts)} points")
        res = res.reset_index(drop=True)
        need = ("brake_torque_nm", "air_mass_flow_kg_h", "fuel_mass_flow_kg_h", "exhaust_temp_k", "knock_index",
                "bmep_bar", "converged", "status")
        missing = [c for c in need if c not in res.columns]
        if missing:
            raise ValueError(f"VirtualBench.measure: evaluate results lack column(s) {missing}")

        base = self._plan(plan)
        out = base.copy()
        sim_status = res["status"].astype(str).to_numpy()
        knock_index = pd.to_numeric(res["knock_index"], errors="coerce").to_numpy(float)
        bmep = pd.to_numeric(res["bmep_bar"], errors="coerce").to_numpy(float)
        converged = res["converged"].astype(bool).to_numpy()
        failed = np.array([s.startswith("failed") for s in sim_status])
        knock = (knock_index >= self.knock_limit) & ~failed
        status = np.full(len(out), "ok", dtype=object)
        detail = sim_status.astype(object).copy()
        status[~converged] = "not_converged"
        low = (bmep < self.min_bmep_bar) & ~failed
        status[low] = "low_load_abort"
        detail[low] = [f"BMEP {b:.2f} bar below the holdable {self.min_bmep_bar:g} bar" for b in bmep[low]]
        status[knock] = "knock_abort"
        detail[knock] = [f"knock index {k:.2f} >= {self.knock_limit:g}" for k in knock_index[knock]]
        status[failed] = "failed"

        out["brake_torque_nm"] = res["brake_torque_nm"].to_numpy(float) * self.eta_trans
        for col in ("air_mass_flow_kg_h", "fuel_mass_flow_kg_h", "exhaust_temp_k"):
            out[col] = res[col].to_numpy(float)
        out["brake_power_kw"] = out["brake_torque_nm"] * 2.0 * math.pi * out["speed_rpm"] / 60.0 / 1e3
        if self.effects:
            # measurement-chain effects see the echoed simulation inputs (ambient state, effect columns)
            echo = [c for c in res.columns if c in ("p_amb_pa", "t_amb_k") or c.startswith("gap_")]
            echo = [c for c in echo if c not in out.columns]
            tmp = pd.concat([out, res[echo]], axis=1)
            tmp = effects_lib.post_effects(tmp, self.effects, eta_base=self.eta_trans, spec=self.spec)
            out = tmp.drop(columns=echo).reset_index(drop=True)
        out = apply_noise(out, self.noise, self.seed)
        bad = status != "ok"
        out.loc[bad, list(MEASURED_COLUMNS)] = np.nan
        out["knock"] = knock
        out["status"] = status.astype(str)
        out["status_detail"] = detail.astype(str)
        first = ["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda", *MEASURED_COLUMNS,
                 "knock", "status", "status_detail"]
        out = out[first + [c for c in out.columns if c not in first]]
        out.attrs = {"source": "virtual_bench", "seed": int(self.seed), "eta_trans": self.eta_trans,
                     "knock_limit": self.knock_limit, "min_bmep_bar": self.min_bmep_bar,
                     "effects": self.effects, "noise": dict(self.noise.__dict__),
                     "spec_hash": self.spec.spec_hash(),
                     "n_ok": int((status == "ok").sum()), "n_knock_abort": int(knock.sum())}
        return out


def run_virtual_bench(plan: pd.DataFrame, spec: EngineSpec | None = None, *, law=None, effects=None,
                      noise: NoiseModel | None = None, eta_trans: float = 0.95, knock_limit: float = 1.0,
                      min_bmep_bar: float = MIN_BMEP_BAR, solver: SolverSettings | None = None, seed: int = 0,
                      evaluate: Callable[[pd.DataFrame], pd.DataFrame] | None = None) -> pd.DataFrame:
    """Function twin of :meth:`VirtualBench.measure` (same parameters, same result)."""
    bench = VirtualBench(spec=spec, law=BurnLaw() if law is None else law, effects=effects,
                         noise=NoiseModel() if noise is None else noise, eta_trans=eta_trans,
                         knock_limit=knock_limit, min_bmep_bar=min_bmep_bar,
                         solver=SolverSettings() if solver is None else solver, seed=seed)
    return bench.measure(plan, evaluate=evaluate)
