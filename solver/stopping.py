"""Stopping the command line by SIGINT (Ctrl-C) or SIGTERM (a batch scheduler's or a
container's stop) without leaving a half-closed cluster behind.

Python raises the stop wherever the main thread happens to be. Landing inside Dask's closing
of the embedded cluster, it left the cluster half closed: the worker process still alive when
the stop came out, and the interpreter's exit 10.7 s longer, waiting on Dask's timeouts
(measured: a SIGTERM 0.05 or 0.3 s into the close; the SIGTERM test of the command line hung
60 s that way on the CI's slower machine).
Inside :meth:`StopSignals.deferred` (starting and closing the cluster) a stop is held and
raised when the section ends; everywhere else it is raised at once, as Python does.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


class Stopped(KeyboardInterrupt):
    """SIGTERM, unwound like Ctrl-C's ``KeyboardInterrupt``."""


class StopSignals:
    """The main thread's handler of SIGINT and SIGTERM (while :meth:`installed`): raises
    ``KeyboardInterrupt`` / :class:`Stopped`, or holds it inside :meth:`deferred`."""

    def __init__(self) -> None:
        self._depth = 0
        self._held: KeyboardInterrupt | None = None

    def _handle(self, signum: int, frame: Any) -> None:
        stop = Stopped() if signum == signal.SIGTERM else KeyboardInterrupt()
        if self._depth:
            if self._held is None:
                self._held = stop
            return
        raise stop

    @contextmanager
    def installed(self) -> Iterator[None]:
        """Handle SIGINT and SIGTERM here (in the main thread only: elsewhere Python allows no
        handler, and nothing is changed); the previous handlers restored at the end."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
            self._held = None

    @contextmanager
    def deferred(self) -> Iterator[None]:
        """A section a stop must not cut: a stop arriving inside is raised when it ends (not
        if an exception already leaves it: that one unwinds the run anyway). Nests."""
        self._depth += 1
        try:
            yield
        except BaseException:
            self._depth -= 1
            if not self._depth:
                self._held = None
            raise
        self._depth -= 1
        if not self._depth and self._held is not None:
            held, self._held = self._held, None
            raise held


STOP_SIGNALS = StopSignals()
"""The process's one handler (signals are the process's)."""
