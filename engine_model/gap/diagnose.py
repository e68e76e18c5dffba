"""Sim-to-real gap diagnosis: residuals, where the gap lies, which candidate effect explains it.

Everything here is linear algebra on a :class:`~engine_model.gap.linear.Linearisation`
(one batch of simulations), so ranking all candidates with K-fold
cross-validation and calibrating the decision threshold on pure-noise trials
costs seconds.

Steps of :func:`diagnose`:

1. the candidates: the library's effects (:mod:`engine_model.effects`, simulated) and an offset-and-gain
   fault of every measured channel (:mod:`engine_model.gap.sensors`, exact columns, no simulation);
2. residuals in sigma units; every fit is least squares with the base prior (:data:`BASE_PRIOR_SD`, and a
   sensor fault's realistic size) as pseudo-observations that are fitted but never held out;
3. where the gap lies, against the base refitted alone: per channel and operating region, reported only
   where it beats the pure-noise distribution of the same statistic on the same plan; the energy chain
   with a share booked only when significant; a smooth residual field and the shape of the error;
4. which candidate: each fitted together with the base on training folds (all sparks of an operating
   point in one fold) and scored on the held-out fold; the verdict is one of :data:`CATEGORIES`: a claim
   ("explained" / "sensor fault") needs an established gap (the base's held-out chi2 above the quantile pure
   noise leaves, or the best candidate's improvement over the base and its structural level per channel
   above the quantile of that statistic on pure noise: the directed test; 99.5 % each, so that together
   they call pure noise a gap in at most 1 %), a held-out
   improvement above the (1 - alpha) quantile of the best improvement pure noise produces on the same
   design, a held-out remainder within what pure noise leaves
   with the same candidate fitted (99 % quantile, :mod:`engine_model.gap.noise`), no parameter at its range
   edge, and no candidate of another kind within the noise threshold that the data cannot reject as the
   truth (a parametric-bootstrap test, :mod:`engine_model.gap.rivals`); otherwise "indistinguishable", "partly explained", "not in the
   library" or "no significant gap".

"Pure noise" is the error model of :mod:`engine_model.gap.covariance`: the
measurement uncertainty plus the base's structural error, either in quadrature
per reading (``"diagonal"``) or as a per-point burn-duration scatter
correlated across a point's readings (``"burn_scatter"``, generalised least
squares).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import pandas as pd

from engine_model.gap.covariance import (DEFAULT_ERROR_MODEL, ErrorModel, get_error_model, level_columns,
                                        whiten_observations)
from engine_model.gap.fitting import (FitProblem, columns_of, fit_all, heldout, make_folds, operating_point_groups)
from engine_model.gap.noise import directed_improvement, expected_noise_chi2, noise_reference, with_level

from engine_model.gap.linear import Linearisation
from engine_model.gap.localise import coded_map, energy_chain, field_fit, region_table, shape_label
from engine_model.gap.covariance import null_base_residuals
from engine_model.gap.verdict import order_ranking, param_text, rivals_of_another_kind, verdict_statement
from engine_model.gap.rivals import RIVAL_ALPHA, rival_p_values
from engine_model.gap.residuals import UNCERTAINTY, align_measured, check_bench_outputs, sigma_of
from engine_model.gap.sensors import SENSOR_STAGE, candidate, is_sensor, with_sensor_faults

__all__ = ["diagnose", "GapDiagnosis", "CHAIN_STAGE", "NO_CANDIDATE", "param_text", "CATEGORIES",
           "BASE_PRIOR_SD"]

NO_CANDIDATE = "no candidate in the library explains it"

#: Answer categories of :func:`diagnose`.
#:
#: * ``no significant gap``: the base's held-out residual is consistent with noise and nothing is claimed
#:   (candidates of two kinds may each beat the noise threshold on such a gap; the verdict lists them);
#: * ``explained`` / ``sensor fault``: the best candidate (a physical effect / an offset-and-gain fault of
#:   one measured channel) beats the noise threshold, leaves a held-out residual no larger than pure noise
#:   leaves (99 % quantile) and none of its parameters sits at the edge of its documented range;
#: * ``indistinguishable``: as above on a gap above noise, but a candidate of another kind (a fault of another
#:   channel, or a physical effect against a sensor fault) scores within the noise threshold of the best and
#:   the data cannot reject it as the truth (:mod:`engine_model.gap.rivals`, 5 %): the verdict names them all
#:   rather than pick one (a rival the test rejects does not stand in the way of the claim);
#: * ``partly explained``: the best candidate beats the noise threshold but leaves more than noise, or
#:   asks for a parameter at its range edge (a larger or another cause); it is reported, not claimed;
#: * ``not in the library``: a gap above noise that no candidate reduces by more than noise would; the
#:   localisation says where it is.
#: Prior standard deviation of a sensor fault's parameters in units of their realistic size
#: (:mod:`engine_model.gap.sensors`).
SENSOR_PRIOR_SCALE = 1.0

CATEGORIES = ("no significant gap", "explained", "sensor fault", "indistinguishable", "partly explained",
              "not in the library")

#: Prior standard deviation of the base's burn-law parameters about the DOE prior (theta = 0), used as
#: pseudo-observations in every fit (a penalised, i.e. MAP, fit; Brynjarsdottir & O'Hagan 2014 on why a
#: calibration without physical priors absorbs model discrepancy).  Sizes: a few times the hold-out error
#: of the identified burn law against bench data (BDUR10-90 RMSE 2.6-3.3 deg, docs/sections/globalmodel.md)
#: for the offset and load term; slopes such that the prior alone allows the same few degrees across the
#: 3000-rpm half-range (speed) and a 10-deg spark excursion (spark).
BASE_PRIOR_SD = {"bdur_offset_deg": 8.0, "bdur_speed_deg_per_krpm": 3.0, "bdur_load_deg": 8.0,
                 "bdur_spark_deg_per_10deg": 4.0, "bdur_speed2_deg_per_krpm2": 1.0,
                 "m_offset": 1.5, "m_speed_per_krpm": 0.5, "airflow_restrictor_cd_factor": 0.1}

#: Where along the energy chain each effect acts.
CHAIN_STAGE = {
    "runner_inertia": "air in", "restrictor": "air in", "exhaust_back_pressure": "air in",
    "intake_air_temperature": "air in", "humidity": "air in",
    "combustion_efficiency": "indicated (combustion)", "blowby": "indicated (combustion)",
    "knock_retard": "indicated (combustion)", "heat_transfer": "indicated (combustion)",
    "friction": "mechanical (friction)",
    "transmission_efficiency": "transmission/dyno", "transmission_speed_loss": "transmission/dyno",
}

# --------------------------------------------------------------------------- result

@dataclass
class GapDiagnosis:
    """Result of :func:`diagnose` (all tables are DataFrames).

    Attributes
    ----------
    named : str or None
        The claimed candidate (category "explained" or "sensor fault"), else None.
    category : str
        One of :data:`CATEGORIES`.
    regions : DataFrame
        Localisation: per output and operating region (speed and load band) the mean normalised residual,
        its standard error and whether it beats the pure-noise distribution of the largest such statistic
        on the same plan (:func:`engine_model.gap.localise.region_table`).
    statement : str
        One-paragraph plain-language verdict.
    confidence : float
        Akaike weight of the named candidate among all candidates [0-1] (Burnham & Anderson 2002).
    ranking : DataFrame
        One row per candidate: fitted parameters +- standard errors, held-out
        chi2 and its reduction, AIC, BIC, signature match, weight, rank.
    residuals : DataFrame
        Per point and output: measured, base-calibrated model, residual,
        normalised residual (sigma units), and after the named (or best) effect.
    field : DataFrame
        Smooth residual field coefficients per output (+- standard errors).
    shape : DataFrame
        Per output: offset, speed slope, curvature, load slope (in sigma units,
        with t values), lack-of-fit chi2 / dof, fraction of positive residuals,
        dominant shape.
    chain : DataFrame
        Energy-chain waterfall: stage, mean share of the torque gap [%], its
        standard error and what pins it down.
    stages : DataFrame
        Best held-out improvement per energy-chain stage (localisation by the library).
    gap_before, gap_after : float
        Held-out RMS of the normalised residual (sigma units) of the base
        model and with the best candidate.
    threshold : float
        Noise-calibrated held-out chi2 improvement a claim must beat.
    base_theta : dict
        Base parameters after the refit on all points (base model alone).
    base_theta_best : dict
        Base parameters fitted together with the best candidate.
    """

    named: str | None
    statement: str
    confidence: float
    ranking: pd.DataFrame
    residuals: pd.DataFrame
    field: pd.DataFrame
    shape: pd.DataFrame
    chain: pd.DataFrame
    stages: pd.DataFrame
    gap_before: float
    gap_after: float
    gap_reduction_pct: float
    threshold: float
    noise_chi2_q: float
    base_theta: dict
    n_points: int
    n_obs: int
    excluded: pd.DataFrame
    best: str | None = None
    base_theta_best: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    category: str = "not in the library"
    regions: pd.DataFrame = field(default_factory=pd.DataFrame)

    def top(self, k: int = 3) -> list[str]:
        return list(self.ranking.sort_values("rank")["effect"].head(k))

    def summary(self) -> str:
        return self.statement

# --------------------------------------------------------------------------- main entry

def diagnose(lin: Linearisation, measured: pd.DataFrame, candidates: Sequence[str] | None = None,
             uncertainty: dict | None = None, error_model: str | ErrorModel = DEFAULT_ERROR_MODEL,
             k_folds: int = 5, alpha: float = 0.05, n_noise: int = 200, seed: int = 0,
             noise_cache: dict | None = None, source: str = "bench", sensor_faults: bool = True,
             base_prior_sd: dict | None = BASE_PRIOR_SD, rival_test: bool = True) -> GapDiagnosis:
    """Diagnose the gap between a bench table and the linearised model.

    Parameters
    ----------
    lin : Linearisation
        From :func:`engine_model.gap.linear.linearise` on the bench's plan.
    measured : DataFrame
        Bench rows (``point_id`` + measured outputs; rows whose ``status`` is
        not 'ok' are excluded and listed).
    candidates : sequence of str, optional
        Effects to rank (default: all effects in ``lin``).
    uncertainty : dict, optional
        Override of :data:`engine_model.gap.residuals.UNCERTAINTY`.
    error_model : str or ErrorModel
        Structural error model of the base and the claim rule it supports
        (:data:`engine_model.gap.covariance.ERROR_MODELS`): ``"diagonal"`` (a structural error in quadrature
        per reading, :data:`~engine_model.gap.covariance.MODEL_ERROR`) or ``"burn_scatter"`` (every point's
        readings get the covariance ``I + tau^2 u u^T`` in sigma units, ``u`` the point's BDUR10-90
        sensitivity, on top of a small diagonal remainder; all fits are generalised least squares by
        per-point block whitening and the pure-noise Monte Carlo draws noise with that covariance).
        Residual tables (``z``) stay in diagonal sigma units.
    k_folds : int
        Folds over operating points (leave-one-out when there are fewer points).
    alpha : float
        False-claim rate the noise threshold is set for.
    n_noise : int
        Pure-noise Monte Carlo trials for the threshold.
    seed : int
        Folds and Monte Carlo seed.
    noise_cache : dict, optional
        Reused between calls with the same design (the benchmark passes one).
    source : str
        Name of the bench table in messages.
    sensor_faults : bool
        Rank an offset-and-gain fault of every measured channel beside the effects
        (:mod:`engine_model.gap.sensors`).
    base_prior_sd : dict or None
        Prior standard deviation per base parameter about the DOE prior (:data:`BASE_PRIOR_SD`); None: no
        prior (plain least squares).
    rival_test : bool
        Test each close rival of another kind as the truth (:mod:`engine_model.gap.rivals`) before it
        withholds a claim; False: closeness alone withholds (the p-values are in ``extra["rival_p"]``).

    Returns
    -------
    GapDiagnosis

    Notes
    -----
    The claim rule needs the gap established and the remainder within noise: nothing is claimed while the
    base's held-out chi2 lies within its pure-noise quantile and the directed test (``extra["directed_q"]``,
    :mod:`engine_model.gap.noise`) fails too (99.5 % each; 99 % for the omnibus test alone under an error
    model without a structural level) ("no significant gap", even when a candidate's improvement beats its
    own noise threshold), and a candidate that removes most but not all of
    an established gap is reported as "partly explained", never claimed.
    """
    unc = dict(UNCERTAINTY)
    unc.update(uncertainty or {})
    em = get_error_model(error_model)
    if sensor_faults:
        usable = check_bench_outputs(measured, source)
        lin = with_sensor_faults(lin, [c for c in lin.outputs if c in usable])
        if candidates is not None:
            candidates = list(candidates) + [g for g in lin.effect_names() if is_sensor(g) and g not in candidates]
    su = _setup(lin, measured, candidates, unc, em, k_folds, seed, source, base_prior_sd)
    prob, folds, cands = su.prob, su.folds, su.cands
    key = (tuple(lin.points["point_id"].astype(str)), tuple(su.pidx), tuple(su.oidx), tuple(folds), tuple(cands),
           k_folds, seed, n_noise, alpha, float(em.burn_scatter_deg), repr(sorted((em.model_error or {}).items())),
           repr(sorted((base_prior_sd or {}).items())), repr(sorted(em.level_error.items())))
    ref = noise_reference(prob, folds, cands, key, n_noise, alpha, seed, noise_cache, su.level)
    thr, q_chi2, noise_best = ref.threshold, ref.base_chi2_q, ref.mean_best_improvement
    x0, ho0, rank = _rank_candidates(su, lin, thr)
    nobs = prob.n_obs
    gap_before = math.sqrt(ho0 / nobs)
    best = rank["effect"].iloc[0] if len(rank) else None
    best_ho = float(rank["heldout_chi2"].iloc[0]) if len(rank) else ho0
    gap_after = math.sqrt(best_ho / nobs)
    # gap above noise: the excess of the held-out chi2 over what a pure-noise data set leaves on this design
    exp_noise = expected_noise_chi2(prob, folds, seed, noise_cache, key)
    excess0 = max(ho0 - exp_noise, 0.0)
    reduction = 100.0 * (ho0 - best_ho) / excess0 if excess0 > 0 else 0.0
    reduction = float(np.clip(reduction, -999.0, 100.0))
    # the remainder against what noise leaves with the same candidate fitted beside the base (gap.noise)
    q_rem = ref.remainder_q(best)
    resid_ok = best_ho <= q_rem
    beats = best is not None and rank["heldout_improvement"].iloc[0] > thr
    at_edge = bool(best is not None and rank["at_range_bound"].iloc[0])
    rivals = rivals_of_another_kind(rank, thr) if beats else []
    # a claim needs an established gap: the base's held-out chi2 above its pure-noise quantile (omnibus), or the
    # best candidate's improvement over the base and its structural level above its own (directed, gap.noise);
    # together they call pure noise a gap in at most 1 %
    directed_d = (directed_improvement(with_level(prob, su.level), folds, cands)
                  if su.level.shape[1] and cands and math.isfinite(ref.directed_q) else float("nan"))
    directed = bool(directed_d > ref.directed_q)
    established = ho0 > ref.omnibus_q or directed
    # a significant gap whose best fit is adequate: a close rival of another kind stands only if the data
    # cannot reject it (gap.rivals; on a gap that is not established, no test)
    rival_p = {}
    if rival_test and rivals and resid_ok and not at_edge and established:
        rival_p = rival_p_values(prob, folds, best, rivals, seed=seed)
        rivals = [c for c in rivals if rival_p[c] >= RIVAL_ALPHA]
    claimed = best if beats and resid_ok and not at_edge and not rivals and established else None
    if claimed:
        category = "sensor fault" if is_sensor(claimed) else "explained"
    elif not established:   # also when a candidate, or rivals of two kinds, beat noise on a gap noise could leave
        category = "no significant gap"
    elif beats and not (resid_ok and not at_edge):
        category = "partly explained"
    elif beats:
        category = "indistinguishable"
    else:
        category = "not in the library"
    conf = float(rank["weight"].iloc[0]) if claimed else 0.0

    resid, delta0, deltab, fit0 = _residual_table(su, lin, x0, best)
    fld, shape = _where(su, lin, fit0)
    regions = _regions(su, lin, x0, n_noise, seed)
    chain = _chain(su, lin, x0, claimed)
    stages = (rank.groupby("stage")["heldout_improvement"].max().sort_values(ascending=False)
              .rename("best_heldout_improvement").reset_index()) if len(rank) else pd.DataFrame()
    if len(stages):
        stages["beats_noise"] = stages["best_heldout_improvement"] > thr
    statement = verdict_statement(category, claimed, best, rank, thr, gap_before, gap_after, reduction, q_rem, chain,
                                  stages, regions, rival_p)
    return GapDiagnosis(named=claimed, statement=statement, confidence=conf, ranking=rank, residuals=resid,
                        field=fld, shape=shape, chain=chain, stages=stages, gap_before=gap_before,
                        gap_after=gap_after, gap_reduction_pct=reduction, threshold=thr, noise_chi2_q=q_chi2,
                        base_theta={p: lin.theta[p] + delta0[j] for j, (g, p) in enumerate(lin.columns)
                                    if g == "base"},
                        base_theta_best={p: lin.theta[p] + deltab[j] for j, (g, p) in enumerate(lin.columns)
                                         if g == "base"},
                        n_points=int(su.point_valid.sum()), n_obs=int(nobs), excluded=su.excluded, best=best,
                        category=category, regions=regions,
                        extra={"indistinguishable": ([best] + rivals) if category == "indistinguishable" else [],
                               "rival_p": rival_p, "heldout_chi2_base": ho0, "expected_noise_chi2": exp_noise,
                               "remainder_chi2_q": q_rem, "directed_q": ref.directed_q, "directed_improvement": directed_d,
                               "established_by": ("omnibus" if ho0 > ref.omnibus_q else "directed" if directed else ""),
                               "error_model": em.name,
                               "noise_mean_best_improvement": noise_best, "outputs": su.outputs,
                               # for a later search over pairs of candidates (gap.pairs)
                               "problem": prob, "folds": folds, "linearisation": lin, "level": su.level})

@dataclass
class _Setup:
    """The diagnosis' data: measured and reference outputs, their sigmas, the whitened problem, the folds."""

    outputs: list[str]
    oi: list[int]
    y: np.ndarray            # (n, o') measured
    yref: np.ndarray         # (n, o') model at the linearisation's reference
    sig: np.ndarray          # (n, o') diagonal sigma
    valid: np.ndarray        # (n, o') usable readings
    point_valid: np.ndarray  # (n,)
    excluded: pd.DataFrame
    pidx: np.ndarray
    oidx: np.ndarray
    cands: list[str]
    prob: FitProblem
    folds: np.ndarray
    r_sig: np.ndarray = None     # (nobs,) measured rows' residuals in diagonal sigma units (not whitened)
    a_sig: np.ndarray = None     # (nobs, p) their columns, step units (not whitened)
    u: np.ndarray = None         # (n, o') burn direction of the burn-scatter covariance, or None
    tau: float = 0.0             # burn scatter [deg]
    level: np.ndarray = None     # (rows of prob, q) whitened structural level per channel (gap.noise)

