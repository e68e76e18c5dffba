"""Clean stops of a real ``mbc sweep``: Ctrl-C, SIGTERM and kill -9 of the driver; loopback-only servers.

Each test starts ``mbc sweep`` as a terminal would (its own session), with no ``PREFECT_API_URL``, so the
command starts its own Prefect server and local Dask cluster, which are exactly what must not outlive it.
The helper processes are recorded by PID (psutil) while the sweep runs and checked by PID afterwards.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import psutil
import pytest

from conftest import small_plan
from engine_model import SolverSettings, load_spec
from flows import store
from flows.sweep import prepare_plan, run_points
from test_flows_sweep import _check_dataset, _parts, _wait_for

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SOLVER = {"step_deg": 1.0, "tolerance": 1e-2}
LOOPBACK = {"127.0.0.1", "::1"}


def _env(tmp_path: Path) -> dict:
    env = dict(os.environ, PREFECT_HOME=str(tmp_path / "prefect_home"))
    env.pop("PREFECT_API_URL", None)        # the command starts (and must stop) its own server
    return env


def _command(plan_csv: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "flows.cli", "sweep", "--plan", str(plan_csv), "--out", str(out), "--workers", "2",
            "--chunk-size", "1", "--step-deg", str(SOLVER["step_deg"]), "--tolerance", str(SOLVER["tolerance"])]


def _start(tmp_path: Path, n_ops: int = 4, per_op: int = 4):
    plan = small_plan(n_ops, per_op)
    src = tmp_path / "plan.csv"
    plan.to_csv(src, index=False)
    out = tmp_path / "out"
    cmd = _command(src, out)
    proc = subprocess.Popen(cmd, start_new_session=True, env=_env(tmp_path), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    return plan, out, cmd, proc


def _helpers(pid: int) -> dict[str, list[psutil.Process]]:
    """The driver's Prefect server and Dask worker processes (psutil handles: safe against PID reuse)."""
    kids = psutil.Process(pid).children(recursive=True)
    found = {"server": [], "workers": []}
    for k in kids:
        try:
            line = " ".join(k.cmdline())
        except psutil.Error:
            continue
        if "uvicorn" in line and "prefect" in line:
            found["server"].append(k)
        elif "multiprocessing.spawn" in line:
            found["workers"].append(k)
    return found


def _running_sweep(tmp_path: Path, chunks: int = 2):
    """Start a sweep, wait until ``chunks`` parts are on disk; (plan, out, cmd, proc, helpers)."""
    plan, out, cmd, proc = _start(tmp_path)
    try:
        _wait_for(lambda: len(_parts(out)) >= chunks or proc.poll() is not None, 300, f"{chunks} finished chunks")
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        helpers = _helpers(proc.pid)
        assert len(helpers["server"]) == 1 and len(helpers["workers"]) == 2, helpers
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    return plan, out, cmd, proc, helpers


def _gone(p: psutil.Process) -> bool:
    try:
        return not p.is_running() or p.status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _assert_helpers_gone(helpers: dict, timeout: float = 15.0) -> None:
    procs = helpers["server"] + helpers["workers"]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not all(_gone(p) for p in procs):
        time.sleep(0.2)
    left = [(p.pid, k) for k, ps in helpers.items() for p in ps if not _gone(p)]
    for p in procs:                       # never leave them to the next test
        if not _gone(p):
            p.kill()
    assert not left, f"still running {timeout} s after the driver ended: {left}"


def _wait_for_exit(proc, failure: str, timeout: float = 30.0) -> str:
    """The stderr of ``proc`` once it has exited; after ``timeout`` s its group is killed and the test fails."""
    try:
        return proc.communicate(timeout=timeout)[1]
    except subprocess.TimeoutExpired:
        with contextlib.suppress(OSError):   # the driver's thread stacks (mbc's SIGUSR1 hook) tell where it hung
            os.kill(proc.pid, signal.SIGUSR1)
        time.sleep(2.0)
        os.killpg(proc.pid, signal.SIGKILL)
        err = proc.communicate()[1]
        raise AssertionError(f"{failure} within {timeout:.0f} s: {err[-12000:]}") from None


