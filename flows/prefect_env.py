"""One Prefect API per run, shared by the driver and every Dask worker.

Prefect's ephemeral mode starts a temporary API server in each process that
needs one; Dask worker processes would each start their own (~7 s each, one
SQLite file; docs/stack.md, "One API per run").  ``prefect_api()`` therefore
starts a single local server for the run when no ``PREFECT_API_URL`` is
configured, points this process at it, and exports the address so that
processes started afterwards (the local Dask cluster's workers) inherit it.
With ``PREFECT_API_URL`` set (a real ``prefect server``), it is used as is.

The server listens on 127.0.0.1 only, runs in its own session (a terminal's Ctrl-C reaches the driver,
which then stops the server after its last report) and dies with the driver (``flows.lifeline``).
Logs queued for the API are sent before the server stops, so a run never ends with Prefect's
"Error logging to API".
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys

from flows.lifeline import die_with_parent, is_stop

# Quiet and offline defaults, before Prefect reads its settings (an explicit
# environment setting wins).
_DEFAULTS = {
    "DO_NOT_TRACK": "1",
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "PREFECT_LOGGING_LEVEL": "WARNING",
    "PREFECT_SERVER_LOGGING_LEVEL": "CRITICAL",
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "60",
    "DASK_LOGGING__DISTRIBUTED": "warning",   # the scheduler/nanny INFO lines drown the progress bar
}
for _k, _v in _DEFAULTS.items():
    os.environ.setdefault(_k, _v)


def configured_api_url() -> str | None:
    """The Prefect API address from the environment or Prefect's profile, if any."""
    from prefect.settings import PREFECT_API_URL

    return os.environ.get("PREFECT_API_URL") or PREFECT_API_URL.value() or None


@contextlib.contextmanager
def prefect_api(verbose: bool = True):
    """Yield the API URL of the Prefect server this run talks to (started here if none is configured)."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    url = configured_api_url()
    if url:
        yield url
        return
    if verbose:
        print("starting a local Prefect server for this run ...", file=sys.stderr, flush=True)
    server = _run_server()
    server.start(timeout=90)
    old = os.environ.get("PREFECT_API_URL")
    os.environ["PREFECT_API_URL"] = server.api_url
    try:
        with temporary_settings(updates={PREFECT_API_URL: server.api_url}):
            try:
                yield server.api_url
            finally:
                _flush_api_logs()   # before the server stops, so nothing is left to send to a closed port
    finally:
        if old is None:
            os.environ.pop("PREFECT_API_URL", None)
        else:
            os.environ["PREFECT_API_URL"] = old
        server.stop()


def _run_server():
    """Prefect's ephemeral API server, started in its own session and bound to die with this process."""
    from prefect.server.api.server import SubprocessASGIServer

    class RunServer(SubprocessASGIServer):
        def _run_uvicorn_command(self):
            real_popen, lifeline = subprocess.Popen, die_with_parent()

            def popen(*args, **kwargs):   # Prefect's command (127.0.0.1, UI off), plus the lifeline
                return real_popen(*args, start_new_session=True, preexec_fn=lifeline, **kwargs)

            subprocess.Popen = popen
            try:
                return super()._run_uvicorn_command()
            finally:
                subprocess.Popen = real_popen

    return RunServer()


def _flush_api_logs() -> None:
    """Send the log records queued for the API while the server is still up."""
    try:
        from prefect.events.worker import EventsWorker
        from prefect.logging.handlers import APILogWorker

        APILogWorker.drain_all(timeout=5)
        EventsWorker.drain_all(timeout=5)
    except Exception:  # noqa: BLE001 - best effort: the records are also on the console
        pass


class _DropMessages:
    """A logging filter dropping records whose message starts with one of ``prefixes`` (known, harmless)."""

    def __init__(self, *prefixes: str):
        self.prefixes = prefixes

    def filter(self, record) -> bool:
        if record.exc_info and record.exc_info[1] is not None and is_stop(record.exc_info[1]):
            return False   # the engine's report of an exception that is a stop (the command reports it once)
        return not str(record.getMessage()).startswith(self.prefixes)


_STOPPED = ("Crash detected! Execution was aborted by an interrupt signal",
            "Crash detected! Execution was aborted by a termination signal")
#: Messages that look like failures but are not, each on the logger that emits it (nothing else is hidden):
#: the nanny's report that it stopped a worker that was still inside a kernel when we closed the cluster;
#: Prefect's note that its events queue is still draining at exit; the flow run's report of an interrupt,
#: which the command already reports in one line (a real crash keeps its message).
KNOWN_NOISE = {
    "distributed.nanny": ("Worker process still alive after",),
    "EventsWorker": ("Still processing items",),
    "APILogWorker": ("Still processing items",),
    "prefect.flow_runs": _STOPPED,
    "prefect.task_runs": _STOPPED,
}


def _hush_known_noise() -> None:
    import logging

    for name, prefixes in KNOWN_NOISE.items():
        logging.getLogger(name).addFilter(_DropMessages(*prefixes))


_hush_known_noise()
