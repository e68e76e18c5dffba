"""Prefect deployments served by ``mbc serve``.

* ``sweep/sweep``: the parameterised sweep (``plan``, ``out``, solver settings);
  trigger with ``prefect deployment run sweep/sweep -p plan=... -p out=...``.
* ``bench-watch/bench-watch``: on a schedule (interval or cron), looks for
  bench files (CSV/Parquet in the bench contract) dropped into a watched folder
  and runs the pipeline (``run`` flow) on each new one.  A file is "new" when
  its content hash is not in ``<watch>/.mbc_processed.json``; a file that fails
  validation is recorded with its error and tried again only when its content
  changes.

The Dask cluster used by served runs comes from ``MBC_DASK_ADDRESS`` (an
existing scheduler) or ``MBC_WORKERS`` (local workers, default 2), which
``mbc serve`` sets from its options before the runner starts flow runs.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
from pathlib import Path

from flows import prefect_env  # noqa: F401
from flows.lifeline import Stop, note_stop, stop_name
from flows.run import run_flow
from flows.sweep import sweep_flow

from prefect import flow  # noqa: E402

from engine_model.io import write_json  # noqa: E402

PROCESSED = ".mbc_processed.json"
BENCH_SUFFIXES = (".csv", ".parquet")


def _file_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def new_bench_files(watch: Path) -> list[tuple[Path, str]]:
    """Bench files in ``watch`` whose content has not been processed yet (sorted by name)."""
    done = _load_processed(watch)
    out = []
    for p in sorted(watch.iterdir()) if watch.is_dir() else []:
        if p.is_file() and p.suffix.lower() in BENCH_SUFFIXES and not p.name.startswith("."):
            h = _file_hash(p)
            if done.get(p.name, {}).get("sha256") != h:
                out.append((p, h))
    return out


def _load_processed(watch: Path) -> dict:
    try:
        return json.loads((watch / PROCESSED).read_text())
    except (OSError, ValueError):
        return {}


@flow(name="bench-watch", log_prints=True, validate_parameters=False)
def watch_flow(watch: str = "bench_inbox", results: str = "results", quick: bool = False) -> dict:
    """Calibrate on every new bench file in ``watch``; results under ``results``/<time>-<file>-<hash>/.

    ``quick``: the small settings of ``mbc run --quick`` (1 deg step, coarse searches).
    """
    from flows.settings import QUICK, settings_to_dict

    settings = {**(settings_to_dict(QUICK) if quick else {}), "stages": ["calibration"]}
    wdir = Path(watch)
    wdir.mkdir(parents=True, exist_ok=True)
    report = {}
    for path, h in new_bench_files(wdir):
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        out = Path(results) / f"{stamp}-{path.stem}-{h[:8]}"
        entry = {"sha256": h, "processed": _dt.datetime.now().isoformat(timespec="seconds")}
        try:
            # a new bench session re-calibrates (airflow match + identification); the map-building stages
            # run from `mbc run` on the full data set
            run_flow(out=str(out), bench=str(path), settings=settings, progress=False)
            entry.update(status="ok", results=str(out))
        except ValueError as exc:      # bad bench file: record why, do not retry the same content
            entry.update(status="refused", error=str(exc))
        print(f"{path.name}: {entry['status']} {entry.get('results', entry.get('error', ''))}")
        processed = _load_processed(wdir)
        processed[path.name] = entry
        write_json(processed, wdir / PROCESSED)
        report[path.name] = entry
    if not report:
        print(f"no new bench files in {wdir}")
    return report


def build_deployments(watch: str, results: str, cron: str | None = None, interval_s: float | None = None):
    """The two deployments (see module docstring); the watcher runs every 600 s unless told otherwise."""
    from prefect.deployments.runner import EntrypointType

    sched = {"cron": cron} if cron else {"interval": interval_s if interval_s else 600.0}
    sweep = sweep_flow.to_deployment(name="sweep", entrypoint_type=EntrypointType.MODULE_PATH,
                                     description="Simulate a plan of operating points into Parquet (resumable).")
    watcher = watch_flow.to_deployment(name="bench-watch", entrypoint_type=EntrypointType.MODULE_PATH,
                                       parameters={"watch": str(Path(watch).resolve()),
                                                   "results": str(Path(results).resolve())},
                                       description="Run the pipeline on new bench files in the watched folder.",
                                       **sched)
    return [sweep, watcher]


def serve_deployments(watch: str = "bench_inbox", cron: str | None = None, interval_s: float | None = None,
                      workers: int = 2, dask_address: str | None = None, results: str = "results") -> None:
    """Register and serve the deployments until interrupted (needs a Prefect API: ``PREFECT_API_URL``)."""
    if cron is None and interval_s is not None and interval_s <= 0:
        raise ValueError(f"--interval = {interval_s} must be > 0 seconds")
    if workers < 1:
        raise ValueError(f"--workers = {workers} must be >= 1")
    if dask_address:
        os.environ["MBC_DASK_ADDRESS"] = dask_address
    os.environ["MBC_WORKERS"] = str(workers)
    Path(watch).mkdir(parents=True, exist_ok=True)
    deployments = build_deployments(watch, results, cron, interval_s)
    if not prefect_env.configured_api_url():
        print("mbc serve: no PREFECT_API_URL set; using a local Prefect server of its own (runs are not visible "
              "to other processes). Start `prefect server start` and export PREFECT_API_URL for a real server.")
    # Our own local server when none is configured (like `mbc run`): on 127.0.0.1, in its own session, and
    # stopped after the runner, so SIGTERM or Ctrl-C (KeyboardInterrupt, flows/lifeline.py) ends `serve`
    # and then the server, instead of leaving the runner polling a server that is gone.
    with prefect_env.prefect_api(verbose=False):
        _serve(deployments)
        # returns only when stopped (Ctrl-C, or SIGTERM): say so, so that `mbc serve` ends like every stopped
        # command
        raise Stop(stop_name())


def _serve(deployments) -> None:
    """Serve ``deployments`` on a Prefect runner until a stop signal; SIGTERM stops it from inside its loop.

    Prefect's own ``serve`` runs a ``Runner`` whose SIGTERM handler calls ``sys.exit(0)``: the ``SystemExit``
    lands at whatever bytecode the main thread is running, and when that is inside a task of the runner's task
    groups (an API request in flight) the group prints an exception-group traceback on the way out (seen once
    in `.ci/run` on a loaded machine: tests/flows/test_stops.py).  Here SIGTERM is recorded as a stop
    (:func:`flows.lifeline.note_stop`; a second one exits at once) and the task that runs the runner is
    cancelled from within the event loop, so the runner leaves through its own clean-up.  Ctrl-C (SIGINT) is
    handled the same way, through the event loop's own signal handling.
    """
    import asyncio
    import signal

    from prefect.runner import Runner

    class _Runner(Runner):
        main_task: asyncio.Task | None = None

        def handle_sigterm(self, *args, **kwargs) -> None:   # Prefect's: self.stop(); sys.exit(0)
            note_stop(signal.SIGTERM)
            task = self.main_task
            if task is not None:
                task.get_loop().call_soon_threadsafe(task.cancel)

    runner = _Runner(pause_on_shutdown=True)
    for d in deployments:
        runner.add_deployment(d)
    print("mbc serve: serving " + ", ".join(f"{d.flow_name}/{d.name}" for d in deployments)
          + " (Ctrl-C or SIGTERM stops)", flush=True)

    async def main():
        task = runner.main_task = asyncio.current_task()

        def on_sigint():    # run by the loop itself, not at an arbitrary bytecode
            note_stop(signal.SIGINT)
            task.cancel()
        asyncio.get_running_loop().add_signal_handler(signal.SIGINT, on_sigint)
        await runner.start()

    try:
        asyncio.run(main())
    except (asyncio.CancelledError, KeyboardInterrupt):
        pass
