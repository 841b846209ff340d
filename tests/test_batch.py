"""solver.batch.reconstruct_many: a real 2-worker Dask LocalCluster (no mocks), per-track
failures isolated and reported, results streamed to Parquet parts, reruns resume."""

from __future__ import annotations

import csv
import json
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from test_io_asterix import SENSORS, encode_recording

from solver.batch import (
    MMAP_THRESHOLD_BYTES,
    PROGRESS,
    QUIET_LOOPS,
    TRACK_COLUMNS,
    TrackProblem,
    reconstruct_many,
    solve_track,
)
from solver.io.asterix import read_recording
from solver.io.split import split_aircraft
from solver.plots import PlotTable


@pytest.fixture(scope="module")
def tracks() -> list:
    """Two aircraft seen by two radars and ADS-B (60 s), and a track of 2 plots that
    the reconstruction refuses."""
    rows = read_recording(encode_recording(duration=60.0).data, SENSORS).rows
    good = list(split_aircraft(rows, SENSORS))  # AircraftTrack: .key and .table
    t = good[0].table
    r = np.flatnonzero(t.sensor == t.sensor[0])[:2]  # two plots of one radar
    two = PlotTable.build([t.sensors[t.sensor[0]]], t.t[r], np.zeros(2, int), t.range_m[r],
                          t.azimuth_rad[r], altitude_m=t.altitude_m[r], reference=t.frame)
    return [good[0], TrackProblem("TOO-SHORT", two), good[1]]


def ledger(out) -> list[dict]:
    return [json.loads(line) for line in (out / PROGRESS).read_text().splitlines()]


@pytest.fixture(scope="module")
def client():
    """A real LocalCluster of 2 single-threaded worker processes, and its client."""
    from distributed import Client, LocalCluster

    # the workers use CasADi's interpreter (same results; compiling the motion model at a
    # worker's start-up costs seconds that these tests do not need to spend)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TRAJRECON_COMPILE", "0")
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                          dashboard_address=":0") as cluster, Client(cluster) as c:
            yield c


def test_local_cluster_two_workers(tmp_path, tracks, client):
    out = tmp_path / "out"
    assert len(client.scheduler_info()["workers"]) == 2
    summary = reconstruct_many(tracks, out, executor=client, flush_tracks=1)
    pids = client.run(lambda: __import__("os").getpid())
    assert len(set(pids.values())) == 2  # two worker processes
    assert (summary.tracks, summary.done, summary.failed, summary.skipped) == (3, 2, 1, 0)
    assert summary.failures["TOO-SHORT"].startswith("InputError: plots has 2 plot(s)")
    states = pq.read_table(out / "tracks.parquet")
    assert tuple(states.column_names) == TRACK_COLUMNS
    by_key = {k: states.filter(pc.equal(states["aircraft"], k)).to_pydict()
              for k in ("4CA2D1", "3C6DD4")}
    for problem in (tracks[0], tracks[2]):
        got = by_key[problem.key]
        np.testing.assert_array_equal(got["t"], problem.table.t)
        assert got["plot"] == list(range(len(problem.table)))
        assert np.all(np.isfinite(got["lat_deg"])) and np.all(np.isfinite(got["cov_x_x"]))
        assert 150.0 < np.median(got["speed"]) < 260.0  # flights at 206 and 234 m/s
    assert summary.plots == len(tracks[0].table) + len(tracks[2].table)
    entries = ledger(out)
    assert sorted(e["aircraft"] for e in entries) == ["3C6DD4", "4CA2D1", "TOO-SHORT"]
    assert {e["aircraft"]: e["status"] for e in entries}["TOO-SHORT"] == "failed"
    for e in entries:  # the task thread's CPU time: a solve on a worker, not waiting
        assert 0.0 < e["cpu_s"] <= e["elapsed_s"] + 1e-3
        if e["status"] == "done":  # a waiting thread's is about 1e-3 of it; a solve's 0.4-1
            assert e["cpu_s"] > 0.1 * e["elapsed_s"]  # (0.43 with the other tests' process
            # and both workers on two cores)
    assert pq.read_table(out / "segments.parquet").num_rows > 0


