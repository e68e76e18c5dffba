"""Structural error model of the base calibration: per-point burn scatter as a correlated reading error.

The smooth global combustion law of the base (:mod:`engine_model.gap.linear`) cannot follow a real
engine's burn point by point.  On the benchmark's noiseless null case what it leaves is mostly a
burn-duration deviation per point (0.23-0.3 deg BDUR10-90 rms, docs/sections/gap.md), which moves torque,
exhaust temperature and (through the exhaust tuning) airflow *together*, along the point's BDUR10-90
sensitivity.  As a reading error it is correlated across the outputs of one point and independent
between points:

    C_i = I + tau^2 u_i u_i^T          (readings of point i, in sigma units)

with ``u_i`` the point's whitened BDUR10-90 sensitivity [sigma per deg] and ``tau`` the scatter
[deg].  A generalised least-squares fit whitens every point's block by ``C_i^(-1/2)``; because the
correction is rank one, the symmetric inverse square root has the closed form

    C_i^(-1/2) = I - (1 - 1/sqrt(1 + tau^2 |u_i|^2)) u_i u_i^T / |u_i|^2,

which only shrinks the component of a reading pattern along ``u_i`` (a burn-like contrast) and leaves
the rest of the pattern as it is.  Pure noise drawn as N(0, I) in the whitened space has exactly the
covariance ``C_i`` in sigma units, so a Monte Carlo threshold computed there covers the structural
misfit as modelled.

The model-discrimination design (:mod:`engine_model.gap.design`) and the diagnosis
(:func:`engine_model.gap.diagnose.diagnose`) use the same whitening, so a plan is judged by the
contrasts the diagnosis will count.

References
----------
Aitken, A. C. (1935). On least squares and linear combination of observations. Proc. R. Soc. Edinb. 55,
42-48 (generalised least squares).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["BURN_SCATTER_DEG", "MODEL_ERROR", "MODEL_ERROR_REMAINDER", "MODEL_ERROR_LEVEL",
           "HELDOUT_ERROR_FACTOR", "level_columns", "ErrorModel", "ERROR_MODELS",
           "DEFAULT_ERROR_MODEL", "get_error_model", "burn_whitener", "whiten_blocks", "whiten_observations",
           "null_base_residuals"]

#: Diagonal structural uncertainty of the base model (1 sigma), added in quadrature to the measurement
#: uncertainty: what a smooth global combustion law cannot follow of a real engine's point-to-point
#: combustion, treated as independent per reading.  Measured on the virtual bench's null case (no effect, no
#: noise, 24-point DOE): after the base calibration the residual is 0.42 % rms on torque, 4.8 K on exhaust
#: temperature, 0.13 % on airflow and 0.26 % on fuel flow; rounded up here.  Without it, the base model's own
#: misfit would make every remaining residual look significant and no effect could ever be claimed.
MODEL_ERROR = {
    "air_mass_flow_kg_h": ("rel", 0.002),
    "brake_torque_nm": ("rel", 0.004),
    "exhaust_temp_k": ("abs", 5.0),
    "fuel_mass_flow_kg_h": ("rel", 0.003),
    "bsfc_g_kwh": ("rel", 0.005),
}

#: What is left of the base's structural misfit once the per-point burn deviation is carried by the
#: burn-scatter covariance (1 sigma, in quadrature with the measurement).  Measured on the gap benchmark's
#: noiseless null case on the default engine (1D gas exchange), the default 32-point plan of
#: ``mbc gap-plan --points 32`` (2026-11-27; 5040-12355 rpm, 30-100 % throttle) and the map-wide base with
#: Wiebe m offset: the base residual per point is split into a BDUR10-90 deviation along the point's burn
#: direction (weighted by the measurement sigma) and a remainder, 0.31 % torque, 2.2 K exhaust temperature,
#: 0.011 % airflow and 0.010 % fuel flow rms; rounded up here.  (On the plan of 2026-11-26: 0.21 % and 1.5 K.)
#: Measure it again whenever the default plan or the base changes: a remainder set below the base's real
#: misfit makes a pure-noise gap look established and an exact candidate's remainder look too large.
MODEL_ERROR_REMAINDER = {
    "air_mass_flow_kg_h": ("rel", 0.001),
    "brake_torque_nm": ("rel", 0.0035),
    "exhaust_temp_k": ("abs", 2.5),
    "fuel_mass_flow_kg_h": ("rel", 0.001),
    "bsfc_g_kwh": ("rel", 0.0035),    # not measured: as torque (bsfc = fuel / power, fuel flow 0.01 %)
}

#: The part of the base's structural misfit that all points of one channel share (a level the smooth burn law
#: cannot set for every channel at once), 1 sigma.  Measured on the gap benchmark's noiseless null case on the
#: default engine (1D gas exchange) and the default 32-point plan of ``mbc gap-plan --points 32`` (2026-11-29,
#: 5040-12355 rpm, 30-100 % throttle): one level per channel fitted beside the base gives torque +0.27 %,
#: exhaust temperature +3.8 K, airflow and fuel flow -0.002 %; rounded up, the last two left out.  It enters
#: only the directed test of an established gap (:mod:`engine_model.gap.noise`): a candidate whose improvement
#: such a level could give is no evidence of a gap.
MODEL_ERROR_LEVEL = {
    "brake_torque_nm": ("rel", 0.003),
    "exhaust_temp_k": ("abs", 4.0),
}

#: Per-point burn-duration scatter of a real engine about the base's smooth law [deg CA BDUR10-90]:
#: 0.34 deg rms per point on the benchmark's noiseless null case (above; 0.33 on the earlier plan),
#: rounded up.
BURN_SCATTER_DEG = 0.35

#: Factor on the structural error of the default error model (the remainder and the burn scatter above) in the
#: diagnosis.  The constants above were measured in-sample on the noiseless null; the claim rule judges held-out
#: chi2, which sees more of the same misfit.  Measured on the gap benchmark's null case with noise (default
#: 32-point plan of 2026-11-29, noise seeds 6000-6059, used for nothing else): the null's mean held-out chi2 over
#: its pure-noise expectation is 1.138 at factor 1.0, 1.068 at 1.1, 1.036 at 1.15, 1.007 at 1.2, 0.955 at 1.3;
#: the factor is the one that makes the two equal.  The discrimination plan (:mod:`engine_model.gap.design`)
#: keeps the in-sample scatter.
HELDOUT_ERROR_FACTOR = 1.2


def burn_whitener(u: np.ndarray, tau: float) -> np.ndarray:
    """Symmetric inverse square root of ``I + tau^2 u u^T`` per point.

    Parameters
    ----------
    u : ndarray (..., o)
        Whitened BDUR10-90 sensitivity of each point's readings [sigma per deg CA]; non-finite
        entries count as 0 (a reading the burn does not move).
    tau : float
        Burn-duration scatter [deg CA], >= 0.

    Returns
    -------
    ndarray (..., o, o)
        ``W`` with ``W @ (I + tau^2 u u^T) @ W.T = I``; the identity where ``u = 0`` or ``tau = 0``.
    """
    if not tau >= 0:
        raise ValueError(f"burn_whitener: tau = {tau!r} deg must be >= 0")
    u = np.where(np.isfinite(u), np.asarray(u, dtype=float), 0.0)
    uu = np.einsum("...o,...o->...", u, u)
    safe = np.where(uu > 0, uu, 1.0)
    c = np.where(uu > 0, (1.0 - 1.0 / np.sqrt(1.0 + tau**2 * uu)) / safe, 0.0)
    eye = np.eye(u.shape[-1])
    return eye - c[..., None, None] * np.einsum("...o,...p->...op", u, u)


def whiten_blocks(blocks: np.ndarray, u: np.ndarray, tau: float) -> np.ndarray:
    """Whiten per-point blocks of readings: ``W_i @ blocks[i]``.

    Parameters
    ----------
    blocks : ndarray (n, o) or (n, o, q)
        Per point, readings (or sensitivity columns) in sigma units.
    u : ndarray (n, o)
        Whitened BDUR10-90 sensitivity per point [sigma per deg CA].
    tau : float
        Burn-duration scatter [deg CA].

    Returns
    -------
    ndarray, same shape as ``blocks``
    """
    w = burn_whitener(u, tau)
    b = np.asarray(blocks, dtype=float)
    return np.einsum("nop,np...->no...", w, b)


def whiten_observations(values: np.ndarray, point: np.ndarray, output: np.ndarray, u: np.ndarray,
                        tau: float) -> np.ndarray:
    """Whiten a flat observation vector (or matrix) whose rows are (point, output) readings.

    Only the readings present are whitened together: point ``i``'s block uses ``u[i]`` restricted to
    the outputs it has (a missing reading neither carries nor receives burn scatter).

    Parameters
    ----------
    values : ndarray (nobs,) or (nobs, q)
        Readings or sensitivity rows in sigma units.
    point, output : ndarray of int (nobs,)
        Point and output index of each row.
    u : ndarray (n, o)
        Whitened BDUR10-90 sensitivity per point and output [sigma per deg CA].
    tau : float
        Burn-duration scatter [deg CA].

    Returns
    -------
    ndarray, same shape as ``values``
    """
    v = np.asarray(values, dtype=float)
    point = np.asarray(point)
    output = np.asarray(output)
    n, o = u.shape
    dense = np.zeros((n, o) + v.shape[1:])
    dense[point, output] = v
    mask = np.zeros((n, o))
    mask[point, output] = 1.0
    wd = whiten_blocks(dense, u * mask, tau)
    return wd[point, output]


@dataclass(frozen=True)
class ErrorModel:
    """Structural error model of the base calibration and the claim rule it supports.

    Parameters
    ----------
    name : str
    model_error : dict
        Diagonal structural uncertainty per output, ``('rel', fraction)`` or ``('abs', value)`` in the
        output's unit, added in quadrature to the measurement uncertainty.
    burn_scatter_deg : float
        Per-point burn-duration scatter carried as the correlated covariance ``tau^2 u u^T`` [deg CA];
        0: none (independent readings).
    doc : str
    level_error : dict
        Structural error shared by all points of a channel (one level per channel, 1 sigma), ``('rel',
        fraction)`` or ``('abs', value)``; only the directed test of an established gap uses it (empty: no
        directed test).
    """

    name: str
    model_error: dict = field(default_factory=dict)
    burn_scatter_deg: float = 0.0
    doc: str = ""
    level_error: dict = field(default_factory=dict)

    def __post_init__(self):
        if not self.burn_scatter_deg >= 0:
            raise ValueError(f"ErrorModel {self.name!r}: burn_scatter_deg = {self.burn_scatter_deg!r} must be >= 0")


#: Error models of the diagnosis (:func:`engine_model.gap.diagnose.diagnose`, ``error_model=``).
ERROR_MODELS = {m.name: m for m in (
    ErrorModel("burn_scatter", {k: (kind, v * HELDOUT_ERROR_FACTOR) for k, (kind, v) in MODEL_ERROR_REMAINDER.items()},
               BURN_SCATTER_DEG * HELDOUT_ERROR_FACTOR,
               "per-point burn scatter as a correlated reading error (GLS), a diagonal remainder and a level "
               "per channel", MODEL_ERROR_LEVEL),
    ErrorModel("diagonal", MODEL_ERROR, 0.0, "structural error in quadrature per reading"),
)}

#: Error model of :func:`engine_model.gap.diagnose.diagnose` when none is given.  'burn_scatter' since
#: 2026-11-25: with the discriminating plan and the curved base it names the withheld effect in 91-93 % of
#: the realistic-magnitude trials and claims an effect in 9.1 % of 340 null trials, where 'diagonal' (the
#: earlier default, with Sobol' points) claims one in 26 % of 220 (docs/sections/gap.md, "Structural error
#: model").
DEFAULT_ERROR_MODEL = "burn_scatter"


def get_error_model(model: "str | ErrorModel") -> ErrorModel:
    """The :class:`ErrorModel` called ``model`` (or ``model`` itself); ValueError listing the valid names."""
    if isinstance(model, ErrorModel):
        return model
    if model not in ERROR_MODELS:
        raise ValueError(f"error model {model!r} unknown; valid: {sorted(ERROR_MODELS)}")
    return ERROR_MODELS[model]




def null_base_residuals(prob, a_sig: np.ndarray, u: np.ndarray | None, tau: float, n_points: int, n_draws: int,
                        seed: int) -> np.ndarray:
    """Base-fit residuals of pure-noise data sets on a diagnosis problem, in diagonal sigma units.

    Noise is drawn with the error model's covariance (unit diagonal plus ``tau^2 u u^T`` per point when
    ``tau > 0``), whitened as the diagnosis whitens, the base columns are refitted (with the prior
    pseudo-observations, which get their own unit noise) and the residual is mapped back to sigma units.

    Parameters
    ----------
    prob : FitProblem
        The diagnosis problem (whitened; rows with ``point < 0`` are prior pseudo-observations, last).
    a_sig : (n_measured_rows, p)
        The measured rows' columns before whitening.
    u, tau
        Burn direction per point and output (or None) and the burn scatter [deg].

    Returns
    -------
    (n_measured_rows, n_draws)
    """
    real = prob.point >= 0
    pr, orr = prob.point[real], prob.output[real]
    nb = prob.base_cols
    rng = np.random.default_rng(seed)
    e = rng.standard_normal((pr.size, n_draws))
    ew = e
    if tau > 0 and u is not None:
        g = rng.standard_normal((n_points, n_draws))
        e = e + tau * u[pr, orr][:, None] * g[pr]
        ew = whiten_observations(e, pr, orr, u, tau)
    prior_noise = rng.standard_normal((prob.r.size - pr.size, n_draws))
    if not nb:
        return e
    coef = np.linalg.lstsq(prob.a[:, nb], np.vstack([ew, prior_noise]), rcond=None)[0]
    return e - a_sig[:, nb] @ coef


def level_columns(outputs: list[str], y: np.ndarray, sig: np.ndarray, point: np.ndarray, output: np.ndarray,
                  level_error: dict, u: np.ndarray | None, tau: float) -> np.ndarray:
    """Whitened columns of a structural level per channel, scaled to one sigma of ``level_error``.

    Parameters
    ----------
    outputs : list of str
        The diagnosis' channels (column order of ``y`` and ``sig``).
    y, sig : ndarray (n, o)
        Measured values and their diagonal sigma per point and channel.
    point, output : ndarray of int (nobs,)
        Point and channel of each measured row.
    level_error : dict
        ``channel -> ('rel', fraction) | ('abs', value)``; channels not named get no column.
    u, tau
        Burn direction per point and channel (or None) and the burn scatter [deg]: the columns are whitened
        as the readings are.

    Returns
    -------
    ndarray (nobs, q)
        One column per channel named in ``level_error`` and present in ``outputs``; a draw ``cols @ g`` with
        ``g ~ N(0, I)`` is a level error of the stated size in the whitened space.
    """
    cols = []
    for k, c in enumerate(outputs):
        if c not in level_error:
            continue
        kind, v = level_error[c]
        rows = output == k
        size = np.abs(y[point, k]) * v if kind == "rel" else np.full(point.size, float(v))
        cols.append(np.where(rows, size / sig[point, k], 0.0))
    if not cols:
        return np.zeros((point.size, 0))
    s = np.column_stack(cols)
    if tau > 0 and u is not None:
        s = whiten_observations(s, point, output, u, tau)
    return s
