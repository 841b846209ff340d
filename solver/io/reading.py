"""A recording read for a run (the command line's, a service job's): the sensor file and the
recording (by suffix: a plot table, else raw ASTERIX, IOSS/FINAL or a pcap/pcapng capture),
split into aircraft, whole (:func:`load`) or in parts as it is read (:func:`stream`: memory
holds the aircraft in the air, not the recording's rows); the checks that refuse a file that
is no recording before anything starts (:func:`check_recording`, :func:`check_recording_head`);
and the aircraft chosen of it (:class:`Selection`).
"""

from __future__ import annotations

import queue
import re
import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..frames import LocalFrame
from ..inputs import InputError
from .asterix import iter_recording, looks_like_recording, read_recording
from .asterix import time_disorder_s as asterix_time_disorder_s
from .dates import resolve_date
from .problems import Problems
from .sensors_file import SensorSet, load_sensors
from .split import (
    DISORDER_S,
    MAX_SPEED_MS,
    AircraftTrack,
    recording_frame,
    split_aircraft,
    split_stream,
)
from .tables import PlotRows, counts_from_midnight, iter_table, read_table, time_disorder_s

TABLE_SUFFIXES = (".csv", ".parquet", ".pq")
STREAM_CHUNK_BYTES = 1 << 18  # ASTERIX decoded in units of this size when streaming
RECORDING_HEAD_BYTES = (1 << 16) + 3  # the longest data block and the next one's header
STREAM_BATCH_ROWS = 1 << 15  # a plot table read in batches of this many rows when streaming
READ_AHEAD_TRACKS = 64  # complete tracks the reading thread may hold ahead of the cluster


@dataclass
class Loaded:
    """A recording read and split: tracks (lazily), problems, sensors, rows."""

    sensors: SensorSet
    rows: PlotRows
    problems: Problems
    tracks: Iterator[AircraftTrack]
    scan_periods: dict[str, float]
    times_of_day: bool = False  # t counts from a UTC midnight (counts_from_midnight)
    date: str | None = None  # the UTC date of that midnight (recording_date)


def recording_date(rows: PlotRows, given: str | None, times_of_day: bool,
                   problems: Problems | None = None) -> str | None:
    """The UTC date of the midnight ``t`` counts from (:func:`solver.io.dates.resolve_date`):
    ``given`` (``--date``, a job's ``options.date``), else the recording's own (``rows.date``:
    a capture's packet times, a table's ``timestamp``). A given date overrides a capture's
    (``date_override`` in ``problems``); :class:`InputError` at ``date`` when it contradicts a
    table's ``timestamp``, or is given for times that do not count from a midnight (a table's
    own ``t``, any epoch)."""
    if given is not None and not times_of_day and rows.date is None and len(rows):
        raise InputError(("date",), f"{given} cannot place the recording's times: its `t` "
                         "counts from no UTC midnight (a table's own t, any epoch): give the "
                         "table a time_of_day_s or a timestamp column, or leave the date out")
    table = rows.origin_unit == "row"
    what = "from its timestamp column" if table else "from its capture's packet times"
    return resolve_date(rows.date, given, what, clock=not table, problems=problems)


def load(recording: Path, sensors_path: Path, max_speed: float = MAX_SPEED_MS, *,
         editions: Mapping[int, Any] | None = None, date: str | None = None) -> Loaded:
    """Read the sensor file and the whole recording (by suffix: a table, else ASTERIX/pcap)
    into memory; :func:`stream` reads it in parts instead. ``max_speed``: the run's fastest
    ground speed (m/s), by which a key's plots are told apart into aircraft; ``editions``:
    the ASTERIX editions (:func:`solver.io.asterix.read_recording`; None: the defaults);
    ``date``: the date given for it (:func:`recording_date`)."""
    sensors = load_sensors(sensors_path)
    periods: dict[str, float] = {}
    if recording.suffix.lower() in TABLE_SUFFIXES:
        rows, problems = read_table(recording)
    else:
        rec = read_recording(recording, sensors, editions=editions)
        rows, problems = rec.rows, rec.problems
        periods = {sid: st.rotation_period_s for sid, st in rec.service.items()
                   if st.rotation_period_s}
    times_of_day = counts_from_midnight(rows)
    day = recording_date(rows, date, times_of_day, problems)
    frame = recording_frame(sensors, rows)
    tracks = split_aircraft(rows, sensors, reference=frame, problems=problems,
                            max_speed=max_speed)
    return Loaded(sensors, rows, problems, tracks, periods, times_of_day, day)


