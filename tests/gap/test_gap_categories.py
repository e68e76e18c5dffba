"""Answer categories of the gap diagnosis on a synthetic linear problem (no simulation).

Sensor faults, claim withholding (range edge, remainder above noise), the base prior, localisation
against pure noise and an energy chain that books only significant shares.  The hand-made
linearisation of ``test_gap_diagnose`` is used with one change: the burn's exhaust-temperature
sensitivity varies over the map (as in the real model), so a burn shift plus an exhaust-T offset is
not an exact copy of a torque-only loss.
"""

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from engine_model.gap.diagnose import BASE_PRIOR_SD, CATEGORIES, diagnose
from engine_model.gap.fitting import heldout
from engine_model.gap.linear import BaseModel
from engine_model.gap.localise import energy_chain
from engine_model.gap.sensors import SENSOR_FAULTS, candidate, sensor_name, with_sensor_faults

from engine_model.gap.residuals import UNCERTAINTY

from test_gap_diagnose import OUTS, _delta, _synthetic


def _lin():
    lin = _synthetic()
    s = (lin.points["speed_rpm"].to_numpy() - 9000) / 3000
    t = lin.points["throttle_pct"].to_numpy()
    j = lin.columns.index(("base", "bdur_offset_deg"))
    lin.jac[:, 2, j] = (12 + 5 * s + 0.05 * (t - 60)) / 2.0
    # the default bases leave Wiebe m at its prior (engine_model.gap.linear.COMBUSTION_BASE): a free m is a
    # torque-only knob that trades exhaust T against torque together with the burn duration
    keep = [k for k, c in enumerate(lin.columns) if c != ("base", "m_offset")]
    return replace(lin, columns=[lin.columns[k] for k in keep], steps=lin.steps[keep], jac=lin.jac[:, :, keep],
                   theta={k: v for k, v in lin.theta.items() if k != "m_offset"},
                   base=BaseModel(params=("bdur_offset_deg", "bdur_speed_deg_per_krpm")))


def _measure(lin, delta, seed):
    """Bench readings: the linear model at ``delta`` plus measurement noise on every output of ``lin``."""
    rng = np.random.default_rng(seed)
    y = lin.predict(delta)
    sig = np.column_stack([UNCERTAINTY[o][1] * np.abs(y[:, k]) if UNCERTAINTY[o][0] == "rel"
                           else np.full(len(y), UNCERTAINTY[o][1]) for k, o in enumerate(lin.outputs)])
    y = y + sig * rng.standard_normal(y.shape)
    return pd.DataFrame({"point_id": lin.points["point_id"], **{o: y[:, k] for k, o in enumerate(lin.outputs)}})


def _fault(m, channel, offset=0.0, gain_pct=0.0):
    m = m.copy()
    m[channel] = m[channel] * (1 + gain_pct / 100) + offset
    return m


def test_sensor_columns_are_exact_and_only_touch_their_channel():
    lin = with_sensor_faults(_lin())
    for ch in ("air_mass_flow_kg_h", "exhaust_temp_k"):
        cols = lin.column_index(sensor_name(ch))
        assert cols, ch
        k = OUTS.index(ch)
        for j in cols:
            assert np.all(lin.jac[:, [i for i in range(len(OUTS)) if i != k], j] == 0)
        off = lin.columns.index((sensor_name(ch), "offset"))
        assert np.allclose(lin.jac[:, k, off], 1.0)
    # no torque candidate: an offset is the friction level, a gain the transmission efficiency
    assert not lin.column_index(sensor_name("brake_torque_nm"))
    assert candidate("sensor_exhaust_temp_k") is SENSOR_FAULTS["sensor_exhaust_temp_k"]


@pytest.mark.slow
@pytest.mark.parametrize("channel,offset,gain", [("air_mass_flow_kg_h", 0.0, 3.0), ("fuel_mass_flow_kg_h", 0.0, -3.0)])
def test_a_single_channel_fault_is_named_as_a_sensor_fault_on_that_channel(channel, offset, gain):
    lin = _lin()
    if channel not in lin.outputs:                 # give the synthetic engine a fuel meter: fuel = air / 13
        k = lin.outputs.index("air_mass_flow_kg_h")
        lin = replace(lin, outputs=lin.outputs + (channel,), y_ref=np.column_stack([lin.y_ref, lin.y_ref[:, k] / 13]),
                      jac=np.concatenate([lin.jac, lin.jac[:, [k], :] / 13], axis=1))
    cats = []
    for seed in range(4):
        m = _fault(_measure(lin, _delta(lin, None), seed), channel, offset, gain)
        d = diagnose(lin, m, n_noise=100, seed=0)
        assert d.category in CATEGORIES
        cats.append((d.category, d.named))
        if d.category in ("explained", "sensor fault"):      # never a confident wrong claim
            assert d.named == sensor_name(channel), cats
    assert sum(c == ("sensor fault", sensor_name(channel)) for c in cats) >= 3, cats