def _stop_and_check(tmp_path: Path, send) -> None:
    """Stop a running sweep with ``send(proc)``; one line, `interrupted`, no helper left, exact resume."""
    plan, out, cmd, proc, helpers = _running_sweep(tmp_path)
    done_before = {int(p.name[5:10]) for p in _parts(out)}
    t0 = time.monotonic()
    send(proc)
    err = _wait_for_exit(proc, "the sweep did not stop")
    took = time.monotonic() - t0
    assert took < 15, f"stopping took {took:.1f} s"
    assert proc.returncode == 130, (proc.returncode, err[-3000:])
    lines = [ln.strip() for ln in err.replace("\r", "\n").splitlines() if ln.strip()]
    noise = [ln for ln in lines if not ln.startswith(("sweep", "starting a local Prefect server"))]
    assert len(noise) == 1 and noise[0].startswith("mbc: interrupted"), noise
    assert "Traceback" not in err and "Error logging to API" not in err
    man = json.loads((out / "manifest.json").read_text())
    assert man["status"] == "interrupted", man["status"]
    _assert_helpers_gone(helpers)

    done_before |= {int(p.name[5:10]) for p in _parts(out)}   # parts written while stopping count too
    res = subprocess.run(cmd, env=_env(tmp_path), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    _check_dataset(out, plan)
    counts = store.attempt_counts(out / "sweep")
    assert all(counts[c] == 1 for c in done_before), "a finished chunk was computed again"
    man = json.loads((out / "manifest.json").read_text())
    assert man["status"] == "complete" and man["chunks_skipped"] == len(done_before)
    assert man["chunks_computed"] == len(plan) - len(done_before)
    # same results as computing each point alone in this process (chunks of one point: no shared state)
    got = store.read_results(out)
    spec = load_spec(None)
    pts = prepare_plan(plan, spec)
    ref = pd.concat([run_points(spec, pts.iloc[[i]], SolverSettings(**SOLVER)) for i in range(len(pts))])
    for col in ("brake_torque_nm", "air_mass_flow_kg_h", "knock_index"):
        assert np.array_equal(got[col].to_numpy(), ref[col].to_numpy(), equal_nan=True), col


def test_ctrl_c_stops_sweep_in_one_line_and_resumes_exactly(tmp_path):
    _stop_and_check(tmp_path, lambda proc: os.killpg(proc.pid, signal.SIGINT))   # as a terminal does


def test_sigterm_to_driver_alone_stops_like_ctrl_c(tmp_path):
    _stop_and_check(tmp_path, lambda proc: os.kill(proc.pid, signal.SIGTERM))


def test_kill_9_of_driver_takes_server_and_workers_with_it(tmp_path):
    plan, out, cmd, proc, helpers = _running_sweep(tmp_path)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(10)
    try:
        _assert_helpers_gone(helpers, timeout=15)
    finally:
        proc.stdout.close()
        proc.stderr.close()


def test_every_server_of_a_run_listens_on_loopback_only(tmp_path):
    plan, out, cmd, proc, helpers = _running_sweep(tmp_path, chunks=1)
    try:
        procs = [psutil.Process(proc.pid)] + psutil.Process(proc.pid).children(recursive=True)
        listening = []
        for p in procs:
            try:
                conns = p.net_connections(kind="inet")
            except psutil.Error:
                continue
            listening += [(p.pid, c.laddr.ip, c.laddr.port) for c in conns if c.status == psutil.CONN_LISTEN]
        owners = {pid for pid, _, _ in listening}
        # the driver (scheduler, dashboard), the Prefect server and each worker listen on something
        assert proc.pid in owners and helpers["server"][0].pid in owners
        assert all(w.pid in owners for w in helpers["workers"])
        assert all(ip in LOOPBACK for _, ip, _ in listening), listening
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        proc.communicate(timeout=60)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["sigterm", "ctrl_c"])
def test_serve_exits_on_sigterm_with_its_server(tmp_path, sig):
    """Prefect's runner answers SIGTERM with sys.exit(0) from its signal handler, which once landed inside a task
    with an API request in flight and printed an exception-group traceback (`.ci/run` on a loaded machine);
    `mbc serve` now cancels the runner from inside its event loop, for SIGTERM and Ctrl-C alike."""
    cmd = [sys.executable, "-m", "flows.cli", "serve", "--watch", str(tmp_path / "inbox"), "--results",
           str(tmp_path / "results"), "--interval", "3600", "--workers", "1"]
    proc = subprocess.Popen(cmd, start_new_session=True, env=_env(tmp_path), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: proc.poll() is not None or _helpers(proc.pid)["server"], 180, "serve's Prefect server")
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        server = _helpers(proc.pid)["server"]
        time.sleep(10)                  # registering the deployments and starting the runner
        assert proc.poll() is None, proc.communicate()[1][-3000:]
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    t0 = time.monotonic()
    os.kill(proc.pid, sig)
    err = _wait_for_exit(proc, f"mbc serve ignored {sig.name}")
    assert time.monotonic() - t0 < 15
    assert proc.returncode == 130, (proc.returncode, err[-3000:])
    assert "Traceback" not in err, err[-3000:]
    assert f"mbc: interrupted ({sig.name})" in err, err[-3000:]
    _assert_helpers_gone({"server": server, "workers": []})