def _setup(lin: Linearisation, measured: pd.DataFrame, candidates, unc: dict, em: ErrorModel, k_folds: int,
           seed: int, source: str, base_prior_sd: dict | None = None) -> _Setup:
    """Align the bench with the linearisation, normalise by sigma, whiten, bound the effect columns, add the
    base prior's pseudo-observations, fold."""
    usable = check_bench_outputs(measured, source)
    outputs = [c for c in lin.outputs if c in usable]
    meas = align_measured(lin.points, measured, outputs)
    cands = lin.effect_names() if candidates is None else [candidate(c).name for c in candidates]
    missing = [c for c in cands if not lin.column_index(c)]
    if missing:
        raise ValueError(f"diagnose: candidate(s) {missing} were not linearised; linearised: {lin.effect_names()}")
    oi = [lin.outputs.index(c) for c in outputs]
    n = len(lin.points)
    y = meas[outputs].to_numpy(float)                      # (n, o')
    yref = lin.y_ref[:, oi]
    sig = np.column_stack([sigma_of(c, y[:, k], unc, em.model_error) for k, c in enumerate(outputs)])
    valid = np.isfinite(y) & np.isfinite(yref) & lin.ok[:, None]
    point_valid = valid.any(axis=1) & valid[:, 0] & valid[:, 1]
    valid &= point_valid[:, None]
    excluded = pd.DataFrame({"point_id": lin.points["point_id"], "reason": [
        (s if s else ("bench status " + b if b != "ok" else ("missing airflow/torque" if not pv else "")))
        for s, b, pv in zip(lin.status, meas["bench_status"], point_valid)]})
    excluded = excluded[~point_valid].reset_index(drop=True)
    pidx, oidx = np.nonzero(valid)
    if np.unique(pidx).size < 3:
        raise ValueError(f"{source}: only {np.unique(pidx).size} usable point(s) (need >= 3); excluded: "
                         f"{excluded.to_dict('records')[:5]}")
    r = ((y - yref) / sig)[pidx, oidx]
    steps = lin.steps
    a_full = (lin.jac[:, oi, :] / sig[:, :, None])[pidx, oidx, :] * steps     # columns in step units
    r_sig, a_sig, u, tau = r.copy(), a_full.copy(), None, 0.0
    lo = np.full(len(steps), -np.inf)
    hi = np.full(len(steps), np.inf)
    for j, (g, p) in enumerate(lin.columns):
        if g == "base":
            continue
        prm = candidate(g).param(p)
        a_, b_ = (prm.lo - prm.neutral) / steps[j], (prm.hi - prm.neutral) / steps[j]
        lo[j], hi[j] = min(a_, b_), max(a_, b_)
    if em.burn_scatter_deg > 0:
        u = _burn_direction(lin, oi, sig)
        tau = float(em.burn_scatter_deg)
        r = whiten_observations(r, pidx, oidx, u, em.burn_scatter_deg)
        a_full = whiten_observations(a_full, pidx, oidx, u, em.burn_scatter_deg)
    level = level_columns(outputs, y, sig, pidx, oidx, em.level_error, u, tau)
    # the base prior: one pseudo-observation per base parameter, (prior mean 0 - reference) / prior sd, in
    # the same step units; point index -1 (always fitted, never held out or counted in a gap)
    prior = [(j, base_prior_sd[p], -lin.theta[p]) for j, (g, p) in enumerate(lin.columns)
             if g == "base" and base_prior_sd and p in base_prior_sd]
    # a sensor fault's size: prior sd = its realistic size (SENSOR_PRIOR_SCALE x), so a fault is not
    # fitted far beyond what instruments do just to cancel a burn-law shift (a degenerate direction)
    prior += [(j, SENSOR_PRIOR_SCALE * abs(candidate(g).param(p).realistic), 0.0)
              for j, (g, p) in enumerate(lin.columns) if is_sensor(g) and g in cands]
    if prior:
        rows = np.zeros((len(prior), a_full.shape[1]))
        rp = np.zeros(len(prior))
        for i, (j, sd, mean) in enumerate(prior):
            rows[i, j] = steps[j] / sd
            rp[i] = mean / sd
        r = np.concatenate([r, rp])
        a_full = np.vstack([a_full, rows])
        level = np.vstack([level, np.zeros((len(prior), level.shape[1]))])
        pidx = np.concatenate([pidx, np.full(len(prior), -1)])
        oidx = np.concatenate([oidx, np.full(len(prior), -1)])
    prob = FitProblem(r=r, a=a_full, point=pidx, output=oidx, base_cols=lin.column_index("base"),
                      cand_cols={c: lin.column_index(c) for c in cands}, lo=lo, hi=hi)
    folds = make_folds(n, point_valid, k_folds, seed, operating_point_groups(lin.points))
    return _Setup(outputs=outputs, oi=oi, y=y, yref=yref, sig=sig, valid=valid, point_valid=point_valid,
                  excluded=excluded, pidx=pidx, oidx=oidx, cands=cands, prob=prob, folds=folds, r_sig=r_sig,
                  a_sig=a_sig, u=u, tau=tau, level=level)

