"""The Python face: contract columns, echoed inputs, and bad input refused before any work."""

import math

import numpy as np
import pandas as pd
import pytest

from engine_model import RESULT_COLUMNS, default_spec

from engine_model.sim import simulate
from engine_model.bench import load_bench


def _points(n=2):
    return pd.DataFrame({
        "point_id": [f"p{i}" for i in range(n)],
        "speed_rpm": np.linspace(9000, 10000, n),
        "throttle_pct": [100.0] * n,
        "spark_deg_btdc": [50.0] * n,
        "lambda": [0.9] * n,
        "bdur_10_90_deg": [24.0] * n,
        "wiebe_m": [6.4] * n,
        "my_tag": ["keep-me"] * n,
    })


def test_contract_columns_and_echo():
    spec = default_spec()
    pts = _points(2)
    res = simulate(spec, pts)
    assert len(res) == len(pts)
    for c in RESULT_COLUMNS:
        assert c in res.columns, c
    for c in pts.columns:
        assert (res[c].to_numpy() == pts[c].to_numpy()).all(), c
    assert res["wiebe_a"].iloc[0] == pytest.approx(-math.log(0.001))
    assert res["p_amb_pa"].iloc[0] == spec.ambient.pressure_pa
    # power = torque * omega, consistently
    p = res["brake_torque_nm"] * res["speed_rpm"] * 2 * math.pi / 60 / 1e3
    np.testing.assert_allclose(res["brake_power_kw"], p, rtol=1e-12)
    # BMEP chain: net = gross - pumping, brake = net - friction
    np.testing.assert_allclose(res["imep_net_bar"], res["imep_gross_bar"] - res["pmep_bar"], rtol=1e-12)
    np.testing.assert_allclose(res["bmep_bar"], res["imep_net_bar"] - res["fmep_bar"], rtol=1e-12)


@pytest.mark.parametrize("col,value,needle", [
    ("speed_rpm", float("nan"), "row 1 (point_id 'p1'), column 'speed_rpm'"),
    ("speed_rpm", 0.0, "column 'speed_rpm': value 0 is outside (0, 16500]"),
    ("speed_rpm", -5.0, "column 'speed_rpm'"),
    ("speed_rpm", 20000.0, "column 'speed_rpm': value 20000 is outside"),
    ("lambda", 0.0, "column 'lambda': value 0"),
    ("lambda", -1.0, "column 'lambda'"),
    ("throttle_pct", 120.0, "column 'throttle_pct': value 120"),
    ("throttle_pct", -1.0, "column 'throttle_pct'"),
    ("wiebe_m", -2.0, "column 'wiebe_m'"),
    ("bdur_10_90_deg", "abc", "column 'bdur_10_90_deg': value 'abc' is not a finite number"),
])
def test_bad_points_raise_naming_row_column_value(col, value, needle):
    pts = _points(3).astype({col: object})
    pts.loc[1, col] = value
    with pytest.raises(ValueError) as exc:
        simulate(default_spec(), pts)
    assert needle in str(exc.value)


def test_missing_column_is_named():
    pts = _points(1).drop(columns=["wiebe_m"])
    with pytest.raises(ValueError, match=r"missing required column\(s\) \['wiebe_m'\]"):
        simulate(default_spec(), pts)


def test_validation_happens_before_any_simulation(monkeypatch):
    """A bad last row must stop the run before the first point is simulated."""
    import importlib
    sim = importlib.import_module("engine_model.sim.simulate")
    calls = []
    monkeypatch.setattr(sim, "simulate_point", lambda *a, **k: calls.append(1))
    pts = _points(3)
    pts.loc[2, "lambda"] = float("nan")
    with pytest.raises(ValueError):
        sim.simulate(default_spec(), pts)
    assert calls == []


def test_packaged_bench_data_is_table2():
    b = load_bench()
    assert list(b["speed_rpm"]) == [8000, 8450, 9000, 9500, 10000, 10500, 11000]
    assert (b["throttle_pct"] == 100).all() and (b["lambda"] == 0.9).all()
    assert b.loc[b.speed_rpm == 9000, "brake_power_kw"].item() == 41.5


def test_spec_override_columns_change_only_their_rows():
    import dataclasses

    from engine_model import default_spec

    from engine_model.sim import simulate

    spec = default_spec()
    base = {"speed_rpm": 9000.0, "throttle_pct": 100.0, "spark_deg_btdc": 50.0, "lambda": 0.9,
            "bdur_10_90_deg": 24.0, "wiebe_m": 6.4}
    pts = pd.DataFrame([base, base]).assign(**{"spec.intake.restrictor_cd": [spec.intake.restrictor_cd, 0.80]})
    res = simulate(spec, pts)
    # row 0 overrides with the spec's own value: identical to no override
    plain = simulate(spec, pd.DataFrame([base]))
    assert res["air_mass_flow_kg_h"].iloc[0] == pytest.approx(plain["air_mass_flow_kg_h"].iloc[0], rel=1e-12)
    # row 1 equals a run on a spec changed the ordinary way, and a narrower restrictor passes less air
    narrow = spec.replace(intake=dataclasses.replace(spec.intake, restrictor_cd=0.80))
    ref = simulate(narrow, pd.DataFrame([base]))
    assert res["air_mass_flow_kg_h"].iloc[1] == pytest.approx(ref["air_mass_flow_kg_h"].iloc[0], rel=1e-12)
    assert res["air_mass_flow_kg_h"].iloc[1] < res["air_mass_flow_kg_h"].iloc[0]


def test_bad_spec_override_names_row_and_key():
    from engine_model import default_spec
    from engine_model.sim import simulate

    base = {"speed_rpm": 9000.0, "throttle_pct": 100.0, "spark_deg_btdc": 50.0, "lambda": 0.9,
            "bdur_10_90_deg": 24.0, "wiebe_m": 6.4}
    with pytest.raises(ValueError, match=r"row 1.*'intake.restrictor_cd'"):
        simulate(default_spec(), pd.DataFrame([base, base]).assign(**{"spec.intake.restrictor_cd": [0.9, -1.0]}))
    with pytest.raises(ValueError, match=r"row 0.*'intake.no_such_field'.*no such field"):
        simulate(default_spec(), pd.DataFrame([base]).assign(**{"spec.intake.no_such_field": [1.0]}))


def test_a_state_of_another_runner_layout_is_refused():
    """A gas-exchange state from a network of another shape (other pipe cells in 1D, other runner segments
    in the lumped model) is a ValueError, not a crash."""
    from engine_model import OperatingPoint, SolverSettings, simulate_point
    spec = default_spec()
    op = OperatingPoint(9000.0, 100.0, 50.0, 0.9, 24.0, 6.4)
    one = SolverSettings(max_cycles=1, min_cycles=1)
    _, state = simulate_point(spec.with_values({"gas_exchange.cell_length_m": 0.06}), op, one)
    with pytest.raises(ValueError, match="do not fit this spec's gas-exchange network"):
        simulate_point(spec, op, state=state)
    lumped = spec.with_values({"gas_exchange.model": "lumped"})
    _, state = simulate_point(lumped.with_values({"intake.runner_segments": 2}), op, one)
    with pytest.raises(ValueError, match="do not fit this spec's gas-exchange network"):
        simulate_point(lumped, op, state=state)
    short = (state[0], state[1][:-1]) + tuple(state[2:])
    with pytest.raises(ValueError, match="do not fit"):
        simulate_point(lumped.with_values({"intake.runner_segments": 2}), op, state=short)