@dataclass
class Streamed:
    """A recording read in parts and split as it is read: ``tracks`` yields each aircraft
    once no later plot can change it (:func:`solver.io.split.split_stream`); the other
    fields fill as the reading goes and are complete once ``tracks`` is exhausted: the
    problems, the rows read, the radars' rotation periods (CAT034 I041) and the recording's
    plane. ``times_of_day``: whether ``t`` counts from a UTC midnight (ASTERIX; a table by
    :func:`solver.io.tables.counts_from_midnight` of its first rows); ``date``: the UTC
    date of that midnight (:func:`recording_date` of the first rows and ``given_date``)."""

    sensors: SensorSet
    problems: Problems
    tracks: Iterator[AircraftTrack]
    scan_periods: dict[str, float] = field(default_factory=dict)
    rows_read: int = 0
    frame: LocalFrame | None = None
    times_of_day: bool | None = None
    mode_c_offsets: list[float] = field(default_factory=list)  # per track whose Mode C moved
    given_date: str | None = None
    date: str | None = None

    def _note(self, rows: PlotRows) -> PlotRows:
        first = self.rows_read == 0 and len(rows) > 0
        self.rows_read += len(rows)
        if self.times_of_day is None and len(rows):
            self.times_of_day = counts_from_midnight(rows)
        if first:  # before any track of them is taken
            self.date = recording_date(rows, self.given_date, bool(self.times_of_day),
                                       self.problems)
        if self.frame is None:  # as split_stream: the first part that gives one
            self.frame = recording_frame(self.sensors, rows)
        return rows


def stream(recording: Path, sensors_path: Path, *, read_ahead: int = READ_AHEAD_TRACKS,
           executor: Any = None, max_speed: float = MAX_SPEED_MS,
           editions: Mapping[int, Any] | None = None, date: str | None = None) -> Streamed:
    """The sensor file read and the recording opened for :func:`solver.io.split.split_stream`
    (by suffix: a table read in batches, else ASTERIX/pcap decoded in units): memory holds
    the aircraft in the air, not the recording's rows. A thread reads, decodes and splits up
    to ``read_ahead`` complete tracks ahead of their consumer (so the decoding overlaps the
    reconstruction); with ``executor`` (a Dask client) ASTERIX units are decoded on it
    (:func:`solver.io.asterix.iter_recording`). What makes the whole input unusable (a
    sensor file or table header it cannot use, a capture of a link type not read) raises
    here, before any track is taken. ``editions``: the ASTERIX editions
    (:func:`solver.io.asterix.read_recording`; None: the defaults); ``date``: the date given
    for it (:func:`recording_date`, checked on the first rows: a table's timestamps it
    contradicts raise here)."""
    sensors = load_sensors(sensors_path)
    out = Streamed(sensors, Problems(), iter(()), given_date=date, date=date)
    parts = _row_parts(recording, out, executor, editions)
    # read up to the first part with rows (those before hold none): the whole input's errors
    # raise now, a date it contradicts too, and the tracks' date is known before the first
    first = None
    try:
        first = next((part for part in parts if len(part)), None)
    except InputError as e:
        raise InputError(e.loc, f"{e.message} (in {recording})") from None

    def rows() -> Iterator[PlotRows]:
        if first is not None:
            yield first
        yield from parts

    def noted(tracks: Iterator[AircraftTrack]) -> Iterator[AircraftTrack]:
        for track in tracks:
            if track.pressure_offset_m is not None:
                out.mode_c_offsets.append(track.pressure_offset_m)
            yield track

    out.tracks = _read_ahead(noted(split_stream(rows(), sensors, problems=out.problems,
                                                max_speed=max_speed)), read_ahead)
    return out


def _row_parts(recording: Path, out: Streamed, executor: Any = None,
               editions: Mapping[int, Any] | None = None) -> Iterator[PlotRows]:
    if recording.suffix.lower() in TABLE_SUFFIXES:
        back = time_disorder_s(recording)
        if back <= DISORDER_S:
            for rows in iter_table(recording, batch_rows=STREAM_BATCH_ROWS,
                                   problems=out.problems):
                yield out._note(rows)
            return
        # rows by aircraft or by sensor: split in batches, an aircraft would be closed at a
        # batch's end and its later rows start a new track (60 aircraft became 70)
        rows, _ = read_table(recording, problems=out.problems)
        yield from _sorted_parts(rows, out, "unordered_table", f"rows up to {back:.0f} s",
                                 "a table")
        return
    with open(recording, "rb") as f:
        check_recording_head(f.read(RECORDING_HEAD_BYTES))
    out.times_of_day = True  # ASTERIX: times of day, t from the midnight before the first
    back = asterix_time_disorder_s(recording, out.sensors, editions=editions)
    if back > DISORDER_S:  # e.g. two recordings concatenated: read whole, sorted
        rec = read_recording(recording, out.sensors, executor=executor, editions=editions,
                             chunk_bytes=STREAM_CHUNK_BYTES)
        out.problems.extend(rec.problems)
        out.scan_periods.update({sid: st.rotation_period_s for sid, st in rec.service.items()
                                 if st.rotation_period_s})
        yield from _sorted_parts(rec.rows, out, "unordered_recording",
                                 f"reports {back:.0f} s or more", "a recording")
        return
    for part in iter_recording(recording, out.sensors, chunk_bytes=STREAM_CHUNK_BYTES,
                               executor=executor, editions=editions):
        out.problems.extend(part.problems)
        for sid, st in part.service.items():
            if st.rotation_period_s:
                out.scan_periods[sid] = st.rotation_period_s
        yield out._note(part.rows)


