"""Gap effects library: every effect moves the outputs it should, in the documented direction; bad input fails clearly."""

import numpy as np
import pandas as pd
import pytest

from engine_model import default_spec

from engine_model import priors

from engine_model.sim import simulate
from engine_model.gap import EFFECTS, apply_effects, check_effects, get_effect, post_effects
from engine_model.effects import ETA_TRANS_BASE
from engine_model.sim.prepare import SolverSettings

# 1 deg steps: the effects change outputs by percent, the step changes them < 1 % and
# identically for the base and the perturbed run (the directions are what is tested).
SOLVER = SolverSettings(step_deg=1.0)
SPEEDS = np.array([6000.0, 9000.0, 12000.0])
OUTS = ["air_mass_flow_kg_h", "brake_torque_nm", "exhaust_temp_k", "fuel_mass_flow_kg_h"]


@pytest.fixture(scope="module")
def wot():
    spec = default_spec()
    pts = priors.with_combustion(pd.DataFrame({
        "point_id": [f"p{i}" for i in range(3)], "speed_rpm": SPEEDS, "throttle_pct": 100.0,
        "spark_deg_btdc": priors.spark_estimate(SPEEDS, 100.0), "lambda": 0.9}))

    def run(effects):
        res = simulate(spec, apply_effects(pts, effects, spec), SOLVER)
        res["brake_torque_nm"] = res["brake_torque_nm"] * ETA_TRANS_BASE
        res["brake_power_kw"] = res["brake_power_kw"] * ETA_TRANS_BASE
        return post_effects(res, effects, spec=spec)

    return run, run({})


def test_library_has_the_required_candidates():
    need = {"transmission_efficiency", "transmission_speed_loss", "runner_inertia", "heat_transfer", "friction",
            "combustion_efficiency", "restrictor", "blowby", "exhaust_back_pressure", "intake_air_temperature",
            "humidity", "knock_retard"}
    assert need <= set(EFFECTS)
    for e in EFFECTS.values():
        assert 1 <= len(e.params) <= 2 and e.source and e.expect
        for p in e.params:
            assert p.lo <= p.neutral <= p.hi and p.unit and p.doc


@pytest.mark.parametrize("name", list(EFFECTS))
def test_effect_moves_outputs_in_documented_direction(wot, name):
    run, base = wot
    eff = EFFECTS[name]
    res = run({name: eff.realistic()})
    assert res["converged"].all()
    for col, sign in eff.expect:
        rel = (res[col].to_numpy() - base[col].to_numpy()) / base[col].to_numpy()
        if sign == 0:
            assert np.max(np.abs(rel)) > 0.005, f"{name}: {col} should change, moved {rel}"
        else:
            assert np.sign(np.mean(rel)) == sign, f"{name}: {col} moved {rel}, documented sign {sign}"
            assert np.abs(np.mean(rel)) > 1e-3, f"{name}: {col} barely moved ({rel})"


def test_mechanical_effects_leave_gas_exchange_alone(wot):
    run, base = wot
    for name in ("transmission_efficiency", "transmission_speed_loss", "friction"):
        res = run({name: EFFECTS[name].realistic()})
        np.testing.assert_allclose(res["air_mass_flow_kg_h"], base["air_mass_flow_kg_h"], rtol=1e-9)
        np.testing.assert_allclose(res["exhaust_temp_k"], base["exhaust_temp_k"], rtol=1e-9)
    # transmission: exactly the efficiency ratio on torque
    res = run({"transmission_efficiency": {"eta": 0.90}})
    np.testing.assert_allclose(res["brake_torque_nm"] / base["brake_torque_nm"], 0.90 / ETA_TRANS_BASE, rtol=1e-12)


def test_neutral_values_change_nothing(wot):
    run, base = wot
    res = run({name: eff.neutral() for name, eff in EFFECTS.items()})
    np.testing.assert_allclose(res[OUTS].to_numpy(), base[OUTS].to_numpy(), rtol=1e-12)


