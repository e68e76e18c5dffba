"""One Prefect API per run, shared by the driver and every Dask worker.

Prefect's ephemeral mode starts a temporary API server in each process that
needs one; Dask worker processes would each start their own (~7 s each, one
SQLite file; docs/stack.md, "One API per run").  ``prefect_api()`` therefore
starts a single local server for the run when no ``PREFECT_API_URL`` is
configured, points this process at it, and exports the address so that
processes started afterwards (the local Dask cluster's workers) inherit it.
With ``PREFECT_API_URL`` set (a real ``prefect server``), it is used as is.
"""

from __future__ import annotations

import contextlib
import os
import sys

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
    from prefect.server.api.server import SubprocessASGIServer

    if verbose:
        print("starting a local Prefect server for this run ...", file=sys.stderr, flush=True)
    server = SubprocessASGIServer()
    server.start(timeout=90)
    old = os.environ.get("PREFECT_API_URL")
    os.environ["PREFECT_API_URL"] = server.api_url
    try:
        with temporary_settings(updates={PREFECT_API_URL: server.api_url}):
            yield server.api_url
    finally:
        if old is None:
            os.environ.pop("PREFECT_API_URL", None)
        else:
            os.environ["PREFECT_API_URL"] = old
        server.stop()
