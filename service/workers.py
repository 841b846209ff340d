"""Solver workers: the reconstruction runs in worker processes, off the event loop.

Each worker (:func:`worker_main`) builds and warms the CasADi solvers once, then serves jobs
from its pipe one at a time. A worker returns the finished JSON body, so the serialisation of
large answers runs in parallel too and the event loop only moves bytes.
"""

from __future__ import annotations

import ctypes
import gc
import os
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from solver.config import ReconstructionConfig
from solver.estimation.measurements import at_estimated_heights
from solver.inputs import InputError
from solver.results import non_finite_part
from solver.warmup import synthetic_track

from .convert import Job, refinement_nodes, response_dict
from .logs import setup_logging
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


def warm_up(window_sizes: list[int], nlp_solver: str) -> None:
    """Build and run every solver a request may need: the refinement's block solvers of every
    size, the sliding windows' NLPs once per window size, and the IMM filters' compiled
    steps (``filters``)."""
    from solver.estimation import imm_ct_step, imm_step
    from solver.reconstruct import reconstruct
    from solver.refine import build_solvers

    build_solvers()
    imm_step.build()
    imm_ct_step.build()
    for m in window_sizes:
        plots, radar = synthetic_track(max(2 * m + 2, 8))
        for method in ("sliding", "refined"):
            config = ReconstructionConfig(window_plots=m, nlp_solver=nlp_solver,  # type: ignore[arg-type]
                                          method=method)
            reconstruct(plots, radar, config)


_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def exit_with_parent(parent_pid: int) -> None:
    """End this process when the server process ``parent_pid`` dies, even by SIGKILL (which
    runs no clean-up in the server): on Linux the kernel sends SIGKILL on the parent's death
    (``prctl(PR_SET_PDEATHSIG)``); everywhere a daemon thread polls ``os.getppid()`` every
    0.5 s (a dead parent's orphans are re-parented). Both: the kernel's is immediate, the thread
    also covers platforms without prctl."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before the line above
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def limit_memory(max_bytes: int) -> None:
    """Cap this process's address space: an allocation beyond it raises ``MemoryError`` in
    this worker (answered 422) instead of the kernel's OOM killer taking a process."""
    if max_bytes > 0:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (max_bytes, max_bytes))


def worker_main(conn: Connection, parent_pid: int, window_sizes: list[int], nlp_solver: str,
                warm: bool, niceness: int = 0, memory_bytes: int = 0,
                log_level: str = "INFO") -> None:
    """A worker process: follow the parent's death, lower the CPU priority by ``niceness`` (so
    the event loop keeps answering when solves saturate the cores), warm the solvers, report
    ``("ready", error or None)``, then answer ``(job, enqueued_at, time_limit_s)`` messages
    with an :class:`Outcome` (or a :class:`SolveError`) until the pipe closes or ``None``
    arrives."""
    exit_with_parent(parent_pid)
    setup_logging(log_level)  # a spawned process starts with no logging configuration
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the server, which stops us
    if niceness:
        os.nice(niceness)
    error = None
    if warm:
        try:
            warm_up(window_sizes, nlp_solver)
        except Exception as e:
            error = f"{type(e).__name__}: {e}"
    limit_memory(memory_bytes)  # after the warm-up: the limit is for the requests' work
    conn.send(("ready", error))
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        try:
            result: Outcome | SolveError = solve(*message)
        except SolveError as e:
            result = e
        except Exception as e:  # a bug here must not end the worker (and retry the job)
            result = SolveError(f"{type(e).__name__}: {e}\n{traceback.format_exc()}"[:20_000])
        try:
            conn.send(result)
        except (BrokenPipeError, OSError):
            return


class _TimeLimit(BaseException):
    """Raised in a worker by the interval timer of :func:`solve` (a ``BaseException``, like
    ``KeyboardInterrupt``, so the solver's ``except Exception`` fallbacks cannot swallow it)."""