def test_recording_decoded_on_the_cluster(client):
    """ASTERIX decoded in units on the workers equals one decode in this process."""
    data = encode_recording(duration=60.0).data
    whole = read_recording(data, SENSORS)
    parts = read_recording(data, SENSORS, executor=client, chunk_bytes=300)
    for name in ("t", "range_m", "lat_deg", "mode_s", "origin"):
        np.testing.assert_array_equal(getattr(parts.rows, name), getattr(whole.rows, name))
    assert parts.records == whole.records and not parts.problems


def test_a_killed_workers_track_is_retried(tmp_path, tracks, client):
    """The first attempt at one track kills its worker process (os._exit); Dask's nanny
    restarts the worker and the scheduler runs the track again: it comes out done, once."""
    marker = tmp_path / "killed-once"

    def task(key, table, config, limit):
        import os

        from solver.batch import solve_track

        if key == tracks[2].key and not marker.exists():
            marker.write_text(str(os.getpid()))
            os._exit(1)
        return solve_track(key, table, config, limit)

    summary = reconstruct_many([tracks[0], tracks[2]], tmp_path / "out", executor=client,
                               task=task)
    assert marker.exists()
    assert (summary.done, summary.failed) == (2, 0), summary.failures
    states = pq.read_table(tmp_path / "out" / "tracks.parquet")
    assert states["aircraft"].to_pylist().count(tracks[2].key) == len(tracks[2].table)


def test_rerun_resumes_and_every_track_appears_once(tmp_path, tracks):
    out = tmp_path / "out"
    with ThreadPoolExecutor(1) as ex:
        first = reconstruct_many(tracks, out, executor=ex, flush_tracks=1)
    assert (first.done, first.failed) == (2, 1)
    # nothing left to do
    with ThreadPoolExecutor(1) as ex:
        again = reconstruct_many(tracks, out, executor=ex)
    assert (again.tracks, again.skipped, again.done, again.failed) == (3, 3, 0, 0)
    # a run killed after writing its last part but before committing it, mid-line
    entries = ledger(out)
    last_done = next(e for e in reversed(entries) if e["status"] == "done")
    kept = [e for e in entries if e is not last_done]
    (out / PROGRESS).write_text("".join(json.dumps(e) + "\n" for e in kept) + '{"airc')
    foreign = out / "tracks.parquet" / "notes.txt"
    foreign.write_text("not the engine's")
    with ThreadPoolExecutor(1) as ex:
        resumed = reconstruct_many(tracks, out, executor=ex)
    assert (resumed.skipped, resumed.done) == (2, 1)
    assert foreign.exists()  # only the engine's own uncommitted parts are deleted
    foreign.unlink()
    states = pq.read_table(out / "tracks.parquet")
    counts = {k: states["aircraft"].to_pylist().count(k) for k in ("4CA2D1", "3C6DD4")}
    assert counts == {p.key: len(p.table) for p in (tracks[0], tracks[2])}
    assert len(ledger(out)) == 3
    # failed tracks are retried on request only
    with ThreadPoolExecutor(1) as ex:
        retried = reconstruct_many(tracks, out, executor=ex, retry_failed=True)
    assert (retried.skipped, retried.failed) == (2, 1)


def test_deadline_fails_the_track_not_the_run(tmp_path, tracks):
    with ThreadPoolExecutor(1) as ex:
        summary = reconstruct_many(tracks[:1], tmp_path, executor=ex, time_limit_s=1e-6)
    assert summary.failed == 1
    assert summary.failures[tracks[0].key].startswith("DeadlineExceeded")


def test_a_key_given_twice_is_refused(tmp_path, tracks):
    with ThreadPoolExecutor(1) as ex, pytest.raises(ValueError, match="given twice"):
        reconstruct_many([tracks[1], tracks[1]], tmp_path, executor=ex)


def test_scheduler_address_names_an_existing_cluster(tmp_path, tracks, client):
    summary = reconstruct_many(tracks[:1], tmp_path, scheduler=client.scheduler.address)
    assert summary.done == 1
    assert len(client.scheduler_info()["workers"]) == 2  # the cluster is left running


