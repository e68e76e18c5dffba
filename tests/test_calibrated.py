"""The calibrated engine: one object for spec + calibrated values, written as a TOML spec that reads back exactly."""

import math
import tomllib

import pytest

from engine_model import default_spec, load_spec
from engine_model.calibrated import CalibratedEngine, spec_to_toml
from engine_model.spec import spec_from_dict

VALUES = {"exhaust.runner_length_m": 0.27549074561475934, "intake.runner_length_m": 0.17719492053497815,
          "intake.restrictor_recovery": 0.7213988209341773}


def test_resolved_spec_carries_the_calibrated_values_and_hash():
    base = CalibratedEngine.from_spec()
    eng = base.calibrated(VALUES)
    assert eng.spec == default_spec().with_values(VALUES)
    assert eng.spec_hash() != base.spec_hash() == default_spec().spec_hash()
    assert eng.overrides == dict(sorted(VALUES.items()))
    # later values win; the base stays the starting spec
    again = eng.calibrated({"intake.runner_length_m": 0.2})
    assert again.spec.intake.runner_length_m == 0.2 and again.base == default_spec()
    # a 'spec.' prefix (plan-column form) is accepted and normalised
    assert CalibratedEngine(default_spec(), {"spec.intake.runner_length_m": 0.2}).overrides == {
        "intake.runner_length_m": 0.2}


def test_bad_override_names_key_and_value():
    with pytest.raises(ValueError, match=r"intake.no_such_field"):
        CalibratedEngine.from_spec().calibrated({"intake.no_such_field": 1.0})
    with pytest.raises(ValueError, match=r"restrictor_recovery"):
        CalibratedEngine.from_spec().calibrated({"intake.restrictor_recovery": 7.0})


def test_toml_round_trip_is_exact(tmp_path):
    eng = CalibratedEngine.from_spec().calibrated(VALUES)
    path = eng.write(tmp_path / "engine.toml")
    # --spec accepts it: the same spec value for value, the same hash
    assert load_spec(path) == eng.spec and load_spec(path).spec_hash() == eng.spec_hash()
    back = CalibratedEngine.load(path)
    assert back.spec == eng.spec and back.overrides == eng.overrides
    doc = tomllib.loads(path.read_text())
    assert doc["calibration"]["base_spec_hash"] == default_spec().spec_hash()
    for key, val in VALUES.items():
        section, field = key.split(".")
        assert doc[section][field] == val                      # full precision, not rounded


def test_writer_covers_every_spec_field():
    """The TOML writer is the inverse of the loader for the packaged engine (no field lost or renamed)."""
    spec = default_spec()
    back = spec_from_dict(tomllib.loads(spec_to_toml(spec)))
    assert back == spec
    # valve events survive the timing-diagram conversion exactly
    assert back.intake_valves.open_deg == spec.intake_valves.open_deg
    assert math.isclose(back.exhaust_valves.close_deg, spec.exhaust_valves.close_deg, rel_tol=0, abs_tol=0)


def test_write_refuses_a_spec_that_does_not_read_back(tmp_path, monkeypatch):
    import engine_model.calibrated as cm

    eng = CalibratedEngine.from_spec().calibrated(VALUES)
    monkeypatch.setattr(cm, "spec_to_toml", lambda spec: spec_to_toml(default_spec()))
    with pytest.raises(RuntimeError, match="does not read back"):
        eng.write(tmp_path / "engine.toml")
    assert not (tmp_path / "engine.toml").exists()
