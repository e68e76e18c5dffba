"""Can the data tell the best candidate from a close rival?  A parametric-bootstrap test of non-nested models.

Two candidates whose held-out chi2 differ by less than the pure-noise claim threshold are not thereby
indistinguishable: that threshold is the largest improvement *any* candidate gets from pure noise, a much
wider spread than the difference between two given candidates when one of them is true.  The question
asked here is the one of Cox (1961, 1962) for non-nested hypotheses, answered by simulation as in
Williams (1970): *if the rival were the truth, how often would it lose to the best candidate by as much
as it does on these data?*

1. fit the rival (with the base) to the data: its prediction is the rival hypothesis' mean;
2. draw data sets = that mean + noise of the diagnosis' error model (the rows are whitened, so the noise
   is standard normal; the prior pseudo-observations keep their values: they are knowledge, not data);
3. on each, the held-out chi2 difference rival - best, scored exactly as on the real data;
4. p = the share of draws where the rival loses by at least the observed margin.  A small p (below
   ``alpha``) rejects the rival: the data would rarely look like this if it were the truth.

The test is one-sided in the rival's disfavour only; the best candidate's own adequacy is checked
elsewhere (its held-out remainder against the pure-noise quantile).  The rival's coefficients are
estimated, not known, so the level is approximate: on a synthetic two-candidate problem a true rival
was rejected in 3-4 % of data sets at sizes where the other candidate still won 20-45 % of them
(tests/gap/test_gap_rivals.py).  Each rival is tested on its own at ``alpha``; with several rivals the
chance that at least one true rival is rejected is larger, which is why the diagnosis asks this only
after the gap and the best candidate have passed their own tests.

References: D. R. Cox, "Tests of separate families of hypotheses", Proc. 4th Berkeley Symp. 1 (1961)
105-123, and "Further results on tests of separate families of hypotheses", J. R. Stat. Soc. B 24 (1962)
406-424; D. A. Williams, "Discrimination between regression models to determine the pattern of enzyme
synthesis in synchronous cell cultures", Biometrics 26 (1970) 23-32 (the simulated version).
"""

from __future__ import annotations

import numpy as np

from engine_model.gap.fitting import FitProblem, columns_of, fit_all, heldout

__all__ = ["rival_p_value", "rival_p_values", "RIVAL_ALPHA", "RIVAL_DRAWS"]

#: Level at which a rival is rejected (the same 5 % as the claim threshold's false-claim rate).
RIVAL_ALPHA = 0.05
#: Simulated data sets per rival (the p-value's resolution is 1 / (draws + 1)).
RIVAL_DRAWS = 200


def rival_p_value(prob: FitProblem, folds: np.ndarray, best: str, rival: str, n_draws: int = RIVAL_DRAWS,
                  seed: int = 0) -> float:
    """P-value of the hypothesis "``rival`` is the truth" against the observed margin by which ``best``
    beats it in held-out chi2 (module docstring).  1.0 when the rival does not lose at all."""
    ho_best, _ = heldout(prob, best, folds)
    ho_rival, _ = heldout(prob, rival, folds)
    d_obs = ho_rival - ho_best
    if d_obs <= 0:
        return 1.0
    x, _, _ = fit_all(prob, rival)
    mean = prob.a[:, columns_of(prob, rival)] @ x
    data = prob.point >= 0
    rng = np.random.default_rng(seed + 104729)
    hits = 0
    for _ in range(n_draws):
        r = prob.r.copy()
        r[data] = mean[data] + rng.standard_normal(int(data.sum()))
        d = heldout(prob, rival, folds, r)[0] - heldout(prob, best, folds, r)[0]
        hits += d >= d_obs
    return float((1 + hits) / (n_draws + 1))


def rival_p_values(prob: FitProblem, folds: np.ndarray, best: str, rivals: list[str],
                   n_draws: int = RIVAL_DRAWS, seed: int = 0) -> dict[str, float]:
    """:func:`rival_p_value` of every rival; a rival survives when its p-value is at least :data:`RIVAL_ALPHA`."""
    return {c: rival_p_value(prob, folds, best, c, n_draws, seed) for c in rivals}
