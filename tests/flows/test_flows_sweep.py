"""The sweep pipeline through real Prefect and real Dask: every point exactly once, resumable, deterministic.

These tests check orchestration, not physics (the physics tests run the
solver at its production settings), so the sweeps here use a coarse solver
(1 deg step, 1 % tolerance) to keep each point at a few tens of ms.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.dataset as ds
import pytest

from conftest import small_plan
from engine_model import RESULT_COLUMNS
from flows import store
from flows.sweep import prepare_plan, run_sweep

QUICK = {"step_deg": 1.0, "tolerance": 1e-2}
MBC = [sys.executable, "-m", "flows.cli"]


def _check_dataset(out: Path, plan: pd.DataFrame) -> pd.DataFrame:
    """Every planned point exactly once, contract columns with the contract's types."""
    table = ds.dataset(out / "sweep", format="parquet").to_table()
    df = table.to_pandas()
    assert sorted(df["point_id"]) == sorted(plan["point_id"]), "each planned point exactly once"
    assert df["point_id"].is_unique
    for c in RESULT_COLUMNS:
        assert c in df.columns, c
    types = {f.name: str(f.type) for f in table.schema}
    assert types["converged"] == "bool" and types["cycles_run"] == "int64" and types["status"] == "string"
    assert types["point_id"] == "string"
    for c in ("speed_rpm", "brake_torque_nm", "air_mass_flow_kg_h", "knock_index"):
        assert types[c] == "double", c
    return df


def test_sweep_on_local_two_worker_cluster_is_complete_and_deterministic(prefect_api, tmp_path):
    plan = small_plan(3, 4)
    src = tmp_path / "plan.csv"
    plan.to_csv(src, index=False)
    man1 = run_sweep(src, tmp_path / "a", workers=2, chunk_size=3, progress=False, **QUICK)
    df1 = _check_dataset(tmp_path / "a", plan)
    # 3 operating points x 4 rows, chunks of <= 3 rows that do not straddle operating points: 2 per point
    assert man1["status"] == "complete" and man1["chunks"] == 6 and man1["chunks_computed"] == 6
    assert man1["dask"]["workers"] == 2 and man1["dask"]["threads"] == 2
    assert man1["counts"]["points"] == 12 and man1["missing_points"] == 0
    assert man1["spec_hash"] and man1["plan_hash"] and man1["package_version"]
    on_disk = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert on_disk["status"] == "complete" and on_disk["counts"] == man1["counts"]
    # physics made it through: torque grows from the slowest to the fastest burn at one point
    op0 = df1[df1["point_id"].str.startswith("op0")].sort_values("bdur_10_90_deg")
    assert op0["brake_torque_nm"].iloc[0] > op0["brake_torque_nm"].iloc[-1]
    # determinism: the same plan and spec give identical values
    run_sweep(src, tmp_path / "b", workers=2, chunk_size=3, progress=False, **QUICK)
    a = store.read_results(tmp_path / "a")
    b = store.read_results(tmp_path / "b")
    assert store.numeric_equal(a, b)
    # and pandas reads the folder as one dataset
    assert len(pd.read_parquet(tmp_path / "a" / "sweep")) == 12


def test_rerun_skips_finished_chunks_and_refuses_a_different_plan(prefect_api, tmp_path):
    plan = small_plan(2, 3)
    src = tmp_path / "plan.csv"
    plan.to_csv(src, index=False)
    out = tmp_path / "out"
    man0 = run_sweep(src, out, workers=1, chunk_size=2, progress=False, **QUICK)
    before = store.attempt_counts(out / "sweep")
    assert sorted(before) == list(range(man0["chunks"])) and set(before.values()) == {1}
    # remove one part: the re-run computes exactly that chunk
    store.part_path(out / "sweep", 1).unlink()
    man = run_sweep(src, out, workers=1, progress=False, **QUICK)
    assert man["chunks_skipped"] == man0["chunks"] - 1 and man["chunks_computed"] == 1
    after = store.attempt_counts(out / "sweep")
    assert after == {**before, 1: before[1] + 1}
    _check_dataset(out, plan)
    # a different plan into the same folder is refused, and nothing is changed
    plan2 = plan.assign(spark_deg_btdc=plan["spark_deg_btdc"] + 1)
    src2 = tmp_path / "plan2.csv"
    plan2.to_csv(src2, index=False)
    with pytest.raises(ValueError, match="different plan"):
        run_sweep(src2, out, workers=1, progress=False, **QUICK)
    assert store.attempt_counts(out / "sweep") == after
    # the same plan with another chunking (explicit chunk_size): the old parts are replaced, none is left
    # over to duplicate points in the dataset
    man3 = run_sweep(src, out, workers=1, chunk_size=len(plan), progress=False, **QUICK)
    assert man3["chunks"] == 1 and len(_parts(out)) == 1
    _check_dataset(out, plan)


def _wait_for(cond, timeout: float, what: str):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if cond():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _parts(out: Path) -> list[Path]:
    return sorted((out / "sweep").glob("part-*.parquet"))


