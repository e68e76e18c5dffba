"""A stage re-run from a finished run: `mbc maps --run`, `mbc gap --run`, `mbc run --stages maps`.

The finished run is the session's one quick run (tests/flows/conftest.py); tests that change a run work on
a copy of it.
"""

import json
import shutil

import pytest

from flows.cli import main

TABLES = ("spark_advance.csv", "injection_time.csv", "lambda_target.csv")


def _stamps(folder, sub):
    """{relative path: (mtime_ns, bytes)} of every file under ``folder/sub``."""
    return {str(p.relative_to(folder)): (p.stat().st_mtime_ns, p.read_bytes())
            for p in sorted((folder / sub).rglob("*")) if p.is_file()}


def test_mbc_maps_run_rebuilds_the_run_tables_exactly(quick_run, tmp_path, capsys):
    """`mbc maps --run DIR --out OTHER` (model, engine, grid, step and settings of the run) gives the run's tables."""
    run = quick_run.out
    manifest_before = (run / "manifest.json").read_bytes()
    other = tmp_path / "other"
    assert main(["maps", "--run", str(run), "--out", str(other)]) == 0
    for name in TABLES:
        assert (other / "maps" / name).read_bytes() == (run / "maps" / name).read_bytes(), name
    assert "tables:" in capsys.readouterr().out
    # --out elsewhere leaves the run as it was
    assert (run / "manifest.json").read_bytes() == manifest_before
    assert not (other / "manifest.json").exists()


def test_mbc_run_stages_maps_reruns_maps_on_a_finished_run(run_copy):
    """`--stages maps` re-runs the maps stage (new files), leaves the other stages' files, keeps their links."""
    out = run_copy
    maps_before = _stamps(out, "maps")
    others_before = {sub: _stamps(out, sub) for sub in ("calibration", "model", "gap", "virtual_bench")}
    engine_before = (out / "engine.toml").read_bytes()
    assert main(["run", "--quick", "--stages", "maps", "--out", str(out)]) == 0
    maps_after = _stamps(out, "maps")
    for name in TABLES:
        rel = f"maps/{name}"
        assert maps_after[rel][0] != maps_before[rel][0], f"{rel} was not rewritten"
        assert maps_after[rel][1] == maps_before[rel][1], f"{rel} changed content on the same inputs"
    for sub, before in others_before.items():
        assert _stamps(out, sub) == before, f"{sub}/ was touched"
    assert (out / "engine.toml").read_bytes() == engine_before
    man = json.loads((out / "manifest.json").read_text())
    assert man["status"] == "complete" and man["stages"] == ["maps"] and list(man["timings_s"]) == ["maps"]
    assert {"calibration", "model", "maps", "gap"} <= set(man)
    page = (out / "index.html").read_text()
    for link in ("calibration/calibration.html", "model/model.json", "gap/", "maps/spark_advance.csv"):
        assert link in page, link
    assert "(missing)" not in page


