"""Benchmark DOE (spark sweeps with a knock back-off), operating-point folds and the base choice (no cycle model).

A stand-in model gives the knock index as a known function of spark, so the operator's back-off and the
sweep layout can be checked exactly without the cost of the simulator.
"""

import numpy as np
import pandas as pd
import pytest

from engine_model import priors
from engine_model.gap.api import choose_base
from engine_model.gap.benchmark import benchmark_plan
from engine_model.gap.fitting import make_folds, operating_point_groups
from engine_model.bench import load_bench

SPARK_BASE = ("bdur_offset_deg", "bdur_speed_deg_per_krpm", "bdur_load_deg", "bdur_spark_deg_per_10deg")


def _knock_model(limit_offset):
    """Knock index 1 at (MBT prior - limit_offset(speed)), rising 0.1 per deg of advance beyond it."""
    def ev(p):
        n = p["speed_rpm"].to_numpy(float)
        t = p["throttle_pct"].to_numpy(float)
        s = p["spark_deg_btdc"].to_numpy(float)
        lim = np.atleast_1d(priors.spark_estimate(n, t)) - limit_offset(n)
        return pd.DataFrame({"knock_index": 1.0 + 0.1 * (s - lim)})
    return ev


def test_sobol_plan_knock_backoff():
    # knock limit 5 deg below the MBT prior below 9000 rpm, none (30 deg beyond) above
    ev = _knock_model(lambda n: np.where(n < 9000.0, 5.0, -30.0))
    plan = benchmark_plan(32, seed=0, evaluate=ev, design="sobol")
    assert len(plan) == 32 and plan["point_id"].is_unique and plan["op_id"].is_unique
    n, t = plan["speed_rpm"].to_numpy(float), plan["throttle_pct"].to_numpy(float)
    top = np.atleast_1d(priors.spark_estimate(n, t))
    # the operator backs off in 4 deg steps until the model's knock index is below 0.85: with the limit 5 deg
    # below MBT the index is 1.1-1.5 at 0-6 deg below the prior, 0.7-1.1 at -4 more, below 0.85 at -8 at the most
    low = n < 9000.0
    assert set(plan.loc[low, "knock_retard_deg"]) <= {4.0, 8.0} and (plan.loc[~low, "knock_retard_deg"] == 0).all()
    ki = 1.0 + 0.1 * (plan["spark_deg_btdc"].to_numpy() - (top - np.where(low, 5.0, -30.0)))
    assert (ki[low] < 0.85 + 0.01).all()
    # sparks 0-6 deg below the prior before the back-off
    back = plan["spark_deg_btdc"].to_numpy() + plan["knock_retard_deg"].to_numpy()
    assert ((top - back) >= -0.06).all() and ((top - back) <= 6.06).all()


def test_sobol_design_kept_and_bad_design_rejected():
    ev = _knock_model(lambda n: np.full_like(n, -30.0))
    plan = benchmark_plan(12, seed=0, evaluate=ev, design="sobol")
    assert len(plan) == 12 and plan["op_id"].is_unique
    with pytest.raises(ValueError, match="design 'grid' unknown"):
        benchmark_plan(12, evaluate=ev, design="grid")


def test_folds_keep_a_sweep_together():
    pts = pd.DataFrame({"speed_rpm": np.repeat([7000.0, 8000.0, 9000.0, 10000.0, 11000.0, 12000.0], 4),
                        "throttle_pct": np.repeat([40.0, 100.0, 70.0, 100.0, 55.0, 90.0], 4),
                        "lambda": 0.9, "spark_deg_btdc": np.tile([30.0, 34.0, 38.0, 42.0], 6)})
    g = operating_point_groups(pts)
    assert len(np.unique(g)) == 6
    folds = make_folds(len(pts), np.ones(len(pts), bool), 5, seed=1, groups=g)
    for k in np.unique(g):
        assert np.unique(folds[g == k]).size == 1
    assert np.unique(folds).size == 5
    # without groups (scattered points) every point is its own unit, as before
    f0 = make_folds(len(pts), np.ones(len(pts), bool), 5, seed=1)
    assert not all(np.unique(f0[g == k]).size == 1 for k in np.unique(g))


