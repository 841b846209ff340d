"""Durable asynchronous jobs: whole recordings (or many tracks) reconstructed in the background.

Layout of the data directory (``Settings.data_dir``)::

    DATA/jobs.sqlite3              job records and each job's track list (SQLite, WAL)
    DATA/jobs/<id>/inputs/         recording.<ast|csv|parquet>, sensors.json, params.json
    DATA/jobs/<id>/out/            solver.batch's out_dir: tracks.parquet/, segments.parquet/,
                                   progress.jsonl (the commit log of finished tracks),
                                   sensor_stats.jsonl, figure_data.parquet/ (what the
                                   tracks' figures are drawn from), figures/<digest>/<key>.png
                                   (each drawn when first asked for); when done:
                                   tracks.csv, tracks.geojsonl, manoeuvres.csv, warnings.csv,
                                   sensors.json, map.png, problems.txt, summary.json, export/
                                   (single-file downloads)

Durability: an accepted job's inputs are written (and synced) under a temporary name, renamed,
and only then its record is inserted (committed) before the 202; a track is finished exactly
when :func:`solver.batch.reconstruct_many` has written its line to ``progress.jsonl``. On start,
every job left ``queued`` or ``running`` is queued again and rerun on the same ``out/``:
``reconstruct_many`` skips the finished tracks and deletes uncommitted parts, so a restart
loses no accepted job and no finished track and never duplicates one.

Jobs run in threads of this process (``jobs_max_running`` of them), off the event loop; their
tracks are tasks on a Dask cluster (an embedded ``LocalCluster`` started with the first job, or
the scheduler at ``dask_scheduler``), separate from the request solver pool.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import hashlib
import json
import os
import shutil
import sqlite3
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import IO, Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from solver.assessment import write_sensors_figure
from solver.batch import SEGMENT_COLUMNS, TRACK_COLUMNS, TrackOutcome, read_part, reconstruct_many
from solver.config import FILTER_GATE_SIGMA, ReconstructionConfig
from solver.figure_data import TrackFigureData, read_stored
from solver.figures import track_png
from solver.inputs import InputError, format_loc
from solver.io.altitudes import offsets_summary
from solver.io.problems import Problems
from solver.io.reading import Selection, load
from solver.io.split import recording_frame
from solver.io.tables import PlotRows
from solver.outputs import output_state, write_csv_and_geojson, write_manoeuvres, write_map
from solver.run_settings import RunSettings, software
from solver.sensor_stats import SensorStats, write_sensor_csv
from solver.track_task import AssessedTrack, assess_track, track_file_name

from .logs import LOGGER
from .settings import Settings

State = Literal["queued", "running", "done", "failed", "cancelled"]
FINISHED: frozenset[str] = frozenset({"done", "failed", "cancelled"})
ACTIVE: frozenset[str] = frozenset({"queued", "running"})
PARQUET_RESULTS = ("tracks.parquet", "segments.parquet", "filters.parquet", "samples.parquet")
"""Combined into one file each when a job is done (``filters.parquet``: with ``filters``)."""
RESULT_COLUMNS = {"tracks.parquet": TRACK_COLUMNS, "segments.parquet": SEGMENT_COLUMNS}
"""Their columns where a part of an earlier version may lack some (:func:`_combine`)."""
RESULT_FILES = (*PARQUET_RESULTS, "tracks.csv", "tracks.geojsonl", "manoeuvres.csv",
                "warnings.csv", "sensors.json", "sensors.csv", "problems.txt", "summary.json",
                "map.png", "sensors.png", "results.zip")
"""A done job's downloads; ``results.zip`` holds the others, and no track's figure: each is
drawn when first asked for (``GET .../tracks/{key}/figure.png``; zipping them would draw a
figure of each of up to 50,000 tracks, 0.8 s each, the cost lazy drawing saves, and a zip of
the figures drawn so far would change with what clients happened to ask for)."""
PROBLEM_EXAMPLES = 20  # problems listed in a job's status (every kind is counted)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
  id TEXT PRIMARY KEY, kind TEXT NOT NULL, state TEXT NOT NULL, created REAL NOT NULL,
  started REAL, finished REAL, error TEXT, tracks_total INTEGER, plots INTEGER,
  rows INTEGER, problems TEXT, input_bytes INTEGER NOT NULL, runs INTEGER NOT NULL DEFAULT 0);
CREATE TABLE IF NOT EXISTS tracks (
  job TEXT NOT NULL, seq INTEGER NOT NULL, aircraft TEXT NOT NULL, plots INTEGER NOT NULL,
  PRIMARY KEY (job, aircraft));
"""


def default_data_dir() -> Path:
    """``$XDG_STATE_HOME/trajrecon``, else ``~/.local/state/trajrecon``, else
    ``./trajrecon-data`` (no home directory)."""
    state = os.environ.get("XDG_STATE_HOME")
    if state:
        return Path(state) / "trajrecon"
    try:
        return Path.home() / ".local" / "state" / "trajrecon"
    except RuntimeError:
        return Path("trajrecon-data").resolve()


STORE_RETRY_S = 5.0
"""The runner's wait before it tries the store again after a write failed (a full disk)."""


class Full(Exception):
    """No room for another job (running and queued at their limits)."""


class Unavailable(Exception):
    """The job store could not be opened (the message says why)."""


class Aborted(BaseException):
    """A running job was cancelled or the service is stopping. A ``BaseException``, like
    ``KeyboardInterrupt``: ``reconstruct_many`` turns an ``Exception`` of a track's future into
    a failed outcome and commits it, which would keep a resumed run from ever solving the
    track; this one stops the run with nothing more committed."""


@dataclass
class JobRecord:
    """One job's row: state, timing (epoch seconds), counts, problems, failure reason."""

    id: str
    kind: str
    state: State
    created: float
    started: float | None
    finished: float | None
    error: str | None
    tracks_total: int | None
    plots: int | None
    rows: int | None
    problems: dict[str, Any] | None
    input_bytes: int
    runs: int


@dataclass
class Progress:
    """Finished tracks of a job, from its commit log (``progress.jsonl``)."""

    done: int = 0
    failed: int = 0
    plots_done: int = 0
    entries: dict[str, dict[str, Any]] = field(default_factory=dict)


# ------------------------------------------------------------------------------------ store