def test_mbc_run_stages_maps_refuses_a_folder_without_a_model(run_copy, capsys):
    """A run folder that lacks the model stage's output is refused before any work (nothing renamed or written)."""
    out = run_copy
    shutil.rmtree(out / "model")
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    assert main(["run", "--quick", "--stages", "maps", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "stage 'maps' needs the 'model' stage's output" in err and "model/model.json" in err
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before
    assert not out.with_name(out.name + ".partial").exists()


def test_mbc_maps_run_in_place_updates_the_run(run_copy, capsys):
    """`mbc maps --run DIR` writes DIR/maps and records the stage in DIR/manifest.json and index.html."""
    out = run_copy
    spark_before = _stamps(out, "maps")["maps/spark_advance.csv"]
    gap_before = _stamps(out, "gap")
    assert main(["maps", "--run", str(out)]) == 0
    spark_after = _stamps(out, "maps")["maps/spark_advance.csv"]
    assert spark_after[0] != spark_before[0] and spark_after[1] == spark_before[1]
    assert _stamps(out, "gap") == gap_before
    man = json.loads((out / "manifest.json").read_text())
    assert man["stages"] == ["maps"] and "maps" in man and "gap" in man and man["status"] == "complete"
    page = (out / "index.html").read_text()
    assert "maps/spark_advance.csv" in page and "model/model.json" in page and "(missing)" not in page


def test_mbc_gap_run_in_place_uses_the_run_bench_copy(quick_run, run_copy, capsys):
    """`mbc gap --run DIR` runs on the run's engine and bench copy (the original bench file is gone)."""
    assert not quick_run.bench.exists()
    out = run_copy
    before = json.loads((out / "gap" / "run.json").read_text())
    mtime = (out / "gap" / "run.json").stat().st_mtime_ns
    assert main(["gap", "--run", str(out)]) == 0
    assert (out / "gap" / "run.json").stat().st_mtime_ns != mtime
    after = json.loads((out / "gap" / "run.json").read_text())
    assert after["bench"] == str(out / "bench.parquet")
    assert after["statement"] == before["statement"] and after["spec_hash"] == before["spec_hash"]
    man = json.loads((out / "manifest.json").read_text())
    assert man["stages"] == ["gap"] and man["gap"]["statement"] == before["statement"]
    assert "maps/spark_advance.csv" in (out / "index.html").read_text()


def test_mbc_gap_run_refuses_a_folder_that_is_not_a_run(tmp_path, capsys):
    """A folder without a run's manifest is refused by name before any work; nothing is written into it."""
    folder = tmp_path / "notarun"
    folder.mkdir()
    (folder / "notes.txt").write_text("x")
    assert main(["gap", "--run", str(folder)]) == 2
    assert f"--run {folder}: not a run folder (no manifest.json)" in capsys.readouterr().err
    (folder / "manifest.json").write_text(json.dumps({"kind": "sweep", "status": "complete"}))
    assert main(["gap", "--run", str(folder)]) == 2
    assert "of kind 'sweep', not 'run'" in capsys.readouterr().err
    assert sorted(p.name for p in folder.iterdir()) == ["manifest.json", "notes.txt"]
    assert main(["maps", "--run", str(tmp_path / "nope")]) == 2
    assert "no such folder" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["maps"], "give --run DIR (a finished `mbc run` folder), or --model FILE and --out DIR"),
    (["gap"], "give --out DIR, or --run DIR"),
])
def test_mbc_maps_and_gap_need_a_run_or_their_inputs(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_mbc_maps_and_gap_run_refuse_model_and_spec(tmp_path, capsys):
    """With --run the model and engine are the run's: --model/--spec beside it are refused before any work."""
    run, other = tmp_path / "run", tmp_path / "other"
    assert main(["maps", "--run", str(run), "--model", str(run / "model" / "model.json"), "--out", str(other)]) == 2
    assert "leave out --model/--spec" in capsys.readouterr().err
    assert main(["gap", "--run", str(run), "--spec", str(run / "engine.toml"), "--out", str(other)]) == 2
    assert "leave out --spec/--override" in capsys.readouterr().err
    assert not other.exists()


def test_mbc_run_stages_naming_no_stage_is_refused(tmp_path, capsys):
    """`--stages ,` would run nothing and call the run complete: refused before any folder exists."""
    assert main(["run", "--quick", "--stages", ",", "--out", str(tmp_path / "r")]) == 2
    assert "names no stage" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_mbc_maps_run_in_place_with_another_grid(run_copy, capsys):
    """An override (here the throttle breakpoints) is built in place on its own sweeps and recorded in the
    manifest, so the run's record says what its maps/ holds and a later rebuild repeats it."""
    import pandas as pd

    out = run_copy
    assert main(["maps", "--run", str(out), "--throttle", "60,100"]) == 0
    spark = pd.read_csv(out / "maps" / "spark_advance.csv", index_col=0)
    assert spark.shape == (2, 3) and [float(v) for v in spark.index] == [60.0, 100.0]
    man = json.loads((out / "manifest.json").read_text())
    assert man["settings"]["map_throttle"] == "60,100" and man["settings"]["map_speed"] == "6000,9000,12000"
    assert man["maps"]["stats"]["cells"] == 6