def test_base_gets_the_spark_slope_only_where_the_sparks_span_it():
    ev = _knock_model(lambda n: np.full_like(n, -30.0))
    ops = benchmark_plan(8, evaluate=ev, design="sobol")
    sweeps = pd.concat([ops.assign(spark_deg_btdc=ops["spark_deg_btdc"] - d,
                                   point_id=ops["point_id"] + f"-s{k}") for k, d in enumerate((12, 8, 4, 0))],
                       ignore_index=True)                     # 4-spark sweeps over 12 deg at 8 operating points
    sweep = choose_base(sweeps)
    assert sweep.params == ("bdur_offset_deg", "bdur_speed_deg_per_krpm", "bdur_load_deg", "bdur_spark_deg_per_10deg")
    # scattered, no knock: sparks 0-6 deg below the prior (span < 6 deg) -> no spark term
    plan = benchmark_plan(32, evaluate=ev, design="sobol")
    ds = plan["spark_deg_btdc"] - priors.spark_estimate(plan["speed_rpm"].to_numpy(), plan["throttle_pct"].to_numpy())
    assert np.ptp(ds) < 6.0
    assert choose_base(plan).params == ("bdur_offset_deg", "bdur_speed_deg_per_krpm", "bdur_load_deg")
    # scattered with knock back-offs below 9000 rpm: sparks spread over > 6 deg -> the spark term is carried
    knocky = benchmark_plan(32, evaluate=_knock_model(lambda n: np.where(n < 9000.0, 5.0, -30.0)), design="sobol")
    assert choose_base(knocky).params == SPARK_BASE
    table2 = choose_base(load_bench(None))          # one WOT line, one spark per speed
    assert table2.params == ("bdur_offset_deg", "bdur_speed_deg_per_krpm")


def test_scattered_points_keep_the_earlier_folds():
    # one point per operating point (Sobol' design, Table 2): grouping by operating point must give exactly
    # the folds of the earlier per-point assignment (a random permutation of the valid points, cycled over k)
    rng = np.random.default_rng(5)
    pts = pd.DataFrame({"speed_rpm": rng.uniform(6000, 12500, 20), "throttle_pct": rng.uniform(30, 100, 20),
                        "lambda": 0.9, "spark_deg_btdc": 40.0})
    valid = np.ones(20, bool)
    valid[[3, 11]] = False
    new = make_folds(20, valid, 5, seed=0, groups=operating_point_groups(pts))
    idx = np.flatnonzero(valid)
    old = np.full(20, -1)
    old[idx[np.random.default_rng(0).permutation(idx.size)]] = np.arange(idx.size) % 5
    np.testing.assert_array_equal(new, old)


class _StandInBench:
    """Bench whose engine knocks above ``limit(speed)`` deg BTDC; torque = spark (to see what ran)."""

    def __init__(self, limit):
        self.limit = limit
        self.calls = []

    def measure(self, plan, evaluate=None):
        self.calls.append(list(plan["point_id"]))
        s = plan["spark_deg_btdc"].to_numpy(float)
        knock = s > self.limit(plan["speed_rpm"].to_numpy(float))
        out = plan.copy()
        out["brake_torque_nm"] = np.where(knock, np.nan, s)
        out["status"] = np.where(knock, "knock_abort", "ok")
        return out


def test_bench_backoff_retards_knocking_points_until_they_run():
    from engine_model.gap.bench_procedure import BENCH_BACKOFF_DEG, backoff_id, measure_with_backoff

    plan = pd.DataFrame({"point_id": ["a", "b", "c", "d"], "speed_rpm": [6000.0, 7000.0, 9000.0, 6500.0],
                         "throttle_pct": [90.0] * 4, "lambda": [0.9] * 4,
                         "spark_deg_btdc": [40.0, 41.0, 45.0, 60.0]})
    # limit 33 deg below 8000 rpm: a needs 2 steps (40 -> 32), b 2 steps (41 -> 33), c runs as planned,
    # d would need 7 steps and stays flagged after the maximum of 3
    bench = _StandInBench(lambda n: np.where(n < 8000.0, 33.0, 90.0))
    run, meas = measure_with_backoff(bench, plan, evaluate=None)
    assert list(run["point_id"]) == [backoff_id("a", 8), backoff_id("b", 8), "c", backoff_id("d", 12)]
    assert list(meas["point_id"]) == list(run["point_id"])
    np.testing.assert_allclose(run["spark_deg_btdc"], [32.0, 33.0, 45.0, 48.0])
    np.testing.assert_allclose(run["bench_backoff_deg"], [2 * BENCH_BACKOFF_DEG, 2 * BENCH_BACKOFF_DEG, 0.0, 12.0])
    assert list(meas["status"]) == ["ok", "ok", "ok", "knock_abort"]
    np.testing.assert_allclose(meas["brake_torque_nm"].to_numpy()[:3], [32.0, 33.0, 45.0])
    # only the knocking points are re-run
    assert bench.calls[0] == ["a", "b", "c", "d"] and all("c" not in c for c in bench.calls[1:])
    # nothing knocks: the plan runs unchanged, once
    bench = _StandInBench(lambda n: np.full_like(n, 90.0))
    run, meas = measure_with_backoff(bench, plan, evaluate=None)
    assert list(run["point_id"]) == list(plan["point_id"]) and len(bench.calls) == 1
    assert (run["bench_backoff_deg"] == 0).all()


