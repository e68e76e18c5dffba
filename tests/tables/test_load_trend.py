"""The part-load trend of the spark table: MBT targets fitted under "no less advance as the throttle closes"."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from engine_model import default_spec, knock
from engine_model.tables import EcuGrid, MapSettings, PriorModel, build_maps
from engine_model.tables.smoothing import isotonic_nonincreasing

VD_M3 = default_spec().geometry.total_displacement_m3


def _minmax(y, w):
    """The order-restricted least-squares fit by its max-min formula (Barlow et al. 1972, thm. 1.4.4), written
    for a non-increasing fit: x_i = min over s <= i of max over t >= i of the weighted mean of y[s..t]."""
    n = len(y)

    def mean(s, t):
        return float(np.dot(w[s:t + 1], y[s:t + 1]) / w[s:t + 1].sum())
    return np.array([min(max(mean(s, t) for t in range(i, n)) for s in range(i + 1)) for i in range(n)])


@pytest.mark.parametrize("seed", range(6))
def test_isotonic_fit_matches_the_max_min_formula(seed):
    rng = np.random.default_rng(seed)
    y, w = rng.normal(0.0, 3.0, 9), rng.uniform(0.2, 3.0, 9)
    x = isotonic_nonincreasing(y, w)
    assert np.all(np.diff(x) <= 1e-12)
    np.testing.assert_allclose(x, _minmax(y, w), atol=1e-10)
    assert np.dot(w, x) == pytest.approx(np.dot(w, y))          # each pool keeps its weighted mean


def test_isotonic_fit_leaves_an_ordered_sequence_and_refuses_bad_input():
    y = np.array([5.0, 4.0, 4.0, -1.0])
    np.testing.assert_array_equal(isotonic_nonincreasing(y, np.ones(4)), y)
    with pytest.raises(ValueError, match="finite"):
        isotonic_nonincreasing(np.array([1.0, np.nan]), np.ones(2))
    with pytest.raises(ValueError, match="one length"):
        isotonic_nonincreasing(np.ones(3), np.ones(2))


# MBT 30 deg at every cell but 50 % throttle (24 deg: a part-load drop); knock border set per throttle
def _engine(border_at_50):
    def evaluate(plan):
        s, n, t = (plan[c].to_numpy(float) for c in ("spark_deg_btdc", "speed_rpm", "throttle_pct"))
        mbt = np.where(t == 50, 24.0, 30.0)
        tmax = 60 * t / 100
        out = plan.copy()
        out["brake_torque_nm"] = tmax - 0.02 * tmax * (s - mbt) ** 2 / 10
        out["knock_index"] = np.exp(0.08 * (s - np.where(t == 50, border_at_50, 80.0)))
        out["bmep_bar"] = out["brake_torque_nm"] * 4 * np.pi / VD_M3 / 1e5
        out["air_mass_flow_kg_h"] = 150 * t / 100 * n / 10000
        out["status"] = "ok"
        return out
    return evaluate


GRID = EcuGrid((50, 80, 100), (6000, 9000))
ST = dict(spark_min_deg_btdc=5.0, max_second_diff_deg=100.0, cycle_advance_deg=0.0, knock_uncertainty_z=0.0)


def _table(border_at_50=80.0, bench=None, **kw):
    res = build_maps(default_spec(), PriorModel(), grid=GRID, evaluate=_engine(border_at_50),
                     settings=MapSettings(**ST, **kw), bench=bench)
    return res, res.cells.set_index(["throttle_pct", "speed_rpm"])


def test_a_part_load_drop_is_pooled_with_the_cells_above_it():
    res, c = _table()
    _, off = _table(mbt_monotone_in_load=False)
    for n in (6000, 9000):
        assert off.loc[(50, n), "spark_deg_btdc"] == pytest.approx(24.0, abs=0.3)      # the drop, left alone
        for t in (50, 80, 100):
            # least squares under the order: the three targets (24, 30, 30) pooled to their mean, 28
            assert c.loc[(t, n), "spark_deg_btdc"] == pytest.approx(28.0, abs=0.3), (t, n)
            assert c.loc[(t, n), "spark_mbt_deg_btdc"] == pytest.approx(off.loc[(t, n), "spark_mbt_deg_btdc"])
        assert c.loc[(50, n), "load_trend_shift_deg"] == pytest.approx(4.0, abs=0.3)
        assert c.loc[(100, n), "load_trend_shift_deg"] == pytest.approx(-2.0, abs=0.3)
    assert res.stats["load_trend"]["cells_raised"] == 2 and res.stats["load_trend"]["cells_lowered"] == 4
    assert (off["load_trend_shift_deg"] == 0).all()
    moves = knock.table_trends(res.cells)["load_trend_moves"]       # the report names the raised cells
    raised = {(m["speed_rpm"], m["throttle_pct"]) for m in moves if m["shift_deg"] > 0}
    assert raised == {(6000.0, 50.0), (9000.0, 50.0)}
    assert all(abs(m["shift_deg"]) <= 2.3 for m in moves if m["throttle_pct"] != 50.0)


def test_the_knock_border_still_caps_a_raised_cell():
    # at 50 % the knock index reaches 1 at 26 deg: the pooled target 28 lies beyond it
    _, c = _table(border_at_50=26.0)
    for n in (6000, 9000):
        assert c.loc[(50, n), "limited_by"] == "knock"
        assert 25.0 <= c.loc[(50, n), "spark_deg_btdc"] <= 26.0
        assert c.loc[(50, n), "knock_index"] < 1.0


def test_a_bench_pinned_wot_cell_holds_and_the_part_load_follows_it():
    bench = pd.DataFrame({"speed_rpm": [6000.0], "throttle_pct": [100.0], "spark_deg_btdc": [33.0],
                          "at_mbt": [True], "knock": [False]})
    _, c = _table(bench=bench, bench_offset_reach_rpm=None)
    assert c.loc[(100, 6000), "spark_deg_btdc"] == pytest.approx(33.0)
    assert c.loc[(100, 6000), "load_trend_shift_deg"] == 0.0
    # the targets 24 and 30 below a held 33: all pooled to the held value (a hair below it, and the table's
    # 0.1 deg resolution rounds towards retard)
    for t in (50, 80):
        assert 32.9 - 1e-9 <= c.loc[(t, 6000), "spark_deg_btdc"] <= 33.0, t
    assert c.loc[(100, 9000), "spark_deg_btdc"] == pytest.approx(28.0, abs=0.3)      # the other speed: its own fit


def test_a_cell_whose_mbt_lies_beyond_spark_max_holds_there():
    """With spark_max 28 deg, MBT (30) lies beyond it at 80 % and WOT: those cells sit at 28 exactly, and the order
    lifts the 50 % cell (MBT 24) to them."""
    _, c = _table(spark_max_deg_btdc=28.0)
    for n in (6000, 9000):
        for t in (80, 100):
            assert c.loc[(t, n), "limited_by"] == "spark_max" and c.loc[(t, n), "spark_deg_btdc"] == 28.0
            assert c.loc[(t, n), "load_trend_shift_deg"] == 0.0
        assert 27.9 - 1e-9 <= c.loc[(50, n), "spark_deg_btdc"] <= 28.0


def test_the_setting_is_validated():
    with pytest.raises(ValueError, match="mbt_monotone_in_load"):
        MapSettings(mbt_monotone_in_load="yes")