class JobStore:
    """Job records in SQLite (WAL, synchronous FULL); one connection behind a lock."""

    def __init__(self, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._db.row_factory = sqlite3.Row
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA busy_timeout=5000")
            self._db.executescript(_SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextlib.contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    @staticmethod
    def _record(row: sqlite3.Row) -> JobRecord:
        d = dict(row)
        d["problems"] = json.loads(d["problems"]) if d["problems"] else None
        return JobRecord(**d)

    def insert(self, job_id: str, kind: str, input_bytes: int, capacity: int) -> JobRecord:
        """Insert a queued job unless ``capacity`` jobs are already queued or running."""
        with self._tx() as db:
            (active,) = db.execute("SELECT count(*) FROM jobs WHERE state IN "
                                   "('queued', 'running')").fetchone()
            if active >= capacity:
                raise Full(f"{active} jobs are queued or running (the limit is {capacity})")
            db.execute("INSERT INTO jobs (id, kind, state, created, input_bytes) VALUES "
                       "(?, ?, 'queued', ?, ?)", (job_id, kind, time.time(), input_bytes))
        got = self.get(job_id)
        assert got is not None
        return got

    def active(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT count(*) FROM jobs WHERE state IN "
                                        "('queued', 'running')").fetchone()[0])

    def get(self, job_id: str) -> JobRecord | None:
        with self._lock:
            row = self._db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return None if row is None else self._record(row)

    def recent(self, limit: int, state: str | None = None) -> list[JobRecord]:
        """The ``limit`` newest jobs (of ``state`` when given), newest first."""
        where, args = ("WHERE state = ?", (state,)) if state else ("", ())
        with self._lock:
            rows = self._db.execute(f"SELECT * FROM jobs {where} ORDER BY created DESC, rowid "
                                    "DESC LIMIT ?", (*args, limit)).fetchall()
        return [self._record(r) for r in rows]

    def ids(self) -> set[str]:
        with self._lock:
            return {r[0] for r in self._db.execute("SELECT id FROM jobs")}

    def requeue_unfinished(self) -> list[str]:
        """Jobs a stopped service left running: queued again (resumed in creation order)."""
        with self._tx() as db:
            ids = [r[0] for r in db.execute("SELECT id FROM jobs WHERE state = 'running'")]
            db.execute("UPDATE jobs SET state = 'queued' WHERE state = 'running'")
        return ids

    def claim(self) -> JobRecord | None:
        """The oldest queued job, now running."""
        with self._tx() as db:
            row = db.execute("SELECT id FROM jobs WHERE state = 'queued' ORDER BY created, "
                             "rowid LIMIT 1").fetchone()
            if row is None:
                return None
            db.execute("UPDATE jobs SET state = 'running', started = coalesce(started, ?), "
                       "runs = runs + 1 WHERE id = ?", (time.time(), row[0]))
        return self.get(row[0])

    def set_tracks(self, job_id: str, tracks: list[tuple[str, int]], rows: int,
                   problems: dict[str, Any]) -> None:
        """The job's track list (replaced: a resumed run splits the same recording again)."""
        with self._tx() as db:
            db.execute("DELETE FROM tracks WHERE job = ?", (job_id,))
            db.executemany("INSERT INTO tracks (job, seq, aircraft, plots) VALUES (?, ?, ?, ?)",
                           [(job_id, i, k, n) for i, (k, n) in enumerate(tracks)])
            db.execute("UPDATE jobs SET tracks_total = ?, plots = ?, rows = ?, problems = ? "
                       "WHERE id = ?", (len(tracks), sum(n for _, n in tracks), rows,
                                        json.dumps(problems), job_id))

    def tracks(self, job_id: str, offset: int = 0, limit: int = -1
               ) -> list[tuple[str, int]]:
        """The job's tracks in order (``limit`` -1: all from ``offset``)."""
        with self._lock:
            return [(r[0], r[1]) for r in self._db.execute(
                "SELECT aircraft, plots FROM tracks WHERE job = ? ORDER BY seq LIMIT ? OFFSET ?",
                (job_id, limit, offset))]

    def track(self, job_id: str, aircraft: str) -> int | None:
        with self._lock:
            row = self._db.execute("SELECT plots FROM tracks WHERE job = ? AND aircraft = ?",
                                   (job_id, aircraft)).fetchone()
        return None if row is None else int(row[0])

    def finish(self, job_id: str, state: State, error: str | None = None,
               only_from: frozenset[str] = ACTIVE) -> bool:
        """Move a job to a final state (if it is in ``only_from``); False if it was not."""
        with self._tx() as db:
            cur = db.execute(
                f"UPDATE jobs SET state = ?, finished = ?, error = coalesce(?, error) "
                f"WHERE id = ? AND state IN ({','.join('?' * len(only_from))})",
                (state, time.time(), error, job_id, *sorted(only_from)))
            return cur.rowcount == 1

    def delete(self, job_id: str) -> None:
        with self._tx() as db:
            db.execute("DELETE FROM tracks WHERE job = ?", (job_id,))
            db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))


def _nothing_reconstructed(progress: Progress, problems: Problems) -> str | None:
    """Why a job that ran to its end reconstructed no track (it is ``failed`` then, with its
    outputs kept: the summary, the problems, each track's error), or None if it did one.
    The command line's exit status 2 and 1 in the same cases (:func:`solver.cli.main`)."""
    if progress.done:
        return None
    if not progress.entries:
        first = "; ".join(str(e) for e in list(problems.entries)[:3])
        return ("no aircraft's track could be read from the job's input"
                + (f" ({first})" if first else "") + "; see problems.txt")
    key, entry = next((k, e) for k, e in progress.entries.items() if e["status"] == "failed")
    n = len(progress.entries)
    return (f"{'the' if n == 1 else f'every one of the {n}'} track{'s' * (n > 1)} failed "
            f"({key}: {entry.get('error')}); see /tracks for each track's reason")


# ------------------------------------------------------------------------------- executor


