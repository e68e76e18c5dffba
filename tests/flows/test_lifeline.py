"""Stops that a library loses are still acted on: the driver's safe points (flows/lifeline.py).

A signal handler's exception is raised wherever the main thread is; code that catches everything at
that instant loses it.  These tests lose one on purpose and check that the next safe point stops the
run, and that SIGTERM, replaced by another handler (as Prefect does inside a flow), is taken back.
"""

from __future__ import annotations

import gc
import os
import signal
import sys

import pytest

from flows import lifeline


@pytest.fixture(autouse=True)
def _fresh_state(monkeypatch):
    monkeypatch.setattr(lifeline, "_SIGNALLED", [])   # never leak a recorded stop into other tests
    monkeypatch.setattr(lifeline, "hush_workers", lambda pids=None: None)


def test_a_stop_swallowed_by_a_library_is_raised_at_the_next_safe_point():
    with lifeline.stop_signals():
        lifeline.checkpoint()                 # nothing asked yet: no stop
        try:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):             # the handler runs between bytecodes
                pass
        except BaseException:                 # noqa: BLE001 - the library that loses it
            pass
        with pytest.raises(lifeline.Stop):
            lifeline.checkpoint()
        assert lifeline.is_stop(ValueError("anything after a stop counts as one"))


def test_sigterm_taken_back_from_another_handler_stops_like_ctrl_c():
    seen = []
    with lifeline.stop_signals():
        ours = signal.getsignal(signal.SIGTERM)
        signal.signal(signal.SIGTERM, lambda *a: seen.append(a))    # a framework's own bridge
        lifeline.checkpoint()
        assert signal.getsignal(signal.SIGTERM) is ours
        with pytest.raises(lifeline.Stop, match="SIGTERM"):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):
                pass
    assert not seen
    assert signal.getsignal(signal.SIGTERM) is not ours             # restored on leaving


def test_checkpoint_outside_stop_signals_leaves_handlers_alone():
    before = signal.getsignal(signal.SIGTERM)
    lifeline.checkpoint()
    assert signal.getsignal(signal.SIGTERM) is before


def test_a_stop_inside_a_gc_callback_is_not_printed_and_is_raised_at_the_next_safe_point(monkeypatch):
    """Dask's GC diagnostics run a callback on every full collection; a signal landing there raised our stop
    where Python can only print it ("Exception ignored in ... Traceback"), a traceback in a clean stop."""
    printed = []
    monkeypatch.setattr(sys, "unraisablehook", printed.append)        # what would have been printed

    def callback(phase, info):
        if phase == "start":
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):             # the handler runs here, inside the callback
                pass

    with lifeline.stop_signals():
        gc.callbacks.append(callback)
        try:
            gc.collect()
        finally:
            gc.callbacks.remove(callback)
        assert lifeline.stop_name() == "SIGTERM"
        with pytest.raises(lifeline.Stop, match="SIGTERM"):
            lifeline.checkpoint()
    assert not printed, [repr(u.exc_value) for u in printed]
    assert sys.unraisablehook == printed.append                      # restored on leaving


def test_a_stop_inside_deferred_stops_is_raised_only_at_a_checkpoint():
    """Inside a library's locks (Dask's as_completed) a stop is recorded, and raised where the loop polls."""
    with lifeline.stop_signals():
        with lifeline.deferred_stops():
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):             # without the deferral the handler would raise here
                pass
            assert lifeline.stop_name() == "SIGTERM"
            with pytest.raises(lifeline.Stop, match="SIGTERM"):
                lifeline.checkpoint()


def test_a_stop_after_deferred_stops_is_raised_at_once():
    with lifeline.stop_signals():
        with lifeline.deferred_stops():
            lifeline.checkpoint()
        with pytest.raises(lifeline.Stop, match="SIGINT"):
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):
                pass
