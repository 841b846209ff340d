"""Faults: a dead worker, a server killed with SIGKILL or stopped while solving, solves that
run into the time limit or ask for too much work."""

from __future__ import annotations

import asyncio
import copy
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
from procs import start_service, stop

from service.convert import to_job
from service.metrics import Metrics
from service.models import ReconstructionRequest
from service.pool import SolverPool
from service.settings import Settings
from solver.inputs import InputError

ROOT = Path(__file__).resolve().parents[1]
SEED_BATCH = json.loads((ROOT / "examples" / "seed_track.json").read_text())


def job_of(body: dict, max_samples: int = 20_000):
    return to_job(ReconstructionRequest.model_validate(body), "sqpmethod", 5000, max_samples)


async def ready(pool: SolverPool, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while pool.state != "ready":
        assert pool.state != "failed" and time.monotonic() < end, pool.detail
        await asyncio.sleep(0.05)


def test_a_dead_worker_disturbs_no_other_solve_and_its_solve_is_retried():
    """Two solves on two workers; the first one's worker is killed mid-solve. The other solve
    is answered normally, the killed one is retried on another worker and answered too, and
    the pool is back to two workers (a ProcessPoolExecutor broke as a whole: both got 503)."""
    job = job_of(SEED_BATCH)

    async def scenario() -> None:
        pool = SolverPool(Settings(workers=2, warmup=False), Metrics())
        pool.start()
        await ready(pool)
        idle = pool._idle
        assert idle is not None
        first = asyncio.create_task(pool.run(job))
        while idle.qsize() != 1:
            await asyncio.sleep(0.005)
        (victim,) = set(pool._workers) - set(idle._queue)  # type: ignore[attr-defined]
        second = asyncio.create_task(pool.run(job))
        while idle.qsize() != 0:
            await asyncio.sleep(0.005)
        os.kill(victim.process.pid, signal.SIGKILL)
        a, b = await asyncio.gather(first, second)
        assert a.body is not None and b.body is not None
        assert json.loads(a.body) == json.loads(b.body) | {
            "diagnostics": json.loads(a.body)["diagnostics"]}
        end = time.monotonic() + 60
        while len(pool._workers) != 2 or idle.qsize() != 2:
            assert time.monotonic() < end, "the dead worker was not replaced"
            await asyncio.sleep(0.05)
        assert not victim.process.is_alive() and victim not in pool._workers
        assert (await pool.run(job)).body is not None
        await pool.close()

    asyncio.run(scenario())


def test_idle_workers_killed_from_outside_are_replaced_not_blamed_on_the_request():
    """Both idle, warmed workers killed (SIGKILL from outside), then a request: it took both
    dead workers as two deaths under it and answered 422 'needs more memory' in 7 ms without
    solving (a tester). A worker found dead while idle is replaced and the request waits for
    the replacement: answered normally."""
    job = job_of(SEED_BATCH)

    async def scenario() -> None:
        pool = SolverPool(Settings(workers=2, warmup=False), Metrics())
        pool.start()
        await ready(pool)
        for w in list(pool._workers):
            os.kill(w.process.pid, signal.SIGKILL)
            w.process.join(10)
        out = await pool.run(job)
        assert out.body is not None, out.error_message
        assert len(pool._workers) >= 1
        await pool.close()

    asyncio.run(scenario())


def test_solve_time_limit_stops_a_sliding_solve_with_a_422():
    """A sliding solve stopped by the limit is the documented input error (it was a 500), and
    ends within a small margin of the limit."""
    body = copy.deepcopy(SEED_BATCH)
    body.update(method="sliding", window={"plots": 3, "trial_step_s": 0.05})
    job = job_of(body)

    async def scenario() -> None:
        pool = SolverPool(Settings(workers=1, warmup=False, solve_time_limit_s=0.5), Metrics())
        pool.start()
        await ready(pool)
        start = time.perf_counter()
        out = await pool.run(job)
        elapsed = time.perf_counter() - start
        assert out.body is None and out.error_loc == ("plots",), out
        assert "solve time limit of 0.5 s" in out.error_message
        assert elapsed < 1.5, elapsed
        assert len(pool._workers) == 1 and pool._idle.qsize() == 1  # the worker lives on
        await pool.close()

    asyncio.run(scenario())


def test_solve_time_limit_stops_sliding_windows_over_sensors():
    """The same over several sensors (the windows over their fixes check the deadline too);
    the message spans the plots' times although the request lists them sensor by sensor."""
    from test_service_sensors import _body

    body = _body()
    body["plots"].sort(key=lambda p: p["sensor"] != "ADSB")  # ADS-B's (1 s on) first
    body.update(method="sliding", window={"plots": 3, "trial_step_s": 0.01})
    times = [p["t"] for p in body["plots"]]
    job = job_of(body)

    async def scenario() -> None:
        pool = SolverPool(Settings(workers=1, warmup=False, solve_time_limit_s=0.5), Metrics())
        pool.start()
        await ready(pool)
        out = await pool.run(job)
        assert out.body is None and out.error_loc == ("plots",), out
        assert f"({len(times)} plots over {max(times) - min(times):g} s)" in out.error_message
        assert times[-1] - times[0] != max(times) - min(times)
        await pool.close()

    asyncio.run(scenario())


@pytest.mark.parametrize(("window", "said", "advice"), [
    ({"plots": 200, "trial_step_s": 5.0}, "about 1047 trial windows of 200 plots",
     "lower window.plots (default 3) or raise window.trial_step_s"),
    ({"plots": 3, "trial_step_s": 0.05}, "trial windows of 3 plots",
     "split the track or raise window.trial_step_s")])
def test_a_sliding_solve_past_its_time_limit_names_its_cost(window, said, advice):
    """Sliding windows cost a step ``m`` times ``m + span / trial_step_s`` window plots: the
    tester's 200-plot windows (the cost) were told only to raise the trial step."""
    from service.workers import solve

    body = copy.deepcopy(SEED_BATCH)
    body.update(method="sliding", window=window)
    out = solve(job_of(body), 0.0, time_limit_s=1e-6)
    assert out.body is None and out.error_loc == ("plots",), out
    assert "solve time limit of 1e-06 s" in out.error_message
    assert said in out.error_message and out.error_message.endswith(advice), out.error_message
    assert ("window.plots (default" in out.error_message) == (window["plots"] > 3)


def test_trial_step_that_asks_for_billions_of_windows_is_a_422_naming_it():
    """1e-9 s is refused by the configuration's bound (MIN_TRIAL_STEP_S); a step above it that asks
    too many trial starts of long windows (plots 10 times farther apart: 380-s windows at
    0.01 s) is the solver's 422 naming it."""
    body = copy.deepcopy(SEED_BATCH)
    body["plots"] = body["plots"][:20]
    body.update(method="sliding", window={"plots": 3, "trial_step_s": 1e-9})
    with pytest.raises(InputError, match=r"must be at least 0\.0078125 s"):
        job_of(body)
    for p in body["plots"]:
        p["t"] *= 10.0
    body.update(window={"plots": 3, "trial_step_s": 0.01},
                bounds={"u": [-7.0, 7.0], "w": [-2.0, 3.0], "v": [1.0, 330.0]})

    async def scenario() -> None:
        pool = SolverPool(Settings(workers=1, warmup=False), Metrics())
        pool.start()
        await ready(pool)
        out = await pool.run(job_of(body))
        assert out.body is None and out.error_loc == ("window", "trial_step_s"), out
        assert "at most 20000" in out.error_message
        await pool.close()

    asyncio.run(scenario())


def _start(tmp_env: dict[str, str]) -> tuple[subprocess.Popen, str]:
    return start_service({"TRAJRECON_WORKERS": "2", "TRAJRECON_WARMUP": "false",
                          "TRAJRECON_LOG_LEVEL": "WARNING", **tmp_env})


def children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        out += [int(c) for c in (task / "children").read_text().split()]
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_exit_when_the_server_is_killed():
    proc, _ = _start({})
    try:
        workers = children(proc.pid)
        assert len(workers) >= 2, workers
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        end = time.monotonic() + 5
        while any(alive(p) for p in workers):
            assert time.monotonic() < end, [p for p in workers if alive(p)]
            time.sleep(0.05)
    finally:
        stop(proc)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_readyz_sees_the_only_worker_killed_and_its_replacement():
    """The only worker, idle and warm, killed from outside: /readyz said ready until a request
    found it dead. It now answers 503 at once, the replacement starts then, and /readyz is
    ready again once it is warm; a request is then answered."""
    proc, url = start_service({"TRAJRECON_WORKERS": "1", "TRAJRECON_WARMUP": "false",
                               "TRAJRECON_LOG_LEVEL": "ERROR"})
    try:
        assert httpx.get(url + "/readyz", timeout=10).status_code == 200
        workers = [c for c in children(proc.pid)
                   if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]
        assert len(workers) == 1, workers
        os.kill(workers[0], signal.SIGKILL)
        end = time.monotonic() + 5
        while alive(workers[0]):
            assert time.monotonic() < end
            time.sleep(0.05)
        r = httpx.get(url + "/readyz", timeout=10)
        assert r.status_code == 503, r.text
        assert r.json() == {"status": "starting", "detail": "no solver worker is alive: their "
                            "replacements are warming up"}
        end = time.monotonic() + 60
        while httpx.get(url + "/readyz", timeout=10).status_code != 200:
            assert time.monotonic() < end, "the replacement never became ready"
            time.sleep(0.2)
        body = dict(SEED_BATCH, plots=SEED_BATCH["plots"][:8])
        assert httpx.post(url + "/v1/reconstructions", json=body, timeout=60).status_code == 200
    finally:
        stop(proc)


def test_shutdown_while_solving_ends_in_bounded_time():
    """SIGTERM with a long solve running: the server is gone within the shutdown timeout plus
    the workers' stop grace, not after the solve."""
    proc, url = _start({"TRAJRECON_SHUTDOWN_TIMEOUT_S": "1"})
    body = copy.deepcopy(SEED_BATCH)
    body.update(method="sliding", window={"plots": 3, "trial_step_s": 0.05})

    def post() -> None:
        try:
            httpx.post(url + "/v1/reconstructions", json=body, timeout=60)
        except httpx.TransportError:
            pass

    thread = threading.Thread(target=post, daemon=True)
    thread.start()
    try:
        end = time.monotonic() + 10
        while "trajrecon_solves_in_flight 1.0" not in httpx.get(url + "/metrics").text:
            assert time.monotonic() < end
            time.sleep(0.05)
        time.sleep(0.5)
        start = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)
        assert time.monotonic() - start < 8
    finally:
        stop(proc)