class _DaskPool:
    """A ``concurrent.futures``-style view of a Dask client for one job, so that
    :func:`solver.batch.reconstruct_many` waits on futures this runner can settle: on
    :meth:`abort` every pending future fails at once with :class:`Aborted` (its Dask task is
    cancelled), which stops the run. ``on_result`` sees every result first (on a Dask
    callback thread)."""

    def __init__(self, client: Any, on_result: Callable[[Any], None] | None = None):
        self._client = client
        self._on_result = on_result
        self._max_workers = max(len(client.scheduler_info()["workers"]), 1)
        self._pending: dict[cf.Future[Any], Any] = {}
        self._lock = threading.Lock()
        self.aborted = threading.Event()

    def submit(self, fn: Callable[..., Any], *args: Any) -> cf.Future[Any]:
        f: cf.Future[Any] = cf.Future()
        if self.aborted.is_set():
            f.set_exception(Aborted("the job was stopped"))
            return f
        task = self._client.submit(fn, *args, pure=False)
        with self._lock:
            self._pending[f] = task
        task.add_done_callback(partial(self._settle, f))
        return f

    def _settle(self, f: cf.Future[Any], task: Any) -> None:
        with self._lock:
            if self._pending.pop(f, None) is None:
                return
        try:
            result = task.result()
        except BaseException as e:  # the task's own error, a cancellation, a dead worker
            _set(f, exc=e)
            return
        if self._on_result is not None:
            try:  # before reconstruct_many sees (and commits) it
                self._on_result(result)
            except Exception as e:
                LOGGER.error("job result hook failed", exc_info=e)
        _set(f, result=result)

    def abort(self) -> None:
        self.aborted.set()
        with self._lock:
            pending, self._pending = self._pending, {}
        for f in pending:
            _set(f, exc=Aborted("the job was stopped"))
        if pending:
            with contextlib.suppress(Exception):
                self._client.cancel(list(pending.values()))


def _set(f: cf.Future[Any], result: Any = None, exc: BaseException | None = None) -> None:
    with contextlib.suppress(cf.InvalidStateError):
        if exc is not None:
            f.set_exception(exc)
        else:
            f.set_result(result)


def job_track(key: str, table: Any, config: ReconstructionConfig | None,
              time_limit_s: float | None, figure_data: bool = False,
              times_of_day: bool = False, filters: tuple[str, ...] = (),
              filter_gate: float | None = FILTER_GATE_SIGMA, samples: bool = False,
              max_samples: int | None = None, date: str | None = None) -> AssessedTrack:
    """The per-track task of a job (on a worker): :func:`solver.track_task.assess_track` (with the
    job's ``filters``, samples and recording's ``date``) keeping, with ``figure_data``, what the
    track's figure is drawn from when first asked for (:mod:`service.job_figures`; drawing
    every figure here took 0.8 s a track against 63 ms to solve a three-plot one)."""
    return assess_track(key, table, config, time_limit_s, filters=filters,
                        filter_gate=filter_gate, times_of_day=times_of_day, samples=samples,
                        max_samples=max_samples, figure_data=figure_data, date=date)


def json_sources(rows: PlotRows) -> Callable[[Any], pa.Array]:
    """``tracks.parquet``'s ``source`` for a job of JSON tracks: a plot's place in the body
    (``tracks.A[3]``, as its errors name it) rather than its row in the table the body was
    stored as (written key by key, each track's plots in order, by :mod:`service.routes_jobs`)."""
    keys = rows.aircraft.astype(str)
    order = np.argsort(rows.origin, kind="stable")
    uniq, first = np.unique(keys[order], return_index=True)
    start = dict(zip(uniq.tolist(), rows.origin[order][first].tolist(), strict=True))

    def names(track: Any) -> pa.Array:
        k, o = keys[track.rows], rows.origin[track.rows]
        return pa.array([format_loc(("tracks", key, int(r - start[key])))
                         for key, r in zip(k.tolist(), o.tolist(), strict=True)], pa.string())
    return names


def figure_dir(root: Path, key: str) -> Path:
    """Where a track's figure is drawn: one directory per key (keys that differ only in
    characters a file name cannot hold do not share a figure)."""
    return root / hashlib.sha256(key.encode()).hexdigest()[:24]


# --------------------------------------------------------------------------------- runner


JOBS_EXTRA_NICENESS = 5
"""The embedded cluster's workers run this much nicer than the single-track workers
(``worker_niceness``): a job is background work, and a 500-plot request took 590-665 ms
during one instead of 170 (a tester's; the job workers ran at niceness 0)."""


def _mode_c_offsets(tracks: list[Any]) -> list[float]:
    return [t.pressure_offset_m for t in tracks if t.pressure_offset_m is not None]