def _rank_candidates(su: _Setup, lin: Linearisation, thr: float) -> tuple[np.ndarray, float, pd.DataFrame]:
    """Base-only fit and every candidate fitted with the base: held-out chi2, AIC/BIC, signature match.

    Returns the base-only solution (step units), its held-out chi2 and the ranking table (best first).
    """
    prob, folds, steps = su.prob, su.folds, lin.steps
    base_cols, cand_cols, nobs = prob.base_cols, prob.cand_cols, prob.r.size
    x0, chi0, res0 = fit_all(prob, None)
    ho0, _ = heldout(prob, None, folds)
    nb = len(base_cols)
    k0 = np.linalg.matrix_rank(prob.a[:, base_cols]) if nb else 0
    ab = prob.a[:, base_cols]

    def perp(m):
        """Residual of ``m`` after projecting out the base columns (for the signature match)."""
        if nb == 0:
            return m
        coef = np.linalg.lstsq(ab, m, rcond=None)[0]
        return m - ab @ coef

    rows = []
    for c in su.cands:
        cols = cand_cols[c]
        x, chi, res = fit_all(prob, c)
        ho, _ = heldout(prob, c, folds)
        k = k0 + np.linalg.matrix_rank(perp(prob.a[:, cols]))
        # standard errors of the effect parameters (unbounded linearised covariance, residual-scaled)
        acols = prob.a[:, base_cols + cols]
        cov = np.linalg.pinv(acols.T @ acols) * max(1.0, chi / max(1, nobs - acols.shape[1]))
        se = np.sqrt(np.clip(np.diag(cov)[nb:], 0, None))
        ap = perp(prob.a[:, cols])
        q, _ = np.linalg.qr(ap) if ap.size else (ap, None)
        rp = res0
        match = float(np.sum((q.T @ rp) ** 2) / (rp @ rp)) if rp @ rp > 0 else 0.0
        eff = candidate(c)
        params = {}
        at_bound = []
        for jj, j in enumerate(cols):
            _g, p = lin.columns[j]
            prm = eff.param(p)
            params[p] = (prm.neutral + x[nb + jj] * steps[j], se[jj] * abs(steps[j]))
            if min(abs(x[nb + jj] - prob.lo[j]), abs(x[nb + jj] - prob.hi[j])) < 1e-6 * max(1.0, abs(x[nb + jj])):
                at_bound.append(p)
        rows.append({
            "effect": c, "stage": SENSOR_STAGE if is_sensor(c) else CHAIN_STAGE.get(c, ""),
            "params": "; ".join(param_text(p, v, s, eff.param(p)) for p, (v, s) in params.items()),
            "param_values": {p: v for p, (v, _) in params.items()},
            "heldout_chi2": ho, "heldout_improvement": ho0 - ho,
            "heldout_gap_rms": math.sqrt(ho / nobs),
            "chi2": chi, "aic": chi + 2 * k, "bic": chi + k * math.log(nobs),
            "delta_aic": (chi + 2 * k) - (chi0 + 2 * k0),
            "delta_bic": (chi + k * math.log(nobs)) - (chi0 + k0 * math.log(nobs)),
            "signature_match": match, "at_range_bound": ",".join(at_bound),
        })
    rank = pd.DataFrame(rows)
    if len(rank):
        rank = order_ranking(rank, thr)
        rank["rank"] = np.arange(1, len(rank) + 1)
        w = np.exp(-0.5 * (rank["aic"] - rank["aic"].min()).clip(upper=700))
        rank["weight"] = w / w.sum()
        rank["beats_noise"] = rank["heldout_improvement"] > thr
    return x0, ho0, rank

