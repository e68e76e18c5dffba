"""Pure-noise reference distributions of the gap diagnosis, on the diagnosis' own design.

Every statistic the claim rule compares is compared with what pure noise (the error model's noise, the base
refitted as on the data) gives on the same plan, the same folds and the same candidates:

* the claim threshold: the (1 - alpha) quantile of the best candidate's held-out improvement;
* the 99 % quantile of the base's held-out chi2 (is the gap established? the omnibus test; 99.5 % when the
  directed test below runs beside it, so that together they call pure noise a gap in at most 1 %);
* per candidate, the 99 % quantile of the held-out chi2 with that candidate fitted beside the base: what
  the remainder of a candidate that is exactly the truth looks like (fitting it costs held-out chi2 on
  noise, 0-5 % at the 99 % quantile on the default plan), so its remainder is judged against it;
* the mean held-out chi2 of the base on noise (the "noise level" the gap is measured above);
* the directed test of an established gap: the 99.5 % quantile of the best candidate's held-out improvement over
  the base *with a structural level per channel fitted beside it* (``level`` columns with a prior of their
  measured size, :func:`engine_model.gap.covariance.level_columns`).  The omnibus test (the base's held-out
  chi2) spreads its power over every reading; a gap that one candidate's shape explains shows first in that
  candidate's improvement.  The base's own misfit has a level per channel (a torque-only loss to a
  candidate's eyes), so the improvement is counted beyond what such a level explains.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from engine_model.gap.fitting import FitProblem, heldout

__all__ = ["NoiseReference", "noise_reference", "expected_noise_chi2", "with_level", "directed_improvement"]

#: Quantile of the base's (and a candidate's) held-out chi2 on pure noise that the claim rule uses.
CHI2_QUANTILE = 0.99

#: Rate at which test 0 of the claim rule calls pure noise an established gap.  With the directed test beside
#: the omnibus one each gets half of it (Bonferroni), so the union of the two stays within it.
ESTABLISH_ALPHA = 0.01


@dataclass(frozen=True)
class NoiseReference:
    """Pure-noise Monte Carlo summary (see the module docstring)."""

    threshold: float                 # (1 - alpha) quantile of the best held-out improvement
    base_chi2_q: float               # CHI2_QUANTILE of the base's held-out chi2
    mean_best_improvement: float
    candidate_chi2_q: dict = field(default_factory=dict)   # candidate -> CHI2_QUANTILE of its held-out chi2
    directed_q: float = float("inf")  # 1 - ESTABLISH_ALPHA/2 quantile of directed_improvement (inf: no level given)
    omnibus_q: float = float("nan")   # the base's held-out chi2 quantile test 0 uses (1 - ESTABLISH_ALPHA, or
                                      # 1 - ESTABLISH_ALPHA/2 beside the directed test)

    def remainder_q(self, candidate: str | None) -> float:
        """The quantile a candidate's held-out remainder is judged against (the base's for None)."""
        return self.candidate_chi2_q.get(candidate, self.base_chi2_q) if candidate else self.base_chi2_q


def noise_reference(prob: FitProblem, folds: np.ndarray, cands: list[str], key: tuple, n_noise: int, alpha: float,
                    seed: int, cache: dict | None, level: np.ndarray | None = None) -> NoiseReference:
    """``n_noise`` pure-noise data sets on the design of ``prob`` (cached under ``key``).

    ``level``: (rows of ``prob``, q) whitened columns of the structural level per channel, one sigma each
    (prior pseudo-observation rows zero); with q > 0 the directed quantile is drawn too
    (:func:`directed_improvement`), else it is inf.
    """
    if cache is not None and key in cache:
        return cache[key]
    rng = np.random.default_rng(seed + 7919)
    best_d, chi_null = [], []
    chi_c = {c: [] for c in cands}
    for _ in range(n_noise):
        e = rng.standard_normal(prob.r.size)
        c0, _ = heldout(prob, None, folds, e)
        chi_null.append(c0)
        for c in cands:
            chi_c[c].append(heldout(prob, c, folds, e)[0])
        best_d.append(max(c0 - chi_c[c][-1] for c in cands) if cands else 0.0)
    directed = float("inf")
    omnibus = float(np.quantile(chi_null, 1.0 - ESTABLISH_ALPHA))
    if level is not None and level.shape[1] and cands:
        aug = with_level(prob, level)
        rng_l = np.random.default_rng(seed + 15485863)
        directed = float(np.quantile([directed_improvement(aug, folds, cands, rng_l.standard_normal(aug.r.size))
                                      for _ in range(n_noise)], 1.0 - ESTABLISH_ALPHA / 2))
        omnibus = float(np.quantile(chi_null, 1.0 - ESTABLISH_ALPHA / 2))
    out = NoiseReference(threshold=float(np.quantile(best_d, 1.0 - alpha)),
                         base_chi2_q=float(np.quantile(chi_null, CHI2_QUANTILE)),
                         mean_best_improvement=float(np.mean(best_d)),
                         candidate_chi2_q={c: float(np.quantile(v, CHI2_QUANTILE)) for c, v in chi_c.items()},
                         directed_q=directed, omnibus_q=omnibus)
    if cache is not None:
        cache[key] = out
    return out


def expected_noise_chi2(prob: FitProblem, folds: np.ndarray, seed: int, cache: dict | None, key: tuple) -> float:
    """Mean held-out chi2 of the base model on pure noise (the 'noise level' of the gap)."""
    k2 = ("expected",) + key
    if cache is not None and k2 in cache:
        return cache[k2]
    rng = np.random.default_rng(seed + 104729)
    vals = [heldout(prob, None, folds, rng.standard_normal(prob.r.size))[0] for _ in range(50)]
    v = float(np.mean(vals))
    if cache is not None:
        cache[k2] = v
    return v


def with_level(prob: FitProblem, level: np.ndarray) -> FitProblem:
    """``prob`` with the structural level columns added to the base, each with a unit prior (one sigma of its
    measured size) as a pseudo-observation; the candidates' columns keep their indices."""
    n, q = prob.r.size, level.shape[1]
    p = prob.a.shape[1]
    a = np.zeros((n + q, p + q))
    a[:n, :p] = prob.a
    a[:n, p:] = level
    a[n:, p:] = np.eye(q)
    return FitProblem(r=np.concatenate([prob.r, np.zeros(q)]), a=a,
                      point=np.concatenate([prob.point, np.full(q, -1)]),
                      output=np.concatenate([prob.output, np.full(q, -1)]),
                      base_cols=list(prob.base_cols) + list(range(p, p + q)), cand_cols=prob.cand_cols,
                      lo=np.concatenate([prob.lo, np.full(q, -np.inf)]), hi=np.concatenate([prob.hi, np.full(q, np.inf)]))


def directed_improvement(aug: FitProblem, folds: np.ndarray, cands: list[str], r: np.ndarray | None = None) -> float:
    """The best held-out chi2 improvement any candidate gives over the base with its structural level
    (``aug`` from :func:`with_level`), on the data ``r`` (default ``aug.r``)."""
    c0, _ = heldout(aug, None, folds, r)
    return max(c0 - heldout(aug, c, folds, r)[0] for c in cands)
