"""Strict inputs: a bad bench file, plan or engine file is refused before any server, cluster or folder, with a
message that names the file, the key or column, the value and the fix."""

from __future__ import annotations

import time

import pandas as pd
import pytest

import flows.prefect_env
from engine_model.bench import load_bench, packaged_bench_path
from engine_model.spec import default_spec, load_spec, spec_from_dict
from flows.cli import main


class _Reached(Exception):
    """Raised where a command would start its Prefect server: the inputs were accepted."""


@pytest.fixture
def no_server(monkeypatch):
    """Fail loudly if a command gets as far as starting a Prefect server."""
    calls = []

    def guard(*_a, **_k):
        calls.append(1)
        raise _Reached("the command got past its input checks and would start a Prefect server now")

    monkeypatch.setattr(flows.prefect_env, "prefect_api", guard)
    return calls


def _fraction_bench(tmp_path):
    df = pd.read_csv(str(packaged_bench_path()))
    df["throttle_pct"] = df["throttle_pct"] / 100.0
    p = tmp_path / "bench_fraction.csv"
    df.to_csv(p, index=False)
    return p


# --------------------------------------------------------------------------- throttle given as a fraction

def test_fraction_throttle_is_refused_naming_file_column_and_fix(tmp_path):
    p = _fraction_bench(tmp_path)
    with pytest.raises(ValueError) as exc:
        load_bench(p)
    msg = str(exc.value)
    assert "bench_fraction.csv" in msg and "throttle_pct" in msg and "fraction" in msg
    assert "Multiply the column by 100" in msg and "--throttle-unit fraction" in msg


def test_throttle_unit_fraction_converts_on_load(tmp_path):
    got = load_bench(_fraction_bench(tmp_path), throttle_unit="fraction")
    want = load_bench(None)
    assert got["throttle_pct"].tolist() == pytest.approx(want["throttle_pct"].tolist())
    assert got["throttle_pct"].min() == pytest.approx(100.0)


def test_throttle_unit_fraction_refuses_a_column_in_percent():
    with pytest.raises(ValueError, match=r"value 100 is not a fraction in \[0, 1\]"):
        load_bench(str(packaged_bench_path()), throttle_unit="fraction")


