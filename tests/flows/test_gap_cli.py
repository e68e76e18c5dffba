"""`mbc gap` input errors are clear and happen before any simulation or Prefect server starts."""

import pandas as pd

from flows.cli import main


def test_gap_bench_missing_outputs(tmp_path, capsys):
    bad = tmp_path / "bench.csv"
    pd.DataFrame({"point_id": ["a"], "speed_rpm": [9000], "throttle_pct": [100], "spark_deg_btdc": [50],
                  "lambda": [0.9], "brake_torque_nm": [44.0]}).to_csv(bad, index=False)
    assert main(["gap", "--bench", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "bench.csv" in err and "air_mass_flow_kg_h" in err and "missing" in err
    assert not (tmp_path / "o").exists()


def test_gap_bench_file_not_found(tmp_path, capsys):
    assert main(["gap", "--bench", str(tmp_path / "nope.csv"), "--out", str(tmp_path / "o")]) == 2
    assert "bench file not found" in capsys.readouterr().err


def test_gap_benchmark_design_option():
    """`--design discriminating` reaches the benchmark; an unknown design is refused by the parser."""
    import pytest

    from flows.cli import build_parser

    args = build_parser().parse_args(["gap-benchmark", "--out", "x", "--design", "discriminating"])
    assert args.design == "discriminating"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["gap-benchmark", "--out", "x", "--design", "dopt"])


def test_gap_plan_options_and_bad_size(tmp_path, capsys):
    """`mbc gap-plan` parses its options and refuses a plan of fewer than 2 points before any simulation."""
    from flows.cli import build_parser

    args = build_parser().parse_args(["gap-plan", "--out", "p.csv", "--points", "24", "--candidates", "100"])
    assert (args.points, args.candidates) == (24, 100)
    assert main(["gap-plan", "--out", str(tmp_path / "p.csv"), "--points", "1"]) == 2
    assert "--points 1" in capsys.readouterr().err
    assert not (tmp_path / "p.csv").exists()


def test_gap_plan_coverage_options_and_too_few_points(tmp_path, capsys):
    """`--max-speed-gap-rpm` and the speed range parse (defaults 1000, 5000-12500 rpm); a plan too small to
    cover the range at the limit is refused before any simulation, naming the minimum."""
    from flows.cli import build_parser

    args = build_parser().parse_args(["gap-plan", "--out", "p.csv"])
    assert (args.max_speed_gap_rpm, args.speed_min, args.speed_max) == (1000.0, 5000.0, 12500.0)
    args = build_parser().parse_args(["gap-plan", "--out", "p.csv", "--max-speed-gap-rpm", "500",
                                      "--speed-min", "8000", "--speed-max", "11000"])
    assert (args.max_speed_gap_rpm, args.speed_min, args.speed_max) == (500.0, 8000.0, 11000.0)
    out = tmp_path / "p.csv"
    assert main(["gap-plan", "--out", str(out), "--points", "6"]) == 2
    err = capsys.readouterr().err
    assert "needs at least 7 points" in err and "--max-speed-gap-rpm" in err
    assert main(["gap-plan", "--out", str(out), "--speed-min", "9000", "--speed-max", "8000"]) == 2
    assert "--speed-min" in capsys.readouterr().err
    assert main(["gap-plan", "--out", str(out), "--max-speed-gap-rpm", "0"]) == 2
    assert "--max-speed-gap-rpm 0" in capsys.readouterr().err
    assert not out.exists()


def test_gap_benchmark_outside_suite_options(tmp_path, capsys):
    """`--suite outside` parses its options; a missing plan file or --plan without it fails before any run."""
    from flows.cli import build_parser

    args = build_parser().parse_args(["gap-benchmark", "--out", "x", "--suite", "outside", "--null-seeds", "70",
                                      "--plan", "p.csv", "--seeds", "4", "--seed-start", "3"])
    assert (args.suite, args.null_seeds, args.plan, args.seeds, args.seed_start) == ("outside", 70, "p.csv", 4, 3)
    assert build_parser().parse_args(["gap-benchmark", "--out", "x"]).suite == "library"
    assert main(["gap-benchmark", "--out", str(tmp_path / "o"), "--suite", "outside",
                 "--plan", str(tmp_path / "nope.csv")]) == 2
    assert "plan file not found" in capsys.readouterr().err
    assert main(["gap-benchmark", "--out", str(tmp_path / "o"), "--plan", str(tmp_path / "nope.csv")]) == 2
    assert "--suite outside" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
