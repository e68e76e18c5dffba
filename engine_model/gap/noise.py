"""Pure-noise reference distributions of the gap diagnosis, on the diagnosis' own design.

Every statistic the claim rule compares is compared with what pure noise (the error model's noise, the base
refitted as on the data) gives on the same plan, the same folds and the same candidates:

* the claim threshold: the (1 - alpha) quantile of the best candidate's held-out improvement;
* the 99 % quantile of the base's held-out chi2 (is the gap established?);
* per candidate, the 99 % quantile of the held-out chi2 with that candidate fitted beside the base: what
  the remainder of a candidate that is exactly the truth looks like (fitting it costs held-out chi2 on
  noise, 0-5 % at the 99 % quantile on the default plan), so its remainder is judged against it;
* the mean held-out chi2 of the base on noise (the "noise level" the gap is measured above).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from engine_model.gap.fitting import FitProblem, heldout

__all__ = ["NoiseReference", "noise_reference", "expected_noise_chi2"]

#: Quantile of the base's (and a candidate's) held-out chi2 on pure noise that the claim rule uses.
CHI2_QUANTILE = 0.99


@dataclass(frozen=True)
class NoiseReference:
    """Pure-noise Monte Carlo summary (see the module docstring)."""

    threshold: float                 # (1 - alpha) quantile of the best held-out improvement
    base_chi2_q: float               # CHI2_QUANTILE of the base's held-out chi2
    mean_best_improvement: float
    candidate_chi2_q: dict = field(default_factory=dict)   # candidate -> CHI2_QUANTILE of its held-out chi2

    def remainder_q(self, candidate: str | None) -> float:
        """The quantile a candidate's held-out remainder is judged against (the base's for None)."""
        return self.candidate_chi2_q.get(candidate, self.base_chi2_q) if candidate else self.base_chi2_q


def noise_reference(prob: FitProblem, folds: np.ndarray, cands: list[str], key: tuple, n_noise: int, alpha: float,
                    seed: int, cache: dict | None) -> NoiseReference:
    """``n_noise`` pure-noise data sets on the design of ``prob`` (cached under ``key``)."""
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
    out = NoiseReference(threshold=float(np.quantile(best_d, 1.0 - alpha)),
                         base_chi2_q=float(np.quantile(chi_null, CHI2_QUANTILE)),
                         mean_best_improvement=float(np.mean(best_d)),
                         candidate_chi2_q={c: float(np.quantile(v, CHI2_QUANTILE)) for c, v in chi_c.items()})
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