class JobRunner:
    """The job store, the background threads that run jobs, and the jobs' read side."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.root = Path(settings.data_dir or default_data_dir())
        self.store: JobStore | None = None
        self.unavailable: str | None = "the job runner is not started"
        self._lock_file: IO[bytes] | None = None
        self._wake = threading.Condition()
        self._stopping = False
        self._threads: list[threading.Thread] = []
        self._running: dict[str, _DaskPool | None] = {}
        self._solving: set[str] = set()  # jobs inside reconstruct_many (writing track parts)
        self._cancelled: set[str] = set()
        self._deleting: set[str] = set()  # finished jobs whose data a DELETE is removing
        self._outputs_due: deque[str] = deque()  # cancelled jobs whose outputs a stop cut
        self._client: Any = None
        self._cluster: Any = None
        self._client_lock = threading.Lock()
        self._progress_cache: dict[str, tuple[tuple[int, int], Progress]] = {}
        self._receiving = 0  # posts being received: places in the queue once accepted
        self._room_lock = threading.Lock()

    # -- life cycle

    @property
    def capacity(self) -> int:
        """Jobs that may be queued or running at once."""
        return self.settings.jobs_max_running + self.settings.jobs_max_queued

    def start(self) -> None:
        """Open the store, queue again the jobs a stopped service left running, drop the
        inputs of posts that never became jobs, start the job threads."""
        try:
            (self.root / "jobs").mkdir(parents=True, exist_ok=True)
            self._lock_file = _lock(self.root / "lock")
            if self._lock_file is None:
                self.unavailable = (f"another service uses the data directory {self.root} "
                                    "(one service per TRAJRECON_DATA_DIR)")
            else:
                self.store = JobStore(self.root / "jobs.sqlite3")
        except (OSError, sqlite3.Error) as e:
            self.unavailable = f"the job store at {self.root} cannot be opened: {e}"
        if self.store is None:  # the service still serves single tracks
            LOGGER.error("jobs unavailable", extra={"fields": {"error": self.unavailable}})
            return
        self.unavailable = None
        resumed = self.store.requeue_unfinished()
        self._outputs_due = deque(j.id for j in reversed(self.store.recent(1 << 62, "cancelled"))
                                  if self._outputs_cut(j.id))
        known = self.store.ids()
        for d in (self.root / "jobs").iterdir():
            if d.name not in known:  # a post interrupted before its 202 (or a deleted job)
                shutil.rmtree(d, ignore_errors=True)
        if resumed:
            LOGGER.info("resuming jobs", extra={"fields": {"jobs": resumed}})
        if self._outputs_due:
            LOGGER.info("writing cancelled jobs' outputs", extra={"fields": {
                "jobs": list(self._outputs_due)}})
        self._stopping = False
        for i in range(self.settings.jobs_max_running):
            t = threading.Thread(target=self._loop, name=f"job-runner-{i}", daemon=True)
            t.start()
            self._threads.append(t)

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the job threads (running jobs stay ``running`` in the store: resumed at the
        next start), then the Dask client and the embedded cluster."""
        with self._wake:
            self._stopping = True
            self._wake.notify_all()
            pools = list(self._running.values())
        for pool in pools:
            if pool is not None:
                pool.abort()
        end = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(max(0.0, end - time.monotonic()))
        self._threads.clear()
        with self._client_lock:
            for thing in (self._client, self._cluster):
                if thing is not None:
                    with contextlib.suppress(Exception):
                        thing.close()
            self._client = self._cluster = None
        if self.store is not None:
            self.store.close()
            self.store = None
        if self._lock_file is not None:
            self._lock_file.close()  # releases the lock
            self._lock_file = None
        self.unavailable = "the service is stopping"

    async def aclose(self) -> None:
        """:meth:`close` off the event loop."""
        import asyncio

        await asyncio.to_thread(self.close)

    def _db(self) -> JobStore:
        if self.store is None:
            raise Unavailable(self.unavailable or "the job store is closed")
        return self.store

    def job_dir(self, job_id: str) -> Path:
        return self.root / "jobs" / job_id

    # -- accepting

    def check_room(self) -> None:
        """Raise :class:`Full` when no job can be accepted now (before reading an upload):
        the jobs queued or running and the posts being received fill the queue."""
        active, receiving = self._db().active(), self._receiving
        if active + receiving >= self.capacity:
            more = f" and {receiving} more are being received" if receiving else ""
            raise Full(f"{active} jobs are queued or running{more} (the limit is "
                       f"{self.capacity})")

    @contextlib.contextmanager
    def receiving(self) -> Iterator[None]:
        """Hold a place in the queue while a post is received and checked (:class:`Full`
        when there is none): the room check counted committed jobs only, so at least 17 JSON
        bodies were received and parsed at once where 17 jobs fit (6 of 30 MB took the
        service from 0.9 to 2.7 GB)."""
        with self._room_lock:
            self.check_room()
            self._receiving += 1
        try:
            yield
        finally:
            with self._room_lock:
                self._receiving -= 1

    def new_inputs(self) -> Path:
        """A fresh directory to write a job's inputs into (see :meth:`accept`)."""
        d = self.root / "jobs" / f".incoming-{uuid.uuid4().hex}"
        (d / "inputs").mkdir(parents=True)
        return d

    def accept(self, incoming: Path, kind: str) -> JobRecord:
        """Make the inputs in ``incoming`` (from :meth:`new_inputs`) a queued job: synced,
        renamed to the job's directory, then the record committed."""
        job_id = uuid.uuid4().hex
        size = 0
        for f in (incoming / "inputs").iterdir():
            size += f.stat().st_size
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
        target = self.job_dir(job_id)
        os.replace(incoming, target)
        _fsync_dir(target.parent)
        try:
            record = self._db().insert(job_id, kind, size, self.capacity)
        except BaseException:
            shutil.rmtree(target, ignore_errors=True)
            raise
        with self._wake:
            self._wake.notify()
        return record

    # -- running

    def _loop(self) -> None:
        while True:
            with self._wake:
                if self._stopping:
                    return
                job_id = self._outputs_due.popleft() if self._outputs_due else None
                if job_id is not None:
                    self._running[job_id] = None  # a DELETE now answers the status
            if job_id is not None:
                try:
                    self._write_cut_outputs(job_id)
                finally:
                    with self._wake:
                        self._running.pop(job_id, None)
                        self._wake.notify_all()
                continue
            with self._wake:
                if self._stopping:
                    return
                try:
                    job = self._db().claim()
                except Exception as e:  # e.g. the disk full: the runner lives on and retries
                    LOGGER.error("job runner could not claim a job", exc_info=e)
                    self._wake.wait(timeout=STORE_RETRY_S)
                    continue
                if job is None:
                    self._wake.wait(timeout=5.0)
                    continue
                self._running[job.id] = None
            try:
                self._run(job)
            except Aborted:  # stopped outside reconstruct_many: resumed (or cancelled)
                pass
            except Exception as e:  # a bug here must not stop the runner
                if self._stopping:  # e.g. the store closed under it: resumed at next start
                    return
                LOGGER.error("job runner error", exc_info=e)
                try:
                    self._db().finish(job.id, "failed", self._public(
                        job.id, f"internal error: {type(e).__name__}: {e}"))
                except Exception as e2:  # the store cannot write either (a full disk): the
                    # job stays running in it, resumed at the next start; the runner goes on
                    LOGGER.error("job runner could not record a failed job", exc_info=e2)
            finally:
                with self._wake:
                    self._running.pop(job.id, None)
                    self._wake.notify_all()

    @property
    def dask_address(self) -> str | None:
        """The scheduler address the jobs' tracks run on (None until the first job)."""
        client = self._client
        return None if client is None else str(client.scheduler.address)

    def _dask(self) -> Any:
        with self._client_lock:
            if self._client is None:
                import dask
                from distributed import Client, LocalCluster

                from solver.batch import dask_settings

                with dask.config.set(dask_settings()):
                    if self.settings.dask_scheduler:
                        self._client = Client(self.settings.dask_scheduler, timeout=30)
                    else:
                        from .dask_plugins import Niceness

                        cluster = LocalCluster(
                            n_workers=self.settings.jobs_workers, threads_per_worker=1,
                            processes=True, dashboard_address=None)
                        try:
                            client = Client(cluster)
                            client.register_plugin(Niceness(min(
                                19, self.settings.worker_niceness + JOBS_EXTRA_NICENESS)))
                        except BaseException:
                            cluster.close()
                            raise
                        self._cluster, self._client = cluster, client  # only once whole
            return self._client

    def _run(self, job: JobRecord) -> None:
        d = self.job_dir(job.id)
        out = d / "out"
        out.mkdir(exist_ok=True)
        redone = self._same_software(job.id, out)
        LOGGER.info("job started", extra={"fields": {"job": job.id, "run": job.runs}})
        began = time.monotonic()
        settings = self.options(job.id)
        try:
            loaded, tracks = self._load(job.id, settings)
            if redone:
                loaded.problems.add("software_changed", "job", f"resumed by other software "
                                    f"(version {software()['version']}, solver sources "
                                    f"changed): its {redone} finished track(s) were redone, "
                                    "so every track is this version's")
        except (InputError, ValueError, OSError, StopIteration) as e:
            reason = self._public(job.id, (
                f"{format_loc(e.loc)} {e.message}" if isinstance(e, InputError)
                else f"the recording could not be read: {type(e).__name__}: {e}"))
            self._db().finish(job.id, "failed", reason)
            LOGGER.info("job failed", extra={"fields": {"job": job.id, "error": reason[:300]}})
            return
        limit = self.settings.jobs_max_tracks
        if len(tracks) > limit:  # a tester's 30,000 three-plot tracks held the slot 6.7 h
            reason = (f"the recording holds {len(tracks)} tracks, more than this service's "
                      f"{limit} a job (TRAJRECON_JOBS_MAX_TRACKS): split it, or choose "
                      "aircraft (options.aircraft)")
            self._db().finish(job.id, "failed", reason)
            LOGGER.info("job failed", extra={"fields": {"job": job.id, "error": reason}})
            return
        self._db().set_tracks(job.id, [(t.key, len(t.table)) for t in tracks],
                              len(loaded.rows), problems_summary(loaded.problems))
        LOGGER.info("job read", extra={"fields": {
            "job": job.id, "rows": len(loaded.rows), "tracks": len(tracks),
            "problems": loaded.problems.total, "read_s": round(time.monotonic() - began, 3)}})
        if not len(loaded.rows):  # nothing of it is a plot: not a recording this reads
            first = "; ".join(str(e) for e in list(loaded.problems.entries)[:3])
            reason = "no plot could be read from the recording" + (f" ({first})" if first
                                                                     else "")
            # what was read is there to see, as for a job that ran to its end (all of it:
            # the status shows a few examples)
            (out / "problems.txt").write_text(loaded.problems.summary() + "\n",
                                              encoding="utf-8")
            _write_whole(out / "summary.json", json.dumps({
                "tracks": 0, "done": 0, "failed": 0, "plots": 0, "rows_in_recording": 0,
                "problems": dict(loaded.problems.counts), "failures": {},
                "error": self._public(job.id, reason)}, indent=1) + "\n")
            self._db().finish(job.id, "failed", self._public(job.id, reason))
            return
        if self._stop_requested(job.id):
            return
        config = settings.config()
        stats_path = out / "sensor_stats.jsonl"
        stats_lock = threading.Lock()

        def record_stats(o: Any) -> None:
            """Before the track is committed: a track redone after a kill writes its line
            again, and the last line of a key wins (:func:`_sensor_reports`)."""
            if isinstance(o, AssessedTrack) and o.status == "done" and o.sensors:
                line = json.dumps({"aircraft": o.key, "sensors": o.sensors}) + "\n"
                with stats_lock, open(stats_path, "a", encoding="utf-8") as f:
                    f.write(line)

        pool = _DaskPool(self._dask(), on_result=record_stats)
        LOGGER.info("job submitting", extra={"fields": {
            "job": job.id, "seconds": round(time.monotonic() - began, 3)}})
        with self._wake:
            self._running[job.id] = pool
            self._solving.add(job.id)

        def on_outcome(o: TrackOutcome) -> None:
            if pool.aborted.is_set():
                raise Aborted("stopped")

        s = self.settings
        try:
            if self._stop_requested(job.id):
                return
            batch = reconstruct_many(
                tracks, out, config=config, executor=pool,
                time_limit_s=s.jobs_track_time_limit_s or None, flush_tracks=8, flush_s=1.0,
                on_outcome=on_outcome,
                task=partial(job_track, figure_data=s.jobs_track_figures,
                             times_of_day=loaded.times_of_day, date=loaded.date,
                             filters=settings.filters, filter_gate=settings.filter_gate_sigma,
                             samples=settings.sample_step_s is not None,
                             max_samples=s.max_samples),
                sources=json_sources(loaded.rows) if job.kind == "tracks" else None)
        except Aborted:
            LOGGER.info("job stopped", extra={"fields": {"job": job.id}})
            self._stopped_solving(job.id)  # before the outputs: DELETE answers now
            self._finish_cancelled(job.id, loaded, tracks)
            return
        finally:
            self._stopped_solving(job.id)
        if self._stop_requested(job.id):
            self._finish_cancelled(job.id, loaded, tracks)
            return
        solved = time.monotonic()
        self._finish_outputs(job.id, loaded, _mode_c_offsets(tracks),
                             rates=(began, batch.elapsed_s, batch.plots_per_s))
        reason = _nothing_reconstructed(self.progress(job.id), loaded.problems)
        self._db().finish(job.id, "failed" if reason else "done", reason)
        LOGGER.info("job failed" if reason else "job done", extra={"fields": {
            "job": job.id, "seconds": round(time.monotonic() - began, 3),
            "outputs_s": round(time.monotonic() - solved, 3),
            **({"error": reason[:300]} if reason else {})}})

    def _load(self, job_id: str, settings: RunSettings) -> tuple[Any, list[Any]]:
        """The job's recording read and split, and its chosen tracks (an aircraft asked for
        and not found is a problem of the recording's)."""
        d = self.job_dir(job_id)
        recording = next((d / "inputs").glob("recording.*"))
        try:
            loaded = load(recording, d / "inputs" / "sensors.json",
                          max_speed=settings.config().bounds.v[1],
                          editions=settings.asterix_editions(), date=settings.date)
        except InputError as e:  # the job's date is its option
            if e.loc != ("date",):
                raise
            raise InputError(("options", "date"), e.message) from None
        chosen = Selection(self.aircraft(job_id))
        tracks = list(chosen.filter(loaded.tracks))
        for key in chosen.missing():
            loaded.problems.add("aircraft_not_found", "options.aircraft",
                                f"{key} is not in the recording (or its track is too "
                                "short: see short_track)")
        return loaded, tracks

    def _same_software(self, job_id: str, out: Path) -> int:
        """Keep ``out/software.json`` (:func:`solver.run_settings.software`); a job resumed by
        other software (the service upgraded while it ran) has its finished tracks removed,
        to be redone: two versions' tracks in one job differed by up to 8.7 m (a walkthrough
        helper, the command line's reruns; a review helper found the service's resume
        unchecked). Returns how many were removed."""
        now = software()
        path = out / "software.json"
        try:
            before = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            before = None
        done = len(self.progress(job_id).entries)
        if before != now and done:
            LOGGER.info("job resumed by other software: finished tracks redone", extra={
                "fields": {"job": job_id, "tracks": done}})
            shutil.rmtree(out)
            out.mkdir()
            self._progress_cache.pop(job_id, None)
        if before != now or not path.is_file():
            tmp = out / ".software.json.tmp"
            tmp.write_text(json.dumps(now) + "\n", encoding="utf-8")
            os.replace(tmp, path)
        return done if before != now else 0

    def _public(self, job_id: str, reason: str) -> str:
        """A failed job's ``reason`` without this server's paths (a reader's message may hold
        them): the job's inputs by their names (``recording.parquet``), other files relative
        to the job's or the data directory."""
        d = self.job_dir(job_id)
        for prefix in (d / "inputs", d, self.root):
            reason = reason.replace(f"{prefix}{os.sep}", "")
        return reason

    def _stop_requested(self, job_id: str) -> bool:
        return self._stopping or job_id in self._cancelled

    def _stopped_solving(self, job_id: str) -> None:
        """The job's thread writes no more track parts (:meth:`cancel` waits for this)."""
        with self._wake:
            self._solving.discard(job_id)
            self._wake.notify_all()

    def _finish_cancelled(self, job_id: str, loaded: Any, tracks: list[Any]) -> None:
        """A cancelled job's whole-job outputs of the tracks it finished (a walkthrough
        helper's cancelled job had 21 finished tracks readable only one by one, its map,
        sensors and results 409); not for a job stopped by the service's stop (it resumes).
        A service stopping just after a DELETE (which no longer waits for these outputs) writes
        them still, within :meth:`close`'s wait for the job threads."""
        if job_id not in self._cancelled or not self.progress(job_id).entries:
            return
        try:
            self._finish_outputs(job_id, loaded, _mode_c_offsets(tracks), cancelled=True)
        except Exception:  # the finished tracks stay readable one by one
            LOGGER.exception("cancelled job's outputs failed", extra={"fields": {
                "job": job_id}})

    def _outputs_cut(self, job_id: str) -> bool:
        """Whether a cancelled job finished tracks but has no whole-job outputs: the service
        was killed after the DELETE and before they were written (its results were 409 for
        good; the summary is written last, whole). A ledger that cannot be read is logged and
        passed over (the service still starts)."""
        try:
            return (not (self.job_dir(job_id) / "out" / "summary.json").is_file()
                    and bool(self.progress(job_id).entries))
        except Exception:
            LOGGER.exception("cancelled job's ledger unreadable", extra={"fields": {
                "job": job_id}})
            return False

    def _write_cut_outputs(self, job_id: str) -> None:
        """The whole-job outputs of a cancelled job whose service was killed before it wrote
        them (:meth:`_outputs_cut`), from its inputs and finished tracks."""
        try:
            if self.get(job_id) is None:  # deleted before its turn
                return
            loaded, tracks = self._load(job_id, self.options(job_id))
            self._finish_outputs(job_id, loaded, _mode_c_offsets(tracks), cancelled=True)
            LOGGER.info("cancelled job's outputs written", extra={"fields": {"job": job_id}})
        except Exception:  # e.g. deleted meanwhile: the finished tracks stay readable
            LOGGER.exception("cancelled job's outputs failed", extra={"fields": {
                "job": job_id}})

    def _finish_outputs(self, job_id: str, loaded: Any, mode_c_offsets: list[float],
                        cancelled: bool = False,
                        rates: tuple[float, float, float] | None = None) -> None:
        """The command line's whole-recording outputs (CSV, GeoJSON lines, map:
        :mod:`solver.outputs`; sensors' statistics: :mod:`solver.sensor_stats`; problems,
        summary) and single-file Parquet downloads; of the tracks finished when ``cancelled``
        (the summary says so). ``rates``: this run's start (``time.monotonic``), its
        reconstruction's seconds and plots per second, for the summary's ``elapsed_s``,
        ``reconstruct_s`` and ``plots_per_s`` as the command line's (this run's: a resumed
        job's rate is of the tracks it reconstructed after the restart; none for a cancelled
        job, whose reconstruction did not run to its end)."""
        out = self.job_dir(job_id) / "out"
        stats = SensorStats(loaded.sensors, loaded.scan_periods)
        for reports in _sensor_reports(out).values():
            stats.add(reports)
        sensor_rows = stats.rows()
        (out / "sensors.json").write_text(json.dumps(sensor_rows, indent=1) + "\n",
                                          encoding="utf-8")
        write_sensor_csv(out, sensor_rows)  # as the command line's outputs (a walkthrough)
        csv_rows, geo_tracks = write_csv_and_geojson(out)
        frame = recording_frame(loaded.sensors, loaded.rows)
        manoeuvres = write_manoeuvres(out, frame, loaded.date)
        write_map(out, loaded.sensors, frame=frame)
        write_sensors_figure(out, [s.id for s in loaded.sensors.sensors])
        (out / "problems.txt").write_text(loaded.problems.summary() + "\n", encoding="utf-8")
        export = out / "export"
        export.mkdir(exist_ok=True)
        progress = self.progress(job_id)
        for name in PARQUET_RESULTS:
            _combine(out / name, _committed_parts(progress), export / name,
                     RESULT_COLUMNS.get(name))
        record = self._db().get(job_id)
        settings = self.options(job_id)
        summary = {"tracks": len(progress.entries), "done": progress.done,
                   "failed": progress.failed, "plots": progress.plots_done,
                   "rows_in_recording": len(loaded.rows), "recording_date": loaded.date,
                   **({} if rates is None else {
                       "elapsed_s": time.monotonic() - rates[0], "reconstruct_s": rates[1],
                       "plots_per_s": rates[2]}),
                   "problems": dict(loaded.problems.counts),
                   "dropped": loaded.problems.left_out(),
                   "mode_c_offsets": offsets_summary(mode_c_offsets),
                   "failures": {k: e["error"] for k, e in progress.entries.items()
                                if e["status"] == "failed"},
                   "runs": record.runs if record else None, **settings.as_json(),
                   "csv_rows": csv_rows, "geojson_tracks": geo_tracks, "manoeuvres": manoeuvres,
                   "sensors": sensor_rows}
        if cancelled:
            summary.update(cancelled=True, not_reconstructed=len(self.tracks(job_id))
                           - len(progress.entries))
        warned = output_state(out)  # and warnings.csv: every track's warnings
        summary.update(tracks_with_warnings=warned["tracks_with_warnings"],
                       warnings=warned["warnings"])
        _write_whole(out / "summary.json", json.dumps(summary, indent=1) + "\n")

    # -- cancelling and deleting

    def cancel(self, job_id: str, wait_s: float = 0.5) -> JobRecord | None:
        """Cancel a queued or running job (its finished tracks stay readable), waiting up to
        ``wait_s`` for it to stop writing tracks (its pending tracks fail at once, so this
        takes milliseconds: the answer's counts are final); delete a finished job with its
        data. None: no such job (or deleted now).
        The cancelled job's thread then writes the whole-job outputs of its finished tracks in
        the background (1.4-2.4 s measured for 6 tracks of 300 s, which DELETE waited for:
        a tester's client timed out), and lets go of the job (a DELETE meanwhile answers its
        status, not 204)."""
        db = self._db()
        job = db.get(job_id)
        if job is None:
            return None
        if job.state in FINISHED:
            with self._wake:
                if job_id in self._running:  # its thread is still winding down
                    return job
                self._deleting.add(job_id)  # no longer found by reads (they raced its files)
                if job_id in self._outputs_due:  # its cut outputs are not written after all
                    self._outputs_due.remove(job_id)
            try:
                # the data first: on a full disk that frees the room the store needs to delete
                # the row (a DELETE again finishes what a failed one began)
                shutil.rmtree(self.job_dir(job_id), ignore_errors=True)
                self._progress_cache.pop(job_id, None)
                db.delete(job_id)
            finally:
                with self._wake:
                    self._deleting.discard(job_id)
            return None
        with self._wake:
            self._cancelled.add(job_id)
            pool = self._running.get(job_id)
        db.finish(job_id, "cancelled", "cancelled by DELETE /v1/jobs/{id}")
        if pool is not None:
            pool.abort()
        with self._wake:  # until its thread writes no more parts (not the outputs after)
            self._wake.wait_for(lambda: job_id not in self._solving, timeout=wait_s)
        return db.get(job_id)

    # -- reading

    def get(self, job_id: str) -> JobRecord | None:
        """The job, or None where there is none or a DELETE is removing it."""
        return None if job_id in self._deleting else self._db().get(job_id)

    def recent(self, limit: int, state: str | None = None) -> list[JobRecord]:
        return self._db().recent(limit, state)

    def progress(self, job_id: str) -> Progress:
        """The job's finished tracks from its commit log (cached on the file's size and
        modification time)."""
        path = self.job_dir(job_id) / "out" / "progress.jsonl"
        try:
            st = path.stat()
        except FileNotFoundError:
            return Progress()
        stamp = (st.st_size, st.st_mtime_ns)
        cached = self._progress_cache.get(job_id)
        if cached is not None and cached[0] == stamp:
            return cached[1]
        p = Progress()
        for line in path.read_bytes().split(b"\n"):
            try:
                entry = json.loads(line)
            except ValueError:  # a torn last line (it is redone on resume)
                continue
            p.entries[entry["aircraft"]] = entry
        for e in p.entries.values():
            if e["status"] == "done":
                p.done += 1
                p.plots_done += int(e.get("plots") or 0)
            else:
                p.failed += 1
        self._progress_cache[job_id] = (stamp, p)
        return p

    def aircraft(self, job_id: str) -> list[str] | None:
        """The aircraft the job asked for (``params.json``; None: every aircraft)."""
        doc = _read_json(self.job_dir(job_id) / "inputs" / "params.json") or {}
        return doc.get("aircraft") or None

    def options(self, job_id: str) -> RunSettings:
        """The job's bounds and filters (``inputs/params.json``; a job accepted before they
        were stored, or by an earlier version without filters: the defaults)."""
        return RunSettings.from_json(
            _read_json(self.job_dir(job_id) / "inputs" / "params.json") or {})

    def tracks(self, job_id: str, offset: int = 0, limit: int = -1) -> list[tuple[str, int]]:
        return self._db().tracks(job_id, offset, limit)

    def track_plots(self, job_id: str, aircraft: str) -> int | None:
        return self._db().track(job_id, aircraft)

    def track_keys(self, job_id: str, aircraft: str) -> list[str]:
        """``[aircraft]`` when the job has that track, else its keys equal to it but for case
        (``4ca2d1`` is the Mode S address ``4CA2D1``), in track order."""
        if self.track_plots(job_id, aircraft) is not None:
            return [aircraft]
        folded = aircraft.casefold()
        return [k for k, _ in self.tracks(job_id) if k.casefold() == folded]

    def track_rows(self, job_id: str, aircraft: str, samples: bool = True
                   ) -> tuple[pa.Table, pa.Table, pa.Table | None, pa.Table | None] | None:
        """A finished track's states, segments, filters' states and samples (each None when
        the job has none, the samples when not asked for), from its committed part; None when
        it is not done."""
        entry = self.progress(job_id).entries.get(aircraft)
        if entry is None or entry["status"] != "done" or not entry.get("part"):
            return None
        out = self.job_dir(job_id) / "out"
        flt = pa.compute.field("aircraft") == aircraft
        states = pq.read_table(out / "tracks.parquet" / entry["part"], filters=flt)
        segments = pq.read_table(out / "segments.parquet" / entry["part"], filters=flt)

        def optional(name: str) -> pa.Table | None:
            path = out / name / entry["part"]
            return pq.read_table(path, filters=flt) if path.is_file() else None

        return (states, segments, optional("filters.parquet"),
                optional("samples.parquet") if samples else None)

    def track_sensors(self, job_id: str, aircraft: str) -> list[dict[str, Any]]:
        return _sensor_reports(self.job_dir(job_id) / "out").get(aircraft, [])

    def figure(self, job_id: str, aircraft: str) -> Path | None:
        """The track's figure once drawn (:meth:`draw_figure`, or on the worker by an earlier
        version), else None."""
        d = figure_dir(self.job_dir(job_id) / "out" / "figures", aircraft)
        return next(iter(sorted(d.glob("*.png"))), None) if d.is_dir() else None

    def figure_data(self, job_id: str, aircraft: str
                    ) -> tuple[TrackFigureData, bool, str | None] | None:
        """A done track's figure's content, whether its times are of the day and their date
        (:func:`solver.figure_data.read_stored`); None when the job kept none for it (its
        figures were off); ``FileNotFoundError`` when the job was deleted (its data gone read
        as none kept: the wrong 404)."""
        entry = self.progress(job_id).entries.get(aircraft)
        if entry is None or entry["status"] != "done" or not entry.get("part"):
            if self.get(job_id) is None:
                raise FileNotFoundError(f"job {job_id} was deleted")
            return None
        return read_stored(self.job_dir(job_id) / "out", entry["part"], aircraft)

    def draw_figure(self, job_id: str, aircraft: str) -> Path | None:
        """Draw a done track's figure from what the job stored (:meth:`figure_data`; None when
        it kept nothing for it) and keep it where :meth:`figure` finds it, written whole under
        a temporary name and renamed. The job's ``out/`` is never made again: a job deleted
        meanwhile raises ``FileNotFoundError`` (answered 404) and leaves nothing behind."""
        began = time.perf_counter()  # solver.figures is imported with this module (0.32 s
        # at start-up, not in the first figure's answer)
        got = self.figure_data(job_id, aircraft)
        if got is None:
            return None
        data, times_of_day, date = got
        image = track_png(data, title=aircraft, times_of_day=times_of_day, date=date)
        figures = self.job_dir(job_id) / "out" / "figures"
        with contextlib.suppress(FileExistsError):
            figures.mkdir()  # not its parents: out/ of a deleted job stays gone
        d = figure_dir(figures, aircraft)
        d.mkdir(exist_ok=True)
        path = d / f"{track_file_name(aircraft)}.png"
        tmp = d / f".{uuid.uuid4().hex}.tmp"
        try:
            tmp.write_bytes(image)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        if self.get(job_id) is None:  # deleted while drawn: its rmtree may have missed it
            shutil.rmtree(self.job_dir(job_id), ignore_errors=True)
            raise FileNotFoundError(f"job {job_id} was deleted")
        LOGGER.info("track figure drawn", extra={"fields": {
            "job": job_id, "track": aircraft, "plots": len(data), "bytes": len(image),
            "ms": round(1e3 * (time.perf_counter() - began), 1)}})
        return path

    def result_file(self, job_id: str, name: str) -> Path | None:
        """A finished job's download (``RESULT_FILES``); the zip is built on first use."""
        out = self.job_dir(job_id) / "out"
        if name in PARQUET_RESULTS:
            path = out / "export" / name
        elif name == "results.zip":
            path = out / "export" / "results.zip"
            if not path.exists():
                # a job that read no plot has no export/ yet (its zip was a 500 every time:
                # a hostile-client tester's); a deleted job's out/ is not made again
                path.parent.mkdir(exist_ok=True)
                _zip(out, path)
        else:
            path = out / name
        return path if path.is_file() else None


