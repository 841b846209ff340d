"""Admission of costly work on the jobs routes: how many large answers are built at once, and
how many bytes of JSON bodies are received and parsed at once. Beyond either the route answers
503 with ``Retry-After`` (the caller turns :class:`Crowded` into that answer)."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from typing import TypeVar

from fastapi.concurrency import run_in_threadpool

T = TypeVar("T")


class Crowded(Exception):
    """No room now; the message says for what and how much is taken."""


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

    async def build(self, fn: Callable[..., T], *args: object) -> T:
        """``fn(*args)`` in the threadpool once a slot is free (its exceptions pass)."""
        await self.acquire()
        try:
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