def test_linearisation_select_rows():
    from engine_model.gap.linear import BaseModel, Linearisation

    pts = pd.DataFrame({"point_id": ["p0", "p1", "p2"], "speed_rpm": [6000.0, 8000.0, 10000.0]})
    jac = np.arange(3 * 2 * 4, dtype=float).reshape(3, 2, 4)
    lin = Linearisation(points=pts, outputs=("a", "b"), y_ref=np.arange(6.0).reshape(3, 2),
                        columns=[("base", "x")] * 4, steps=np.ones(4), jac=jac, ok=np.array([True, False, True]),
                        status=["", "bad", ""], theta={}, base=BaseModel())
    sub = lin.select(["p2", "p0"])
    assert list(sub.points["point_id"]) == ["p2", "p0"]
    np.testing.assert_array_equal(sub.jac, jac[[2, 0]])
    np.testing.assert_array_equal(sub.y_ref, lin.y_ref[[2, 0]])
    assert list(sub.ok) == [True, True] and sub.status == ["", ""]
    with pytest.raises(ValueError, match="'p9'"):
        lin.select(["p0", "p9"])


def test_spark_slope_needs_enough_scattered_points():
    # sparks +-3.2 deg about the MBT prior (span 6.4 deg, std 3.2 deg) at varied speed and throttle:
    # 8 points give std x sqrt(n) = 9.1 deg < 10 (slope not pinned), 16 points 12.8 deg (carried)
    def table(n):
        rng = np.random.default_rng(3)
        sp = rng.uniform(6000, 12500, n)
        th = rng.uniform(30, 100, n)
        ds = np.where(np.arange(n) % 2 == 0, 3.2, -3.2)
        return pd.DataFrame({"speed_rpm": sp, "throttle_pct": th, "lambda": 0.9,
                             "spark_deg_btdc": np.atleast_1d(priors.spark_estimate(sp, th)) + ds})
    assert choose_base(table(8)).params == ("bdur_offset_deg", "bdur_speed_deg_per_krpm", "bdur_load_deg")
    assert choose_base(table(16)).params == SPARK_BASE


# --------------------------------------------------------------------------- model-discrimination design

def _two_alike_effects(n=60, special=(7, 23, 41), seed=3):
    """Synthetic whitened blocks: base column (a level on output 0), effects A and B with the SAME
    signature everywhere except at ``special`` points, where B moves output 1 instead of output 0."""
    from engine_model.gap.design import DesignProblem

    rng = np.random.default_rng(seed)
    blocks = np.zeros((n, 2, 3))                  # columns: base, A, B
    blocks[:, 0, 0] = 1.0
    g = rng.uniform(0.5, 1.5, n)
    blocks[:, 0, 1] = g
    blocks[:, 1, 1] = 3.0 * g                     # both stand far out of noise (output 1 has no base term)
    blocks[:, 0, 2] = g
    blocks[:, 1, 2] = 3.0 * g
    for k in special:                             # only here B differs from A, by about 1 sigma
        blocks[k, 0, 2] = g[k] - 0.7
        blocks[k, 1, 2] = 3.0 * g[k] + 0.7
    return DesignProblem(blocks, [0], {"A": [1], "B": [2]}), list(special)


