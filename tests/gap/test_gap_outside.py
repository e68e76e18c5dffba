"""The outside-library gap benchmark: case truths, scoring, report columns.

Fast unit tests for the scorer and the reading-side truths (no simulation); one slow module-scoped run of
the machinery on a 10-point Sobol' plan, four cases + the null and a 3-effect library (~250 simulations).
"""

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from engine_model.gap.bench_procedure import BENCH_SOLVER
from engine_model.gap.outside import (CATEGORIES, OUTSIDE_COLUMNS, category_of, outside_cases, prepared_of,
                                      run_outside_benchmark, score_diagnosis, summarise_outside, overall_outside,
                                      write_outside_report)
from engine_model.sim import simulate

from conftest import SIM_WORKERS

MEASURED = ["brake_torque_nm", "air_mass_flow_kg_h", "fuel_mass_flow_kg_h", "exhaust_temp_k"]
CASES = {c.name: c for c in outside_cases()}


def _rows(n=12, seed=3):
    rng = np.random.default_rng(seed)
    speed = rng.uniform(5000, 12500, n)
    thr = rng.uniform(30, 100, n)
    tq = 20 + 0.4 * thr
    df = pd.DataFrame({"point_id": [f"p{i}" for i in range(n)], "speed_rpm": speed, "throttle_pct": thr,
                       "spark_deg_btdc": 40.0, "lambda": 0.9, "brake_torque_nm": tq,
                       "air_mass_flow_kg_h": 0.02 * speed * thr / 100, "fuel_mass_flow_kg_h": 0.0015 * speed * thr / 100,
                       "exhaust_temp_k": 1100 + 0.01 * speed})
    df["brake_power_kw"] = df["brake_torque_nm"] * 2 * np.pi * df["speed_rpm"] / 60e3
    df["bsfc_g_kwh"] = df["fuel_mass_flow_kg_h"] * 1e3 / df["brake_power_kw"]
    return df


def _changed(a, b):
    return [c for c in MEASURED if not np.allclose(a[c].to_numpy(float), b[c].to_numpy(float), rtol=1e-12, atol=0)]


# --------------------------------------------------------------------------- reading-side truths (fast)

@pytest.mark.parametrize("name", [c.name for c in outside_cases() if c.kind == "sensor fault"])
def test_sensor_fault_changes_only_its_channel(name):
    c = CASES[name]
    m = _rows()
    assert _changed(m, c.readings(m)) == [c.channel]
    from engine_model.gap.sensors import SENSOR_FAULTS
    if f"sensor_{c.channel}" in SENSOR_FAULTS:       # a channel with a fault candidate: that one is the answer
        assert f"sensor_{c.channel}" in c.accept
    else:                                           # torque: its offset is the friction level to the data
        assert c.accept == {"friction"}


def test_reading_truths_change_the_channels_their_form_says():
    m = _rows()
    assert _changed(m, CASES["torque_load_loss"].readings(m)) == ["brake_torque_nm"]
    assert _changed(m, CASES["friction_speed_squared"].readings(m)) == ["brake_torque_nm"]
    assert _changed(m, CASES["exhaust_port_cooling"].readings(m)) == ["exhaust_temp_k"]
    assert set(_changed(m, CASES["ve_dip_10k"].readings(m))) == {"brake_torque_nm", "air_mass_flow_kg_h",
                                                                 "fuel_mass_flow_kg_h"}
    # torque-only load loss grows with throttle; speed-squared friction with speed; VE dip localised
    t = CASES["torque_load_loss"].readings(m)
    loss = 1 - t["brake_torque_nm"] / m["brake_torque_nm"]
    assert np.corrcoef(loss, m["throttle_pct"])[0, 1] > 0.99
    f = CASES["friction_speed_squared"].readings(m)
    dtq = m["brake_torque_nm"] - f["brake_torque_nm"]
    assert np.allclose(dtq / m["speed_rpm"] ** 2, (dtq / m["speed_rpm"] ** 2).iloc[0])
    v = CASES["ve_dip_10k"].readings(m)
    r = v["air_mass_flow_kg_h"] / m["air_mass_flow_kg_h"]
    far = (m["speed_rpm"] - 10200).abs() > 2000
    assert (r[far] > 0.995).all() and r.min() < 1.0
    # power and BSFC follow the changed torque
    assert np.allclose(t["brake_power_kw"], t["brake_torque_nm"] * 2 * np.pi * t["speed_rpm"] / 60e3)


