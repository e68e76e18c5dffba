"""The speed-dependent knock multiplier (engine_model.knock.speed_term) on synthetic evidence with a known answer."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from engine_model.knock import calibrate_knock, calibrate_knock_speed, multiplier_at, with_speed_multiplier
from engine_model.knock.speed_term import SLOPE_PRIOR_SD


def _evidence(speeds, a, b, scatter=0.05, seed=0, per_speed=24):
    """Sweeps at each speed: ln K of the fastest cycles from -0.6 to +0.4 around the true border ln m(n); knock
    drawn with probit scatter ``scatter`` (the bench's detection)."""
    rng = np.random.default_rng(seed)
    rows = []
    for n in speeds:
        lnm = a + b * math.log(n / 6000.0)
        for y in lnm + np.linspace(-0.6, 0.4, per_speed):
            rows.append({"speed_rpm": float(n), "ln_ki_cycle_m1": float(y),
                         "knock": bool(y - lnm + scatter * rng.standard_normal() >= 0.0)})
    return pd.DataFrame(rows)


@pytest.mark.parametrize("b_true", [-0.3, 0.0, 0.25])
def test_recovers_a_known_speed_slope_from_onsets_at_three_speeds(b_true):
    a_true = math.log(0.75)
    fit = calibrate_knock_speed(_evidence((3000.0, 6000.0, 12000.0), a_true, b_true))
    for n in (3000.0, 6000.0, 9000.0, 12000.0):
        want = math.exp(a_true + b_true * math.log(n / 6000.0))
        assert fit.multiplier_median(n) == pytest.approx(want, rel=0.05), n
    med, lo, hi = fit.slope()
    assert lo <= b_true <= hi or abs(med - b_true) < 0.05
    assert hi - lo < 0.3 * SLOPE_PRIOR_SD * 2            # the data, not the prior, set the slope


def test_onsets_at_one_speed_leave_the_slope_at_its_prior():
    fit = calibrate_knock_speed(_evidence((3000.0,), math.log(0.75), 0.0))
    assert fit.multiplier_median(3000.0) == pytest.approx(0.75, rel=0.05)
    med, lo, hi = fit.slope()
    # the prior's 68 % interval is +-0.5; the data at one speed pin a + b ln(0.5), not b
    assert hi - lo > 0.6


def test_no_usable_evidence_is_refused():
    ev = pd.DataFrame({"speed_rpm": [6000.0], "ln_ki_cycle_m1": [np.nan], "knock": [False]})
    with pytest.raises(ValueError, match="no evidence row"):
        calibrate_knock_speed(ev)


def test_tables_use_the_speed_term_only_where_the_data_inform_the_slope():
    a = math.log(0.75)
    assert calibrate_knock_speed(_evidence((3000.0, 6000.0, 12000.0), a, 0.2, per_speed=12)).supported
    assert not calibrate_knock_speed(_evidence((3000.0,), a, 0.0, per_speed=12)).supported
    # knock-free points only (as Table 2): a bound on the multiplier, nothing on its slope
    clean = _evidence((8000.0, 9000.0, 10000.0, 11000.0), a, 0.0, per_speed=6).assign(knock=False)
    assert not calibrate_knock_speed(clean).supported


def test_table_multiplier_is_the_one_parameter_tables_at_the_reference_speed():
    """At n_ref the slope drops out: the predictive 2 % quantile equals the one-parameter fit's on the same
    evidence (the two fits share the link and the priors of a and sigma; grids and draws differ by ~1 %)."""
    ev = _evidence((6000.0,), math.log(0.75), 0.0)
    one = calibrate_knock(ev)
    two = calibrate_knock_speed(ev)
    assert float(two.table_multiplier(6000.0)[0]) == pytest.approx(one.multiplier_table, rel=0.03)
    # the knock-prone side: below the median at every speed, and the prior's slope widens it away from the data
    n = np.array([3000.0, 6000.0, 12000.0])
    tab = two.table_multiplier(n)
    med = np.array([two.multiplier_median(v) for v in n])
    assert (tab < med).all()
    assert med[0] / tab[0] > 1.05 * med[1] / tab[1] and med[2] / tab[2] > 1.05 * med[1] / tab[1]


def test_multiplier_at_interpolates_in_log_speed_and_holds_beyond_the_list():
    t = [[4000.0, 0.5], [8000.0, 1.0]]
    m = multiplier_at(t, [2000.0, 4000.0, 4000.0 * math.sqrt(2.0), 8000.0, 16000.0])
    np.testing.assert_allclose(m, [0.5, 0.5, math.sqrt(0.5), 1.0, 1.0], rtol=1e-12)
    plan = pd.DataFrame({"speed_rpm": [4000.0, 8000.0]})
    assert with_speed_multiplier(plan, t)["spec.knock.delay_multiplier"].tolist() == [0.5, 1.0]
    with pytest.raises(ValueError, match="table_multipliers"):
        multiplier_at([[4000.0, -1.0]], 5000.0)
