"""Job tracks' figures drawn when first asked for (``GET .../tracks/{key}/figure.png``), from
what the job stored of the track (:meth:`service.jobs.JobRunner.draw_figure`), then answered
from the job's directory. Drawing every track's figure on the workers took 0.8 s a figure
against 63 ms to solve a three-plot track: a job of 30,000 short tracks spent most of its
6.7 h on figures nobody asked for (a tester's).

Drawing runs in the service's threads, off the event loop, one figure at a time
(:data:`solver.figures.DRAWING`: matplotlib's mathtext parser is not thread-safe); at most
``jobs_figure_draws`` figures are drawn or waiting for that at once (a figure asked for beyond
is :class:`Busy`: 503 with Retry-After); requests for a figure being drawn wait for that
drawing (on the event loop, holding no thread) and answer from the cache. Measured on the real
server, 12 figures drawn one after another: ``/healthz`` answered in 4.7-8.8 ms (median; 1.8-3
idle), p95 15-30 ms, with single pauses of 0.4-0.9 s, the interpreter's full garbage
collections (400-580 ms over the service's 450,000 objects), which drawing's allocations bring
on sooner."""

from __future__ import annotations

import asyncio
from pathlib import Path

from fastapi.concurrency import run_in_threadpool

from .jobs import JobRunner

WAITS = 2
"""A request waits for at most this many drawings of its figure by others (each one's
figure, once kept, answers it) before it draws the figure itself."""


class Busy(Exception):
    """Every drawing slot is taken."""


class TrackFigures:
    """The figures being drawn (per job and key) and how many; used on the event loop only."""

    def __init__(self, runner: JobRunner, max_draws: int):
        self.runner = runner
        self.max_draws = max_draws
        self.drawing = 0
        self._pending: dict[tuple[str, str], asyncio.Future[None]] = {}

    async def path(self, job_id: str, key: str) -> Path | None:
        """The done track ``key``'s figure, drawn now if it never was; None when the job kept
        nothing to draw it from. Raises :class:`Busy` when ``max_draws`` figures are being
        drawn."""
        for _ in range(WAITS + 1):
            path = await run_in_threadpool(self.runner.figure, job_id, key)
            if path is not None:
                return path
            pending = self._pending.get((job_id, key))
            if pending is None:
                break
            await asyncio.shield(pending)  # its drawing done (kept, or not: then look again)
        if self.drawing >= self.max_draws:
            raise Busy(f"{self.drawing} figures are being drawn (the limit is "
                       f"{self.max_draws}, jobs_figure_draws)")
        self.drawing += 1
        done = asyncio.get_running_loop().create_future()
        self._pending[(job_id, key)] = done

        def finished(_: asyncio.Future[Path | None]) -> None:
            self.drawing -= 1
            if self._pending.get((job_id, key)) is done:
                del self._pending[(job_id, key)]
            done.set_result(None)

        # the slot is given back when the drawing's thread ends, not when this request is
        # cancelled (the thread runs on: more drawings than max_draws would run at once)
        drawing = asyncio.ensure_future(run_in_threadpool(self.runner.draw_figure, job_id, key))
        drawing.add_done_callback(finished)
        return await asyncio.shield(drawing)