def test_case_list_covers_the_issue():
    kinds = pd.Series([c.kind for c in outside_cases()]).value_counts()
    assert kinds["functional form"] >= 3 and kinds["sensor fault"] >= 3 and kinds["structural"] >= 2
    assert kinds["null"] == 1
    for c in outside_cases():
        assert (c.readings is None) != (c.spec_change is None) or c.kind == "null", c.name
    # at least three sensor faults only their own sensor candidate explains
    must = [c.name for c in outside_cases() if c.must_name]
    assert len(must) >= 3 and "sensor_torque_offset" not in must


# --------------------------------------------------------------------------- scoring (fast)

def _diag(named=None, best=None, category=None, at_bound="", ho=10.0, q=20.0, ho0=30.0):
    rank = pd.DataFrame({"effect": [best or named or "friction", "heat_transfer"], "heldout_chi2": [ho, ho + 5],
                         "at_range_bound": [at_bound, ""]})
    d = SimpleNamespace(named=named, best=best or named or "friction", ranking=rank, noise_chi2_q=q,
                        gap_before=1.5, gap_after=1.0, n_obs=10, extra={"heldout_chi2_base": ho0})
    if category is not None:
        d.category = category
    return d


def test_category_fallback_and_field():
    assert category_of(_diag(named="friction")) == "explained"
    assert category_of(_diag(named="sensor_exhaust_temp_k")) == "sensor fault"
    assert category_of(_diag(ho0=30.0, q=20.0)) == "not in the library"
    assert category_of(_diag(ho0=10.0, q=20.0)) == "no significant gap"
    assert category_of(_diag(named=None, category="partly explained")) == "partly explained"


def test_scoring_outcomes():
    null, sens, fr = CASES["none"], CASES["sensor_exhaust_t_offset"], CASES["friction_speed_squared"]
    assert score_diagnosis(null, _diag(ho0=5.0))["outcome"] == "right"
    s = score_diagnosis(null, _diag(named="friction"))
    assert s["outcome"] == "wrong_claim" and not s["confident_wrong"]
    s = score_diagnosis(sens, _diag(named="sensor_exhaust_temp_k", category="sensor fault"))
    assert s["outcome"] == "right" and s["sensor_right_channel"] and s["acceptable"]
    s = score_diagnosis(sens, _diag(named="heat_transfer", category="explained"))
    assert s["outcome"] == "wrong_claim" and not s["sensor_right_channel"]
    # a refusal on a sensor fault is not acceptable (it must be named); on friction it is
    s = score_diagnosis(sens, _diag(category="not in the library"))
    assert s["outcome"] == "refusal" and not s["acceptable"]
    assert score_diagnosis(fr, _diag(category="partly explained", best="friction"))["acceptable"]
    # "partly explained" with a named best is not a claim
    s = score_diagnosis(fr, _diag(named="blowby", category="partly explained"))
    assert s["outcome"] == "refusal" and s["named"] == ""
    # "indistinguishable" names nothing: a refusal, with the set and whether it holds an accepted name
    d = _diag(category="indistinguishable", best="friction")
    d.extra["indistinguishable"] = ["friction", "transmission_speed_loss"]
    s = score_diagnosis(fr, d)
    assert s["outcome"] == "refusal" and s["hedge_has_right"] and s["hedge_set"] == "friction,transmission_speed_loss"
    assert not score_diagnosis(sens, d)["hedge_has_right"]
    # confident wrong: at the range edge, or more left than the noise quantile
    assert score_diagnosis(fr, _diag(named="blowby", at_bound="fraction_at_6000"))["confident_wrong"]
    assert score_diagnosis(fr, _diag(named="blowby", ho=25.0, q=20.0))["confident_wrong"]
    assert not score_diagnosis(fr, _diag(named="friction", ho=25.0, q=20.0))["confident_wrong"]


def test_summary_counts():
    rows = []
    for case, outcome, conf in [("a", "right", False), ("a", "wrong_claim", True), ("n", "right", False),
                                ("n", "wrong_claim", False), ("s", "refusal", False)]:
        kind = {"a": "functional form", "n": "null", "s": "sensor fault"}[case]
        rows.append({"case": case, "kind": kind, "outcome": outcome, "confident_wrong": conf,
                     "acceptable": outcome == "right", "named": "x" if outcome == "wrong_claim" else "",
                     "category": "explained", "sensor_right_channel": False, "must_name": case == "s"})
    t = pd.DataFrame(rows)
    s = summarise_outside(t).set_index("kind")
    assert s.loc["functional form", "right_pct"] == 50 and s.loc["functional form", "confident_wrong"] == 1
    assert s.loc["sensor fault", "refusal_pct"] == 100
    ov = overall_outside(t)
    assert ov["null_false_claims"] == 1 and ov["null_trials"] == 2 and ov["right_or_refusal_pct"] == 60
    assert ov["sensor_must_name_trials"] == 1 and ov["sensor_right_channel_pct"] == 0
    assert ov["null_gap_reported"] == 2 and ov["null_hedged"] == 0