def test_a_solve_over_the_memory_limit_is_a_422():
    """With ``worker_memory_mb`` a solve that needs more memory (10^6 samples with their
    covariances) is answered 422 naming the cause, and the worker serves on."""
    body = copy.deepcopy(SEED_BATCH)
    body["plots"] = body["plots"][:50]
    body["sample_step_s"] = 0.001

    async def scenario() -> None:
        pool = SolverPool(Settings(workers=1, warmup=False, worker_memory_mb=1200), Metrics())
        pool.start()
        await ready(pool)
        out = await pool.run(job_of(body, max_samples=10**9))
        assert out.body is None, "the solve fitted in 1200 MiB: raise the sample count"
        assert ("more memory than this service allows" in out.error_message
                or "larger than this service's memory" in out.error_message), out
        small = dict(body, sample_step_s=1.0)
        assert (await pool.run(job_of(small))).body is not None
        assert len(pool._workers) == 1
        await pool.close()

    asyncio.run(scenario())


def test_a_non_finite_result_is_a_422_not_a_failed_response_validation():
    """The worker checks the result's arrays before it builds the answer: a NaN anywhere is
    a 422 naming the part (the response validation found it late, as a 500)."""
    import numpy as np

    from solver.estimation import run_filters
    from solver.reconstruct import reconstruct
    from solver.results import non_finite_part as _finite

    body = copy.deepcopy(SEED_BATCH)
    body["plots"] = body["plots"][:12]
    job = job_of(body)
    rec = reconstruct(job.plots, job.radar, job.config)
    est = run_filters(["cv_rts"], job.plots, job.radar)
    assert _finite(rec, est) is None
    rec.samples.vz[3] = np.inf
    assert _finite(rec, est) == "trajectory.samples"
    rec.samples.vz[3] = 0.0
    est["cv_rts"].states.cov[2, 1, 1] = np.nan
    assert _finite(rec, est) == "filters.cv_rts"
    assert _finite(rec) is None
    rec.diagnostics.criterion_values = [np.nan]  # a stored job track failed every read
    assert _finite(rec) == "diagnostics.criterion_values"


