"""Global map-wide combustion model: (BDUR10-90, m) = f(load, speed, spark, lambda).

The paper ends where this starts: "by applying the method on a set of points
predefined by a DOE plan, form an overall model relating load, speed and spark
advance to combustion parameters over the whole map" [P].  :class:`MapModel`
takes the combustion parameters identified at DOE points and fits each output
with several model families (:mod:`engine_model.globalmodel.surrogates`: a polynomial
response surface with PRESS term selection, a Gaussian process), chooses the
family per output by K-fold cross-validation, and predicts with uncertainty.

With ``parametrisation='phasing'`` the fitted outputs are the CA50 offset
(ignition-to-CA50 angle) and m, and BDUR10-90 is derived from them: sweep
identification without a pressure sensor fixes the phasing far better than
either burn parameter (measured in docs/sections/mapmodel.md).

Its ``predict(points)`` has the same protocol as the truth engine's
:meth:`engine_model.bench.burnlaw.BurnLaw.predict`, so either can drive the
table-building code.

Inputs are coded to -1..1 over the training range.  By default spark enters as
its offset from the MBT prior :func:`engine_model.priors.spark_estimate` (the
plans sweep spark *around* MBT, which moves 35 deg over the map; the offset
makes the factor space nearly rectangular and the response smoother).
Factors constant in the training data are left out of the fit and recorded;
a prediction at another value is flagged as extrapolation.

A saved model (JSON) carries the engine spec hash; :meth:`MapModel.load` with
a spec, or :meth:`MapModel.check_spec`, refuses a model fitted for another
engine.

References
----------
.. [P] Mrda et al., MVM2012-024, conclusions.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from engine_model import io as _io
from engine_model import wiebe
from engine_model.globalmodel.blas import single_thread_blas
from engine_model.contracts import COMBUSTION_INPUTS, COMBUSTION_OUTPUTS, check_combustion_inputs
from engine_model.globalmodel.surrogates import FAMILIES, make_family

__all__ = ["MapModel", "fit_map_model", "load", "kfold_indices", "FORMAT", "PARAMETRISATIONS", "CA50_OFFSET",
           "ca50_offset_deg", "bdur_10_90_from_ca50_offset"]

#: ``kind`` tag and version of the saved JSON (version 2 adds the load table, version 3 the parametrisation;
#: version 1 and 2 files still load, as the 'bdur_m' parametrisation).
FORMAT = {"kind": "mbc_map_model", "version": 3}
_READABLE_VERSIONS = (1, 2, 3)

#: Ignition-to-CA50 angle [deg]: CA50 [deg ATDC] + spark [deg BTDC], the combustion phasing of a Wiebe burn
#: that starts at the spark (``CA50 - SOC`` in the issue's words, SOC counted in deg ATDC).
CA50_OFFSET = "ca50_offset_deg"
#: What the model fits: 'bdur_m' fits BDUR10-90 and m; 'phasing' fits the CA50 offset and m and derives
#: BDUR10-90 from them (:func:`bdur_10_90_from_ca50_offset`).
PARAMETRISATIONS = ("bdur_m", "phasing")


def ca50_offset_deg(bdur_10_90_deg, m):
    """Ignition-to-CA50 angle [deg] of a Wiebe burn: ``BDUR (ln2/a)^(1/(m+1))`` with BDUR from BDUR10-90 (eq 4-5)."""
    return wiebe.burn_angles(0.0, bdur_10_90_deg, m)["ca50_deg_atdc"]


def bdur_10_90_from_ca50_offset(offset_deg, m):
    """BDUR10-90 [deg] of the Wiebe burn with ignition-to-CA50 angle ``offset_deg`` [deg] and shape ``m``."""
    unit50 = wiebe.angle_at_fraction(0.5, 0.0, 1.0, m)          # CA50 of a unit-duration burn from SOC 0
    return wiebe.bdur_to_bdur_10_90(np.asarray(offset_deg, float) / unit50, m)

_SPARK_REFS = ("estimate", "absolute")
_EXTRAPOLATION = ("clamp", "linear", "extend")
_FD_STEP = 0.02  # coded-unit step of the one-sided gradient used by extrapolation='linear' (1 % of the range)
_LINEAR_REACH = 1.0  # extrapolation='linear' continues at most this far beyond the box [coded units], then flat
_STD_SCALE_RANGE = (0.5, 5.0)  # limits of the CV calibration factor of the predicted std


def kfold_indices(n: int, k: int, seed: int) -> list[np.ndarray]:
    """Test-index arrays of a seeded, shuffled K-fold split of ``n`` rows (k <= n)."""
    perm = np.random.default_rng(seed).permutation(n)
    return [np.sort(f) for f in np.array_split(perm, k)]


def _spec_hash(spec) -> str | None:
    if spec is None:
        return None
    if isinstance(spec, str):
        return spec
    return spec.spec_hash()


class MapModel:
    """Global model of BDUR10-90 and Wiebe m over the operating map.

    Parameters
    ----------
    families : sequence of str
        Candidate families per output (``'poly'``, ``'gp'``).
    factors : sequence of str
        Input factors, a subset of ``throttle_pct, speed_rpm, spark_deg_btdc,
        lambda``.
    outputs : sequence of str
        Outputs to model (default ``bdur_10_90_deg, wiebe_m``).
    spark_reference : {'estimate', 'absolute'}
        Spark enters as ``spark - spark_estimate(speed, throttle)`` [deg] or
        as is.
    k_folds : int
        Folds of the cross-validation that chooses the family (>= 2; reduced
        to n if fewer points).
    seed : int
        Seed of the fold split and of the GP restarts.
    extrapolation : {'clamp', 'linear', 'extend'}
        Outside the training box: 'clamp' evaluates the model at the nearest
        point of the box (a flat continuation: a cubic surface cannot run away
        when the table builder searches spark beyond the planned range);
        'linear' continues it along its gradient at that point (first-order
        Taylor continuation: the trend, e.g. a longer burn at more advance,
        carries on, the curvature does not) for up to half the training range
        beyond the edge, flat after that; 'extend' evaluates the surface
        as it is.  Either way the row is flagged.
    load_table : LoadTable, optional
        With a table (:func:`engine_model.globalmodel.load_table.build_load_table`: the
        calibrated simulator's plenum pressure ratio or volumetric efficiency
        over throttle x speed), the throttle factor enters as that *load*
        (coordinate ``load`` in ``ranges_``), not as throttle angle: the burn
        follows charge density and dilution, which are strongly nonlinear in
        throttle at part load.  The table is stored in the model file; its
        spec hash must match the fit's.  A point outside the table's grid is
        flagged as extrapolation.
    parametrisation : {'bdur_m', 'phasing'}
        'bdur_m' (default) fits BDUR10-90 and m.  'phasing' fits the CA50
        offset (ignition-to-CA50 angle, :data:`CA50_OFFSET`, computed from the
        data's BDUR10-90 and m) and m, and predicts BDUR10-90 from the two:
        identification without a pressure sensor pins the phasing much better
        than either burn parameter (their errors are correlated along the
        iso-phasing ridge, docs/sections/mapmodel.md), and MBT follows the
        phasing.  Needs both outputs; ``predict`` adds ``ca50_offset_deg``.
        The per-point std of the offset is read from ``ca50_offset_deg_std``
        if the data have it (the independent BDUR10-90 and m bounds would
        overstate it).

    Attributes (after ``fit``)
    ----------
    chosen_ : dict fitted output -> family (fitted outputs: ``outputs``, or
        ``ca50_offset_deg, wiebe_m`` with ``parametrisation='phasing'``)
    cv_rmse_ : dict output -> {family: K-fold CV RMSE [output unit]}
    std_scale_ : dict output -> factor applied to the chosen family's std so
        that, over the CV folds, std^2 matches the held-out error^2 minus the
        fitted noise variance (clipped to 0.5-5); a polynomial's coefficient
        std ignores the bias of a low-order surface, this puts it back
    models_ : dict output -> fitted estimator
    ranges_ : dict coordinate -> (low, high) in model coordinates (spark as offset; ``load`` in
        place of ``throttle_pct`` with a load table)
    fixed_factors_ : dict factor -> value, factors constant in the data
    n_points_ : int, rows used; excluded_ : list of point ids (or row numbers)
        left out because an output was missing (failed identification)
    spec_hash_ : str or None
    """

    def __init__(self, *, families=("poly", "gp"), factors=COMBUSTION_INPUTS, outputs=COMBUSTION_OUTPUTS,
                 spark_reference: str = "estimate", k_folds: int = 5, seed: int = 0, extrapolation: str = "clamp",
                 load_table=None, output_transform: str = "none", parametrisation: str = "bdur_m"):
        self.families = tuple(families)
        self.factors = tuple(factors)
        self.outputs = tuple(outputs)
        self.spark_reference = spark_reference
        self.k_folds = k_folds
        self.seed = seed
        self.extrapolation = extrapolation
        self.load_table = load_table
        self.output_transform = output_transform
        self.parametrisation = parametrisation

    def _fitted_outputs(self) -> tuple[str, ...]:
        """The outputs the surrogates model (``outputs``, or the CA50 offset and m)."""
        return (CA50_OFFSET, "wiebe_m") if self.parametrisation == "phasing" else self.outputs

    # ------------------------------------------------------------------ inputs
    def _check_settings(self):
        bad = [f for f in self.families if f not in FAMILIES]
        if bad or not self.families:
            raise ValueError(f"MapModel: unknown/empty families {bad or list(self.families)}; "
                             f"choose from {sorted(FAMILIES)}")
        bad = [f for f in self.factors if f not in COMBUSTION_INPUTS]
        if bad or not self.factors or len(set(self.factors)) != len(self.factors):
            raise ValueError(f"MapModel: factors {list(self.factors)} must be distinct names from "
                             f"{list(COMBUSTION_INPUTS)}")
        if self.spark_reference not in _SPARK_REFS:
            raise ValueError(f"MapModel: spark_reference = {self.spark_reference!r}; choose from {_SPARK_REFS}")
        if not (isinstance(self.k_folds, (int, np.integer)) and self.k_folds >= 2):
            raise ValueError(f"MapModel: k_folds = {self.k_folds!r} must be an integer >= 2")
        if not self.outputs:
            raise ValueError("MapModel: no outputs")
        if self.output_transform not in ("none", "log"):
            raise ValueError(f"MapModel: output_transform = {self.output_transform!r}; choose 'none' or 'log'")
        if self.parametrisation not in PARAMETRISATIONS:
            raise ValueError(f"MapModel: parametrisation = {self.parametrisation!r}; choose from {PARAMETRISATIONS}")
        if self.parametrisation == "phasing" and sorted(self.outputs) != sorted(COMBUSTION_OUTPUTS):
            raise ValueError(f"MapModel: parametrisation='phasing' needs outputs {list(COMBUSTION_OUTPUTS)} (the CA50 "
                             f"offset is computed from both), got {list(self.outputs)}")
        if self.extrapolation not in _EXTRAPOLATION:
            raise ValueError(f"MapModel: extrapolation = {self.extrapolation!r}; choose from {_EXTRAPOLATION}")
        if self.load_table is not None:
            from engine_model.globalmodel.load_table import LoadTable
            if not isinstance(self.load_table, LoadTable):
                raise ValueError(f"MapModel: load_table must be an engine_model.globalmodel.load_table.LoadTable, got "
                                 f"{type(self.load_table).__name__}")
            if "throttle_pct" not in self.factors:
                raise ValueError("MapModel: a load_table replaces the throttle factor; 'throttle_pct' is not among "
                                 f"the factors {list(self.factors)}")

    def _model_coords(self, points: pd.DataFrame, who: str) -> dict[str, np.ndarray]:
        x = check_combustion_inputs(points, who)
        if self.spark_reference == "estimate":
            from engine_model.priors import spark_estimate

            x["spark_deg_btdc"] = x["spark_deg_btdc"] - np.atleast_1d(
                spark_estimate(x["speed_rpm"], x["throttle_pct"]))
        out = {f: x[f] for f in self.factors}
        if self.load_table is not None:
            out["load"] = self.load_table(x["throttle_pct"], x["speed_rpm"])
            del out["throttle_pct"]
        return out

    def _coordinates(self) -> tuple[str, ...]:
        """Model coordinates in factor order (``load`` in place of ``throttle_pct`` with a load table)."""
        return tuple("load" if (f == "throttle_pct" and self.load_table is not None) else f for f in self.factors)

    def _coded(self, xm: dict[str, np.ndarray]) -> np.ndarray:
        cols = [2.0 * (xm[f] - lo) / (hi - lo) - 1.0 for f, (lo, hi) in self.ranges_.items()]
        return np.column_stack(cols) if cols else np.zeros((len(next(iter(xm.values()))), 0))

    # ------------------------------------------------------------------ fit
    def fit(self, data: pd.DataFrame, spec=None) -> "MapModel":
        """Fit every output with every family, choose by K-fold CV, refit the winner (see ``_fit``)."""
        with single_thread_blas():
            return self._fit(data, spec)

    def _fit(self, data: pd.DataFrame, spec=None) -> "MapModel":
        """Fit every output with every family, choose by K-fold CV, refit the winner on all rows.

        Parameters
        ----------
        data : DataFrame, n rows
            Factor columns and output columns; optional ``<output>_std``
            (identification uncertainty, same unit, used as per-point noise by
            the GP) and ``point_id``.  Rows with a missing output (failed or
            aborted identification) are left out of that fit and listed in
            ``excluded_``.
        spec : EngineSpec or str, optional
            The engine the data came from (or its hash); stored and checked
            on load.

        Returns
        -------
        self
        """
        self._check_settings()
        if self.load_table is not None:
            self.load_table.check_spec(spec)
        missing = [c for c in self.outputs if c not in data.columns]
        if missing:
            raise ValueError(f"MapModel.fit: data lack output column(s) {missing}")
        xm = self._model_coords(data, "MapModel.fit")
        ys = {o: pd.to_numeric(data[o], errors="coerce").to_numpy(float) for o in self.outputs}
        if self.parametrisation == "phasing":
            b, m = ys.pop("bdur_10_90_deg"), ys.pop("wiebe_m")
            good = np.isfinite(b) & np.isfinite(m) & (b > 0) & (m > -1)
            off = np.full(len(b), np.nan)
            off[good] = ca50_offset_deg(b[good], m[good])
            bad = (np.isfinite(b) & np.isfinite(m)) & ~good
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise ValueError(f"MapModel.fit: row {i}: bdur_10_90_deg = {b[i]:g}, wiebe_m = {m[i]:g}; the "
                                 "'phasing' parametrisation needs BDUR10-90 > 0 and m > -1")
            ys = {CA50_OFFSET: off, "wiebe_m": m}
        ok = np.all([np.isfinite(v) for v in ys.values()], axis=0)
        ids = data["point_id"].astype(str).to_numpy() if "point_id" in data.columns else np.arange(len(data))
        self.excluded_ = [str(i) for i in ids[~ok]]
        n = int(ok.sum())
        if n < 6:
            raise ValueError(f"MapModel.fit: only {n} rows with finite outputs (need >= 6); "
                             f"excluded: {self.excluded_[:10]}")
        self.ranges_, self.fixed_factors_ = {}, {}
        if self.load_table is not None:
            xd = check_combustion_inputs(data, "MapModel.fit")
            out = ~self.load_table.covers(xd["throttle_pct"], xd["speed_rpm"]) & ok
            if out.any():
                i = int(np.flatnonzero(out)[0])
                raise ValueError(f"MapModel.fit: data row {i} (throttle {xd['throttle_pct'][i]:g} %, speed "
                                 f"{xd['speed_rpm'][i]:g} rpm) lies outside the load table's grid (throttle "
                                 f"{self.load_table.throttle_pct[0]:g}-{self.load_table.throttle_pct[-1]:g} %, speed "
                                 f"{self.load_table.speed_rpm[0]:g}-{self.load_table.speed_rpm[-1]:g} rpm); "
                                 "rebuild the table over the data")
        for f in self._coordinates():
            v = xm[f][ok]
            lo, hi = float(v.min()), float(v.max())
            if hi - lo <= 1e-9 * max(1.0, abs(hi)):
                self.fixed_factors_[f] = lo
            else:
                self.ranges_[f] = (lo, hi)
        if not self.ranges_:
            raise ValueError("MapModel.fit: every factor is constant in the data; nothing to model")
        x = self._coded({f: xm[f][ok] for f in self.ranges_})
        k = min(self.k_folds, n)
        folds = kfold_indices(n, k, self.seed)
        self.cv_rmse_, self.chosen_, self.models_, self.std_scale_ = {}, {}, {}, {}
        for o in self._fitted_outputs():
            y_out = ys[o][ok]
            ystd = None
            if f"{o}_std" in data.columns:
                ystd = pd.to_numeric(data[f"{o}_std"], errors="coerce").to_numpy(float)[ok]
            if self.output_transform == "log":
                if np.any(y_out <= 0):
                    i = int(np.flatnonzero(y_out <= 0)[0])
                    raise ValueError(f"MapModel.fit: output_transform='log' needs {o} > 0; row {i} has {y_out[i]!r}")
                y = np.log(y_out)
                ystd = None if ystd is None else ystd / y_out      # delta method: std of log y
            else:
                y = y_out
            scores, calib = {}, {}
            for fam in self.families:
                err, sd, noise = np.empty(n), np.empty(n), np.empty(n)
                for test in folds:
                    train = np.setdiff1d(np.arange(n), test)
                    est = make_family(fam, self.seed).fit(x[train], y[train],
                                                          None if ystd is None else ystd[train])
                    mean, sd[test] = est.predict(x[test])
                    noise[test] = est.noise_variance() + (0.0 if ystd is None else np.nan_to_num(ystd[test]) ** 2)
                    if self.output_transform == "log":   # CV error, std and noise in the output's own unit
                        mean = np.exp(mean)
                        sd[test] *= mean
                        noise[test] *= mean ** 2
                    err[test] = mean - y_out[test]
                scores[fam] = float(math.sqrt(np.mean(err**2)))
                # held-out err^2 = (model error)^2 + noise: scale the std so that it matches the model error
                ratio = (np.mean(err**2) - np.mean(noise)) / max(float(np.mean(sd**2)), 1e-300)
                calib[fam] = float(math.sqrt(min(max(ratio, _STD_SCALE_RANGE[0] ** 2), _STD_SCALE_RANGE[1] ** 2)))
            best = min(scores, key=scores.get)
            self.cv_rmse_[o] = scores
            self.chosen_[o] = best
            self.std_scale_[o] = calib[best]
            self.models_[o] = make_family(best, self.seed).fit(x, y, ystd)
        self.n_points_ = n
        self.spec_hash_ = _spec_hash(spec)
        return self

    # ------------------------------------------------------------------ use
    def _check_fitted(self):
        if not hasattr(self, "models_"):
            raise ValueError("MapModel: not fitted (call fit or MapModel.load)")

    def predict(self, points: pd.DataFrame) -> pd.DataFrame:
        """Predicted outputs with uncertainty.

        Parameters
        ----------
        points : DataFrame, m rows
            ``throttle_pct`` [%], ``speed_rpm`` [rpm], ``spark_deg_btdc``
            [deg BTDC], ``lambda`` [-].

        Returns
        -------
        DataFrame, m rows, same index
            Each output (e.g. ``bdur_10_90_deg`` [deg], ``wiebe_m`` [-]), its
            ``<output>_std`` (1-sigma uncertainty of the model mean) and
            ``extrapolation`` (True where a factor leaves the training range
            by more than 1 % of it, or a fixed factor differs).
        """
        self._check_fitted()
        xm = self._model_coords(points, "MapModel.predict")
        x = self._coded(xm)
        out = {}
        xe = x if self.extrapolation == "extend" else np.clip(x, -1.0, 1.0)
        for o in self._fitted_outputs():
            with single_thread_blas():
                mean, std = self.models_[o].predict(xe)
                if self.extrapolation == "linear":
                    mean = mean + self._linear_continuation(self.models_[o], x, xe, mean)
            if self.output_transform == "log":
                mean = np.exp(mean)
                std = std * mean                           # delta method
            out[o], out[f"{o}_std"] = mean, std * self.std_scale_.get(o, 1.0)
        if self.parametrisation == "phasing":
            out = self.burn_from_phasing(out)
        extra = np.zeros(len(points), dtype=bool)
        if x.size:
            extra |= np.any(np.abs(x) > 1.02, axis=1)
        for f, v in self.fixed_factors_.items():
            extra |= np.abs(xm[f] - v) > 1e-6 * max(1.0, abs(v))
        if self.load_table is not None:
            xp = check_combustion_inputs(points, "MapModel.predict")
            extra |= ~self.load_table.covers(xp["throttle_pct"], xp["speed_rpm"])
        out["extrapolation"] = extra
        return pd.DataFrame(out, index=points.index)

    def burn_from_phasing(self, fitted: dict) -> dict:
        """(CA50 offset, m) predictions -> outputs in ``self.outputs`` order, BDUR10-90 with a delta-method std
        (offset and m errors taken as independent), then the offset and its std.  BDUR10-90 is NaN where the
        predicted offset is <= 0 or m <= -1 (possible only without the log transform, far outside the data)."""
        off, m = fitted[CA50_OFFSET], fitted["wiebe_m"]
        # an untransformed surface extended or continued beyond the data can leave the Wiebe domain: no burn there
        ok = np.isfinite(off) & np.isfinite(m) & (off > 0) & (m > -1 + 1e-3)
        b, b_std = np.full(len(off), np.nan), np.full(len(off), np.nan)
        o, mm, h = off[ok], m[ok], 1e-4
        b[ok] = bdur_10_90_from_ca50_offset(o, mm)
        db_dm = (bdur_10_90_from_ca50_offset(o, mm + h) - bdur_10_90_from_ca50_offset(o, mm - h)) / (2 * h)
        b_std[ok] = np.hypot(b[ok] / o * fitted[f"{CA50_OFFSET}_std"][ok], db_dm * fitted["wiebe_m_std"][ok])
        full = {"bdur_10_90_deg": b, "bdur_10_90_deg_std": b_std, "wiebe_m": m, "wiebe_m_std": fitted["wiebe_m_std"]}
        out = {}
        for o in self.outputs:
            out[o], out[f"{o}_std"] = full[o], full[f"{o}_std"]
        out[CA50_OFFSET], out[f"{CA50_OFFSET}_std"] = off, fitted[f"{CA50_OFFSET}_std"]
        return out

    @staticmethod
    def _linear_continuation(est, x: np.ndarray, xc: np.ndarray, mean_c: np.ndarray) -> np.ndarray:
        """g . (x - xc) for rows outside the box: g the one-sided (inward) difference gradient at the clamped xc."""
        add = np.zeros(len(x))
        outside = np.any(np.abs(x - xc) > 0.0, axis=1)
        if not outside.any():
            return add
        xo, co, mo = x[outside], xc[outside], mean_c[outside]
        for j in range(x.shape[1]):
            dx = np.clip(xo[:, j] - co[:, j], -_LINEAR_REACH, _LINEAR_REACH)
            sel = dx != 0.0
            if not sel.any():
                continue
            step = -_FD_STEP * np.sign(dx[sel])          # step back into the box
            probe = co[sel].copy()
            probe[:, j] += step
            grad = (mo[sel] - est.predict(probe)[0]) / (-step)
            part = np.zeros(len(xo))
            part[sel] = grad * dx[sel]
            add[outside] += part
        return add

    def cv_table(self) -> pd.DataFrame:
        """K-fold CV RMSE per fitted output and family: ``output, family, cv_rmse, chosen``."""
        self._check_fitted()
        rows = [{"output": o, "family": f, "cv_rmse": v, "chosen": f == self.chosen_[o]}
                for o, s in self.cv_rmse_.items() for f, v in s.items()]
        return pd.DataFrame(rows)

    def check_spec(self, spec) -> None:
        """ValueError unless the model was fitted for ``spec`` (EngineSpec or hash).

        A model fitted without a spec (``spec_hash_`` None) passes with a warning.
        """
        self._check_fitted()
        want = _spec_hash(spec)
        if self.spec_hash_ is None:
            warnings.warn(f"MapModel: the model records no engine spec hash (fitted without spec=); cannot "
                          f"confirm it belongs to spec {want}", stacklevel=2)
            return
        if want != self.spec_hash_:
            raise ValueError(f"MapModel: model was fitted for engine spec {self.spec_hash_}, not for spec "
                             f"{want}; refit it on data of this engine")

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict:
        self._check_fitted()
        return {**FORMAT, "families": list(self.families), "factors": list(self.factors),
                "outputs": list(self.outputs), "spark_reference": self.spark_reference,
                "k_folds": self.k_folds, "seed": self.seed, "extrapolation": self.extrapolation,
                "spec_hash": self.spec_hash_,
                "load_table": None if self.load_table is None else self.load_table.to_dict(),
                "output_transform": self.output_transform, "parametrisation": self.parametrisation,
                "ranges": [[k, *v] for k, v in self.ranges_.items()],  # a list: JSON sorts keys, order matters
                "fixed_factors": self.fixed_factors_,
                "n_points": self.n_points_, "excluded": self.excluded_, "cv_rmse": self.cv_rmse_,
                "chosen": self.chosen_, "std_scale": self.std_scale_, "models": {o: m.to_dict() for o, m in self.models_.items()}}

    def save(self, path) -> Path:
        """Write the fitted model as JSON (atomically)."""
        return _io.write_json(self.to_dict(), path)

    @classmethod
    def from_dict(cls, d: dict, source: str = "<dict>") -> "MapModel":
        if d.get("kind") != FORMAT["kind"]:
            raise ValueError(f"{source}: not a map model file (kind = {d.get('kind')!r}, expected "
                             f"{FORMAT['kind']!r})")
        if d.get("version") not in _READABLE_VERSIONS:
            raise ValueError(f"{source}: map model format version {d.get('version')!r}; this code reads "
                             f"{list(_READABLE_VERSIONS)}")
        try:
            table = d.get("load_table")
            if table is not None:
                from engine_model.globalmodel.load_table import LoadTable
                table = LoadTable.from_dict(table)
            obj = cls(families=d["families"], factors=d["factors"], outputs=d["outputs"],
                      spark_reference=d["spark_reference"], k_folds=d["k_folds"], seed=d["seed"],
                      extrapolation=d.get("extrapolation", "clamp"), load_table=table,
                      output_transform=d.get("output_transform", "none"),
                      parametrisation=d.get("parametrisation", "bdur_m"))
            if obj.parametrisation not in PARAMETRISATIONS:
                raise ValueError(f"{source}: parametrisation {obj.parametrisation!r} is not one of "
                                 f"{PARAMETRISATIONS}")
            obj.spec_hash_ = d["spec_hash"]
            obj.ranges_ = {k: (float(lo), float(hi)) for k, lo, hi in d["ranges"]}
            obj.fixed_factors_ = {k: float(v) for k, v in d["fixed_factors"].items()}
            obj.n_points_ = int(d["n_points"])
            obj.excluded_ = list(d["excluded"])
            obj.cv_rmse_ = d["cv_rmse"]
            obj.chosen_ = d["chosen"]
            obj.std_scale_ = {k: float(v) for k, v in d.get("std_scale", {}).items()}
            obj.models_ = {o: FAMILIES[m["family"]].from_dict(m) for o, m in d["models"].items()}
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{source}: map model file is incomplete or malformed ({exc!r})") from None
        return obj

    @classmethod
    def load(cls, path, spec=None) -> "MapModel":
        """Read a saved model; with ``spec``, refuse a model of another engine (ValueError)."""
        p = Path(path)
        if not p.is_file():
            raise ValueError(f"{p}: map model file not found")
        try:
            d = json.loads(p.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{p}: not valid JSON ({exc})") from None
        obj = cls.from_dict(d, str(p))
        if spec is not None:
            try:
                obj.check_spec(spec)
            except ValueError as exc:
                raise ValueError(f"{p}: {exc}") from None
        return obj


def fit_map_model(data: pd.DataFrame, spec=None, **settings) -> MapModel:
    """Function twin: ``MapModel(**settings).fit(data, spec)``."""
    return MapModel(**settings).fit(data, spec)


def load(path, spec=None) -> MapModel:
    """Function twin of :meth:`MapModel.load` (used by :func:`engine_model.tables.load_model`)."""
    return MapModel.load(path, spec=spec)
