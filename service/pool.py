"""The solver pool: warm-up, readiness, and a bound on queued and running solves."""

from __future__ import annotations

import asyncio
import multiprocessing
import time
from concurrent.futures import Executor, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from .convert import Job
from .logs import LOGGER
from .metrics import Metrics
from .settings import Settings
from .workers import Outcome, init_worker, ping, solve


class Busy(Exception):
    """Every solver slot and queue place is taken (answered 503 with Retry-After)."""


class SolverPool:
    """``workers`` solver processes, each warmed once.

    At most ``solve_slots`` solves are handed to the pool at once; up to ``max_queued_solves``
    more requests wait for a slot; any further request is refused at once (:class:`Busy`).
    Processes, not threads: the solver caches its CasADi functions and solvers per process, and
    two threads using them at once corrupt the heap (measured: a 2-thread pool aborted with
    ``malloc(): unaligned tcache chunk detected`` during warm-up); processes also run the
    Python parts of the solves in parallel. Workers start with ``spawn``: forking a process
    that runs an event loop and threads is unsafe.
    """

    def __init__(self, settings: Settings, metrics: Metrics):
        self.settings = settings
        self.metrics = metrics
        self.state = "starting"
        self.detail = ""
        self._executor: Executor | None = None
        self._slots: asyncio.Semaphore | None = None
        self._pending = 0
        self._warm_task: asyncio.Task[None] | None = None

    # ------------------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Create the pool and warm every worker in the background (``/readyz`` waits)."""
        s = self.settings
        self._slots = asyncio.Semaphore(s.solve_slots)
        self._executor = self._new_executor()
        self._warm_task = asyncio.create_task(self._warm())

    def _new_executor(self) -> Executor:
        s = self.settings
        args = (list(s.warmup_window_plots), s.nlp_solver, s.warmup, s.worker_niceness)
        ctx = multiprocessing.get_context("spawn")
        return ProcessPoolExecutor(s.workers, ctx, init_worker, args)

    async def _warm(self) -> None:
        """Start every worker (each warms up in its initializer) and wait for them all."""
        self.state, self.detail = "starting", ""
        self.metrics.ready.set(0)
        start = time.perf_counter()
        loop = asyncio.get_running_loop()
        try:
            await asyncio.gather(*(loop.run_in_executor(self._executor, ping)
                                   for _ in range(self.settings.workers)))
        except Exception as e:  # a failed warm-up leaves the service alive but not ready
            self.state, self.detail = "failed", f"warm-up failed: {type(e).__name__}: {e}"
            LOGGER.error("warm-up failed", exc_info=True)
            return
        self.state = "ready"
        self.metrics.ready.set(1)
        LOGGER.info("solvers ready", extra={"fields": {
            "workers": self.settings.workers,
            "warmup_ms": round((time.perf_counter() - start) * 1e3, 1)}})

    async def close(self) -> None:
        """Stop warming, cancel queued solves, and shut the workers down."""
        if self._warm_task is not None:
            self._warm_task.cancel()
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)

    # -------------------------------------------------------------------------- solving

    async def run(self, job: Job) -> Outcome:
        """Solve ``job`` in a worker; raise :class:`Busy` when the queue is full."""
        assert self._slots is not None and self._executor is not None, "pool not started"
        s = self.settings
        if self._pending >= s.solve_slots + s.max_queued_solves:
            self.metrics.rejected.inc()
            raise Busy(f"{self._pending} reconstructions are running or queued; retry later")
        self._pending += 1
        self.metrics.in_flight.inc()
        enqueued = time.time()
        try:
            async with self._slots:
                executor = self._executor
                try:
                    return await asyncio.get_running_loop().run_in_executor(
                        executor, solve, job, enqueued, s.solve_time_limit_s)
                except BrokenProcessPool:
                    self._replace(executor)
                    raise Busy("a solver worker died; the pool is restarting") from None
        finally:
            self._pending -= 1
            self.metrics.in_flight.dec()

    def _replace(self, broken: Executor) -> None:
        """Swap a broken process pool for a fresh one (once, whoever notices first)."""
        if self._executor is not broken:
            return
        LOGGER.error("solver pool broken; restarting it")
        broken.shutdown(wait=False, cancel_futures=True)
        self._executor = self._new_executor()
        self._warm_task = asyncio.create_task(self._warm())