def check_recording(recording: Path) -> None:
    """Raise :class:`InputError` at ``recording`` when the file is missing, unreadable or
    (not a plot table by its name) no ASTERIX recording nor capture by its first bytes."""
    try:
        with open(recording, "rb") as f:
            head = f.read(RECORDING_HEAD_BYTES)
    except OSError as e:
        raise InputError(("recording",), f"{recording}: {e.strerror or e}") from None
    if recording.suffix.lower() not in TABLE_SUFFIXES:
        try:
            check_recording_head(head)
        except InputError as e:
            raise InputError(e.loc, f"{e.message} (in {recording})") from None


def check_recording_head(head: bytes) -> None:
    """Raise :class:`InputError` at ``recording`` unless ``head`` (a file's first
    :data:`RECORDING_HEAD_BYTES`, or all of it) starts an ASTERIX recording or a capture."""
    if not looks_like_recording(head):
        raise InputError(("recording",), f"is not an ASTERIX recording (its first bytes "
                         f"{head[:8].hex(' ')} are no data block header followed by another), "
                         "nor a pcap/pcapng capture; a plot table's name ends in "
                         + " or ".join(TABLE_SUFFIXES))


def _sorted_parts(rows: PlotRows, out: Streamed, kind: str, how_far: str, what: str
                  ) -> Iterator[PlotRows]:
    """A recording out of time order, read whole, sorted by time and handed on in batches
    (said in the problems: its memory is the whole recording's)."""
    out.problems.add(kind, "file", f"{how_far} out of time order: read whole "
                     f"and sorted by time ({len(rows)} rows in memory; {what} in time order "
                     "is read in parts)")
    rows = rows.take(np.argsort(rows.t, kind="stable"))
    for i in range(0, len(rows), STREAM_BATCH_ROWS):
        yield out._note(rows.take(np.arange(i, min(i + STREAM_BATCH_ROWS, len(rows)))))


class _Raised:
    def __init__(self, error: BaseException):
        self.error = error


_END = object()


def _read_ahead(items: Iterator[Any], size: int) -> Iterator[Any]:
    """``items`` produced by a thread up to ``size`` ahead of the consumer (the queue
    bounds the memory); its exception is raised to the consumer; a consumer that stops
    early stops the thread."""
    q: queue.Queue[Any] = queue.Queue(max(size, 1))
    stop = threading.Event()

    def put(x: Any) -> bool:
        while not stop.is_set():
            try:
                q.put(x, timeout=0.2)
                return True
            except queue.Full:
                continue
        return False

    def work() -> None:
        try:
            for x in items:
                if not put(x):
                    return
        except BaseException as e:  # handed to the consumer
            put(_Raised(e))
            return
        put(_END)

    thread = threading.Thread(target=work, name="trajrecon-read", daemon=True)
    thread.start()
    try:
        while True:
            x = q.get()
            if x is _END:
                return
            if isinstance(x, _Raised):
                raise x.error
            yield x
    finally:
        stop.set()


class Selection:
    """The aircraft keys to reconstruct (the command line's ``--aircraft``, a job's
    ``aircraft``; None: all). A key selects its track
    and the later pieces of it (``KEY#2`` ...: the same key after a gap, :mod:`solver.io.split`),
    and the sensor tracks associated into another's key (``R2:track:40`` selects
    ``R1:track:12`` that holds it: :attr:`AircraftTrack.members`); a Mode S address matches in
    either case (``4ca2d1`` is ``4CA2D1``)."""

    def __init__(self, keys: Sequence[str] | None):
        self.keys = None if not keys else {normal_key(k) for k in keys}
        self.found: set[str] = set()

    def filter(self, tracks: Iterator[AircraftTrack]) -> Iterator[AircraftTrack]:
        if self.keys is None:
            yield from tracks
            return
        for track in tracks:
            names = [n for k in (track.key, *track.members)
                     for n in (k, k.rsplit("#", 1)[0] if re.search(r"#\d+$", k) else k)]
            hit = next((k for k in names if k in self.keys), None)
            if hit is not None:
                self.found.add(hit)
                yield track

    def missing(self) -> list[str]:
        """The keys named that matched no track (after the whole recording was read)."""
        return sorted((self.keys or set()) - self.found)


def normal_key(key: str) -> str:
    """A Mode S address (with its pieces' ``#n`` / ``~n``) in upper case, any other key as it
    is: an aircraft key as given, matched against the recording's."""
    return key.upper() if re.fullmatch(r"[0-9a-fA-F]{6}([#~]\d+)*", key) else key
