"""Best pair of effects (engine_model.gap.pairs) on the synthetic linear problem of test_gap_diagnose.

Two planted effects must be named as the pair; one planted effect or pure noise must not make a pair
claim more often than the 5 % each noise threshold is set for allows (counted over 10 noise seeds, with
a margin of one trial for the binomial scatter: P(>= 2 of 10 | p = 0.05) = 8.6 %, P(>= 3) = 1.2 %).
"""

import numpy as np
import pytest

from engine_model.gap import NO_PAIR, best_pair
from engine_model.gap.diagnose import diagnose
from test_gap_diagnose import _delta, _measure, _synthetic

SEEDS = range(100, 110)


@pytest.fixture(scope="module")
def lin():
    return _synthetic()


def _pairs(lin, delta):
    out = []
    for s in SEEDS:
        d = diagnose(lin, _measure(lin, delta, s), n_noise=100)
        out.append((d, best_pair(d, n_noise=100)))
    return out


@pytest.mark.slow
def test_two_planted_effects_are_named_as_the_pair(lin):
    delta = _delta(lin, "heat_transfer") + _delta(lin, "friction", base_shift=False)
    res = _pairs(lin, delta)
    named = [tuple(sorted(p.named)) if p.named else None for _, p in res]
    assert named.count(("friction", "heat_transfer")) >= 9, named
    for d, p in res:
        top = p.table.iloc[0]
        # the pair removes more of the held-out gap than the best single candidate did
        assert top["heldout_chi2"] < d.ranking["heldout_chi2"].min()
        assert top["improvement_over_best_single"] > p.excess_threshold
        assert "heat_transfer" in top["params"] and "friction" in top["params"]


@pytest.mark.slow
@pytest.mark.parametrize("effect", ["heat_transfer", "restrictor"])
def test_one_planted_effect_makes_no_pair_claim(lin, effect):
    res = _pairs(lin, _delta(lin, effect))
    claims = [p.named for _, p in res if p.named]
    assert len(claims) <= 2, claims
    # whatever the pair verdict, the planted effect is in the best pair
    assert all(effect in (p.table["effect_a"].iloc[0], p.table["effect_b"].iloc[0]) for _, p in res)


@pytest.mark.slow
def test_pure_noise_makes_no_pair_claim(lin):
    res = _pairs(lin, np.zeros(len(lin.columns)))
    claims = [p.named for _, p in res if p.named]
    assert len(claims) <= 1, claims
    assert all(NO_PAIR in p.statement.lower() for _, p in res if not p.named)


def test_thresholds_come_from_noise(lin):
    d = diagnose(lin, _measure(lin, _delta(lin, "friction"), 1), n_noise=100)
    p1 = best_pair(d, n_noise=100, alpha=0.05)
    p2 = best_pair(d, n_noise=100, alpha=0.01)
    assert p2.threshold > p1.threshold and p2.excess_threshold > p1.excess_threshold
    assert len(p1.table) == len(d.ranking) * (len(d.ranking) - 1) // 2


def test_bad_input(lin):
    d = diagnose(lin, _measure(lin, _delta(lin, "friction"), 1), n_noise=50)
    with pytest.raises(ValueError, match="not part of the diagnosis"):
        best_pair(d, candidates=["friction", "humidity"])
    with pytest.raises(ValueError, match="unknown effect .humidityx."):
        best_pair(d, candidates=["friction", "humidityx"])
    with pytest.raises(ValueError, match="at least two"):
        best_pair(d, candidates=["friction"])
    d.extra.pop("problem")
    with pytest.raises(ValueError, match="problem"):
        best_pair(d)


def test_noise_closed_form_equals_the_fold_by_fold_fit(lin):
    from engine_model.gap.fitting import heldout_columns
    from engine_model.gap.pairs import heldout_chi2_linear

    d = diagnose(lin, _measure(lin, np.zeros(len(lin.columns)), 5), n_noise=20)
    prob, folds = d.extra["problem"], d.extra["folds"]
    e = np.random.default_rng(0).standard_normal((prob.r.size, 4))
    for cols in (prob.base_cols, prob.base_cols + prob.cand_cols["friction"] + prob.cand_cols["heat_transfer"]):
        direct = [heldout_columns(prob, cols, folds, e[:, j])[0] for j in range(4)]
        np.testing.assert_allclose(heldout_chi2_linear(prob, cols, folds, e), direct, rtol=1e-9)