def test_embedded_local_cluster_by_default(tmp_path, tracks, monkeypatch):
    import os

    monkeypatch.setenv("TRAJRECON_COMPILE", "0")
    summary = reconstruct_many(tracks, tmp_path / "out", workers=2, time_limit_s=120.0,
                               task=_task_reporting_pid(tmp_path))
    assert (summary.done, summary.failed) == (2, 1), summary.failures
    seen = [json.loads(p.read_text()) for p in tmp_path.glob("pid-*")]
    assert os.getpid() not in {w["pid"] for w in seen}
    assert len(seen) == 2  # two worker processes did the work
    for w in seen:  # solver.batch.dask_settings reached the workers
        assert w["mmap_threshold"] == str(MMAP_THRESHOLD_BYTES)
        assert w["profile"] is False
        assert w["tick"] == QUIET_LOOPS["distributed.admin.tick.interval"]
        assert w["warmed"] > 0  # solver.batch.warm_workers ran before the worker's first track
        assert w["sigint_ignored"]  # solver.batch.dask_setup: Ctrl-C is the command line's


def _task_reporting_pid(folder):
    """solve_track that leaves a file named by its process id (what its first track found
    there: the settings, and the refinement solvers already built), and takes at least 0.5 s
    so that both workers get tracks."""
    def task(key, table, config, limit):
        import os
        import signal
        import time

        import dask

        from solver.batch import solve_track
        from solver.refine.nlp import block_solver

        report = folder / f"pid-{os.getpid()}"
        if not report.exists():
            report.write_text(json.dumps({
                "pid": os.getpid(), "mmap_threshold": os.environ.get("MALLOC_MMAP_THRESHOLD_"),
                "profile": dask.config.get("distributed.worker.profile.enabled"),
                "tick": dask.config.get("distributed.admin.tick.interval"),
                "warmed": block_solver.cache_info().currsize,
                "sigint_ignored": signal.getsignal(signal.SIGINT) == signal.SIG_IGN}))
        time.sleep(0.5)
        return solve_track(key, table, config, limit)

    return task


def test_outcomes_are_reported_once_committed_and_never_twice(tmp_path, tracks):
    """on_outcome sees an outcome once it is on disk; a run stopped by it (an exception) and
    resumed reports every track exactly once over both runs."""
    reported: list[str] = []

    class Stop(Exception):
        pass

    def stop_after_first(o):
        assert o.key in {e["aircraft"] for e in ledger(tmp_path)}  # committed already
        reported.append(o.key)
        raise Stop

    with ThreadPoolExecutor(1) as ex, pytest.raises(Stop):
        reconstruct_many(tracks, tmp_path, executor=ex, flush_tracks=1, max_in_flight=1,
                         on_outcome=stop_after_first)
    assert len(reported) == 1
    with ThreadPoolExecutor(1) as ex:
        reconstruct_many(tracks, tmp_path, executor=ex, on_outcome=lambda o: reported.append(
            o.key))
    assert sorted(reported) == sorted(p.key for p in tracks)


def test_closing_the_embedded_cluster_mid_track_is_quiet(capfd):
    """A stop (Ctrl-C, SIGTERM) closes the embedded cluster while tracks run: the workers no
    longer log "Async instruction ... ended with CancelledError", one line per running track
    on the operator's terminal (their other warnings stay)."""
    import time

    import dask
    from distributed import Client

    from solver.batch import dask_settings, embedded_cluster

    with dask.config.set(dask_settings()):
        cluster = embedded_cluster(1)
        client = Client(cluster)
        fut = client.submit(time.sleep, 30, pure=False)
        deadline = time.monotonic() + 60
        while not client.processing() or not any(client.processing().values()):
            assert time.monotonic() < deadline
            time.sleep(0.1)
        time.sleep(0.5)  # the task running in the worker's thread
        client.close()
        cluster.close()
    del fut
    err = capfd.readouterr().err
    assert "CancelledError" not in err, err


def test_an_interrupt_before_a_dask_call_starts_logs_no_traceback(caplog):
    """A stop landing in Dask's ``sync`` before its coroutine made its future: Dask's cancel
    callback reads the unassigned future and tornado logged that NameError's traceback (seen
    once in the command line's SIGTERM test). Made deterministic here: the loop is kept busy
    so the coroutine cannot start, and an alarm interrupts the wait. The interrupt still goes
    through; with :func:`solver.batch.quiet_interrupted_sync` nothing is logged."""
    import asyncio
    import logging
    import signal
    import time

    from distributed.utils import LoopRunner, sync

    from solver.batch import quiet_interrupted_sync

    quiet_interrupted_sync()
    runner = LoopRunner(asynchronous=False)
    runner.start()

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        with caplog.at_level(logging.ERROR):
            runner.loop.add_callback(time.sleep, 1.0)  # the coroutine cannot start yet
            signal.setitimer(signal.ITIMER_REAL, 0.1)
            with pytest.raises(KeyboardInterrupt):
                sync(runner.loop, asyncio.sleep, 0.01)
            time.sleep(1.5)  # the loop runs the cancel callback, then the coroutine
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        runner.stop()
    assert not [r for r in caplog.records if r.exc_info], caplog.text