def test_a_worker_that_overruns_its_limit_is_killed():
    """The pool's last resort when a solver call ignores both the deadline and the alarm: a
    worker that has not answered in time is killed (here: a 0.3-s wait on a solve of seconds
    sent without a limit)."""
    from concurrent.futures import ThreadPoolExecutor

    from service.pool import Worker, WorkerDied

    body = copy.deepcopy(SEED_BATCH)
    body.update(method="sliding", window={"plots": 3, "trial_step_s": 0.05})
    job = job_of(body)

    async def scenario() -> None:
        readers = ThreadPoolExecutor(2)
        worker = Worker(Settings(workers=1, warmup=False), 1, readers)
        assert await worker.receive(60) == ("ready", None)
        worker.conn.send((job, time.time(), 0.0))
        start = time.perf_counter()
        with pytest.raises(WorkerDied) as died:
            await worker.receive(0.3)
        assert died.value.exitcode is None and time.perf_counter() - start < 2
        # the pool's reader thread also joins the dead worker: whichever thread reaps it sets
        # the exit code, the other may see None for a moment (a flaky failure in CI)
        end = time.monotonic() + 5
        while worker.process.exitcode is None and time.monotonic() < end:
            worker.process.join(0.05)
        assert worker.process.exitcode == -signal.SIGKILL
        readers.shutdown()

    asyncio.run(scenario())


