"""Shared fixtures, and the test tiers.

Tiers: ``make test-fast`` runs ``-m "not slow and not integration"`` (physics, numerics, contracts; no
Prefect server, no Dask cluster; under 2 minutes); ``make test`` runs everything.  Every test under
``tests/flows/`` is marked ``integration`` here (real Prefect, real Dask, ``mbc`` subprocesses).

``prefect_api``: one real Prefect API server (Prefect's test harness: a
uvicorn subprocess on a temporary database) for the whole test session (one
per pytest-xdist worker that asks for it),
exported through ``PREFECT_API_URL`` so that Dask worker processes and ``mbc``
subprocesses started by a test talk to the same server (docs/stack.md).
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import socket
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import pytest


@pytest.hookimpl(tryfirst=True)       # before pytest-xdist reads the groups
def pytest_collection_modifyitems(config, items):
    flows_dir = os.path.join(os.path.dirname(__file__), "flows") + os.sep
    for item in items:
        if str(item.fspath).startswith(flows_dir):
            item.add_marker(pytest.mark.integration)
        # Under pytest-xdist (``--dist loadgroup``, how ``make test`` runs) a group runs on one worker, so a
        # module-scoped fixture is built once: each module is a group, and every test that reads the shared
        # quick run joins one group whichever module it is in, so the run is built once.
        shared = {"quick_run", "run_copy"} & set(getattr(item, "fixturenames", ()))
        item.add_marker(pytest.mark.xdist_group("quick_run" if shared else item.nodeid.split("::")[0]))


@pytest.fixture(scope="session")
def prefect_api():
    import flows.prefect_env  # noqa: F401  (quiet defaults)
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    old = os.environ.get("PREFECT_API_URL")
    with prefect_test_harness(server_startup_timeout=90):
        url = PREFECT_API_URL.value()
        os.environ["PREFECT_API_URL"] = url
        try:
            yield url
        finally:
            if old is None:
                os.environ.pop("PREFECT_API_URL", None)
            else:
                os.environ["PREFECT_API_URL"] = old


#: Processes a test shares an in-process simulation batch among (``simulate(..., workers=)``): the cores
#: there are, at most 4 (CI has 2).
SIM_WORKERS = max(1, min(4, os.cpu_count() or 1))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def small_plan(n_ops: int = 3, per_op: int = 4) -> pd.DataFrame:
    """A plan of ``n_ops`` WOT operating points x ``per_op`` Wiebe settings (cheap, all physical)."""
    rows = []
    for i, speed in enumerate([8000.0, 9500.0, 11000.0, 6000.0, 10000.0][:n_ops]):
        for j in range(per_op):
            rows.append({"point_id": f"op{i}-w{j}", "speed_rpm": speed, "throttle_pct": 100.0,
                         "spark_deg_btdc": 40.0 + 2 * i, "lambda": 0.9,
                         "bdur_10_90_deg": 20.0 + 30.0 * j / max(per_op - 1, 1),
                         "wiebe_m": 3.0 + 3.0 * j / max(per_op - 1, 1)})
    return pd.DataFrame(rows)


#: Volumetric efficiency of the synthetic engine of :func:`synthetic_map` (relative to plenum pressure, 293.15 K).
SYNTHETIC_VE = 0.9


def synthetic_plenum_bar(throttle_pct, speed_rpm):
    """Plenum pressure [bar] of the synthetic engine: rises with throttle, falls a little with speed."""
    import numpy as np
    t, n = np.asarray(throttle_pct, float), np.asarray(speed_rpm, float)
    return 0.3 + 0.7 * (1.0 - np.exp(-t / 30.0)) - 0.01 * n / 1000.0 * t / 100.0


def synthetic_map(grid=((20.0, 40.0, 70.0, 100.0), (3000.0, 6000.0, 9000.0, 12000.0))):
    """(spec, MapResult) of a map build on a synthetic engine, in-process, ~2 s.

    Torque a parabola in spark (MBT 20 + 3 n/1000 deg), knock log-linear in spark, plenum
    pressure :func:`synthetic_plenum_bar`, air = :data:`SYNTHETIC_VE` of the displacement
    filled at plenum pressure and 293.15 K (so the VE of the ECU export is known exactly).
    """
    import numpy as np

    from engine_model import default_spec
    from engine_model.tables import EcuGrid, MapSettings, PriorModel, build_maps
    from engine_model.tables.ecu_table import R_AIR_J_KG_K

    spec = default_spec()
    vd = spec.geometry.total_displacement_m3

    def engine(plan):
        s, n, t = (plan[c].to_numpy(float) for c in ("spark_deg_btdc", "speed_rpm", "throttle_pct"))
        p = synthetic_plenum_bar(t, n)
        tmax = 60 * t / 100 - 5 * n / 10000 + 5
        out = plan.copy()
        out["brake_torque_nm"] = tmax - 0.02 * np.abs(tmax) * (s - (20 + 3 * n / 1000)) ** 2 / 10
        out["knock_index"] = np.exp(0.08 * (s - (60 + 3 * n / 1000 - 45 * t / 100)))
        out["bmep_bar"] = out["brake_torque_nm"] * 4 * np.pi / vd / 1e5
        out["air_mass_flow_kg_h"] = SYNTHETIC_VE * p * 1e5 * vd / (R_AIR_J_KG_K * 293.15) * n / 120 * 3600
        out["plenum_pressure_bar"] = p
        out["status"] = "ok"
        return out

    res = build_maps(spec, PriorModel(), grid=EcuGrid(*grid), evaluate=engine,
                     settings=MapSettings(spark_min_deg_btdc=20.0))
    return spec, res


def ecu_run_folder(run):
    """A run folder as the pipeline leaves it for ``mbc export``: maps/ (write_maps) and engine.toml."""
    from pathlib import Path

    from engine_model.calibrated import CalibratedEngine
    from engine_model.tables import write_maps

    run = Path(run)
    spec, res = synthetic_map()
    write_maps(res, run / "maps", figures=False, spec=spec)
    CalibratedEngine.from_spec(spec).write(run / "engine.toml")
    return run, spec, res


# One finished `mbc run --quick` for the whole session (a quick run takes minutes), shared by the tests
# that read a finished run; a test that changes a run works on its own copy (`run_copy`).
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