def test_pair_distance_is_the_residual_of_a_regression_on_the_rival_and_base():
    from engine_model.gap.design import pair_distances

    prob, special = _two_alike_effects()
    idx = np.array([0, 3, 7, 10, 23, 30])
    x = prob.blocks[idx].reshape(-1, 3)
    d = pair_distances(prob, prob.gram[idx].sum(axis=0))
    for (i, j), d2 in d.items():
        s = x[:, prob.effect_cols[i][0]]
        m = x[:, [0] + ([] if j is None else prob.effect_cols[j])]
        res = s - m @ np.linalg.lstsq(m, s, rcond=None)[0]
        assert d2 == pytest.approx(float(res @ res), rel=1e-6, abs=1e-9)
    # without the special points A and B are indistinguishable
    d0 = pair_distances(prob, prob.gram[[0, 3, 10, 30]].sum(axis=0))
    assert d0[("A", "B")] < 1e-6 and d0[("B", "A")] < 1e-6     # 0 up to the 1e-9 relative ridge


@pytest.mark.parametrize("criterion", ["maximin", "error"])
def test_discriminating_selection_finds_the_few_separating_points_and_beats_random_plans(criterion):
    from engine_model.gap.design import pair_distances, select_discriminating

    prob, special = _two_alike_effects()
    idx, info = select_discriminating(prob, 8, criterion=criterion)
    assert len(set(idx.tolist())) == 8
    assert set(special) <= set(idx.tolist())
    assert info["min_d2"] == pytest.approx(min(info["pairs"].values()))
    rng = np.random.default_rng(0)
    rand = [min(pair_distances(prob, prob.gram[rng.choice(prob.n, 8, replace=False)].sum(axis=0)).values())
            for _ in range(300)]
    assert info["min_d2"] > max(rand)
    with pytest.raises(ValueError, match="n_points = 61"):
        select_discriminating(prob, 61)
    with pytest.raises(ValueError, match="criterion 'dopt' unknown"):
        select_discriminating(prob, 8, criterion="dopt")


def test_discrimination_plan_from_a_given_linearisation():
    """Plumbing: the whitening, the non-converged candidates skipped, the pool rows returned."""
    from engine_model.gap.design import discrimination_plan
    from engine_model.gap.linear import BaseModel, Linearisation

    n = 20
    rng = np.random.default_rng(1)
    pool = pd.DataFrame({"point_id": [f"c{i}" for i in range(n)], "speed_rpm": np.linspace(6000, 12000, n),
                         "throttle_pct": 100.0, "spark_deg_btdc": 40.0, "lambda": 0.9})
    outs = ("air_mass_flow_kg_h", "brake_torque_nm", "exhaust_temp_k", "fuel_mass_flow_kg_h")
    y_ref = np.column_stack([np.full(n, 150.0), np.full(n, 40.0), np.full(n, 1100.0), np.full(n, 15.0)])
    jac = np.zeros((n, 4, 3))
    jac[:, 1, 0] = 1.0                                  # base: torque level
    jac[:, 1, 1] = -0.4 * rng.uniform(0.8, 1.2, n)      # transmission_efficiency: torque only
    jac[:, 1, 2] = -0.4 * rng.uniform(0.8, 1.2, n)      # blowby: torque ...
    jac[[4, 15], 2, 2] = -25.0                          # ... and exhaust T at two points only
    ok = np.ones(n, bool)
    ok[15] = False                                      # one of them did not converge
    lin = Linearisation(points=pool, outputs=outs, y_ref=y_ref, columns=[("base", "bdur_offset_deg"),
                        ("transmission_efficiency", "eta"), ("blowby", "fraction_at_6000")],
                        steps=np.array([2.0, -0.04, 0.02]), jac=jac, ok=ok, status=[""] * n, theta={},
                        base=BaseModel(params=("bdur_offset_deg",)))
    # 5 points cover the pool's 6000-12000 rpm at 1500 rpm (at 1000 rpm these candidates need 6)
    plan, info = discrimination_plan(5, candidates=pool, candidate_lin=lin, max_speed_gap_rpm=1500.0,
                                     effects=["transmission_efficiency", "blowby"], evaluate=lambda p: None)
    assert len(plan) == 5 and "c4" in set(plan["point_id"]) and "c15" not in set(plan["point_id"])
    assert (plan["design"] == "discriminating").all()
    assert info["closest"][0] in ("transmission_efficiency", "blowby")
    assert info["coverage"]["speed_range"] == (6000.0, 12000.0) and info["coverage"]["largest_speed_gap_rpm"] <= 1500.0
    assert info["free"]["error_bound"] <= info["error_bound"] + 1e-12
    with pytest.raises(ValueError, match="needs at least 6 points of these candidates"):
        discrimination_plan(5, candidates=pool, candidate_lin=lin, max_speed_gap_rpm=1000.0,
                            effects=["transmission_efficiency", "blowby"], evaluate=lambda p: None)