def test_interrupted_sweep_resumes_without_recompute(prefect_api, tmp_path):
    plan = small_plan(4, 4)
    src = tmp_path / "plan.csv"
    plan.to_csv(src, index=False)
    out = tmp_path / "out"
    # production solver settings here: chunks long enough (~0.2 s) that the kill lands mid-sweep
    cmd = MBC + ["sweep", "--plan", str(src), "--out", str(out), "--workers", "1", "--chunk-size", "1"]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _wait_for(lambda: len(_parts(out)) >= 3, 120, "three finished chunks")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)      # the whole process group: driver and its Dask workers
        proc.wait()
    done_before = {int(p.name[5:10]) for p in _parts(out)}
    assert 3 <= len(done_before) < 16, "interrupted mid-sweep"
    man = json.loads((out / "manifest.json").read_text())
    assert man["status"] == "running", "an interrupted sweep never claims success"
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "16/16 points" in res.stdout
    _check_dataset(out, plan)
    counts = store.attempt_counts(out / "sweep")
    assert all(counts[c] == 1 for c in done_before), "finished chunks are not recomputed"
    assert set(counts) == set(range(16))
    man = json.loads((out / "manifest.json").read_text())
    assert man["status"] == "complete" and man["chunks_skipped"] == len(done_before)


@pytest.mark.parametrize("mutate, words", [
    (lambda p: p.drop(columns=["wiebe_m"]), ["missing required column", "wiebe_m"]),
    (lambda p: p.assign(lambda_=None).pipe(lambda q: q.assign(**{"lambda": [0.9, np.nan] + [0.9] * (len(q) - 2)}))
     .drop(columns=["lambda_"]), ["row 1", "'lambda'", "not a finite number"]),
    (lambda p: p.assign(point_id=["x", "x"] + list(p["point_id"].iloc[2:])), ["row 1", "'point_id'", "duplicates row 0"]),
    (lambda p: p.assign(throttle_pct=[100.0, 100.0, 140.0] + [100.0] * (len(p) - 3)),
     ["row 2", "'throttle_pct'", "140"]),
])
def test_bad_plan_refused_naming_file_row_column(tmp_path, mutate, words):
    bad = mutate(small_plan(2, 2))
    src = tmp_path / "bad_plan.csv"
    bad.to_csv(src, index=False)
    out = tmp_path / "out"
    res = subprocess.run(MBC + ["sweep", "--plan", str(src), "--out", str(out)], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 2
    assert str(src) in res.stderr
    for w in words:
        assert w in res.stderr, (w, res.stderr)
    assert not out.exists(), "nothing is created for a refused plan"


def test_prepare_plan_numbers_points_and_keeps_order():
    from engine_model import default_spec

    plan = small_plan(1, 3).drop(columns=["point_id"])
    pts = prepare_plan(plan, default_spec())
    assert list(pts["point_id"]) == ["p00000", "p00001", "p00002"]
    assert list(pts["plan_row"]) == [0, 1, 2]


def test_chunking_covers_every_row_once():
    for n, size in [(1, 1), (10, 3), (10, 10), (10, 25), (1000, 7)]:
        b = store.chunk_bounds(n, size)
        rows = [i for a, z in b for i in range(a, z)]
        assert rows == list(range(n)) and all(z - a <= size for a, z in b)
    with pytest.raises(ValueError):
        store.chunk_bounds(5, 0)


def test_torn_part_is_not_a_finished_chunk(tmp_path):
    p = tmp_path / "part-00000.parquet"
    p.write_bytes(b"PAR1 not really")
    assert store.read_part_meta(p) is None


def test_chunks_follow_state_groups():
    keys = ["a"] * 5 + ["b"] * 2 + ["c"] * 9 + ["d"]
    b = store.chunk_bounds(len(keys), 4, groups=keys)
    rows = [i for a, z in b for i in range(a, z)]
    assert rows == list(range(len(keys)))
    # run "a" (5 rows <= 1.25 x 4) stays whole; run "c" (9 rows) is cut into three near-equal pieces of <= 4
    # rows, the last of which takes the short run "d" after it; no chunk starts inside a run otherwise
    assert b == [(0, 5), (5, 7), (7, 10), (10, 13), (13, 17)]
    assert all(z - a <= int(store.RUN_STRETCH * 4) for a, z in b)
    run_start = {0: "a", 5: "b", 7: "c", 16: "d"}
    assert all(keys[a] == "c" for a, _ in b if a not in run_start)
    assert store.chunk_bounds(len(keys), 20, groups=keys) == [(0, 17)]
    assert store.chunk_bounds(len(keys), 7, groups=keys) == [(0, 7), (7, 11), (11, 17)]
    # without the stretch every chunk respects the size strictly
    b1 = store.chunk_bounds(len(keys), 4, groups=keys, stretch=1.0)
    assert all(z - a <= 4 for a, z in b1) and [i for a, z in b1 for i in range(a, z)] == list(range(len(keys)))
    with pytest.raises(ValueError):
        store.chunk_bounds(5, 2, groups=["a"] * 5, stretch=0.5)