@pytest.mark.slow
def test_a_fault_the_burn_law_can_mimic_is_never_pinned_on_something_else():
    """Torque and exhaust T both move with the burn: a burn shift plus a two-channel effect can copy an
    exhaust-T offset, so the answer may be 'indistinguishable', but the fault is among the named."""
    lin = _lin()
    channel = "exhaust_temp_k"
    for seed in range(4):
        d = diagnose(lin, _fault(_measure(lin, _delta(lin, None), seed), channel, 20.0), n_noise=100, seed=0)
        assert d.category in ("sensor fault", "indistinguishable"), (d.category, d.best)
        named = [d.named] if d.named else d.extra["indistinguishable"]
        assert sensor_name(channel) in named, (d.category, named)
        if d.category == "indistinguishable":
            assert "Indistinguishable" in d.statement and "not claimed" in d.statement


def test_a_physical_effect_is_not_turned_into_a_sensor_fault():
    lin = _lin()
    for effect in ("heat_transfer", "restrictor"):
        named = [diagnose(lin, _measure(lin, _delta(lin, effect), s), n_noise=100, seed=0).named for s in range(3)]
        assert named.count(effect) >= 2, (effect, named)


@pytest.mark.slow
def test_null_is_no_significant_gap_and_localises_nothing():
    lin = _lin()
    cats, flagged = [], 0
    for seed in range(12):
        d = diagnose(lin, _measure(lin, _delta(lin, None), seed), n_noise=100, seed=0)
        cats.append(d.category)
        flagged += bool(d.regions["significant"].any())
    # each rule is set for 5 % per trial: 12 trials with 4 or more is a failure (P < 0.3 %)
    assert sum(c not in ("no significant gap", "not in the library") for c in cats) <= 3, cats
    assert flagged <= 3, flagged


def test_an_effect_beyond_its_range_is_only_partly_explained():
    lin = _lin()
    cats = []
    for seed in range(3):
        # twice the friction range's upper end: the fit sits at the edge, the claim is withheld
        d = diagnose(lin, _measure(lin, _delta(lin, "friction", scale=8.0), seed), n_noise=100, seed=0,
                     sensor_faults=False)
        row = d.ranking.iloc[0]
        cats.append(d.category)
        if d.best == "friction":
            assert row["at_range_bound"], row
    assert all(c == "partly explained" for c in cats), cats
    assert "Partly explained" in d.statement


def test_a_localised_gap_is_localised_in_its_band():
    lin = _lin()
    n = lin.points["speed_rpm"].to_numpy()
    hits = 0
    for seed in range(3):
        m = _measure(lin, _delta(lin, None), seed)
        band = n > np.quantile(n, 2 / 3)
        m.loc[band, "air_mass_flow_kg_h"] *= 1.05
        d = diagnose(lin, m, n_noise=100, seed=0)
        sig = d.regions[d.regions["significant"]]
        hits += bool(len(sig)) and set(sig["output"]) == {"air_mass_flow_kg_h"} and all(
            float(r.split("-")[0]) >= np.quantile(n, 2 / 3) - 1 for r in sig["region"])
    assert hits >= 2


