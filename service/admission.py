"""Admission of costly work on the jobs routes: how many large answers are built at once, and
how many bytes of JSON bodies are received and parsed at once. Beyond either the route answers
503 with ``Retry-After`` (the caller turns :class:`Crowded` into that answer)."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Awaitable, Callable
from typing import TypeVar

from fastapi.concurrency import run_in_threadpool

T = TypeVar("T")

DISCONNECT_POLL_S = 0.5
"""How often a request waiting for its turn checks that its client is still there (s)."""


class Crowded(Exception):
    """No room now; the message says for what and how much is taken."""


class Gone(Exception):
    """The client left before its answer was built."""


class BuildSlots:
    """At most ``slots`` answers built at once (each in the threadpool), at most ``waiting``
    more waiting for a slot; beyond, :class:`Crowded`.

    Building a job track's answer is Python work holding the GIL (a 19.6-MB answer: 2.0 s of
    rows, 1.0 s of validation, 0.3 s of JSON); 20 built at once starved the event loop, whose
    ``/healthz`` then took up to 10.8 s. One or two at a time leave it the GIL most of the
    time, and waiting costs no thread."""

    def __init__(self, slots: int, waiting: int):
        self.slots = slots
        self.max_waiting = waiting
        self.building = 0
        self.waiting = 0
        self._free: asyncio.Semaphore | None = None

    def _semaphore(self) -> asyncio.Semaphore:
        if self._free is None:  # made on the serving loop (a test client's loop is its own)
            self._free = asyncio.Semaphore(self.slots)
        return self._free

    async def acquire(self) -> None:
        """Take a slot, waiting for one when there is room to wait; else :class:`Crowded`."""
        free = self._semaphore()
        if free.locked() and self.waiting >= self.max_waiting:
            raise Crowded(f"{self.building} large answers are being built and {self.waiting} "
                          "wait (the limits are jobs_answer_builds and jobs_answer_waiting)")
        self.waiting += 1
        try:
            await free.acquire()
        finally:
            self.waiting -= 1
        self.building += 1

    def release(self) -> None:
        self.building -= 1
        self._semaphore().release()

    async def build(self, fn: Callable[..., T], *args: object,
                    gone: Callable[[], Awaitable[bool]] | None = None) -> T:
        """``fn(*args)`` in the threadpool once a slot is free (its exceptions pass).
        ``gone()`` is asked every :data:`DISCONNECT_POLL_S` while waiting and once more before
        building: a client that left gives its place up (:class:`Gone`). A reviewer's 30
        requests dropped after 0.5 s each still had their 56-MB answers built one after
        another, 4.5 s each: a small answer asked for behind them took 134.6 s."""
        waiter = asyncio.ensure_future(self.acquire())
        while True:
            done, _ = await asyncio.wait({waiter}, timeout=DISCONNECT_POLL_S)
            if done:
                waiter.result()  # Crowded passes
                break
            if gone is not None and await gone():
                waiter.cancel()
                try:
                    await waiter
                except asyncio.CancelledError:
                    raise Gone() from None
                self.release()  # the slot came as it was cancelled
                raise Gone()
        try:
            if gone is not None and await gone():
                raise Gone()
            return await run_in_threadpool(fn, *args)
        finally:
            self.release()


class ByteBudget:
    """Bytes of bodies received and parsed at once: a reservation of ``size`` fits when the
    budget holds it beside those already made, or when none is made (so one body as large as
    the single-body limit is always let in alone), or when it is 0 (a post that holds no body
    in memory); else :class:`Crowded`. Thread-safe."""

    def __init__(self, budget: int, what: str):
        self.budget = budget
        self.what = what
        self.taken = 0
        self._lock = threading.Lock()

    def reserve(self, size: int) -> None:
        with self._lock:
            if size and self.taken and self.taken + size > self.budget:
                raise Crowded(f"{self.taken} bytes of {self.what} are being received or "
                              f"checked and this one would add {size} (the limit is "
                              f"{self.budget})")
            self.taken += size

    def release(self, size: int) -> None:
        with self._lock:
            self.taken -= size