def test_a_filter_that_fails_leaves_the_track_and_says_why(tracks, monkeypatch):
    """--filters: a filter raising anything (here a bug stand-in) keeps the track done with
    the reconstruction's rows and the other filters' rows, its reason among the warnings."""
    import solver.estimation as estimation

    real = estimation.run_filter

    def broken(name, table, *args, **kwargs):
        if name == "singer":
            raise RuntimeError("a bug")
        return real(name, table, *args, **kwargs)

    monkeypatch.setattr(estimation, "run_filter", broken)
    out = solve_track(tracks[0].key, tracks[0].table, filters=("singer", "cv_rts"),
                      times_of_day=True)
    assert out.status == "done" and out.states is not None
    assert "filters.singer: RuntimeError: a bug" in out.warnings
    assert out.filters is not None and set(out.filters.column("filter").to_pylist()) == {
        "cv_rts"}
    assert out.filters.num_rows == len(tracks[0].table)
    tod = np.asarray(out.states.column("time_of_day_s"))
    np.testing.assert_allclose(tod, np.mod(tracks[0].table.t, 86_400.0))


def test_parts_of_an_earlier_version_conform(tmp_path):
    """A run resumed across an upgrade holds parts without the newer columns (the plots'
    residuals, time_of_day_s): the CSV and a job's combined Parquet take both kinds, the
    missing columns null (writing the second kind with the first's schema failed)."""
    from service.jobs import _combine
    from solver.batch import RESIDUAL_COLUMNS, read_part
    from solver.outputs import write_csv_and_geojson

    parts = tmp_path / "tracks.parquet"
    parts.mkdir()
    n = 4
    new = {c: pa.array(np.full(n, 1.0)) for c in TRACK_COLUMNS}
    new.update(aircraft=pa.array(["NEW"] * n), sensor=pa.array(["R1"] * n),
               plot=pa.array(np.arange(n, dtype=np.int32)), gated=pa.array([False] * n),
               wild=pa.array([False] * n), no_reference=pa.array([False] * n),
               lat_deg=pa.array(np.linspace(46, 46.1, n)), lon_deg=pa.array(np.full(n, 14.0)),
               time_utc=pa.array(np.arange(n) * 10**6, pa.int64()).cast(
                   pa.timestamp("us", tz="UTC")))
    old = {k: v for k, v in new.items() if k not in (*RESIDUAL_COLUMNS, "time_of_day_s",
                                                     "time_utc")}
    old["aircraft"] = pa.array(["OLD"] * n)
    pq.write_table(pa.table(old), parts / "part-000001.parquet")
    pq.write_table(pa.table(new), parts / "part-000002.parquet")
    back = read_part(parts / "part-000001.parquet")
    assert tuple(back.column_names) == TRACK_COLUMNS
    assert back.column("gated").type == pa.bool_() and back.column("gated").null_count == n
    assert back.column("range_residual_m").null_count == n
    rows, tracks = write_csv_and_geojson(tmp_path)
    assert (rows, tracks) == (2 * n, 2)
    combined = tmp_path / "combined.parquet"
    _combine(parts, ["part-000001.parquet", "part-000002.parquet"], combined, TRACK_COLUMNS)
    table = pq.read_table(combined)
    assert table.num_rows == 2 * n and table.column("gated").to_pylist() == [None] * n + [
        False] * n
    utc = table.column("time_utc")
    assert utc.type == pa.timestamp("us", tz="UTC") and utc.null_count == n
    with open(tmp_path / "tracks.csv", newline="") as f:
        text = [r["time_utc"] for r in csv.DictReader(f)]
    assert text == [""] * n + [f"1970-01-01T00:00:0{k}.000000Z" for k in range(n)]