def _residual_table(su: _Setup, lin: Linearisation, x0: np.ndarray, best: str | None):
    """Residuals per point and output against the localisation base ``x0`` and with the best candidate.

    Returns the table, the base and best-candidate parameter changes (physical units) and the base fit.
    """
    prob, steps = su.prob, lin.steps
    xb, _, _ = fit_all(prob, best) if best else (x0, None, None)
    cols_b = columns_of(prob, best) if best else prob.base_cols
    delta0 = np.zeros(len(steps))
    delta0[prob.base_cols] = x0 * steps[prob.base_cols]
    deltab = np.zeros(len(steps))
    deltab[cols_b] = xb * steps[cols_b]
    fit0 = lin.predict(delta0)[:, su.oi]
    fitb = lin.predict(deltab)[:, su.oi]
    y, sig = su.y, su.sig
    recs = []
    for i in range(len(lin.points)):
        for k, c in enumerate(su.outputs):
            recs.append({"point_id": lin.points["point_id"].iloc[i],
                         "speed_rpm": lin.points["speed_rpm"].iloc[i],
                         "throttle_pct": lin.points["throttle_pct"].iloc[i],
                         "spark_deg_btdc": lin.points["spark_deg_btdc"].iloc[i],
                         "output": c, "measured": y[i, k], "model": fit0[i, k], "sigma": sig[i, k],
                         "residual": y[i, k] - fit0[i, k], "z": (y[i, k] - fit0[i, k]) / sig[i, k],
                         "model_with_best": fitb[i, k], "z_with_best": (y[i, k] - fitb[i, k]) / sig[i, k],
                         "used": bool(su.valid[i, k])})
    return pd.DataFrame(recs), delta0, deltab, fit0

