"""One finished ``mbc run --quick`` for the whole session (a quick run takes minutes), shared by the tests
that read a finished run; a test that changes a run works on its own copy (``run_copy``)."""

from __future__ import annotations

import contextlib
import io
import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest


@dataclass(frozen=True)
class QuickRun:
    """A finished quick run: its folder, what ``mbc run`` printed, and the bench file it was given (deleted
    after the run, so a later stage can only use the run's own copy)."""

    out: Path
    stdout: str
    bench: Path


@pytest.fixture(scope="session")
def quick_run(prefect_api, tmp_path_factory) -> QuickRun:
    from engine_model.bench import packaged_bench_path
    from flows.cli import main

    base = tmp_path_factory.mktemp("quick")
    bench = base / "my_bench.csv"
    bench.write_bytes(packaged_bench_path().read_bytes())
    out = base / "run"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["run", "--quick", "--bench", str(bench), "--out", str(out)])
    assert code == 0
    bench.unlink()
    return QuickRun(out=out, stdout=buf.getvalue(), bench=bench)


@pytest.fixture
def run_copy(quick_run, tmp_path) -> Path:
    """A copy of the shared quick run (sweeps included) that the test may change."""
    return Path(shutil.copytree(quick_run.out, tmp_path / "run"))
