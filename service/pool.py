"""The solver pool: warm-up, readiness, a bound on queued and running solves, and workers that
fail alone."""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import signal
import time
from collections.abc import Coroutine
from concurrent.futures import ThreadPoolExecutor
from multiprocessing.process import BaseProcess
from typing import Any

from .convert import Job
from .logs import LOGGER
from .metrics import Metrics
from .settings import Settings
from .workers import Outcome, SolveError, remedy, worker_main

# a worker that has not answered this long after its solve time limit is killed: the limit
# is enforced inside the worker (deadline, SIGALRM), so this only catches a solver call that
# ignores both
KILL_GRACE_S = 5.0
RESPAWN_DELAY_S = 5.0  # between attempts to replace a dead worker whose successor failed
STOP_GRACE_S = 2.0  # on shutdown, a worker gets this long to leave before it is killed


class Busy(Exception):
    """Every solver slot and queue place is taken (answered 503 with Retry-After)."""


class WorkerDied(Exception):
    """The worker process running a solve ended (killed, out of memory, crashed)."""

    def __init__(self, exitcode: int | None):
        super().__init__(f"solver worker ended (exit code {exitcode})")
        self.exitcode = exitcode


class Worker:
    """One solver process and the parent's end of its pipe."""

    def __init__(self, settings: Settings, number: int, readers: ThreadPoolExecutor):
        s = settings
        self.readers = readers
        ctx = multiprocessing.get_context("spawn")
        self.number = number
        self._reading: asyncio.Future[object] | None = None
        self.conn, child = ctx.Pipe(duplex=True)
        args = (child, os.getpid(), list(s.warmup_window_plots), s.nlp_solver, s.warmup,
                s.worker_niceness, s.worker_memory_mb * 2**20, s.log_level)
        self.process: BaseProcess = ctx.Process(target=worker_main, args=args,
                                                name=f"trajrecon-solver-{number}", daemon=True)
        self.process.start()
        child.close()  # only the worker holds its end: its death makes our recv() fail

    async def receive(self, timeout: float | None = None) -> object:
        """The worker's next message; :class:`WorkerDied` if it ends first (or overruns
        ``timeout``, when it is killed)."""
        if self._reading is None:  # one read at a time: a cancelled wait leaves it running
            self._reading = asyncio.get_running_loop().run_in_executor(self.readers, self._recv)
            self._reading.add_done_callback(self._read_done)
        try:
            return await asyncio.wait_for(asyncio.shield(self._reading), timeout)
        except TimeoutError:
            self.kill()
            raise WorkerDied(None) from None

    def _read_done(self, future: asyncio.Future[object]) -> None:
        self._reading = None
        if not future.cancelled():
            future.exception()  # retrieved: a read nobody waits for any more is no error

    def _recv(self) -> object:
        try:
            return self.conn.recv()
        except (EOFError, OSError):
            self.process.join(5)
            raise WorkerDied(self.process.exitcode) from None

    def kill(self) -> None:
        if self.process.is_alive():
            os.kill(self.process.pid, signal.SIGKILL)  # type: ignore[arg-type]

    async def stop(self) -> None:
        """Ask the worker to leave; kill it after :data:`STOP_GRACE_S`."""
        try:
            self.conn.send(None)
        except OSError:
            pass
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self.readers, self.process.join, STOP_GRACE_S)
        self.kill()
        await loop.run_in_executor(self.readers, self.process.join, STOP_GRACE_S)
        self.conn.close()