# ---------------------------------------------------------------------------------- helpers


def problems_summary(problems: Any) -> dict[str, Any]:
    """Counts by kind, their total, and the first examples (each locating its problem)."""
    return {"total": problems.total, "counts": dict(problems.counts),
            "dropped": problems.left_out(),
            "examples": [str(p) for p in list(problems.entries)[:PROBLEM_EXAMPLES]]}


def _sensor_reports(out: Path) -> dict[str, list[dict[str, Any]]]:
    """Per-track sensor statistics (the last line of a key wins: a redone track's)."""
    path = out / "sensor_stats.jsonl"
    reports: dict[str, list[dict[str, Any]]] = {}
    if path.exists():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            reports[entry["aircraft"]] = entry["sensors"]
    return reports


def _committed_parts(progress: Progress) -> list[str]:
    return sorted({e["part"] for e in progress.entries.values() if e.get("part")})


def _combine(parts_dir: Path, parts: list[str], target: Path,
             columns: Sequence[str] | None = None) -> None:
    """One Parquet file of the committed parts, written part by part (memory bounded); a
    part without rows here (``filters.parquet`` of tracks whose filters all failed) is
    skipped, and nothing is written when no part has any. ``columns``: every part read with
    exactly these (:func:`solver.batch.read_part`: parts of an earlier version conform)."""
    tmp = target.with_suffix(".tmp")
    writer: pq.ParquetWriter | None = None
    for name in parts:
        if not (parts_dir / name).is_file():
            continue
        table = (pq.read_table(parts_dir / name) if columns is None
                 else read_part(parts_dir / name, columns))
        if writer is None:
            writer = pq.ParquetWriter(tmp, table.schema)
        writer.write_table(table)
    if writer is None:
        return
    writer.close()
    os.replace(tmp, target)


def _zip(out: Path, target: Path) -> None:
    import zipfile

    tmp = target.with_name(f".{uuid.uuid4().hex}.tmp")  # two requests may build it at once
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for name in RESULT_FILES:
            src = out / "export" / name if name.endswith(".parquet") else out / name
            if name != "results.zip" and src.is_file():
                z.write(src, name)
    os.replace(tmp, target)


def _lock(path: Path) -> IO[bytes] | None:
    """An exclusive lock on ``path`` held while the returned file is open (released by the
    kernel when the process dies, SIGKILL included); None: another process holds it."""
    import fcntl

    f = open(path, "ab")  # held open for the service's life
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        return None
    return f


def _write_whole(path: Path, text: str) -> None:
    """``text`` written to ``path`` whole or not at all (a kill mid-write leaves the old file
    or none): a job's summary.json says its whole-job results are there."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
