"""Shared fixtures, and the test tiers.

Tiers: ``make test-fast`` runs ``-m "not slow and not integration"`` (physics, numerics, contracts; no
Prefect server, no Dask cluster; under 2 minutes); ``make test`` runs everything.  Every test under
``tests/flows/`` is marked ``integration`` here (real Prefect, real Dask, ``mbc`` subprocesses).

``prefect_api``: one real Prefect API server (Prefect's test harness: a
uvicorn subprocess on a temporary database) for the whole test session,
exported through ``PREFECT_API_URL`` so that Dask worker processes and ``mbc``
subprocesses started by a test talk to the same server (docs/stack.md).
"""

from __future__ import annotations

import os
import socket

import pandas as pd
import pytest


def pytest_collection_modifyitems(config, items):
    flows_dir = os.path.join(os.path.dirname(__file__), "flows") + os.sep
    for item in items:
        if str(item.fspath).startswith(flows_dir):
            item.add_marker(pytest.mark.integration)


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
