"""Order of the gap diagnosis' ranking (engine_model.gap.verdict.order_ranking).

Held-out chi2 decides which candidates lead (within the noise threshold of the best); AIC orders the lead.
The synthetic problem mirrors the diagnosis' hardest in-library pair: two torque-only losses over speed, a
1/speed law (blow-by) against a constant (friction level), with a smooth base (linear and quadratic in
speed) that absorbs part of both, unit noise on 32 points.
"""

import numpy as np
import pandas as pd
import pytest

from engine_model.gap.fitting import FitProblem, fit_all, heldout, make_folds
from engine_model.gap.verdict import order_ranking

N = 32
KRPM = np.linspace(3.0, 13.0, N)
A = np.column_stack([KRPM / 10, (KRPM / 10) ** 2, 6.0 / KRPM, np.ones(N)])
COLS = {"inverse_speed": [2], "constant": [3]}


def problem(r: np.ndarray) -> FitProblem:
    return FitProblem(r=r, a=A, point=np.arange(N), output=np.zeros(N, int), base_cols=[0, 1], cand_cols=COLS,
                      lo=np.full(4, -np.inf), hi=np.full(4, np.inf))


def ranking(prob: FitProblem, folds: np.ndarray) -> pd.DataFrame:
    rows = []
    for c in COLS:
        chi = fit_all(prob, c)[1]
        rows.append({"effect": c, "heldout_chi2": heldout(prob, c, folds)[0], "aic": chi + 2 * 3,
                     "bic": chi + 3 * np.log(N)})
    return pd.DataFrame(rows)


def test_the_lead_is_ordered_by_aic_and_the_rest_by_heldout_chi2():
    rank = pd.DataFrame({"effect": list("abcde"),
                         "heldout_chi2": [10.0, 11.0, 12.0, 30.0, 25.0],
                         "aic": [20.0, 15.0, 18.0, 1.0, 2.0],
                         "bic": [0.0] * 5})
    out = order_ranking(rank, thr=5.0)
    # lead a, b, c (within 5 of 10) by AIC: b, c, a; then e, d by held-out chi2 although d has the lowest AIC
    assert list(out["effect"]) == ["b", "c", "a", "e", "d"]
    assert list(order_ranking(rank, thr=0.5)["effect"]) == ["a", "b", "c", "e", "d"]   # lead of one


@pytest.mark.parametrize("size", [4.0, 6.0])
def test_aic_in_the_lead_names_the_true_loss_more_often_than_heldout_alone(size):
    """Truth: the 1/speed loss at ``size`` sigma at 6000 rpm.  Over 300 data sets (fold seed = noise seed),
    with both candidates in the lead, AIC ordering names the truth more often than held-out chi2 alone
    (measured 228 vs 222 at size 4, 257 vs 250 at size 6; a decision flips only on an exact tie, so the
    margin is not at solver noise), and more often than chance (>= 65 %)."""
    by_aic = by_heldout = 0
    for seed in range(300):
        folds = make_folds(N, np.ones(N, bool), 5, seed)
        prob = problem(size * A[:, 2] + np.random.default_rng(seed).standard_normal(N))
        rank = ranking(prob, folds)
        by_aic += order_ranking(rank, thr=np.inf)["effect"].iloc[0] == "inverse_speed"
        by_heldout += order_ranking(rank, thr=0.0)["effect"].iloc[0] == "inverse_speed"
    assert by_aic > by_heldout
    assert by_aic / 300 >= 0.65
