"""Best pair of candidate effects, for when no single effect explains the gap.

The single-effect diagnosis (:func:`engine_model.gap.diagnose.diagnose`) asks
whether one library effect, fitted together with the base calibration, removes
the gap on held-out points.  A real bench can carry two unmodelled effects at
once (a transmission loss *and* a wave-tuning error, say), and then no single
candidate is enough.  :func:`best_pair` fits every pair of candidates together
with the base on the same K folds over operating points and scores it the same
way.  Because a pair has more parameters than a single effect, it must earn its
place twice, each test calibrated by Monte Carlo on pure noise through the same
matrices and folds:

1. its held-out improvement over the base beats the (1 - alpha) quantile of
   the best pair's improvement on pure noise, and
2. its held-out improvement over the best *single* candidate beats the
   (1 - alpha) quantile of that excess on pure noise (the pair must explain
   something the best single effect cannot),

and, as for a single claim, it removes at least half of the held-out gap above
noise or leaves a held-out chi2 no larger than pure noise leaves (99 %
quantile).  Otherwise the answer stays "no pair in the library explains it
either".

Everything here is linear algebra on the whitened problem that ``diagnose``
kept in ``GapDiagnosis.extra``; no simulation.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from engine_model.gap.diagnose import GapDiagnosis
from engine_model.gap.fitting import heldout_columns, solve_bounded
from engine_model.gap.sensors import candidate

__all__ = ["PairSearch", "best_pair", "NO_PAIR"]

NO_PAIR = "no pair of candidates in the library explains it either"


@dataclass
class PairSearch:
    """Result of :func:`best_pair`.

    Attributes
    ----------
    table : DataFrame
        One row per pair, best first: ``effect_a, effect_b, params, heldout_chi2,
        improvement_over_base, improvement_over_best_single, reduction_pct`` (share of the held-out
        gap above noise removed [%]), ``at_range_bound``.
    named : tuple of str or None
        The claimed pair, or None.
    statement : str
        Plain-language verdict.
    threshold : float
        Noise quantile the pair's held-out improvement over the base must beat [chi2].
    excess_threshold : float
        Noise quantile its improvement over the best single candidate must beat [chi2].
    """

    table: pd.DataFrame
    named: tuple[str, str] | None
    statement: str
    threshold: float
    excess_threshold: float


def _pair_cols(prob, a: str, b: str) -> list[int]:
    return prob.base_cols + prob.cand_cols[a] + prob.cand_cols[b]


def heldout_chi2_linear(prob, cols: list[int], folds: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Held-out chi2 of the columns ``cols`` for many residual vectors at once, without parameter bounds.

    For a fixed design the K-fold held-out residuals are linear in the data: on fold f they are
    ``r_test - A_test (A_train' A_train + lam I)^-1 A_train' r_train`` (the ridge of ``diagnose.solve_bounded``).
    The pure-noise Monte Carlo uses this closed form (one small solve per fold and column set instead
    of one per draw).  Bounds are left out: pure-noise fits lie well inside the documented ranges, and
    where one would not, the unbounded fit removes more noise, so the thresholds err on the high side.

    Parameters
    ----------
    e : (n_obs, n_draws) float64
        Residual vectors (whitened, as ``prob.r``).

    Returns
    -------
    (n_draws,) float64
    """
    a = prob.a[:, cols]
    fold_of_obs = prob.fold_of_obs(folds)
    out = np.zeros(e.shape[1])
    for f in np.unique(fold_of_obs[fold_of_obs >= 0]):
        test = fold_of_obs == f
        train = ~test
        at = a[train]
        ata = at.T @ at
        lam = 1e-9 * (np.trace(ata) / a.shape[1] + 1e-30)
        coef = np.linalg.solve(ata + lam * np.eye(a.shape[1]), at.T @ e[train])
        res = e[test] - a[test] @ coef
        out += np.einsum("ij,ij->j", res, res)
    return out


def _params(lin, prob, cols: list[int], x: np.ndarray) -> tuple[str, str]:
    """'name = value' text of the effect parameters in ``cols`` (fitted step units ``x``) and bound flags."""
    nb = len(prob.base_cols)
    txt, bound = [], []
    for jj, j in enumerate(cols[nb:]):
        g, p = lin.columns[j]
        prm = candidate(g).param(p)
        xv = x[nb + jj]
        txt.append(f"{g}.{p} = {prm.neutral + xv * lin.steps[j]:.4g}")
        if min(abs(xv - prob.lo[j]), abs(xv - prob.hi[j])) < 1e-6 * max(1.0, abs(xv)):
            bound.append(f"{g}.{p}")
    return "; ".join(txt), ",".join(bound)