def test_prior_rows_are_fitted_but_never_held_out():
    lin = _lin()
    m = _measure(lin, _delta(lin, None), 0)
    d = diagnose(lin, m, n_noise=50, seed=0)
    prob, folds = d.extra["problem"], d.extra["folds"]
    n_prior = int(np.count_nonzero(prob.point < 0))
    assert n_prior == len([p for p in lin.base.params if p in BASE_PRIOR_SD]) + sum(
        len(e.params) for e in SENSOR_FAULTS.values() if e.name in d.ranking["effect"].tolist())
    assert prob.n_obs == prob.r.size - n_prior
    _, res = heldout(prob, None, folds)
    assert np.all(res[prob.point < 0] == 0)
    # the prior enters the fits: without it the same data give another base and no pseudo-observation
    # for the base; a 1000-times tighter prior pins the base at the DOE prior (theta 0)
    d0 = diagnose(lin, m, n_noise=50, seed=0, base_prior_sd=None)
    assert d0.extra["problem"].n_obs == prob.n_obs
    assert int(np.count_nonzero(d0.extra["problem"].point < 0)) == n_prior - len(lin.base.params)
    assert d0.base_theta["bdur_offset_deg"] != pytest.approx(d.base_theta["bdur_offset_deg"], abs=1e-9)
    tight = diagnose(lin, m, n_noise=50, seed=0, base_prior_sd={p: s / 1000 for p, s in BASE_PRIOR_SD.items()})
    assert abs(tight.base_theta["bdur_offset_deg"]) < 0.05 < abs(d0.base_theta["bdur_offset_deg"])


def test_energy_chain_books_no_share_when_torque_agrees():
    lin = _lin()
    y = lin.y_ref.copy()
    rng = np.random.default_rng(0)
    y = y * (1 + 0.001 * rng.standard_normal(y.shape))
    y_t = y.copy()
    y_t[:, 2] += 25.0                      # exhaust T reads 25 K high, torque unchanged
    ch = energy_chain(lin, list(OUTS), y_t, lin.y_ref, np.ones_like(y, bool)).set_index("stage")
    assert not ch["booked"].any(), ch
    y_l = y.copy()
    y_l[:, 1] *= 0.97                       # a torque-only loss: booked at the mechanical stage only
    ch = energy_chain(lin, list(OUTS), y_l, lin.y_ref, np.ones_like(y, bool)).set_index("stage")
    assert ch.loc["mechanical + transmission", "booked"] and not ch.loc["air in", "booked"]
    assert not ch.loc["indicated (combustion, heat)", "booked"]
    assert ch.loc["mechanical + transmission", "mean_pct"] == pytest.approx(-3.0, abs=0.3)


@pytest.mark.slow
def test_a_close_rival_of_another_kind_is_tested_and_the_verdict_follows_the_test():
    """An exhaust-T offset of 30-35 K: heat transfer or friction scores within the noise threshold in some
    trials.  Such a rival blocks the claim exactly when the parametric test cannot reject it (p >= 5 %), and
    the verdict names it as rejected otherwise; over 12 trials the test rejects a rival at least once
    (measured: 6 of 12, p 0.02-0.04)."""
    from engine_model.gap.rivals import RIVAL_ALPHA
    lin = _lin()
    rejected = 0
    for off in (30.0, 35.0):
        for seed in range(6):
            d = diagnose(lin, _fault(_measure(lin, _delta(lin, None), seed), "exhaust_temp_k", off),
                         n_noise=100, seed=0)
            rp = d.extra["rival_p"]
            standing = [c for c, p in rp.items() if p >= RIVAL_ALPHA]
            if standing:
                assert d.category == "indistinguishable" and set(standing) <= set(d.extra["indistinguishable"])
            elif rp:
                assert d.category == "sensor fault" and d.named == "sensor_exhaust_temp_k"
                assert "rejected by a parametric test" in d.statement
                assert all(f"'{c}' (p = " in d.statement for c in rp)
                rejected += 1
    assert rejected >= 1


def test_nothing_is_claimed_on_a_gap_that_noise_could_leave():
    """Claim test 0: a planted transmission loss at a fifth of its realistic size.  On every seed a candidate
    beats the noise threshold of the improvement, but the base's held-out chi2 stays within the pure-noise 99 %
    quantile: the gap is not established, so nothing is claimed.  (Without test 0 every one of these trials was
    claimed, half of them as another effect: heat transfer or the restrictor.)  Sensor faults are left out, so
    no rival of another kind withholds the claim for its own reason."""
    lin = _lin()
    for seed in range(4):
        d = diagnose(lin, _measure(lin, _delta(lin, "transmission_efficiency", scale=0.2), seed), n_noise=100,
                     seed=0, sensor_faults=False)
        assert d.extra["heldout_chi2_base"] <= d.noise_chi2_q
        assert d.ranking["heldout_improvement"].iloc[0] > d.threshold      # a candidate beats noise ...
        assert d.named is None and d.category == "no significant gap"       # ... but no claim
        assert "would each reduce it by more than noise alone" in d.statement