class SolverPool:
    """``workers`` solver processes, each warmed once, each with its own pipe.

    At most ``solve_slots`` solves run at once; up to ``max_queued_solves`` more requests wait
    for a slot; any further request is refused at once (:class:`Busy`). A solve takes an idle
    worker and gives it back when answered. When a worker dies (killed, out of memory, a
    crash), only its own solve notices: the worker is replaced (warmed in the background) and
    the solve retried once on another worker; solves on other workers are not disturbed (a
    ``ProcessPoolExecutor`` breaks as a whole when one of its processes dies: measured, the
    innocent request on the healthy worker got a 503 too). Workers end with the server, even
    when it is killed (:func:`service.workers.exit_with_parent`).

    Processes, not threads: the solver caches its CasADi functions and solvers per process, and
    two threads using them at once corrupt the heap (measured: a 2-thread pool aborted with
    ``malloc(): unaligned tcache chunk detected`` during warm-up); processes also run the
    Python parts of the solves in parallel. Workers start with ``spawn``: forking a process
    that runs an event loop and threads is unsafe. Standard library rather than Dask's
    ``LocalCluster``: its workers run tasks in threads (the per-solve ``SIGALRM`` needs the main
    thread) and come with a nanny process each.
    """

    def __init__(self, settings: Settings, metrics: Metrics):
        self.settings = settings
        self.metrics = metrics
        self.state = "starting"
        self.detail = ""
        self._slots: asyncio.Semaphore | None = None
        self._idle: asyncio.Queue[Worker] | None = None
        self._workers: set[Worker] = set()
        self._warming: set[Worker] = set()
        self._starting: set[asyncio.Task[None]] = set()
        self._pending = 0
        self._count = 0
        self._closing = False
        self._warm_all: asyncio.Task[None] | None = None
        # one blocking pipe read per worker at most (a solve, or a warm-up's report) plus the
        # joins of a shutdown: the event loop's default executor has min(32, cores + 4) threads
        self._readers = ThreadPoolExecutor(2 * settings.workers + 2,
                                           thread_name_prefix="solver-pipe")

    # ------------------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Start every worker; each warms up in the background (``/readyz`` waits for all)."""
        s = self.settings
        self._slots = asyncio.Semaphore(s.solve_slots)
        self._idle = asyncio.Queue()
        self.state, self.detail = "starting", ""
        self.metrics.ready.set(0)
        self._warm_all = asyncio.create_task(self._start_all())

    async def _start_all(self) -> None:
        start = time.perf_counter()
        results = await asyncio.gather(*(self._spawn() for _ in range(self.settings.workers)))
        errors = [e for e in results if e]
        if errors:
            self.state, self.detail = "failed", f"warm-up failed: {errors[0]}"
            LOGGER.error("warm-up failed", extra={"fields": {"error": errors[0]}})
            return
        self.state = "ready"
        self.metrics.ready.set(1)
        LOGGER.info("solvers ready", extra={"fields": {
            "workers": self.settings.workers,
            "warmup_ms": round((time.perf_counter() - start) * 1e3, 1)}})

    async def _spawn(self) -> str | None:
        """Start one worker, wait for its warm-up, and make it idle; the warm-up's error, if
        any (the worker is then stopped)."""
        self._count += 1
        worker = Worker(self.settings, self._count, self._readers)
        self._workers.add(worker)
        self._warming.add(worker)
        try:
            _, error = await worker.receive()  # type: ignore[misc]
        except WorkerDied as e:
            self._workers.discard(worker)
            return str(e)
        finally:
            self._warming.discard(worker)
        if error is not None or self._closing:
            self._workers.discard(worker)
            await worker.stop()
            return error
        assert self._idle is not None
        self._idle.put_nowait(worker)
        return None

    def serving(self) -> int:
        """Warm workers alive now (idle or solving); idle ones found dead are replaced here
        (killed from outside, they were found only when a request took them: until then
        ``/readyz`` said ready with no worker alive)."""
        if self._idle is None or self._closing:
            return 0
        idle = [self._idle.get_nowait() for _ in range(self._idle.qsize())]
        for worker in idle:
            if worker.process.is_alive():
                self._idle.put_nowait(worker)
            else:
                self._replace(worker)
        return sum(w.process.is_alive() for w in self._workers - self._warming)

    def _replace(self, worker: Worker) -> None:
        """Forget a dead worker and start its successor in the background."""
        self._workers.discard(worker)
        worker.conn.close()
        if self._closing:
            return
        LOGGER.error("solver worker died; starting a new one", extra={"fields": {
            "worker": worker.number, "exitcode": worker.process.exitcode}})
        self._background(self._respawn())

    def _background(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.create_task(coro)
        self._starting.add(task)
        task.add_done_callback(self._starting.discard)

    async def _reclaim(self, worker: Worker) -> None:
        """A solve was cancelled (its client's request task, a shutdown) while its worker
        works on: take the answer when it comes and make the worker idle again (or replace
        it), so no cancellation leaks a worker."""
        limit = self.settings.solve_time_limit_s
        try:
            await worker.receive(limit + KILL_GRACE_S if limit > 0 else None)
        except WorkerDied:
            self._replace(worker)
            return
        if not self._closing and self._idle is not None:
            self._idle.put_nowait(worker)

    async def _respawn(self) -> None:
        """Start a successor; while that fails (its warm-up), the pool is not ready and tries
        again every :data:`RESPAWN_DELAY_S` (solves wait for the workers that are left)."""
        while (error := await self._spawn()) is not None and not self._closing:
            self.state, self.detail = "failed", f"a replacement worker failed: {error}"
            self.metrics.ready.set(0)
            LOGGER.error("replacement worker failed", extra={"fields": {"error": error}})
            await asyncio.sleep(RESPAWN_DELAY_S)
        if error is None and self.state == "failed" and self._warm_all is not None and \
                self._warm_all.done():
            self.state, self.detail = "ready", ""
            self.metrics.ready.set(1)

    async def close(self) -> None:
        """Stop warming, and stop every worker (killed after :data:`STOP_GRACE_S`): bounded
        even when a solve is running."""
        self._closing = True
        for task in [self._warm_all, *self._starting]:
            if task is not None:
                task.cancel()
        await asyncio.gather(*(w.stop() for w in list(self._workers)))
        self._workers.clear()
        self._readers.shutdown(wait=False, cancel_futures=True)

    # -------------------------------------------------------------------------- solving

    async def run(self, job: Job) -> Outcome:
        """Solve ``job`` in a worker; raise :class:`Busy` when the queue is full,
        :class:`SolveError` when the solver failed (or its worker died twice)."""
        assert self._slots is not None and self._idle is not None, "pool not started"
        s = self.settings
        if self._pending >= s.solve_slots + s.max_queued_solves:
            self.metrics.rejected.inc()
            raise Busy(f"{self._pending} reconstructions are running or queued; retry later")
        self._pending += 1
        self.metrics.in_flight.inc()
        enqueued = time.time()
        try:
            if not await self._take_slot(s.max_queue_wait_s):
                self.metrics.rejected.inc()
                raise Busy(f"waited {s.max_queue_wait_s:g} s for a solver ({self._pending} "
                           "reconstructions are running or queued); retry later")
            try:
                for attempt in (1, 2):
                    worker = await self._idle.get()
                    while not worker.process.is_alive():  # died idle: not this job's doing
                        self._replace(worker)  # (killed from outside); wait for the next
                        worker = await self._idle.get()
                    try:
                        result = await self._solve_on(worker, job, enqueued)
                    except asyncio.CancelledError:
                        self._background(self._reclaim(worker))
                        raise
                    except WorkerDied as e:
                        self._replace(worker)
                        if e.exitcode is None:  # overran its time limit: killed by us
                            return _overran(job, s.solve_time_limit_s)
                        if attempt == 2:
                            return _died_twice(job, e.exitcode)
                        LOGGER.warning("solve retried on another worker", extra={"fields": {
                            "exitcode": e.exitcode}})
                        continue
                    self._idle.put_nowait(worker)
                    if isinstance(result, SolveError):
                        raise result
                    assert isinstance(result, Outcome)
                    return result
                raise AssertionError("unreachable")
            finally:
                self._slots.release()
        finally:
            self._pending -= 1
            self.metrics.in_flight.dec()

    async def _take_slot(self, wait_s: float) -> bool:
        """A solve slot within ``wait_s`` seconds (0: however long it takes); False if none."""
        assert self._slots is not None
        if wait_s <= 0:
            await self._slots.acquire()
            return True
        try:
            async with asyncio.timeout(wait_s):
                await self._slots.acquire()
        except TimeoutError:
            return False
        return True

    async def _solve_on(self, worker: Worker, job: Job, enqueued: float) -> object:
        limit = self.settings.solve_time_limit_s
        try:
            worker.conn.send((job, enqueued, limit))
        except OSError:
            raise WorkerDied(worker.process.exitcode) from None
        return await worker.receive(limit + KILL_GRACE_S if limit > 0 else None)


def _overran(job: Job, limit_s: float) -> Outcome:
    return Outcome(None, error_loc=("plots",), error_message=(
        f"needs more than this service's solve time limit of {limit_s:g} s "
        f"({len(job.plots)} plots); {remedy(job)}"))


def _died_twice(job: Job, exitcode: int | None) -> Outcome:
    """Two workers ended under this job (a worker found dead while idle is not counted: it is
    replaced and the job waits for the next). Killed (SIGKILL: the kernel's OOM killer; the
    worker's own memory cap raises MemoryError instead, answered 422 by the worker) most likely
    means it needs more memory than the service has: the client's to change (422), said with
    the other cause, a kill from outside. Anything else is a crash of the solver, a bug
    (500)."""
    if exitcode == -signal.SIGKILL:
        return Outcome(None, error_loc=("plots",), error_message=(
            f"needs more memory than this service has, most likely ({len(job.plots)} plots): "
            f"the solve's worker was killed (SIGKILL: the system's out-of-memory killer, or "
            f"from outside) twice; {remedy(job)}, or raise sample_step_s"))
    raise SolveError(f"the solver worker crashed twice on this request (exit code {exitcode})")
