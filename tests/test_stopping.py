"""Stopping the command line (SIGINT, SIGTERM) where it leaves nothing half done."""

from __future__ import annotations

import os
import signal
import threading
import time

import psutil
import pytest

from solver.stopping import Stopped, StopSignals


def _signal(signum: int) -> None:
    os.kill(os.getpid(), signum)
    time.sleep(0.01)  # Python runs the handler at the next bytecode: give it one


def test_a_stop_outside_a_deferred_section_is_raised_at_once():
    stops = StopSignals()
    with stops.installed():
        with pytest.raises(Stopped):
            _signal(signal.SIGTERM)
        with pytest.raises(KeyboardInterrupt) as e:
            _signal(signal.SIGINT)
        assert not isinstance(e.value, Stopped)


def test_a_stop_inside_a_deferred_section_is_raised_when_it_ends():
    stops = StopSignals()
    reached = []
    with stops.installed():
        with pytest.raises(Stopped):
            with stops.deferred():
                with stops.deferred():  # nested: held to the outer section's end
                    _signal(signal.SIGTERM)
                    _signal(signal.SIGINT)  # the first stop is the one raised
                reached.append("inner end")
                reached.append("outer end")
    assert reached == ["inner end", "outer end"]


def test_an_error_leaving_a_deferred_section_drops_the_held_stop():
    stops = StopSignals()
    with stops.installed():
        with pytest.raises(ValueError):
            with stops.deferred():
                _signal(signal.SIGTERM)
                raise ValueError("the run's own error unwinds it")
        with stops.deferred():  # nothing left over for the next section
            pass


def test_the_previous_handlers_come_back():
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with StopSignals().installed():
        assert signal.getsignal(signal.SIGTERM) is not before[0]
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


def test_a_sigterm_while_the_cluster_closes_leaves_no_worker_behind():
    """Measured before the fix: a SIGTERM 0.05 s into the close left the worker process alive
    and the interpreter's exit took 10.7 s more; the command line's SIGTERM test hung 60 s
    on a slow machine."""
    from solver import cli
    from solver.stopping import STOP_SIGNALS

    me = psutil.Process()

    def workers() -> list[psutil.Process]:
        return [p for p in me.children(recursive=True)
                if "resource_tracker" not in " ".join(p.cmdline())]  # lives with this process

    before = {p.pid for p in workers()}  # another test's processes in this test process
    with STOP_SIGNALS.installed():
        with pytest.raises(Stopped):
            with cli._cluster(None, 1) as client:
                assert client.submit(sum, [1, 2]).result() == 3
                started = [p for p in workers() if p.pid not in before]
                threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGTERM)).start()
    assert started, "the embedded cluster's worker process"
    assert not [p for p in started if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
