"""Deployments served by `mbc serve` against a real `prefect server`, triggered, finishing Completed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import httpx
import pandas as pd
import pytest

from conftest import free_port, small_plan
from engine_model.bench import load_bench
from test_flows_sweep import _check_dataset, _wait_for

pytestmark = pytest.mark.slow


def _healthy(url: str) -> bool:
    try:
        return httpx.get(f"{url}/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


@pytest.fixture
def prefect_server(tmp_path):
    """`prefect server start` on a free port with its own database; its API URL."""
    port = free_port()
    env = dict(os.environ, PREFECT_HOME=str(tmp_path / "prefect_home"))
    env.pop("PREFECT_API_URL", None)
    proc = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1", "--port",
                             str(port)], env=env, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}/api"
    try:
        _wait_for(lambda: _healthy(url), 120, "prefect server healthy")
        yield url
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)


def _deployment(url: str, name: str):
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings(updates={PREFECT_API_URL: url}):
        with get_client(sync_client=True) as client:
            try:
                return client.read_deployment_by_name(name)
            except Exception:  # noqa: BLE001 - not registered yet
                return None


def _run(url: str, name: str, parameters: dict | None = None):
    from prefect.deployments import run_deployment
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings(updates={PREFECT_API_URL: url}):
        return run_deployment(name, parameters=parameters or {}, timeout=300, poll_interval=1)


def test_served_deployments_run_to_completed(prefect_server, tmp_path):
    url = prefect_server
    watch, results = tmp_path / "inbox", tmp_path / "results"
    env = dict(os.environ, PREFECT_API_URL=url, PREFECT_HOME=str(tmp_path / "serve_home"))
    serve = subprocess.Popen([sys.executable, "-m", "flows.cli", "serve", "--watch", str(watch), "--results",
                              str(results), "--interval", "3600", "--workers", "1"], env=env,
                             start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _wait_for(lambda: _deployment(url, "bench-watch/bench-watch") is not None
                  and _deployment(url, "sweep/sweep") is not None, 120, "deployments registered")
        dep = _deployment(url, "bench-watch/bench-watch")
        assert dep.schedules and dep.schedules[0].schedule.interval.total_seconds() == 3600

        # 1) the parameterised sweep
        plan = small_plan(1, 3)
        src = tmp_path / "plan.csv"
        plan.to_csv(src, index=False)
        out = tmp_path / "sweep_out"
        fr = _run(url, "sweep/sweep", {"plan": str(src), "out": str(out), "step_deg": 1.0, "tolerance": 0.01})
        assert fr.state.is_completed(), fr.state
        _check_dataset(out, plan)

        # 2) the watcher: a bench file dropped into the folder is picked up once
        watch.mkdir(exist_ok=True)
        bench = load_bench().iloc[[0, 3]]
        bench.to_csv(watch / "session1.csv", index=False)
        fr = _run(url, "bench-watch/bench-watch", {"quick": True})
        assert fr.state.is_completed(), fr.state
        done = json.loads((watch / ".mbc_processed.json").read_text())
        assert done["session1.csv"]["status"] == "ok"
        run_dir = done["session1.csv"]["results"]
        air = pd.read_parquet(f"{run_dir}/calibration/airflow_match.parquet")
        assert list(air["point_id"]) == list(bench["point_id"])
        # nothing new: a second trigger computes nothing
        n_runs = len(list(results.iterdir()))
        fr = _run(url, "bench-watch/bench-watch", {"quick": True})
        assert fr.state.is_completed() and len(list(results.iterdir())) == n_runs
    finally:
        os.killpg(serve.pid, signal.SIGINT)
        try:
            serve.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(serve.pid, signal.SIGKILL)