def test_humidity_airflow_reading_uses_the_moist_mass():
    pts = pd.DataFrame({"speed_rpm": [9000.0], "throttle_pct": [100.0], "spark_deg_btdc": [45.0],
                        "air_mass_flow_kg_h": [100.0], "t_amb_k": [298.15], "p_amb_pa": [101325.0]})
    fx = {"humidity": {"relative_humidity": 1.0}}
    a = apply_effects(pts, fx)
    pv = 101325.0 - a["p_amb_pa"].iloc[0]
    assert 3100 < pv < 3250           # saturation pressure of water at 25 C: 3.17 kPa
    out = post_effects(a, fx)
    assert out["air_mass_flow_kg_h"].iloc[0] == pytest.approx(100.0 * (1 + 0.622 * pv / (101325.0 - pv)))


def test_unknown_effect_and_parameter_and_range_errors():
    pts = pd.DataFrame({"speed_rpm": [9000.0], "throttle_pct": [100.0], "spark_deg_btdc": [45.0]})
    with pytest.raises(ValueError, match="unknown effect 'warp_drive'.*valid effects"):
        apply_effects(pts, {"warp_drive": {"x": 1}})
    with pytest.raises(ValueError, match="unknown effect"):
        get_effect("nope")
    with pytest.raises(ValueError, match="no parameter 'etaa'.*valid"):
        check_effects({"transmission_efficiency": {"etaa": 0.9}})
    with pytest.raises(ValueError, match=r"transmission_efficiency.*'eta' = 1.2.*range \[0.85, 0.99\]"):
        post_effects(pts, {"transmission_efficiency": {"eta": 1.2}})
    with pytest.raises(ValueError, match="heat_transfer.*factor.*nan"):
        apply_effects(pts, {"heat_transfer": {"factor": float("nan")}})


def test_apply_effects_composes_with_existing_overrides():
    spec = default_spec()
    pts = pd.DataFrame({"speed_rpm": [9000.0], "throttle_pct": [100.0], "spark_deg_btdc": [45.0],
                        "spec.losses.combustion_efficiency": [0.98]})
    out = apply_effects(pts, {"combustion_efficiency": {"eta": 0.95}, "blowby": {"fraction_at_6000": 0.03}}, spec)
    assert out["spec.losses.combustion_efficiency"].iloc[0] == pytest.approx(0.98 * 0.95 * (1 - 0.03 * 6000 / 9000))
    out = apply_effects(pts, {"restrictor": {"cd_factor": 0.9}}, spec)
    assert out["spec.intake.restrictor_cd"].iloc[0] == pytest.approx(spec.intake.restrictor_cd * 0.9)


def test_linearise_matches_the_exact_transmission_sensitivity():
    """One batch gives the Jacobian; transmission efficiency acts exactly as torque / eta_base."""
    from engine_model.gap.linear import BaseModel, linearise

    spec = default_spec()
    pts = pd.DataFrame({"point_id": ["a", "b"], "speed_rpm": [7000.0, 11000.0], "throttle_pct": 100.0,
                        "spark_deg_btdc": priors.spark_estimate(np.array([7000.0, 11000.0]), 100.0), "lambda": 0.9})
    lin = linearise(pts, lambda p: simulate(spec, p, SOLVER), BaseModel(params=("bdur_offset_deg",)),
                    effects=["transmission_efficiency", "friction"], spec=spec)
    assert lin.ok.all() and lin.n_simulations == 2 * 4   # ref, base step, 2 friction steps; transmission reuses ref
    k_tq, k_air = lin.outputs.index("brake_torque_nm"), lin.outputs.index("air_mass_flow_kg_h")
    j = lin.columns.index(("transmission_efficiency", "eta"))
    np.testing.assert_allclose(lin.jac[:, k_tq, j], lin.y_ref[:, k_tq] / ETA_TRANS_BASE, rtol=1e-9)
    assert np.all(lin.jac[:, k_air, j] == 0.0)
    jf = lin.columns.index(("friction", "delta_a_bar"))
    # +1 bar of constant FMEP costs Vd/(4 pi) * 1e5 N m at the crank, x eta_base at the dyno
    vd = spec.geometry.total_displacement_m3
    np.testing.assert_allclose(lin.jac[:, k_tq, jf], -vd * 1e5 / (4 * np.pi) * ETA_TRANS_BASE, rtol=1e-3)
    jb = lin.columns.index(("base", "bdur_offset_deg"))
    # a longer burn moves torque and exhaust temperature (the base column is informative)
    assert np.all(np.abs(lin.jac[:, k_tq, jb]) > 0.05)
    assert np.all(lin.jac[:, lin.outputs.index("exhaust_temp_k"), jb] > 0)   # later burn, hotter exhaust
