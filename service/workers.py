"""Solver workers: the reconstruction runs in a pool, off the event loop.

Each worker builds and warms the CasADi solvers once (``init_worker``), then serves
``solve`` calls. A worker returns the finished JSON body, so the serialisation of large answers
runs in parallel too and the event loop only moves bytes.
"""

from __future__ import annotations

import gc
import os
import signal
import threading
import time
import traceback
from dataclasses import dataclass

import numpy as np

from solver.config import ReconstructionConfig
from solver.inputs import InputError, Plots, Radar
from solver.motion import propagate

from .convert import Job, response_dict
from .models import ReconstructionResponse


class SolveError(RuntimeError):
    """A reconstruction raised inside a worker (a solver bug: the input had passed
    validation). Carries the worker's traceback as text; picklable."""


@dataclass(frozen=True)
class Outcome:
    """What a worker sends back: a JSON body, or an input error the solver found late."""

    body: bytes | None
    solver_failures: int = 0
    error_loc: tuple[str | int, ...] = ()
    error_message: str = ""


def synthetic_track(n: int) -> tuple[Plots, Radar]:
    """``n`` noiseless plots every 10 s of a 200 m/s aircraft turning at 2 m/s^2 (warm-up)."""
    t = 10.0 * np.arange(n)
    x, z, _, _ = propagate(50e3, 20e3, 0.5, 200.0, 2.0, 0.2, t)
    radar = Radar(range_error_m=300.0, azimuth_error_rad=np.deg2rad(0.5))
    return Plots.from_arrays(t, np.hypot(x, z), np.arctan2(z, x)), radar


def warm_up(window_sizes: list[int], nlp_solver: str) -> None:
    """Build and run every solver a request may need: the refinement's block solvers of every
    size, and the sliding windows' NLPs once per window size."""
    from solver.reconstruct import reconstruct
    from solver.refine import build_solvers

    build_solvers()
    for m in window_sizes:
        plots, radar = synthetic_track(max(2 * m + 2, 8))
        for method in ("sliding", "refined"):
            config = ReconstructionConfig(window_plots=m, nlp_solver=nlp_solver,  # type: ignore[arg-type]
                                          method=method)
            reconstruct(plots, radar, config)


_warm_up_error: str | None = None


def init_worker(window_sizes: list[int], nlp_solver: str, warm: bool, niceness: int = 0) -> None:
    """Pool initializer: lower this worker's CPU priority by ``niceness`` (so the event loop
    keeps answering when solves saturate the cores), then warm the solvers before the first
    request reaches this worker.

    A failure is kept and reported by :func:`ping` (an initializer that raises would only
    break the pool with no message)."""
    global _warm_up_error
    if niceness:
        os.nice(niceness)
    if warm:
        try:
            warm_up(window_sizes, nlp_solver)
        except Exception as e:
            _warm_up_error = f"{type(e).__name__}: {e}"


def ping() -> float:
    """The readiness probe of one worker: runs after its warm-up, raises if that failed."""
    if _warm_up_error is not None:
        raise RuntimeError(_warm_up_error)
    return time.time()


class _TimeLimit(BaseException):
    """Raised in a worker by the interval timer of :func:`solve` (a ``BaseException``, like
    ``KeyboardInterrupt``, so the solver's ``except Exception`` fallbacks cannot swallow it)."""


_expired = False  # set by the timer: CasADi may swallow the exception raised inside a solve


def _time_limit(signum: int, frame: object) -> None:
    global _expired
    _expired = True
    raise _TimeLimit


def solve(job: Job, enqueued_at: float, time_limit_s: float = 0.0) -> Outcome:
    """Reconstruct, run the requested filters, and serialise the validated response.

    ``time_limit_s`` > 0 stops the work after that many seconds (a ``SIGALRM`` timer; pool
    workers run tasks in their main thread, and each CasADi call inside lasts milliseconds)
    and answers an input error naming the limit: some valid but absurd inputs (a track of
    years with 5-s trial steps) would otherwise hold a worker for hours.
    """
    from solver.estimation import run_filters
    from solver.reconstruct import reconstruct

    global _expired
    started = time.time()
    timed = time_limit_s > 0 and threading.current_thread() is threading.main_thread()
    _expired = False
    if timed:
        signal.signal(signal.SIGALRM, _time_limit)
        # re-fires every 0.1 s: CasADi's interrupt check inside a solve may consume one alarm
        signal.setitimer(signal.ITIMER_REAL, time_limit_s, 0.1)
    try:
        rec = reconstruct(job.plots, job.radar, job.config)
        t0 = time.perf_counter()
        estimates = run_filters(list(job.filters), job.plots, job.radar) if job.filters else {}
        filters_ms = (time.perf_counter() - t0) * 1e3
        if _expired:  # the limit fired inside a solve, where CasADi swallowed the exception
            raise _TimeLimit
        gc.disable()  # ~1e5 small objects: cyclic GC passes would triple this step's time
        try:
            body = response_dict(rec, estimates)
            body["diagnostics"]["filters_ms"] = filters_ms
            body["diagnostics"]["queue_ms"] = max(0.0, (started - enqueued_at) * 1e3)
            out = ReconstructionResponse.model_validate(body).model_dump_json().encode()
        finally:
            gc.enable()
        return Outcome(out, rec.diagnostics.solver_failures)
    except InputError as e:
        return Outcome(None, error_loc=e.loc, error_message=e.message)
    except (_TimeLimit, KeyboardInterrupt):
        # the alarm may reach us through CasADi, which reports it as a KeyboardInterrupt
        if not timed:
            raise
        return Outcome(None, error_loc=("plots",), error_message=(
            f"needs more than this service's solve time limit of {time_limit_s:g} s "
            f"({len(job.plots)} plots over {float(job.plots.t[-1] - job.plots.t[0]):g} s); "
            "split the track or raise window.trial_step_s"))
    except Exception as e:
        raise SolveError(f"{type(e).__name__}: {e}\n{traceback.format_exc()}") from None
    finally:
        if timed:
            signal.setitimer(signal.ITIMER_REAL, 0)
