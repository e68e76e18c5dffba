"""Clean stops: a run's helper processes die with it, and SIGTERM stops a run like Ctrl-C.

A run (``mbc run``, ``mbc sweep``, the other Dask commands) starts helper processes: a Prefect API
server (``flows.prefect_env``) and the local Dask cluster's worker processes.  They must not outlive
the driver, however it ends:

* Ctrl-C or SIGTERM: :func:`stop_signals` turns the first one into ``KeyboardInterrupt`` in the
  driver, which marks its manifests ``interrupted``, closes the cluster and stops the server in that
  order (the server runs in its own session, so a terminal's Ctrl-C does not reach it before the
  driver has reported to it; the workers ignore SIGINT for the same reason, :func:`dask_setup`).
  A second signal during that clean-up exits at once.
* ``kill -9`` of the driver: nothing runs in the driver, so the children watch it themselves.  The
  Prefect server gets Linux's parent-death signal (:func:`die_with_parent`, set between fork and
  exec); Dask's worker processes already exit when the pipe their parent holds open closes.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import sys
import threading

PR_SET_PDEATHSIG = 1   # linux/prctl.h


def die_with_parent(sig: int = signal.SIGTERM):
    """A ``preexec_fn`` for ``subprocess.Popen``: Linux sends ``sig`` to the child when its parent dies.

    The C library is looked up here, in the parent (a lookup may start processes, which a ``preexec_fn``
    must not); elsewhere than Linux the returned function does nothing.  Linux sends the signal when the
    *thread* that started the child ends, so start such children from a thread that lives as long as
    they should (the driver's main thread here).  The setting survives ``exec``.
    """
    if not sys.platform.startswith("linux"):
        return lambda: None
    prctl = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True).prctl

    def preexec() -> None:
        if prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")

    return preexec


_SIGNALLED: list[int] = []   # signals seen by stop_signals() in this process
_HANDLER: list = []          # the handler stop_signals() installed, while it is active
_DEFERRED: list[bool] = []   # non-empty inside deferred_stops(): a stop is recorded, not raised


def is_stop(exc: BaseException | None) -> bool:
    """Whether ``exc`` is (a consequence of) a stop: Ctrl-C, SIGTERM, or any error after one was received.

    Prefect raises its own ``TerminationSignal`` on SIGTERM inside a flow; raised while a library
    serialises (pydantic), it can arrive wrapped in a ``ValueError`` that keeps only its name.
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, KeyboardInterrupt) or type(exc).__name__ == "TerminationSignal":
            return True
        if "TerminationSignal" in str(exc)[:500]:
            return True
        exc = exc.__cause__ or exc.__context__
    return bool(_SIGNALLED)


class Stop(KeyboardInterrupt):
    """The driver was asked to stop (Ctrl-C or SIGTERM); a ``KeyboardInterrupt`` so every layer treats it so."""


@contextlib.contextmanager
def stop_signals():
    """SIGINT and SIGTERM raise :class:`Stop` once; a second one exits at once (status 130).

    A :class:`Stop` that lands where Python cannot raise it (a garbage-collector callback such as Dask's
    GC diagnostics, a ``__del__``) is not printed as "Exception ignored": it is recorded, and
    :func:`checkpoint` raises it.
    """
    if os.name != "posix":
        yield
        return
    def handler(signum, frame):
        note_stop(signum)
        if _DEFERRED:   # inside a library's locks (deferred_stops): checkpoint() raises it
            return
        raise Stop(signal.Signals(signum).name)

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    old_hook = sys.unraisablehook

    def unraisable(u):   # see the docstring: a recorded stop is not printed
        if isinstance(u.exc_value, Stop) and _SIGNALLED:
            return
        old_hook(u)

    sys.unraisablehook = unraisable
    _HANDLER.append(handler)
    try:
        yield
    finally:
        _HANDLER.remove(handler)
        sys.unraisablehook = old_hook
        for s, h in old.items():
            signal.signal(s, h)