ALARM_GRACE_S = 1.0  # the SIGALRM fires this long after the deadline the solver checks itself
_expired = False  # set by the timer: CasADi may swallow the exception raised inside a solve
_armed = False  # whether the timer may raise: cleared before the outcome of a solve is built


def _time_limit(signum: int, frame: object) -> None:
    global _expired
    _expired = True
    if _armed:
        raise _TimeLimit


DEFAULT_WINDOW_PLOTS = ReconstructionConfig().window_plots
GAP_NODES_SHARE = 0.5
"""Nodes added in gaps beyond this share of the plots are named as a cost in :func:`remedy`."""


def remedy(job: Job) -> str:
    """What made a solve costly and what the client can change: the node intervals of the
    refinement, the offsets estimated with them (``estimate_bias``), the nodes long gaps add.
    A tester's 16 radars with ``estimate_bias`` (2,000 plots, no gap longer than 2 s) were
    told of gaps when the 48 offsets were the cost."""
    table = job.table
    if job.config.method == "sliding":
        return _sliding_remedy(np.sort(table.t), job.config.window_plots,
                               job.config.trial_step_s)
    step = job.config.refine.max_node_step_s
    nodes = refinement_nodes(table.t, step) if len(table) > 1 else 0
    biased = [s.id for s in table.sensors if s.estimate_bias] if len(table.sensors) > 1 else []
    said = f"the refinement solves {nodes} node intervals"
    if biased:
        names = ", ".join(biased[:5]) + (f" and {len(biased) - 5} more" if len(biased) > 5 else "")
        said += (f" with the {3 * len(biased)} offsets of {len(biased)} sensor(s) with "
                 f"estimate_bias ({names}): every offset is joined to every node, so an "
                 "iteration's work grows with the nodes times the square of the offsets")
    gap_nodes = nodes - max(len(table) - 1, 0)
    if gap_nodes > GAP_NODES_SHARE * len(table):
        said += (f"; {gap_nodes} of the nodes fill long gaps between plots (one every "
                 f"{step:g} s)")
    advice = ("estimate_bias on fewer sensors or over a shorter stretch of the track, or split "
              "the track") if biased else "split the track"
    return f"{said}; {advice}"


def _sliding_remedy(t: np.ndarray, plots: int, step: float) -> str:
    """The sliding windows' cost: every step fits one trial window of ``m`` plots per plot of
    the current window and per ``trial_step_s`` over its span (:func:`solver.sliding.
    candidate_times`), so a step's work grows with ``m`` times ``m + span / step``: the
    tester's 200-plot windows were told to raise only the trial step."""
    m = max(min(plots, t.size - 1), 1)
    span = float(np.median(t[m - 1:] - t[:t.size - m + 1])) if t.size > 1 else 0.0
    trials = m + span / step
    said = (f"each sliding step fits about {trials:.0f} trial windows of {m} plots (one per "
            f"plot of the window, window.plots, and one every window.trial_step_s {step:g} s "
            f"over its {span:.4g} s)")
    advice = ["split the track"]
    if m > DEFAULT_WINDOW_PLOTS:
        advice.append(f"lower window.plots (default {DEFAULT_WINDOW_PLOTS})")
    if span / step >= 1:
        advice.append("raise window.trial_step_s")
    return f"{said}; {', '.join(advice[:-1])} or {advice[-1]}" if len(advice) > 1 \
        else f"{said}; {advice[0]}"


def _too_long(job: Job, time_limit_s: float) -> Outcome:
    return Outcome(None, error_loc=("plots",), error_message=(
        f"needs more than this service's solve time limit of {time_limit_s:g} s "
        f"({len(job.table)} plots over {float(job.table.t.max() - job.table.t.min()):g} s); "
        f"{remedy(job)}"))


