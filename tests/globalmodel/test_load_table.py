"""Load table from the cycle model (engine_model.globalmodel.load_table): physics of the plenum pressure, failed nodes flagged.

A 4 x 4 grid at the load table's default solver (1 deg step, 1 % tolerance): the plenum pressure converges long
before the cycle work does; 16 simulations, a few seconds.
"""

import numpy as np
import pytest

from engine_model import default_spec

from engine_model.sim import simulate
from engine_model.globalmodel.load_table import LOAD_SOLVER, build_load_table, load_plan

THR, SPD = (20.0, 30.0, 50.0, 100.0), (5000.0, 7000.0, 9000.0, 12000.0)


@pytest.fixture(scope="module")
def runs():
    spec = default_spec()
    calls = []

    def evaluate(plan):
        calls.append(plan.copy())
        return simulate(spec, plan, LOAD_SOLVER)
    return spec, build_load_table(spec, evaluate=evaluate, throttle_pct=THR, speed_rpm=SPD), calls


@pytest.mark.slow
def test_plenum_pressure_rises_with_throttle_and_stays_near_ambient(runs):
    spec, lt, calls = runs
    a = lt.array
    assert len(calls) == 1 and len(calls[0]) == 16 and lt.spec_hash == spec.spec_hash() and not lt.filled
    # opening the throttle cannot lower the plenum pressure; throttled, it is well below ambient
    assert np.all(np.diff(a, axis=0) > 0), a
    assert np.all(a > 0.2) and np.all(a < 1.05)
    assert a[0].max() < 0.9 and a[-1].min() > 0.85
    # at WOT the restrictor's loss grows with the flow (speed): the plenum pressure falls from 5000 to 12000 rpm
    assert a[-1, -1] < a[-1, 0]
    # the table answers at its nodes with the simulated values
    np.testing.assert_allclose(lt(np.array(THR)[:, None], np.array(SPD)[None, :]), a, rtol=1e-12)


def test_failed_nodes_are_filled_flagged_and_too_few_is_an_error():
    spec = default_spec()
    plan = load_plan(spec, THR, SPD)

    def fake(p):     # a smooth synthetic answer; one node fails, as the cycle model does at tiny openings
        out = p.copy()
        out["plenum_pressure_bar"] = 1.01325 * (0.3 + 0.007 * out["throttle_pct"] - 1e-5 * out["speed_rpm"] / 10)
        out["vol_eff"] = 0.5
        out["converged"] = True
        out["status"] = "ok"
        bad = (out["throttle_pct"] == 30.0) & (out["speed_rpm"] == 7000.0)
        out.loc[bad, ["plenum_pressure_bar", "vol_eff"]] = np.nan
        out.loc[bad, ["converged", "status"]] = [False, "failed: negative mass in cylinder 4"]
        return out
    lt = build_load_table(spec, evaluate=fake, throttle_pct=THR, speed_rpm=SPD)
    assert lt.filled == ((30.0, 7000.0),)
    # filled linearly in throttle between the good neighbours of the same speed
    want = np.interp(30.0, (20.0, 50.0), (lt.array[0, 1], lt.array[2, 1]))
    assert lt.array[1, 1] == pytest.approx(want)
    assert lt.to_frame()["filled"].sum() == 1

    def worse(p):
        out = fake(p)
        out.loc[out["speed_rpm"] == 9000.0, "converged"] = False
        return out
    with pytest.raises(ValueError, match=r"at 9000 rpm only 0 of 4 throttle nodes simulated"):
        build_load_table(spec, evaluate=worse, throttle_pct=THR, speed_rpm=SPD)
    with pytest.raises(ValueError, match=r"evaluate returned 3 rows for a plan of 16"):
        build_load_table(spec, evaluate=lambda p: p.iloc[:3], throttle_pct=THR, speed_rpm=SPD)
    assert len(plan) == 16 and plan["p_amb_pa"].eq(spec.ambient.pressure_pa).all()