@contextlib.contextmanager
def deferred_stops():
    """Within: a stop signal is recorded and the workers hushed, but nothing is raised; :func:`checkpoint` raises.

    An exception raised by a signal handler lands at an arbitrary bytecode of the main thread.  Where that
    thread holds a lock shared with another thread, it can leave the lock held for good: Dask's
    ``as_completed`` takes a condition lock that its event-loop thread also takes to report a finished
    future, and a stop landing between the acquire and the ``with`` block freezes the event loop, so the
    clean-up that needs it (closing the cluster) never returns.  A loop that waits on such a library runs
    inside this context and polls :func:`checkpoint` between short waits.  A second signal still exits at once.
    """
    _DEFERRED.append(True)
    try:
        yield
    finally:
        _DEFERRED.pop()


def note_stop(signum: int) -> None:
    """Record a stop signal (the first counts; :func:`stop_name`, :func:`checkpoint`) and hush the workers; a
    second one exits at once (status 130).  For :func:`stop_signals`' handler and for a library's own handler
    that takes a signal over and must stop without raising (``mbc serve``'s Prefect runner, flows/deploy.py)."""
    if _SIGNALLED:
        os.write(2, b"\nmbc: stopped at once (second signal)\n")
        os._exit(130)
    _SIGNALLED.append(signum)
    hush_workers()


def stop_name() -> str:
    """The name of the first stop signal seen by :func:`stop_signals` (``"stopped"`` if none was)."""
    return signal.Signals(_SIGNALLED[0]).name if _SIGNALLED else "stopped"


def checkpoint() -> None:
    """A safe point in a long driver loop: a stop whose exception was lost is raised here.

    A signal handler's exception is raised wherever the main thread happens to be; a library that
    catches everything at that moment (a serialiser converting errors, a clean-up that swallows them)
    loses it, and the run would go on as if nothing had been asked.  Two guards, both cheap:

    * a stop seen by :func:`stop_signals` and not yet acted on raises :class:`Stop` here;
    * inside a Prefect flow, Prefect replaces the SIGTERM handler by its own (it raises
      ``TerminationSignal``, which such a library can lose before anything records it); while
      :func:`stop_signals` is active, SIGTERM is taken back so that it is recorded like Ctrl-C.
      Prefect restores the handler it found (ours) when the flow ends.
    """
    if _SIGNALLED:
        raise Stop(stop_name())
    if _HANDLER and threading.current_thread() is threading.main_thread():
        if signal.getsignal(signal.SIGTERM) is not _HANDLER[-1]:
            signal.signal(signal.SIGTERM, _HANDLER[-1])


def dask_setup(worker) -> None:   # noqa: ARG001 - Dask's preload hook
    """Dask preload for the local cluster's workers: SIGINT means "the run is stopping", not "die".

    The driver closes its workers in order after a Ctrl-C (the terminal sends SIGINT to the workers too)
    or a SIGTERM (the driver then sends them SIGINT, :func:`hush_workers`).  On SIGINT a worker keeps
    running until closed but stops logging: its reports of a scheduler going away are expected then.
    """
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _quiet_worker)


def _quiet_worker(signum, frame) -> None:   # noqa: ARG001
    import logging

    logging.disable(logging.CRITICAL)


def hush_workers(pids=None) -> None:
    """SIGINT to the worker processes ``pids``; None: this process's children in its own process group."""
    if pids is None:
        try:
            import psutil
        except ImportError:
            return
        pgrp = os.getpgrp()
        pids = []
        for child in psutil.Process().children():
            try:
                if os.getpgid(child.pid) == pgrp:
                    pids.append(child.pid)
            except (OSError, psutil.Error):
                pass
    for pid in pids:
        if pid:
            try:
                os.kill(pid, signal.SIGINT)
            except OSError:
                pass