def solve(job: Job, enqueued_at: float, time_limit_s: float = 0.0) -> Outcome:
    """Reconstruct, run the requested filters, and serialise the validated response.

    ``time_limit_s`` > 0 stops the work after that many seconds and answers an input error
    naming the limit: some valid but absurd inputs (a track of years with 5-s trial steps)
    would otherwise hold a worker for hours. The solver gets the deadline where it takes one
    (checked between sliding steps; IPOPT's wall-time limit); a ``SIGALRM`` timer (workers
    run jobs in their main thread) stops whatever does not check it, and the pool kills a
    worker that overruns even that (:class:`service.pool.SolverPool`).
    """
    from solver.estimation import run_filters
    from solver.reconstruct import reconstruct
    from solver.refine import DeadlineExceeded

    global _expired, _armed
    started = time.time()
    timed = time_limit_s > 0 and threading.current_thread() is threading.main_thread()
    deadline = time.monotonic() + time_limit_s if time_limit_s > 0 else None
    _expired = False
    if timed:
        signal.signal(signal.SIGALRM, _time_limit)
        _armed = True
        # after the solver's own deadline checks had their chance; re-fires every 0.1 s:
        # CasADi's interrupt check inside a solve may consume one alarm
        signal.setitimer(signal.ITIMER_REAL, time_limit_s + ALARM_GRACE_S, 0.1)
    try:
        rec = reconstruct(job.plots, job.radar, job.config, deadline=deadline)
        t0 = time.perf_counter()
        estimates = run_filters(list(job.filters), at_estimated_heights(
            job.plots, rec.at_plots.h) if job.radar is None else job.plots,
            job.radar, gate=job.filter_gate) if job.filters else {}
        filters_ms = (time.perf_counter() - t0) * 1e3
        _armed = False
        if _expired:  # the limit fired inside a solve, where CasADi swallowed the exception
            raise _TimeLimit
    except BaseException as e:
        _armed = False  # first: an alarm must not break the handling below
        if isinstance(e, InputError):
            return Outcome(None, error_loc=e.loc, error_message=e.message)
        if isinstance(e, _TimeLimit | KeyboardInterrupt | DeadlineExceeded) or (
                _expired and isinstance(e, Exception)):
            # the alarm may reach us through CasADi, as a KeyboardInterrupt or another error
            if not timed and deadline is None:
                raise
            return _too_long(job, time_limit_s)
        if isinstance(e, MemoryError):
            return Outcome(None, error_loc=("plots",), error_message=(
                f"needs more memory than this service allows one solve ({len(job.plots)} "
                f"plots over {float(job.plots.t[-1] - job.plots.t[0]):g} s); split the track "
                "or raise window.trial_step_s or sample_step_s"))
        if isinstance(e, Exception):
            raise SolveError(f"{type(e).__name__}: {e}\n{traceback.format_exc()}"[:20_000]
                             ) from None
        raise
    finally:
        _armed = False
        if timed:
            signal.setitimer(signal.ITIMER_REAL, 0)
    bad = non_finite_part(rec, estimates)
    if bad is not None:
        return Outcome(None, error_loc=("bounds",), error_message=(
            f"give a result that is not finite ({bad} holds NaN or infinity): the "
            "bounds, radar errors or plots are too extreme for a numerical solution"))
    gc.disable()  # ~1e5 small objects: cyclic GC passes would triple this step's time
    try:
        body = response_dict(rec, estimates, job.omit, job.notes, job.sensors)
        body["diagnostics"]["filters_ms"] = filters_ms
        body["diagnostics"]["queue_ms"] = max(0.0, (started - enqueued_at) * 1e3)
        out = ReconstructionResponse.model_validate(body).model_dump_json().encode()
    except MemoryError:
        return Outcome(None, error_loc=("sample_step_s",), error_message=(
            "gives an answer larger than this service's memory allows; raise it"))
    finally:
        gc.enable()
    return Outcome(out, rec.diagnostics.solver_failures)