def test_a_run_resumed_over_parts_of_before_a_column_keeps_it(tmp_path, tracks):
    """An output directory with a part written before ``source`` existed, resumed: reading
    the directory as one table took the old part's schema and lost ``source`` for every
    row. The old part is rewritten with the column (null: its input places are not known)."""
    out = tmp_path / "out"
    with ThreadPoolExecutor(1) as ex:
        reconstruct_many(tracks[:1], out, executor=ex, flush_tracks=1)
    part = next((out / "tracks.parquet").glob("part-*.parquet"))
    pq.write_table(pq.read_table(part).drop(["source"]), part)  # as the version before
    with ThreadPoolExecutor(1) as ex:
        summary = reconstruct_many([tracks[0], tracks[2]], out, executor=ex, flush_tracks=1)
    assert (summary.done, summary.skipped) == (1, 1)
    table = pq.read_table(out / "tracks.parquet")
    assert tuple(table.column_names) == TRACK_COLUMNS
    source = table.column("source").to_pylist()
    keys = table.column("aircraft").to_pylist()
    assert all(s is None for s, k in zip(source, keys, strict=True) if k == tracks[0].key)
    assert all(s.startswith("byte ") for s, k in zip(source, keys, strict=True)
               if k == tracks[2].key)


def _unpicklable(rec) -> dict:
    """A track's extras Dask cannot send back (a lock pickles in no way)."""
    import threading

    return {"lock": threading.Lock()}


def test_a_result_dask_cannot_send_back_fails_in_one_line(tmp_path, tracks, client, caplog):
    """A tester's track whose result Dask could not pickle (a MemoryError then) failed with
    Dask's 40-line message, a whole traceback, as its reason in summary.json: the reason is
    one line, the whole message (with its traceback) in the log."""
    from functools import partial

    with caplog.at_level("ERROR", logger="solver.batch"):
        summary = reconstruct_many(tracks[:1], tmp_path, executor=client,
                                   task=partial(solve_track, extras=_unpicklable))
    reason = summary.failures[tracks[0].key]
    assert summary.failed == 1 and "\n" not in reason and "Traceback" not in reason
    assert reason.startswith("TypeError: ") and reason.endswith("(the rest in the log)")
    assert [json.loads(line)["error"] for line in (tmp_path / PROGRESS).read_text().splitlines()
            ] == [reason]
    assert any("Traceback" in r.getMessage() and tracks[0].key in r.getMessage()
               for r in caplog.records)


def test_samples_are_capped_by_default(tracks):
    """``solve_track`` without ``max_samples`` kept every sample asked (the command line
    passed none: a 44-min track with ``--samples 0.001`` asked 2.6 M): the shared default
    (:data:`solver.config.MAX_SAMPLES`) keeps none of a track over it, with a warning that
    counts them; under it, every sample is kept."""
    from dataclasses import replace as with_

    from solver.config import MAX_SAMPLES, ReconstructionConfig

    t = tracks[0].table
    span = float(t.t.max() - t.t.min())
    step = span / MAX_SAMPLES  # MAX_SAMPLES + 1 samples
    out = solve_track("A", t, with_(ReconstructionConfig(), sample_step_s=step), samples=True)
    assert out.status == "done" and out.samples is None
    (warning,) = [w for w in out.warnings if w.startswith("samples:")]
    assert f"gives {MAX_SAMPLES + 1} samples" in warning and f"limit is {MAX_SAMPLES}" in warning
    kept = solve_track("A", t, with_(ReconstructionConfig(), sample_step_s=span / 10),
                       samples=True)
    assert kept.samples is not None and kept.samples.num_rows == 11


def test_samples_cap_keeps_exactly_max_samples(tracks):
    """``max_samples`` is the most a track keeps: a step giving exactly that many keeps them,
    one more keeps none (the docs said "that many or more keeps none": a reviewer's)."""
    from dataclasses import replace as with_

    from solver.config import ReconstructionConfig

    t = tracks[0].table
    config = with_(ReconstructionConfig(), sample_step_s=float(t.t.max() - t.t.min()) / 10)
    kept = solve_track("A", t, config, samples=True, max_samples=11)  # 11 samples
    assert kept.samples is not None and kept.samples.num_rows == 11
    over = solve_track("A", t, config, samples=True, max_samples=10)
    assert over.samples is None and any("gives 11 samples" in w for w in over.warnings)
