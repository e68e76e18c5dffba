"""Engine spec: the embedded R6 carries the paper's values; bad specs are refused by name."""

import dataclasses

import pytest

from engine_model.spec import default_spec, load_spec, spec_from_dict

import tomllib
from importlib import resources


def _doc():
    return tomllib.loads(resources.files("engine_model.engines").joinpath("yamaha_r6_fs.toml").read_text())


def test_default_spec_has_the_papers_engine():
    s = default_spec()
    g = s.geometry
    assert (g.bore_m, g.stroke_m, g.compression_ratio, g.n_cylinders) == (0.067, 0.0425, 12.8, 4)
    assert g.firing_order == (1, 2, 4, 3)
    # 599 cc (paper: 599 cc), from bore and stroke
    assert g.total_displacement_m3 == pytest.approx(599e-6, rel=2e-3)
    assert s.intake.restrictor_throat_m == 0.020
    # valve events in cycle degrees: IVO 39 BTDC, IVC 65 ABDC, EVO 64 BBDC, EVC 24 ATDC
    assert s.intake_valves.open_deg == pytest.approx(321.0)
    assert s.intake_valves.open_deg + s.intake_valves.duration_deg == pytest.approx(605.0)
    assert s.exhaust_valves.open_deg == pytest.approx(116.0)
    assert s.exhaust_valves.open_deg + s.exhaust_valves.duration_deg == pytest.approx(384.0)
    # firing order 1-2-4-3, 180 deg apart
    assert g.phase_deg() == (0.0, 180.0, 540.0, 360.0)


def test_every_constant_in_the_toml_has_a_source_comment():
    text = resources.files("engine_model.engines").joinpath("yamaha_r6_fs.toml").read_text()
    missing = []
    for line in text.splitlines():
        s = line.strip()
        if "=" in s and not s.startswith("#") and not s.startswith("name"):
            key = s.split("=")[0].strip()
            if key in ("runner_inertia", "per_cylinder", "multiplier", "cd_ld", "cd"):
                continue  # switches / table rows documented in the comment block above them
            if "#" not in s:
                missing.append(key)
    assert not missing, f"constants without a source comment: {missing}"


def test_spec_hash_is_stable_and_sensitive():
    a, b = default_spec(), default_spec()
    assert a.spec_hash() == b.spec_hash()
    c = a.replace(intake=dataclasses.replace(a.intake, restrictor_cd=0.9))
    assert c.spec_hash() != a.spec_hash()


@pytest.mark.parametrize("section,key,value,needle", [
    ("geometry", "bore_m", 0.0, "geometry.bore_m = 0.0"),
    ("geometry", "bore_m", -0.067, "geometry.bore_m"),
    ("geometry", "compression_ratio", 1.0, "geometry.compression_ratio = 1.0"),
    ("geometry", "compression_ratio", 0.5, "geometry.compression_ratio"),
    ("geometry", "firing_order", [1, 2, 2, 3], "firing_order"),
    ("intake", "restrictor_cd", 1.5, "intake.restrictor_cd = 1.5"),
    ("intake_valves", "closes_deg_abdc", -200.0, "inconsistent valve timing"),
    ("exhaust_valves", "opens_deg_bbdc", -100.0, "inconsistent valve timing"),
    ("fuel", "h_to_c", -1.0, "fuel.h_to_c"),
])
def test_invalid_spec_names_the_field(section, key, value, needle):
    doc = _doc()
    doc[section][key] = value
    with pytest.raises(ValueError, match=needle.replace(".", r"\.").replace("[", r"\[")):
        spec_from_dict(doc, "test.toml")


def test_inconsistent_valve_overlap_is_refused():
    doc = _doc()
    # intake opening before the exhaust opens makes no four-stroke sense
    doc["intake_valves"]["opens_deg_btdc"] = 250.0
    with pytest.raises(ValueError, match="valve timing"):
        spec_from_dict(doc, "test.toml")


def test_missing_section_and_file_errors(tmp_path):
    doc = _doc()
    del doc["friction"]
    with pytest.raises(ValueError, match=r"missing section \[friction\]"):
        spec_from_dict(doc, "x.toml")
    with pytest.raises(ValueError, match="not found"):
        load_spec(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("geometry = [")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_spec(bad)


def test_unknown_key_is_refused():
    doc = _doc()
    doc["geometry"]["bore_mm"] = 67
    with pytest.raises(ValueError, match="bore_mm"):
        spec_from_dict(doc, "x.toml")


@pytest.mark.parametrize("value", [0, 9, 2.5, True])
def test_runner_segments_must_be_a_small_integer(value):
    doc = _doc()
    doc["intake"]["runner_segments"] = value
    with pytest.raises(ValueError, match=r"intake\W{1,3}runner_segments"):
        spec_from_dict(doc, "x.toml")