# --------------------------------------------------------------------------- the machinery (slow)

SLOW_CASES = ["friction_speed_squared", "sensor_exhaust_t_offset", "sensor_airflow_gain", "lumped_gas_exchange",
              "none"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from engine_model import doe

    plan = doe.sobol(10, bounds={"speed_rpm": (6000.0, 12500.0), "throttle_pct": (40.0, 100.0)}, seed=1)
    plan["spark_deg_btdc"] = np.round(plan["spark_deg_btdc"].to_numpy(float) - 4.0, 1)
    plan = plan[["point_id", "speed_rpm", "throttle_pct", "spark_deg_btdc", "lambda"]]
    res = run_outside_benchmark(plan=plan, seeds=2, null_seeds=3, cases=[CASES[n] for n in SLOW_CASES],
                                candidates=["transmission_efficiency", "friction", "heat_transfer"],
                                base_iterations=1, k_folds=4, n_noise=30,
                                evaluate_for=lambda sp: (lambda p: simulate(sp, p, BENCH_SOLVER, workers=SIM_WORKERS)))
    paths = write_outside_report(res, tmp_path_factory.mktemp("outside"))
    return res, paths


@pytest.mark.slow
def test_truths_differ_from_the_null_where_they_should(run):
    res, _ = run
    tr, pl = res["truth"], res["plans"]
    null = tr["none"]
    for name in ("sensor_exhaust_t_offset", "sensor_airflow_gain"):
        assert _changed(null, tr[name]) == [CASES[name].channel]
    assert _changed(null, tr["friction_speed_squared"]) == ["brake_torque_nm"]
    # the structural truth is another engine: its torque differs where it ran the same points
    s = tr["lumped_gas_exchange"].set_index("point_id")
    n = null.set_index("point_id")
    common = s.index.intersection(n.index)
    assert len(common) >= 5
    d = (s.loc[common, "brake_torque_nm"] - n.loc[common, "brake_torque_nm"]).abs()
    assert np.nanmax(d.to_numpy(float)) > 0.2
    assert list(pl["none"]["point_id"]) == list(pl["sensor_airflow_gain"]["point_id"])


@pytest.mark.slow
def test_trial_table_and_report(run):
    res, paths = run
    t = pd.read_csv(paths["trials"], keep_default_na=False, na_values=[""])
    assert tuple(t.columns[:len(OUTSIDE_COLUMNS)]) == OUTSIDE_COLUMNS
    counts = t["case"].value_counts()
    assert counts["none"] == 3 and all(counts[n] == 2 for n in SLOW_CASES if n != "none")
    assert set(t["outcome"]) <= {"right", "refusal", "wrong_claim"}
    assert set(t["category"]) <= set(CATEGORIES)
    assert sorted(set(t.loc[t["case"] == "none", "seed"])) == [0, 1, 2]
    s = pd.read_csv(paths["summary"], keep_default_na=False, na_values=[""])
    assert set(s["kind"]) == {"functional form", "sensor fault", "structural", "null"}
    assert (s["right_pct"] + s["refusal_pct"] + s["wrong_pct"]).round(6).eq(100).all()
    # the sensor faults and the friction truths are seen: their gap exceeds the null's
    g = t.groupby("case")["gap_before"].median()
    assert g["sensor_exhaust_t_offset"] > g["none"] + 0.3
    assert g["friction_speed_squared"] > g["none"]
    md = paths["markdown"].read_text()
    assert "Per case kind" in md and all(n in md for n in SLOW_CASES)


@pytest.mark.slow
def test_prepared_truths_rediagnose_without_simulation(run):
    res, _ = run
    again = run_outside_benchmark(prepared=prepared_of(res), seeds=2, null_seeds=3,
                                  cases=[CASES[n] for n in SLOW_CASES], k_folds=4, n_noise=30)
    cols = ["case", "seed", "category", "named", "best", "gap_before", "gap_after"]
    pd.testing.assert_frame_equal(res["table"][cols], again["table"][cols])
    assert again["timing"]["linearisation_s"] == 0.0