@pytest.mark.parametrize("command", ["run", "calibrate", "gap"])
def test_fraction_throttle_is_refused_by_every_command_before_any_folder(tmp_path, capsys, no_server, command):
    bench, out = _fraction_bench(tmp_path), tmp_path / "out"
    assert main([command, "--bench", str(bench), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "bench file" in err and "bench_fraction.csv" in err and "'throttle_pct'" in err
    assert "--throttle-unit fraction" in err
    assert not out.exists() and not out.with_name("out.partial").exists()
    assert not no_server


@pytest.mark.parametrize("command", ["run", "calibrate", "gap"])
def test_throttle_unit_fraction_is_accepted_by_the_commands(tmp_path, no_server, command):
    bench, out = _fraction_bench(tmp_path), tmp_path / "out"
    with pytest.raises(_Reached):
        main([command, "--bench", str(bench), "--out", str(out), "--throttle-unit", "fraction"])
    assert no_server == [1]


def test_sweep_converts_a_fraction_plan_on_load(tmp_path, capsys, no_server):
    plan = pd.read_csv(str(packaged_bench_path())).iloc[:3][["point_id", "speed_rpm", "throttle_pct",
                                                              "spark_deg_btdc", "lambda"]]
    plan["throttle_pct"] = [0.2, 0.5, 1.0]
    plan["bdur_10_90_deg"], plan["wiebe_m"] = 30.0, 3.0
    src, out = tmp_path / "plan.csv", tmp_path / "sweep_out"
    plan.to_csv(src, index=False)
    assert main(["sweep", "--plan", str(src), "--out", str(out)]) == 2
    assert "plan file" in capsys.readouterr().err and not out.exists()
    with pytest.raises(_Reached):
        main(["sweep", "--plan", str(src), "--out", str(out), "--throttle-unit", "fraction"])
    saved = pd.read_parquet(out / "plan_input.parquet")
    assert saved["throttle_pct"].tolist() == pytest.approx([20.0, 50.0, 100.0])


# --------------------------------------------------------------------------- mbc gap: the bench file first

@pytest.mark.parametrize("change, needle", [
    (lambda df: df.drop(columns=["lambda"]), "missing column(s) ['lambda']"),
    (lambda df: df.assign(spark_deg_btdc=["x"] + [50.0] * (len(df) - 1)), "column 'spark_deg_btdc': value 'x'"),
    (lambda df: df.assign(point_id=["a"] * len(df)), "appears twice"),
])
def test_gap_checks_its_bench_file_before_anything(tmp_path, capsys, no_server, change, needle):
    import flows.stages.gap  # noqa: F401  (import time is not the command's time)

    bench, out = tmp_path / "bench.csv", tmp_path / "out"
    change(pd.read_csv(str(packaged_bench_path()))).to_csv(bench, index=False)
    t0 = time.perf_counter()
    assert main(["gap", "--bench", str(bench), "--out", str(out)]) == 2
    assert time.perf_counter() - t0 < 10.0
    err = capsys.readouterr().err
    assert f"bench file {bench}" in err and needle in err and "plan" not in err
    assert not out.exists() and not no_server


# --------------------------------------------------------------------------- engine files

def _doc():
    import tomllib
    from importlib import resources

    return tomllib.loads(resources.files("engine_model.engines").joinpath("yamaha_r6_fs.toml").read_text())


def test_unknown_key_names_section_key_and_nearest_name():
    doc = _doc()
    doc["intake"]["restrictor_cdd"] = doc["intake"].pop("restrictor_cd")
    with pytest.raises(ValueError, match=r"x\.toml: unknown key intake\.restrictor_cdd; did you mean "
                                         r"'intake\.restrictor_cd'\?"):
        spec_from_dict(doc, "x.toml")


def test_unknown_section_names_it_and_the_nearest_section():
    doc = _doc()
    doc["heat_transfr"] = {"multiplier": 1.0}
    with pytest.raises(ValueError, match=r"unknown section \[heat_transfr\]; did you mean 'heat_transfer'\?"):
        spec_from_dict(doc, "x.toml")


def test_unknown_key_of_the_calibration_record_is_refused():
    doc = _doc()
    doc["calibration"] = {"overides": {"intake.restrictor_cd": 0.9}}
    with pytest.raises(ValueError, match=r"unknown key calibration\.overides; did you mean 'calibration\.overrides'"):
        spec_from_dict(doc, "x.toml")


@pytest.mark.parametrize("section, key, value, needle", [
    ("geometry", "bore_m", "0.067", "geometry.bore_m = '0.067' is a text (in quotes), expected a number in m; "
                                    "write it without quotes"),
    ("intake", "runner_inertia", 1, "intake.runner_inertia = 1 is a whole number, expected true or false"),
    ("ambient", "temperature_k", [298.0], "ambient.temperature_k = [298.0] is a list, expected a number in K"),
])
def test_wrong_type_names_key_value_type_and_unit(section, key, value, needle):
    doc = _doc()
    doc[section][key] = value
    with pytest.raises(ValueError) as exc:
        spec_from_dict(doc, "x.toml")
    assert needle in str(exc.value)


def test_quoted_number_in_an_engine_file_is_a_clear_error(tmp_path, capsys):
    from importlib import resources

    text = resources.files("engine_model.engines").joinpath("yamaha_r6_fs.toml").read_text()
    bad = tmp_path / "engine.toml"
    bad.write_text(text.replace("restrictor_cd = 0.97", 'restrictor_cd = "0.97"', 1))
    with pytest.raises(ValueError, match=r"engine\.toml: intake\.restrictor_cd = '0\.97' is a text"):
        load_spec(bad)
    assert main(["gap-plan", "--spec", str(bad), "--out", str(tmp_path / "p.csv")]) == 2
    assert "intake.restrictor_cd" in capsys.readouterr().err


def test_override_with_a_typo_names_the_nearest_field():
    with pytest.raises(ValueError, match=r"did you mean 'intake\.restrictor_cd'"):
        default_spec().with_values({"intake.restrictor_cdd": 0.9})