def test_a_cancelled_solve_gives_its_worker_back():
    """A solve cancelled while its worker works (its request task cancelled) must not leak
    the worker: it is idle again once its answer arrives, and serves the next solve."""
    job = job_of(dict(SEED_BATCH, plots=SEED_BATCH["plots"][:60]))

    async def scenario() -> None:
        pool = SolverPool(Settings(workers=1, warmup=False), Metrics())
        pool.start()
        await ready(pool)
        task = asyncio.create_task(pool.run(job))
        while pool._idle.qsize() != 0:
            await asyncio.sleep(0.005)
        await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        out = await asyncio.wait_for(pool.run(job), 60)  # the only worker serves again
        assert out.body is not None
        assert len(pool._workers) == 1
        await pool.close()

    asyncio.run(scenario())


def test_requests_whose_clients_left_leave_the_queue():
    """Three slow requests (3 plots over 6000 s: about 7 s each) on one worker, their clients
    gone after 1 s: the two queued behind the first stayed in flight and took the worker in
    turn (a tester: a quick request behind six such took 28 s instead of 0.35 s). Now they
    leave once their clients are gone: no request in flight (the running solve finishes in
    its worker, which then takes the next request)."""
    slow = copy.deepcopy(SEED_BATCH)
    slow["plots"] = slow["plots"][:3]
    slow["plots"][2]["t"] = 6000.0
    slow["omit"] = ["samples"]
    proc, url = start_service({"TRAJRECON_WORKERS": "1", "TRAJRECON_WARMUP": "false",
                               "TRAJRECON_LOG_LEVEL": "WARNING"})
    try:
        def abandon() -> None:
            with pytest.raises(httpx.TimeoutException):
                httpx.post(url + "/v1/reconstructions", json=slow, timeout=1.0)

        clients = [threading.Thread(target=abandon) for _ in range(3)]
        for c in clients:
            c.start()
            time.sleep(0.1)
        for c in clients:
            c.join()
        time.sleep(1.5)  # three polls of the disconnect check
        metrics = httpx.get(url + "/metrics", timeout=5).text
        in_flight = float(re.search(r"^trajrecon_solves_in_flight (\S+)$", metrics,
                                    re.M).group(1))  # type: ignore[union-attr]
        assert in_flight == 0.0, in_flight
    finally:
        stop(proc)