def _where(su: _Setup, lin: Linearisation, fit0: np.ndarray) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Where the gap lies: a smooth residual field over the map per output, and the shape of the error."""
    from scipy.stats import chi2 as _chi2

    xmap, mnames = coded_map(lin.points)
    frows, srows = [], []
    y, sig = su.y, su.sig
    for k, c in enumerate(su.outputs):
        z = np.where(su.valid[:, k], (y[:, k] - fit0[:, k]) / sig[:, k], np.nan)
        coef, se, chi, dof, names = field_fit(z, xmap, list(mnames))
        for nm, cf, s in zip(names, coef, se):
            frows.append({"output": c, "term": nm, "coef_sigma": cf, "se_sigma": s, "t": cf / s if s > 0 else np.nan})
        get = dict(zip(names, zip(coef, se)))

        def t_of(term):
            return get[term][0] / get[term][1] if term in get and get[term][1] > 0 else np.nan
        zz = z[np.isfinite(z)]
        srow = {"output": c, "n": int(zz.size), "rms_sigma": float(np.sqrt(np.mean(zz**2))) if zz.size else np.nan,
                "offset_sigma": get.get("offset", (np.nan,))[0], "offset_t": t_of("offset"),
                "speed_slope_sigma": get.get("speed", (np.nan,))[0], "speed_t": t_of("speed"),
                "curvature_sigma": get.get("speed^2", (np.nan,))[0], "speed2_t": t_of("speed^2"),
                "load_slope_sigma": get.get("load", (np.nan,))[0], "load_t": t_of("load"),
                "lack_of_fit_chi2_per_dof": chi / dof, "lack_of_fit_p": float(_chi2.sf(chi, dof)),
                "frac_positive": float(np.mean(zz > 0)) if zz.size else np.nan}
        srow["shape"] = shape_label(srow)
        srows.append(srow)
    return pd.DataFrame(frows), pd.DataFrame(srows)

def _burn_direction(lin: Linearisation, oi: Sequence[int], sig: np.ndarray) -> np.ndarray:
    """Per point and output, the BDUR10-90 sensitivity in sigma units [sigma per deg CA], (n, o').

    Raises
    ------
    ValueError
        When the linearisation has no base column ``bdur_offset_deg``.
    """
    j = [k for k, c in enumerate(lin.columns) if c == ("base", "bdur_offset_deg")]
    if not j:
        raise ValueError("diagnose: burn_scatter_deg > 0 needs the base column bdur_offset_deg in the "
                         f"linearisation; base: {list(lin.base.params)}")
    u = lin.jac[:, oi, j[0]] / sig
    return np.where(np.isfinite(u) & lin.ok[:, None], u, 0.0)

def _regions(su: _Setup, lin: Linearisation, x0: np.ndarray, n_noise: int, seed: int) -> pd.DataFrame:
    """Localisation per output and operating region against pure noise on the same plan (base refitted to
    every noise draw as to the data)."""
    prob = su.prob
    real = prob.point >= 0
    z = su.r_sig - su.a_sig[:, prob.base_cols] @ x0
    null_z = null_base_residuals(prob, su.a_sig, su.u, su.tau, len(lin.points), max(200, n_noise), seed + 31337)
    return region_table(z, null_z, prob.point[real], prob.output[real], lin.points, su.outputs)


def _chain(su: _Setup, lin: Linearisation, x0: np.ndarray, claimed: str | None) -> pd.DataFrame:
    """Energy chain of the base fit; a claimed sensor fault is taken out of the readings first."""
    prob, steps = su.prob, lin.steps
    delta = np.zeros(len(steps))
    delta[prob.base_cols] = x0 * steps[prob.base_cols]
    y = su.y
    if claimed and is_sensor(claimed):
        cols = columns_of(prob, claimed)
        xb, _, _ = fit_all(prob, claimed)
        delta = np.zeros(len(steps))
        delta[cols] = xb * steps[cols]
        sens = prob.cand_cols[claimed]
        y = su.y - lin.jac[:, su.oi, :][:, :, sens] @ delta[sens]
        delta[sens] = 0.0
    return energy_chain(lin, su.outputs, y, lin.predict(delta)[:, su.oi], su.valid)