def test_burn_scatter_discounts_contrasts_a_burn_deviation_can_mimic():
    """A torque-vs-exhaust-T contrast along a point's BDUR10-90 sensitivity counts less with burn scatter,
    one orthogonal to it (airflow) does not change."""
    from engine_model.gap.design import design_problem, pair_distances
    from engine_model.gap.linear import BaseModel, Linearisation

    n = 6
    pts = pd.DataFrame({"point_id": [f"c{i}" for i in range(n)], "speed_rpm": 9000.0, "throttle_pct": 100.0,
                        "spark_deg_btdc": 40.0, "lambda": 0.9})
    outs = ("air_mass_flow_kg_h", "brake_torque_nm", "exhaust_temp_k", "fuel_mass_flow_kg_h")
    y_ref = np.tile([150.0, 40.0, 1100.0, 15.0], (n, 1))
    jac = np.zeros((n, 4, 3))
    jac[:, 1, 0], jac[:, 2, 0] = -0.2, 10.0             # base BDUR10-90: torque down, exhaust T up (per deg)
    jac[:, 1, 1] = -0.4                                 # effect A: torque only
    jac[:, 1, 2] = -0.4                                 # effect B: torque ...
    jac[0, 2, 2] = 250.0                                # ... and, at point 0, exhaust T along the burn direction
    lin = Linearisation(points=pts, outputs=outs, y_ref=y_ref, columns=[("base", "bdur_offset_deg"),
                        ("transmission_efficiency", "eta"), ("blowby", "fraction_at_6000")],
                        steps=np.array([2.0, -0.04, 0.02]), jac=jac, ok=np.ones(n, bool), status=[""] * n,
                        theta={}, base=BaseModel(params=("bdur_offset_deg",)))
    d = {t: pair_distances(p, p.gram.sum(axis=0)) for t, p in
         ((t, design_problem(lin, burn_scatter_deg=t)) for t in (0.0, 0.5))}
    assert d[0.5][("blowby", "transmission_efficiency")] < 0.8 * d[0.0][("blowby", "transmission_efficiency")]
    jac[0, 2, 2], jac[0, 0, 2] = 0.0, 3.0               # the contrast on airflow instead: unaffected
    d2 = {t: pair_distances(p, p.gram.sum(axis=0)) for t, p in
          ((t, design_problem(lin, burn_scatter_deg=t)) for t in (0.0, 0.5))}
    assert d2[0.5][("blowby", "transmission_efficiency")] == pytest.approx(
        d2[0.0][("blowby", "transmission_efficiency")], rel=0.02)


def test_speed_curvature_and_m_offset_only_when_asked_and_carried():
    # 32 scattered map-wide points over 6000-12500 rpm: carried when asked; 12 points or one load line: never
    def table(n, thr=None):
        rng = np.random.default_rng(4)
        sp = np.linspace(6000, 12500, n)
        th = rng.uniform(30, 100, n) if thr is None else np.full(n, thr)
        return pd.DataFrame({"speed_rpm": sp, "throttle_pct": th, "lambda": 0.9,
                             "spark_deg_btdc": np.atleast_1d(priors.spark_estimate(sp, th))})
    curv = "bdur_speed2_deg_per_krpm2"
    assert curv not in choose_base(table(32)).params
    assert choose_base(table(32), speed_curvature=True).params[-2:] == (curv, "m_offset")
    for small in (table(12), table(32, thr=100.0), load_bench(None)):
        assert not {curv, "m_offset"} & set(choose_base(small, speed_curvature=True).params)


def test_speed_curvature_moves_the_burn_by_the_square_of_the_speed_offset():
    from engine_model.gap.linear import CURVED_BASE, BaseModel

    pts = pd.DataFrame({"speed_rpm": [6000.0, 9000.0, 12500.0], "throttle_pct": 80.0, "lambda": 0.9,
                        "spark_deg_btdc": 40.0})
    base = BaseModel(params=CURVED_BASE)
    d = (base.plan(pts, {"bdur_speed2_deg_per_krpm2": 0.1})["bdur_10_90_deg"]
         - base.plan(pts, {})["bdur_10_90_deg"]).to_numpy()
    np.testing.assert_allclose(d, [0.9, 0.0, 1.225], atol=1e-12)