def best_pair(d: GapDiagnosis, n_noise: int = 200, alpha: float = 0.05, seed: int = 0,
              candidates: list[str] | None = None,
              noise_cache: dict | None = None) -> PairSearch:
    """Search all pairs of candidate effects for one that explains the gap together.

    Parameters
    ----------
    d : GapDiagnosis
        From :func:`~engine_model.gap.diagnose.diagnose` (its ``extra`` holds the whitened problem).
    n_noise : int
        Pure-noise Monte Carlo trials for the two thresholds.
    alpha : float
        False-claim rate each threshold is set for.
    seed : int
        Monte Carlo seed.
    candidates : list of str, optional
        Effects to pair (default: every candidate the diagnosis ranked).
    noise_cache : dict, optional
        Thresholds reused between calls on the same design (same whitened matrix, folds and candidates).

    Returns
    -------
    PairSearch
    """
    for key in ("problem", "folds", "linearisation"):
        if key not in d.extra:
            raise ValueError(f"best_pair: the diagnosis carries no {key!r}; run engine_model.gap.diagnose first")
    prob, folds, lin = d.extra["problem"], d.extra["folds"], d.extra["linearisation"]
    cands = list(d.ranking["effect"]) if candidates is None else [candidate(c).name for c in candidates]
    unknown = [c for c in cands if c not in prob.cand_cols]
    if unknown:
        raise ValueError(f"best_pair: candidate(s) {unknown} were not part of the diagnosis")
    pairs = list(itertools.combinations(cands, 2))
    if not pairs:
        raise ValueError("best_pair: needs at least two candidates")

    # ---- noise calibration: best pair's improvement over the base, and over the best single
    key = ("pairs", prob.a.tobytes(), prob.point.tobytes(), prob.output.tobytes(), folds.tobytes(), tuple(cands),
           n_noise, alpha, seed)
    if noise_cache is not None and key in noise_cache:
        thr, thr_x = noise_cache[key]
    else:
        e = np.random.default_rng(seed + 15485863).standard_normal((prob.r.size, n_noise))
        h0 = heldout_chi2_linear(prob, prob.base_cols, folds, e)
        h1 = np.min([heldout_chi2_linear(prob, prob.base_cols + prob.cand_cols[c], folds, e) for c in cands], axis=0)
        h2 = np.min([heldout_chi2_linear(prob, _pair_cols(prob, a, b), folds, e) for a, b in pairs], axis=0)
        thr = float(np.quantile(h0 - h2, 1.0 - alpha))
        thr_x = float(np.quantile(h1 - h2, 1.0 - alpha))
        if noise_cache is not None:
            noise_cache[key] = (thr, thr_x)

    # ---- the data
    ho0 = float(d.extra["heldout_chi2_base"])
    single = d.ranking.set_index("effect")["heldout_chi2"]
    ho1 = float(single.loc[cands].min())
    best_single = str(single.loc[cands].idxmin())
    excess0 = max(ho0 - float(d.extra["expected_noise_chi2"]), 0.0)
    rows = []
    for a, b in pairs:
        cols = _pair_cols(prob, a, b)
        ho = heldout_columns(prob, cols, folds)[0]
        x = solve_bounded(prob.a[:, cols], prob.r, prob.lo[cols], prob.hi[cols])
        txt, bound = _params(lin, prob, cols, x)
        red = 100.0 * (ho0 - ho) / excess0 if excess0 > 0 else 0.0
        rows.append({"effect_a": a, "effect_b": b, "params": txt, "heldout_chi2": ho,
                     "heldout_gap_rms": math.sqrt(ho / prob.n_obs), "improvement_over_base": ho0 - ho,
                     "improvement_over_best_single": ho1 - ho, "reduction_pct": float(np.clip(red, -999.0, 100.0)),
                     "at_range_bound": bound})
    table = pd.DataFrame(rows).sort_values("heldout_chi2").reset_index(drop=True)
    top = table.iloc[0]
    beats = top["improvement_over_base"] > thr
    beyond = top["improvement_over_best_single"] > thr_x
    # the single candidate's claim rule: what the pair leaves is within noise, no parameter at a range edge
    enough = top["heldout_chi2"] <= d.noise_chi2_q
    inside = not top["at_range_bound"]
    named = (top["effect_a"], top["effect_b"]) if (beats and beyond and enough and inside) else None
    pair_txt = f"'{top['effect_a']}' + '{top['effect_b']}' ({top['params']})"
    gap_txt = (f"held-out gap {d.gap_before:.2f} -> {top['heldout_gap_rms']:.2f} sigma rms, "
               f"{top['reduction_pct']:.0f} % of the gap above noise")
    if named:
        statement = (f"Best pair: {pair_txt}; {gap_txt}; it improves on the best single candidate "
                     f"'{best_single}' by {top['improvement_over_best_single']:.1f} (noise threshold {thr_x:.1f}), "
                     "so the two together explain the gap.")
    else:
        why = []
        if not beats:
            why.append(f"its improvement over the base ({top['improvement_over_base']:.1f}) does not beat noise "
                       f"({thr:.1f})")
        if not beyond:
            why.append(f"it adds {top['improvement_over_best_single']:.1f} to the best single candidate "
                       f"'{best_single}', within what noise adds ({thr_x:.1f})")
        if not enough:
            why.append(f"what it leaves (held-out chi2 {top['heldout_chi2']:.0f}) is more than noise leaves (99 % "
                       f"quantile {d.noise_chi2_q:.0f}); it removes {top['reduction_pct']:.0f} % of the gap above noise")
        if not inside:
            edge = top["at_range_bound"].split(",")
            why.append(f"{' and '.join(edge)} {'sit' if len(edge) > 1 else 'sits'} at the edge of the documented "
                       "range (the data ask for more than the effects can give: read the pair as the direction of "
                       "the missing physics)")
        statement = f"Best pair: {pair_txt}; {gap_txt}. {NO_PAIR[0].upper() + NO_PAIR[1:]}: " + "; ".join(why) + "."
    return PairSearch(table=table, named=named, statement=statement, threshold=thr, excess_threshold=thr_x)
