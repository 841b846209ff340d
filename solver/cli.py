"""The command line (spec recordings.md):

    trajrecon reconstruct RECORDING --sensors SENSORS.json --out DIR [--scheduler ADDRESS]
        [--workers N] [--method refined|sliding] [--bounds NAME=MIN,MAX ...]
        [--filters NAME ...] [--samples STEP] [--aircraft KEY ...] [--figures] ...
    trajrecon plot RECORDING --sensors SENSORS.json --out DIR [--aircraft KEY ...] [--map]

(``trajrecon RECORDING ...`` is ``trajrecon reconstruct RECORDING ...``.) ``reconstruct`` reads a
recording (raw ASTERIX or a pcap/pcapng capture of it: CAT048, CAT021, CAT034; or a plot table
in CSV or Parquet, see ``solver/io/README.md``) and the sensor file, splits it into aircraft,
reconstructs every track on Dask (an embedded ``LocalCluster`` sized to the cores, or the
cluster at ``--scheduler``) with a progress bar, and writes into ``DIR``:

- ``tracks.parquet/``, ``segments.parquet/``, with ``--filters`` ``filters.parquet/`` and
  with ``--samples STEP`` ``samples.parquet/`` (streamed as tracks finish; a rerun
  resumes), ``progress.jsonl`` (:mod:`solver.batch`), and at the end ``tracks.csv`` and
  ``tracks.geojsonl`` (one GeoJSON LineString feature per aircraft, for maps; a
  MultiLineString cut at the antimeridian where a track crosses it) and
  ``manoeuvres.csv`` (every track's turns and speed changes, :mod:`solver.manoeuvres`, with
  latitude and longitude at their start and end);
- ``sensors.json`` and ``sensors.csv``: per sensor, against the reconstruction
  (SASS-C/TRES-style assessment): plots, detection rate (plots over expected scans at the
  estimated scan period, holes in coverage apart: :data:`HOLE_CHANCE`), wild plots, bias
  and sigma of the range and azimuth residuals, estimated offsets where asked;
- ``run.json``: the method, bounds, filters and sample step; a rerun resumes only a run with
  the same (:mod:`solver.run_settings`);
- ``sensors.png``: each radar's range and azimuth residuals over range and azimuth
  (:mod:`solver.assessment`);
- ``problems.txt`` (everything left out of the recording, located and counted), ``map.png``
  (every track with the radar sites), ``figures/<track>.png`` with ``--figures``,
  ``summary.json``; a summary is printed at the end (tracks, plots, failures, plots/s).

``plot`` draws ``figures/<aircraft>.png`` for the named aircraft and, with ``--map``,
``map.png`` and ``sensors.png`` again.
"""

from __future__ import annotations

import argparse
import csv
import gc
import itertools
import json
import math
import os
import queue
import re
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from .assessment import write_sensors_figure
from .batch import (
    TRACK_COLUMNS,
    BatchSummary,
    TrackOutcome,
    dask_settings,
    embedded_cluster,
    ledger_entries,
    quiet_interrupted_sync,
    read_part,
    reconstruct_many,
    solve_track,
)
from .config import FILTER_GATE_SIGMA, ReconstructionConfig
from .frames import LocalFrame
from .inputs import Bounds, InputError
from .io.altitudes import offsets_summary
from .io.asterix import iter_recording, looks_like_recording, read_recording
from .io.asterix import time_disorder_s as asterix_time_disorder_s
from .io.problems import Problems
from .io.scans import scan_step
from .io.sensors_file import SensorSet, load_sensors
from .io.split import (
    DISORDER_S,
    MAX_SPEED_MS,
    AircraftTrack,
    recording_frame,
    split_aircraft,
    split_stream,
)
from .io.tables import PlotRows, counts_from_midnight, iter_table, read_table, time_disorder_s
from .plots import PlotTable
from .refine.output import sigma_estimates
from .results import Reconstruction
from .run_settings import RunSettings, keep_inputs, parse_bounds
from .run_settings import keep as keep_settings
from .run_settings import stored as stored_settings
from .sensors import RadarSensor
from .stopping import STOP_SIGNALS, Stopped

TABLE_SUFFIXES = (".csv", ".parquet", ".pq")
SENSOR_COLUMNS = ("sensor", "kind", "tracks", "plots", "plots_gated", "plots_wild",
                  "plots_no_reference", "scan_period_s",
                  "detection_rate", "coverage_holes", "coverage_hole_s",
                  "range_residual_mean_m", "range_residual_sigma_m", "range_sigma_estimate_m",
                  "azimuth_residual_mean_deg", "azimuth_residual_sigma_deg",
                  "azimuth_sigma_estimate_deg", "position_residual_rms_m",
                  "position_sigma_estimate_m", "along_track_residual_mean_m",
                  "along_track_residual_sigma_m", "cross_track_residual_mean_m",
                  "cross_track_residual_sigma_m", "range_bias_m", "range_bias_sigma_m",
                  "azimuth_bias_deg", "azimuth_bias_sigma_deg", "time_bias_s",
                  "time_bias_sigma_s", "offset_tracks", "time_bias_reference")
MAP_POINTS_PER_TRACK = 200  # a recording map draws each track with at most this many points
STREAM_CHUNK_BYTES = 1 << 18  # ASTERIX decoded in units of this size when streaming
RECORDING_HEAD_BYTES = (1 << 16) + 3  # the longest data block and the next one's header
WARNING_EXAMPLES = 20  # tracks whose warnings summary.json repeats (warnings.csv has all)
STREAM_BATCH_ROWS = 1 << 15  # a plot table read in batches of this many rows when streaming
READ_AHEAD_TRACKS = 64  # complete tracks the reading thread may hold ahead of the cluster
GC_YOUNG_THRESHOLD = 10_000
"""Allocations between two collections of the cyclic garbage collector's youngest generation
while the command line runs (Python's default: 700). libasterix builds and drops several
objects per item it parses, and every young collection walks what survived: measured on the
200-aircraft benchmark recording decoded in a process that has imported what the command line
imports, 0.25 ms CPU a plot with the default, 0.16-0.17 with this (gc disabled: 0.19-0.21, in
the noise of a shared machine); the reference counts free almost everything anyway."""


# ----------------------------------------------------------------------------- the task


@dataclass
class AssessedTrack(TrackOutcome):
    """A track's outcome with its sensors' statistics (:class:`solver.results.SensorReport`
    as dicts, plus each sensor's plot times span and median interval for the detection
    rate)."""

    sensors: list[dict[str, Any]] = field(default_factory=list)


def assess_track(key: str, table: PlotTable, config: ReconstructionConfig | None,
                 time_limit_s: float | None, figures_dir: str | None = None,
                 filters: Sequence[str] = (), filter_gate: float | None = FILTER_GATE_SIGMA,
                 times_of_day: bool = False, samples: bool = False,
                 max_samples: int | None = None) -> AssessedTrack:
    """:func:`solver.batch.solve_track` (with its keyword arguments) plus the
    per-sensor statistics and, with ``figures_dir``, the track's figure (drawn on the
    worker)."""
    spans = _sensor_spans(table)

    def extras(rec: Reconstruction) -> dict[str, Any]:
        if figures_dir is not None:
            from .figures import save, track_figure

            save(track_figure(table, rec, title=key, times_of_day=times_of_day),
                 Path(figures_dir) / f"{_safe(key)}.png")
        return {"sensors": [{**asdict(r), **spans.get(r.id, {})} for r in rec.sensors]}

    out = solve_track(key, table, config, time_limit_s, extras=extras, filters=filters,
                      filter_gate=filter_gate, times_of_day=times_of_day, samples=samples,
                      max_samples=max_samples)
    return AssessedTrack(**{k: v for k, v in vars(out).items() if k != "extras"},
                         sensors=out.extras.get("sensors", []))


HOLE_CHANCE = 0.01
"""A run of missed scans is a hole in the sensor's coverage of the track (the aircraft out of
range, masked, in the cone of silence, an outage), not missed detections, when a detection
rate of what the track shows elsewhere gives it less than this chance anywhere in the track
(runs of more than ``log(HOLE_CHANCE / scans) / log(1 - rate)`` misses, at least
:data:`MIN_HOLE_MISSES`): 5-6 misses in a row at 0.9 over 750 scans, 17 at 0.5, 50 at 0.2.
The detection rate then counts the scans expected over the track's time within coverage, as a
radar assessment does; the holes are counted beside it."""
MIN_HOLE_MISSES = 5


def _sensor_spans(table: PlotTable) -> dict[str, dict[str, float]]:
    """Per sensor of the track: the time its plots cover without the holes of
    :data:`HOLE_CHANCE` (``span_s``), in how many stretches (``stretches``), the holes' count
    and time, and its scan period estimated from the track (``median_step_s``)."""
    out: dict[str, dict[str, float]] = {}
    for k, s in enumerate(table.sensors):
        t = np.sort(table.t[table.sensor == k])
        if not t.size:
            continue
        dt = np.diff(t)
        step = scan_step(dt) if t.size > 1 else 0.0
        hole = np.zeros(dt.size, dtype=bool)
        if step > 0:
            steps = np.round(dt / step)  # scans from plot to plot (0: a split plot)
            misses = np.maximum(steps - 1.0, 0.0)
            for _ in range(2):  # the rate without the holes found, then the holes again
                scans = float(steps[~hole].sum()) + np.count_nonzero(hole) + 1.0
                # scans with a plot: a split plot (a second in one scan) is no detection more
                # (counted as one, 40 % split plots at 0.6 read holes in 205 of 300 tracks)
                seen = np.count_nonzero(steps[~hole] > 0) + np.count_nonzero(hole) + 1.0
                rate = min(max(seen / scans, 1e-3), 1.0 - 1e-9)
                longest = max(MIN_HOLE_MISSES,
                              math.log(HOLE_CHANCE / scans) / math.log(1.0 - rate))
                hole = misses > longest
        out[s.id] = {"span_s": float(dt[~hole].sum()), "stretches": int(hole.sum()) + 1,
                     "holes": int(hole.sum()), "hole_s": float(dt[hole].sum()),
                     "median_step_s": step}
    return out


def _safe(key: str) -> str:
    """A file name for a track's key: a gap piece's ``#n`` and another aircraft's ``~n``
    apart (both became ``_n``: one figure over the other, a reviewer's)."""
    key = key.replace("#", "-gap").replace("~", "-apart")
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", key)[:120]


# ----------------------------------------------------------------------------- reading


@dataclass
class Loaded:
    """A recording read and split: tracks (lazily), problems, sensors, rows."""

    sensors: SensorSet
    rows: PlotRows
    problems: Problems
    tracks: Iterator[AircraftTrack]
    scan_periods: dict[str, float]
    times_of_day: bool = False  # t counts from a UTC midnight (counts_from_midnight)


def load(recording: Path, sensors_path: Path, max_speed: float = MAX_SPEED_MS) -> Loaded:
    """Read the sensor file and the whole recording (by suffix: a table, else ASTERIX/pcap)
    into memory; :func:`stream` reads it in parts instead. ``max_speed``: the run's fastest
    ground speed (m/s), by which a key's plots are told apart into aircraft."""
    sensors = load_sensors(sensors_path)
    periods: dict[str, float] = {}
    if recording.suffix.lower() in TABLE_SUFFIXES:
        rows, problems = read_table(recording)
    else:
        rec = read_recording(recording, sensors)
        rows, problems = rec.rows, rec.problems
        periods = {sid: st.rotation_period_s for sid, st in rec.service.items()
                   if st.rotation_period_s}
    frame = recording_frame(sensors, rows)
    tracks = split_aircraft(rows, sensors, reference=frame, problems=problems,
                            max_speed=max_speed)
    return Loaded(sensors, rows, problems, tracks, periods, counts_from_midnight(rows))


@dataclass
class Streamed:
    """A recording read in parts and split as it is read: ``tracks`` yields each aircraft
    once no later plot can change it (:func:`solver.io.split.split_stream`); the other
    fields fill as the reading goes and are complete once ``tracks`` is exhausted: the
    problems, the rows read, the radars' rotation periods (CAT034 I041) and the recording's
    plane. ``times_of_day``: whether ``t`` counts from a UTC midnight (ASTERIX; a table by
    :func:`solver.io.tables.counts_from_midnight` of its first rows)."""

    sensors: SensorSet
    problems: Problems
    tracks: Iterator[AircraftTrack]
    scan_periods: dict[str, float] = field(default_factory=dict)
    rows_read: int = 0
    frame: LocalFrame | None = None
    times_of_day: bool | None = None
    mode_c_offsets: list[float] = field(default_factory=list)  # per track whose Mode C moved

    def _note(self, rows: PlotRows) -> PlotRows:
        self.rows_read += len(rows)
        if self.times_of_day is None and len(rows):
            self.times_of_day = counts_from_midnight(rows)
        if self.frame is None:  # as split_stream: the first part that gives one
            self.frame = recording_frame(self.sensors, rows)
        return rows


def stream(recording: Path, sensors_path: Path, *, read_ahead: int = READ_AHEAD_TRACKS,
           executor: Any = None, max_speed: float = MAX_SPEED_MS) -> Streamed:
    """The sensor file read and the recording opened for :func:`solver.io.split.split_stream`
    (by suffix: a table read in batches, else ASTERIX/pcap decoded in units): memory holds
    the aircraft in the air, not the recording's rows. A thread reads, decodes and splits up
    to ``read_ahead`` complete tracks ahead of their consumer (so the decoding overlaps the
    reconstruction); with ``executor`` (a Dask client) ASTERIX units are decoded on it
    (:func:`solver.io.asterix.iter_recording`). What makes the whole input unusable (a
    sensor file or table header it cannot use, a capture of a link type not read) raises
    here, before any track is taken."""
    sensors = load_sensors(sensors_path)
    out = Streamed(sensors, Problems(), iter(()))
    parts = _row_parts(recording, out, executor)
    try:
        first = next(parts, None)  # the whole input's errors raise now
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


def _row_parts(recording: Path, out: Streamed, executor: Any = None) -> Iterator[PlotRows]:
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
    back = asterix_time_disorder_s(recording, out.sensors)
    if back > DISORDER_S:  # e.g. two recordings concatenated: read whole, sorted
        rec = read_recording(recording, out.sensors, executor=executor,
                             chunk_bytes=STREAM_CHUNK_BYTES)
        out.problems.extend(rec.problems)
        out.scan_periods.update({sid: st.rotation_period_s for sid, st in rec.service.items()
                                 if st.rotation_period_s})
        yield from _sorted_parts(rec.rows, out, "unordered_recording",
                                 f"reports {back:.0f} s or more", "a recording")
        return
    for part in iter_recording(recording, out.sensors, chunk_bytes=STREAM_CHUNK_BYTES,
                               executor=executor):
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


# ----------------------------------------------------------------------------- outputs


class SensorStats:
    """Per-sensor statistics pooled over tracks (plot-weighted means and variances), in
    accumulators of a fixed size whatever the number of tracks: sums, and for the medians
    (of the tracks' median plot intervals, of their estimated offsets) the values themselves
    up to :data:`MEDIAN_SAMPLE` per sensor, beyond that a uniform sample of that many
    (reservoir sampling, seeded: the same tracks in the same order give the same result)."""

    def __init__(self, sensors: SensorSet, periods: dict[str, float]):
        self.sensors = sensors
        self.periods = dict(periods)
        self.acc: dict[str, dict[str, Any]] = {
            s.id: {"tracks": 0, "plots": 0, "plots_gated": 0, "plots_wild": 0,
                   "plots_no_reference": 0, "used": 0,
                   "steps": _Sample(MEDIAN_SAMPLE), "span_s": 0.0, "spans": 0,
                   "holes": 0, "hole_s": 0.0,
                   "r1": 0.0, "r2": 0.0, "a1": 0.0, "a2": 0.0, "p2": 0.0,
                   "along": [0, 0.0, 0.0], "cross": [0, 0.0, 0.0],
                   # the tracks with degrees of freedom: plots, sums, the dof (range,
                   # azimuth, position)
                   "dof": {"n": 0, "r1": 0.0, "r2": 0.0, "a1": 0.0, "a2": 0.0, "p2": 0.0,
                           "range": 0.0, "azimuth": 0.0, "position": 0.0},
                   "biases": _Sample(MEDIAN_SAMPLE)} for s in sensors.sensors}

    def add(self, reports: Sequence[dict[str, Any]]) -> None:
        # a track with a sensor whose offsets were not estimated has its time (ADS-B's, a
        # radar's without estimate_bias); without one the estimating sensors' mean is held
        anchored = any(r.get("time_bias_s") is None and r.get("plots") for r in reports)
        for r in reports:
            a = self.acc.get(r["id"])
            if a is None:
                continue
            wild = r.get("plots_wild", r["plots_gated"])  # (a report of before the field)
            far = r.get("plots_no_reference", 0)
            n = r["plots"] - wild - far  # the plots its statistics are of
            a["tracks"] += 1
            a["plots"] += r["plots"]
            a["plots_gated"] += r["plots_gated"]
            a["plots_wild"] += wild
            a["plots_no_reference"] += far
            a["span_s"] += r.get("span_s", 0.0)
            a["spans"] += r.get("stretches", 1)
            a["holes"] += r.get("holes", 0)
            a["hole_s"] += r.get("hole_s", 0.0)
            if r.get("median_step_s"):
                a["steps"].add(r["median_step_s"])
            if n <= 0:
                continue
            a["used"] += n
            if r["range_residual_mean_m"] is not None:
                a["r1"] += n * r["range_residual_mean_m"]
                a["r2"] += n * r["range_residual_rms_m"] ** 2
                a["a1"] += n * r["azimuth_residual_mean_rad"]
                a["a2"] += n * r["azimuth_residual_rms_rad"] ** 2
            if r["position_residual_rms_m"] is not None:
                a["p2"] += n * r["position_residual_rms_m"] ** 2
            e = a["dof"]
            if r.get("range_dof") is not None and r["range_residual_mean_m"] is not None:
                e["n"] += n
                e["r1"] += n * r["range_residual_mean_m"]
                e["r2"] += n * r["range_residual_rms_m"] ** 2
                e["a1"] += n * r["azimuth_residual_mean_rad"]
                e["a2"] += n * r["azimuth_residual_rms_rad"] ** 2
                e["range"] += r["range_dof"]
                e["azimuth"] += r["azimuth_dof"]
            if r.get("position_dof") is not None and r["position_residual_rms_m"] is not None:
                e["p2"] += n * r["position_residual_rms_m"] ** 2
                e["position"] += r["position_dof"]
            for name in ("along", "cross"):  # count, sum, sum of squares
                mean = r.get(f"{name}_track_residual_mean_m")
                if mean is not None:
                    sigma = r[f"{name}_track_residual_sigma_m"]
                    acc = a[name]
                    acc[0] += n
                    acc[1] += n * mean
                    acc[2] += n * (sigma**2 + mean**2)
            if r.get("time_bias_s") is not None:  # a position sensor: its time offset alone
                a["biases"].add((anchored, *(math.nan if r.get(k) is None else r[k] for k in (
                    "range_bias_m", "azimuth_bias_rad", "time_bias_s", "range_bias_sigma_m",
                    "azimuth_bias_sigma_rad", "time_bias_sigma_s"))))

    def rows(self) -> list[dict[str, Any]]:
        out = []
        for s in self.sensors.sensors:
            a = self.acc[s.id]
            n = a["used"]
            row: dict[str, Any] = {"sensor": s.id, "kind": s.kind, "tracks": a["tracks"],
                                   "plots": a["plots"], "plots_gated": a["plots_gated"],
                                   "plots_wild": a["plots_wild"],
                                   "plots_no_reference": a["plots_no_reference"]}
            steps = a["steps"].values
            period = self.periods.get(s.id) or (float(np.median(steps)) if steps else None)
            row["scan_period_s"] = period
            # sum over the tracks' stretches within coverage of (span / period + 1)
            expected = a["span_s"] / period + a["spans"] if period else 0.0
            row["detection_rate"] = min(a["plots"] / expected, 1.0) if expected else None
            row["coverage_holes"], row["coverage_hole_s"] = a["holes"], a["hole_s"]
            radar = isinstance(s, RadarSensor)
            if radar and n:
                r_mean, a_mean = a["r1"] / n, a["a1"] / n
                row["range_residual_mean_m"] = r_mean
                row["range_residual_sigma_m"] = float(np.sqrt(max(a["r2"] / n - r_mean**2, 0)))
                row["azimuth_residual_mean_deg"] = float(np.rad2deg(a_mean))
                row["azimuth_residual_sigma_deg"] = float(np.rad2deg(
                    np.sqrt(max(a["a2"] / n - a_mean**2, 0.0))))
            if not radar and n:
                row["position_residual_rms_m"] = float(np.sqrt(a["p2"] / n))
            est = sigma_estimates(a["dof"])
            row["range_sigma_estimate_m"] = est.get("range_sigma_estimate_m")
            row["position_sigma_estimate_m"] = est.get("position_sigma_estimate_m")
            if est.get("azimuth_sigma_estimate_rad") is not None:
                row["azimuth_sigma_estimate_deg"] = float(np.rad2deg(
                    est["azimuth_sigma_estimate_rad"]))
            for name in ("along", "cross"):
                count, total, squares = a[name]
                if count:
                    mean = total / count
                    row[f"{name}_track_residual_mean_m"] = mean
                    row[f"{name}_track_residual_sigma_m"] = float(
                        np.sqrt(max(squares / count - mean**2, 0.0)))
            if a["biases"].values:
                row.update(pooled_offsets(np.array(a["biases"].values, dtype=float), radar))
            out.append({k: row.get(k) for k in SENSOR_COLUMNS})
        return out


def pooled_offsets(values: np.ndarray, radar: bool) -> dict[str, Any]:
    """A sensor's offsets over its tracks (rows: anchored, range, azimuth, time, and their
    sigmas): each the median weighted by the tracks' inverse variances (a track whose offsets
    are barely observable counted as much as a well-registered one: +-184 m against +-7 m),
    with the sigma of that median (``1.2533 / sqrt(sum of the weights)``, the median's
    efficiency for Gaussian errors); of one or two tracks their weighted mean and its sigma
    (the lower median of two read 100 m for 100 and 120, -0.65 sigma on average; a
    reviewer's); the sigma scaled by the square root of the reduced chi-square of the tracks
    about their weighted mean where it is above 1 (the Birge ratio: ADS-B latencies differing
    by aircraft scatter a radar's time offsets beyond their sigmas). The time offset pools
    the tracks with a sensor that did not estimate its own
    (their time reference, e.g. ADS-B's) where there are any, else those whose estimating
    sensors' mean time is held: the two are other quantities (a radar without an offset read
    -0.54 s, its tracks' ADS-B latency, where the pooled median of both kinds had mixed -0.56
    and -0.19 s; a tester's)."""
    anchored = values[:, 0] > 0
    keep = anchored if anchored.any() else np.ones(len(values), bool)
    out: dict[str, Any] = {
        "offset_tracks": int(np.count_nonzero(np.isfinite(values[:, 1:4]).any(axis=1))),
        "time_bias_reference": ("the sensors not estimating their offsets" if anchored.any()
                                else "the mean of the estimating sensors")}
    terms = (("time_bias_s", 3, 6, keep, 1.0),) + ((
        ("range_bias_m", 1, 4, np.ones(len(values), bool), 1.0),
        ("azimuth_bias_deg", 2, 5, np.ones(len(values), bool), float(np.rad2deg(1.0))))
        if radar else ())
    for name, col, sig, rows, unit in terms:
        v, sd = values[rows, col], values[rows, sig]
        v, sd = v[np.isfinite(v)], sd[np.isfinite(v)]
        if not v.size:
            continue
        if not np.all(np.isfinite(sd) & (sd > 0)):  # reports without sigmas: the median
            out[name] = float(np.median(v)) * unit
            continue
        w = 1.0 / sd**2
        if v.size <= 2:
            value, sigma = float(w @ v / w.sum()), float(1.0 / np.sqrt(w.sum()))
        else:
            value, sigma = weighted_median(v, w), float(1.2533 / np.sqrt(w.sum()))
        if v.size > 1:  # tracks scattered beyond their sigmas (ADS-B latency differing by
            # aircraft: reduced chi-square 10.7, the sigma 3x small; a tester's): scaled
            chi2 = float(w @ (v - w @ v / w.sum()) ** 2) / (v.size - 1)
            sigma *= float(np.sqrt(max(chi2, 1.0)))
        out[name] = value * unit
        out[name.replace("_bias", "_bias_sigma")] = sigma * unit
    return out


def weighted_median(v: np.ndarray, w: np.ndarray) -> float:
    """The value with half the weight on either side (where a cut falls between two values
    exactly at half, their midpoint: the median of equal weights)."""
    order = np.argsort(v)
    v, cum = v[order], np.cumsum(w[order])
    half = 0.5 * cum[-1]
    k = int(np.searchsorted(cum, half))
    if np.isclose(cum[k], half, rtol=1e-12, atol=0.0) and k + 1 < v.size:
        return float((v[k] + v[k + 1]) / 2)
    return float(v[k])


MEDIAN_SAMPLE = 4096
"""Values kept per sensor for a median of :class:`SensorStats` (all of them up to this)."""


class _Sample:
    """Up to ``size`` values: all of them, then a uniform sample (reservoir sampling)."""

    def __init__(self, size: int, seed: int = 16):
        self.size = size
        self.seen = 0
        self.values: list[Any] = []
        self._rng = np.random.default_rng(seed)

    def add(self, value: Any) -> None:
        self.seen += 1
        if len(self.values) < self.size:
            self.values.append(value)
            return
        j = int(self._rng.integers(self.seen))
        if j < self.size:
            self.values[j] = value


def line_geometry(coords: list[list[float]]) -> dict[str, Any]:
    """A GeoJSON LineString of ``[lon, lat]`` points, cut into a MultiLineString where it
    crosses the antimeridian (RFC 7946, 3.1.9: a step of more than 180 deg of longitude is a
    crossing; each part ends at +-180 deg at the latitude interpolated linearly in longitude),
    so maps do not draw the track across the whole world."""
    parts, part = [], [coords[0]]
    for a, b in itertools.pairwise(coords):
        step = b[0] - a[0]
        if abs(step) > 180.0:
            edge = 180.0 if step < 0 else -180.0  # the side a is on
            span = step + (360.0 if step < 0 else -360.0)  # the short way round
            lat = a[1] + (b[1] - a[1]) * (edge - a[0]) / span if span else a[1]
            part.append([edge, round(lat, 7)])
            parts.append(part)
            part = [[-edge, round(lat, 7)]]
        part.append(b)
    parts.append(part)
    if len(parts) == 1:
        return {"type": "LineString", "coordinates": coords}
    return {"type": "MultiLineString", "coordinates": parts}


def write_csv_and_geojson(out: Path) -> tuple[int, int]:
    """``tracks.csv`` and ``tracks.geojsonl`` from the Parquet parts, one part at a time
    (memory bounded by a part), each written whole under another name and then renamed;
    returns (rows, tracks)."""
    parts = sorted((out / "tracks.parquet").glob("part-*.parquet"))
    rows = tracks = 0
    writer: pacsv.CSVWriter | None = None
    csv_tmp, geo_tmp = out / ".tracks.csv.tmp", out / ".tracks.geojsonl.tmp"
    with open(geo_tmp, "w", encoding="utf-8") as geo:
        for part in parts:
            table = read_part(part)
            if writer is None:
                writer = pacsv.CSVWriter(csv_tmp, table.schema)
            writer.write_table(table)
            rows += table.num_rows
            keys = table.column("aircraft").to_numpy(zero_copy_only=False)
            lat = table.column("lat_deg").to_numpy(zero_copy_only=False).astype(float)
            lon = table.column("lon_deg").to_numpy(zero_copy_only=False).astype(float)
            t = table.column("t").to_numpy()
            for key, sel in _key_groups(keys):
                coords = [[round(b, 7), round(a, 7)]
                          for a, b in zip(lat[sel].tolist(), lon[sel].tolist(), strict=True)
                          if math.isfinite(a) and math.isfinite(b)]
                if len(coords) < 2:
                    continue
                feature = {"type": "Feature", "geometry": line_geometry(coords),
                           "properties": {"aircraft": key, "t_start": float(t[sel].min()),
                                          "t_end": float(t[sel].max()),
                                          "plots": int(sel.size)}}
                geo.write(json.dumps(feature) + "\n")
                tracks += 1
    if writer is None:  # no track: the header alone, as the other tables have theirs
        writer = pacsv.CSVWriter(csv_tmp, pa.schema(
            [(n, pa.string() if n in ("aircraft", "source", "sensor") else pa.float64())
             for n in TRACK_COLUMNS]))
    writer.close()
    os.replace(csv_tmp, out / "tracks.csv")  # whole files only: a stop leaves the old ones
    os.replace(geo_tmp, out / "tracks.geojsonl")
    return rows, tracks


def write_manoeuvres(out: Path, frame: LocalFrame | None) -> int:
    """``manoeuvres.csv`` from the segments' Parquet parts (:mod:`solver.manoeuvres`), one part
    at a time, with latitude and longitude at both ends in the recording's plane ``frame``
    (empty without one); returns the rows written."""
    from .manoeuvres import Manoeuvre, from_segment_rows

    fields = list(Manoeuvre.__dataclass_fields__)
    schema = pa.schema([("aircraft", pa.string())] + [
        (k, pa.string() if k in ("kind", "direction") else pa.float64()) for k in fields] + [
        (k, pa.float64()) for k in ("lat_start_deg", "lon_start_deg", "lat_end_deg",
                                    "lon_end_deg")])
    rows = 0
    tmp = out / ".manoeuvres.csv.tmp"
    with pacsv.CSVWriter(tmp, schema) as writer:
        for part in sorted((out / "segments.parquet").glob("part-*.parquet")):
            table = pq.read_table(part)
            keys = table.column("aircraft").to_numpy(zero_copy_only=False)
            found: list[tuple[str, Manoeuvre]] = []
            for key, sel in _key_groups(keys):
                found += [(key, m) for m in from_segment_rows(table.take(sel))]
            if not found:
                continue
            cols: dict[str, Any] = {"aircraft": [k for k, _ in found]}
            cols.update({f: [getattr(m, f) for _, m in found] for f in fields})
            for end in ("start", "end"):
                x, z = np.array(cols[f"x_{end}"]), np.array(cols[f"z_{end}"])
                lat, lon = frame.to_geodetic(x, z) if frame is not None else (None, None)
                cols[f"lat_{end}_deg"], cols[f"lon_{end}_deg"] = lat, lon
            writer.write_table(pa.table({f.name: pa.nulls(len(found), f.type)
                                         if cols[f.name] is None else
                                         pa.array(cols[f.name], f.type) for f in schema},
                                        schema=schema))
            rows += len(found)
    os.replace(tmp, out / "manoeuvres.csv")
    return rows


def _key_groups(keys: np.ndarray) -> Iterator[tuple[Any, np.ndarray]]:
    """``(key, rows)`` of every distinct key of a part, in order of first appearance, rows in
    order: what ``keys == key`` selects for each key, by one sort instead of a scan of the part
    per key (a part holds 32 tracks or more)."""
    if not keys.size:
        return
    uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    groups = np.split(np.argsort(inverse, kind="stable"),
                      np.cumsum(np.bincount(inverse, minlength=uniq.size))[:-1])
    for g in np.argsort(first, kind="stable").tolist():
        yield uniq[g], groups[g]


def write_map(out: Path, sensors: SensorSet, rows: PlotRows | None = None, *,
              frame: LocalFrame | None = None) -> Path | None:
    """``map.png``: every reconstructed track (thinned) and the radar sites, in the
    recording's plane ``frame`` (default: :func:`solver.io.split.recording_frame` of
    ``rows``)."""
    from .figures import recording_map, save

    parts = sorted((out / "tracks.parquet").glob("part-*.parquet"))
    lines = []
    for part in parts:
        table = pq.read_table(part, columns=["aircraft", "x", "z"])
        keys = table.column("aircraft").to_numpy(zero_copy_only=False)
        x, z = table.column("x").to_numpy(), table.column("z").to_numpy()
        for key, sel in _key_groups(keys):
            sel = sel[:: max(1, sel.size // MAP_POINTS_PER_TRACK)]
            lines.append((key, x[sel], z[sel]))
    if not lines:
        return None
    if frame is None and rows is not None:
        frame = recording_frame(sensors, rows)
    sites = []
    for s in sensors.sensors:
        if isinstance(s, RadarSensor):
            if frame is None or s.site is None:
                sites.append((s.id, 0.0, 0.0))
            else:
                px, pz = frame.to_plane(np.array([s.site.lat_deg]), np.array([s.site.lon_deg]))
                sites.append((s.id, float(px[0]), float(pz[0])))
    return save(recording_map(lines, sites), out / "map.png")


def write_sensor_csv(out: Path, rows: list[dict[str, Any]]) -> None:
    """``out/sensors.csv``: the sensors' statistics (:data:`SENSOR_COLUMNS`)."""
    cols = {k: [r[k] for r in rows] for k in SENSOR_COLUMNS}
    types = {k: pa.string() if k in ("sensor", "kind", "time_bias_reference") else
             pa.int64() if k in ("tracks", "plots", "plots_gated", "plots_wild",
                                 "plots_no_reference", "coverage_holes", "offset_tracks")
             else pa.float64()
             for k in SENSOR_COLUMNS}
    pacsv.write_csv(pa.table({k: pa.array(v, types[k]) for k, v in cols.items()}),
                    out / "sensors.csv")


# ----------------------------------------------------------------------------- main


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The whole pipeline; returns the summary (also written as ``summary.json``)."""
    with _young_collections(GC_YOUNG_THRESHOLD):
        return _run(args)


@contextmanager
def _young_collections(threshold: int) -> Iterator[None]:
    """The garbage collector's first threshold set to ``threshold``, restored at the end."""
    old = gc.get_threshold()
    gc.set_threshold(threshold, *old[1:])
    try:
        yield
    finally:
        gc.set_threshold(*old)


def _run(args: argparse.Namespace) -> dict[str, Any]:
    out = Path(args.out)
    _check_out(out, Path(args.sensors))
    started = time.perf_counter()
    load_sensors(Path(args.sensors))  # a bad sensor file is refused before a cluster starts
    check_recording(Path(args.recording))  # a missing one too (it took 25 s: the cluster's)
    settings = _settings(args)
    keep_settings(out, settings)  # a rerun resumes only the same run
    keep_inputs(out, Path(args.recording), Path(args.sensors))  # ... of the same files
    with _cluster(args.scheduler, args.workers) as client:
        workers = max(len(client.scheduler_info()["workers"]), 1)
        on_cluster = args.decode == "cluster" or (args.decode == "auto" and workers > 1)
        loaded = stream(Path(args.recording), Path(args.sensors),
                        executor=client if on_cluster else None,
                        max_speed=settings.config().bounds.v[1])
        chosen = Selection(getattr(args, "aircraft", None))
        loaded.tracks = chosen.filter(loaded.tracks)
        summary, first_result_s = _reconstruct(args, settings, out, loaded, client, started)
    return _finish(args, settings, out, loaded, summary, first_result_s, started, chosen)


class Selection:
    """``--aircraft``: the aircraft keys to reconstruct (None: all). A key selects its track
    and the later pieces of it (``KEY#2`` ...: the same key after a gap, :mod:`solver.io.split`);
    a Mode S address matches in either case (``4ca2d1`` is ``4CA2D1``)."""

    def __init__(self, keys: Sequence[str] | None):
        self.keys = None if not keys else {_normal_key(k) for k in keys}
        self.found: set[str] = set()

    def filter(self, tracks: Iterator[AircraftTrack]) -> Iterator[AircraftTrack]:
        if self.keys is None:
            yield from tracks
            return
        for track in tracks:
            base = track.key.rsplit("#", 1)[0] if re.search(r"#\d+$", track.key) else track.key
            hit = next((k for k in (track.key, base) if k in self.keys), None)
            if hit is not None:
                self.found.add(hit)
                yield track

    def missing(self) -> list[str]:
        """The keys named that matched no track (after the whole recording was read)."""
        return sorted((self.keys or set()) - self.found)


def _normal_key(key: str) -> str:
    return key.upper() if re.fullmatch(r"[0-9a-fA-F]{6}([#~]\d+)*", key) else key


def _settings(args: argparse.Namespace) -> RunSettings:
    given = [name for name, value in (("--window-plots", args.window_plots),
                                      ("--trial-step", args.trial_step),
                                      ("--criterion", args.criterion)) if value is not None]
    if given and args.method != "sliding":
        raise InputError(("method",), f"{', '.join(given)} set the sliding windows, which the "
                         f"{args.method} method does not use: add --method sliding, or leave "
                         "them out")
    return RunSettings(args.method, parse_bounds(args.bounds), tuple(args.filters),
                       args.samples, **_windows(args, RunSettings()),
                       filter_gate_sigma=args.filter_gate)


def _check_out(out: Path, sensors: Path) -> None:
    """``--out`` must be a directory (or not yet exist), and the statistics' ``sensors.json``
    must not overwrite the sensor file given."""
    if out.exists() and not out.is_dir():
        raise InputError(("out",), f"{out} is a file, not a directory")
    target = out / "sensors.json"
    if target.exists() and sensors.exists() and target.samefile(sensors):
        raise InputError(("out",), f"{out} holds the sensor file {sensors}, which the run "
                         "would overwrite with the sensors' statistics: choose another --out")


@contextmanager
def _cluster(scheduler: str | None, workers: int | None) -> Iterator[Any]:
    """A Dask client of the scheduler at ``scheduler``, else of an embedded ``LocalCluster``
    of ``workers`` processes (default: the usable cores; as :func:`solver.batch.
    reconstruct_many` would start), closed at the end. A stop (SIGINT, SIGTERM) while it
    starts or closes is held until it has (:mod:`solver.stopping`)."""
    import dask
    from distributed import Client

    stack = ExitStack()
    try:
        with STOP_SIGNALS.deferred(), dask.config.set(dask_settings()):
            if scheduler is not None:
                try:
                    client = stack.enter_context(Client(scheduler))
                except OSError as e:  # distributed's connection timeout is an OSError too
                    raise InputError(("scheduler",), f"no Dask scheduler answers at "
                                     f"{scheduler} ({e})") from None
            else:
                cluster = stack.enter_context(embedded_cluster(workers))
                client = stack.enter_context(Client(cluster))
        yield client
    finally:
        with STOP_SIGNALS.deferred():
            stack.close()


def _reconstruct(args: argparse.Namespace, settings: RunSettings, out: Path, loaded: Streamed,
                 client: Any, started: float) -> tuple[BatchSummary, float | None]:
    """Every track of ``loaded`` on ``client``, with the sensors' statistics recorded as
    they come; the summary and the time to the first result."""
    config = settings.config()
    stats_path = out / "sensor_stats.jsonl"
    first_result: list[float] = []
    bar = _progress(args.no_progress)

    def on_outcome(o: TrackOutcome) -> None:
        if not first_result:
            first_result.append(time.perf_counter() - started)
        if isinstance(o, AssessedTrack) and o.sensors:  # on disk only, read back at the end
            with open(stats_path, "a", encoding="utf-8") as f:
                f.write(json.dumps({"aircraft": o.key, "sensors": o.sensors}) + "\n")
        if bar is not None:
            bar.update(1)
            bar.set_postfix(plots=o.plots, failed=o.status == "failed", refresh=False)

    figures = str(out / "figures") if args.figures else None

    task = partial(assess_track, figures_dir=figures, filters=settings.filters,
                   filter_gate=settings.filter_gate_sigma,
                   times_of_day=bool(loaded.times_of_day),
                   samples=settings.sample_step_s is not None)
    summary: BatchSummary = reconstruct_many(
        loaded.tracks, out, config=config, executor=client,
        time_limit_s=args.time_limit or None, retry_failed=args.retry_failed,
        on_outcome=on_outcome, task=task)
    if bar is not None:
        bar.close()
    return summary, first_result[0] if first_result else None


def _finish(args: argparse.Namespace, settings: RunSettings, out: Path, loaded: Streamed,
            summary: BatchSummary, first_result_s: float | None, started: float,
            chosen: Selection | None = None) -> dict[str, Any]:
    """The whole-recording outputs once every track is in."""
    stats_path = out / "sensor_stats.jsonl"
    stats = SensorStats(loaded.sensors, loaded.scan_periods)  # the periods read by now
    for reports in _iter_stats(stats_path):
        stats.add(reports)
    sensor_rows = stats.rows()
    write_sensor_csv(out, sensor_rows)
    (out / "sensors.json").write_text(json.dumps(sensor_rows, indent=1) + "\n",
                                      encoding="utf-8")
    (out / "summary.json").unlink(missing_ok=True)  # stale while the files below are written
    csv_rows, geo_tracks = write_csv_and_geojson(out)
    manoeuvres = write_manoeuvres(out, loaded.frame)
    state = output_state(out)
    write_map(out, loaded.sensors, frame=loaded.frame)
    write_sensors_figure(out, [s.id for s in loaded.sensors.sensors])
    (out / "problems.txt").write_text(loaded.problems.summary() + "\n", encoding="utf-8")
    result = {
        "recording": str(args.recording), **settings.as_json(),
        "tracks": summary.tracks, "done": summary.done,
        "failed": summary.failed, "skipped": summary.skipped, "plots": summary.plots,
        "rows_in_recording": loaded.rows_read, "elapsed_s": time.perf_counter() - started,
        "reconstruct_s": summary.elapsed_s, "plots_per_s": summary.plots_per_s,
        "time_to_first_result_s": first_result_s,
        "mode_c_offsets": offsets_summary(loaded.mode_c_offsets),
        "problems": dict(loaded.problems.counts),
        "dropped": loaded.problems.left_out(), "failures": summary.failures,
        "csv_rows": csv_rows, "geojson_tracks": geo_tracks, "manoeuvres": manoeuvres,
        "output": state, "sensors": sensor_rows}
    if chosen is not None and chosen.keys is not None:
        result.update(aircraft=sorted(chosen.keys), aircraft_not_found=chosen.missing())
    (out / "summary.json").write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    return result


def output_state(out: Path) -> dict[str, Any]:
    """The whole output directory, this run and the earlier ones it resumed (each track's last
    line of ``progress.jsonl``): tracks done and failed, their plots, the failures' reasons,
    and the tracks whose reconstruction warned (listed one warning a line in ``warnings.csv``,
    ``aircraft,warning``)."""
    # of each track's last line, the few fields needed (not its diagnostics)
    last: dict[str, dict[str, Any]] = {}
    for entry in ledger_entries(out):
        last[entry["aircraft"]] = {k: entry.get(k) for k in ("status", "plots", "error",
                                                               "warnings")}
    done = [e for e in last.values() if e["status"] == "done"]
    warned = [(k, e["warnings"]) for k, e in last.items()
              if e["status"] == "done" and e["warnings"]]
    tmp = out / ".warnings.csv.tmp"
    with open(tmp, "w", encoding="utf-8", newline="") as f:
        w = csv.writer(f)
        w.writerow(["aircraft", "warning"])
        for key, texts in warned:
            w.writerows([key, text] for text in texts)
    os.replace(tmp, out / "warnings.csv")
    return {"tracks_done": len(done),
            "tracks_failed": len(last) - len(done),
            "plots_done": sum(int(e["plots"]) for e in done),
            "failures": {k: e["error"] for k, e in last.items() if e["status"] != "done"},
            "tracks_with_warnings": len(warned),
            "warnings": dict(warned[:WARNING_EXAMPLES])}


def _iter_stats(path: Path) -> Iterator[list[dict[str, Any]]]:
    """The per-track sensor statistics of this run and earlier ones (a resumed run keeps
    them), one track at a time; a track written twice counts once, its last line. Streamed
    (twice through the file: the last line of each aircraft, then the lines): what is held
    is the aircraft keys, not their statistics."""
    if not path.exists():
        return
    last: dict[str, int] = {}
    for i, entry in _stats_lines(path):
        last[entry["aircraft"]] = i
    for i, entry in _stats_lines(path):
        if last[entry["aircraft"]] == i:
            yield entry["sensors"]


def _stats_lines(path: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    with open(path, encoding="utf-8") as f:
        for i, line in enumerate(f):
            try:
                entry = json.loads(line)
            except ValueError:  # torn by a killed run
                continue
            yield i, entry


def _progress(disabled: bool) -> Any:
    if disabled:
        return None
    from tqdm import tqdm

    return tqdm(unit="track", desc="reconstructing", dynamic_ncols=True)


def print_summary(result: dict[str, Any], file: Any = None) -> None:
    """The end-of-run summary: counts, rate, problems, failures, the sensors' table."""
    file = file or sys.stdout
    p = result
    print(f"tracks: {p['tracks']} ({p['done']} reconstructed by {p.get('method', 'refined')}, "
          f"{p['failed']} failed, "
          f"{p['skipped']} finished before); plots: {p['plots']}; "
          f"{p['plots_per_s']:.0f} plots/s; {p['elapsed_s']:.1f} s in all", file=file)
    if p["problems"]:
        lost = p.get("dropped") or {}
        print("left out or reported: " + ", ".join(
            f"{k} {n}" + (f" ({lost[k]} plots left out)" if lost.get(k) else "")
            for k, n in p["problems"].items()), file=file)
    for key, why in list(p["failures"].items())[:10]:
        print(f"failed {key}: {why}", file=file)
    state = p.get("output")
    if state:
        earlier = {k: v for k, v in state["failures"].items() if k not in p["failures"]}
        if earlier:
            print(f"{len(earlier)} track(s) failed in an earlier run and were not retried "
                  "(--retry-failed redoes them):", file=file)
            for key, why in list(earlier.items())[:10]:
                print(f"failed {key}: {why}", file=file)
        if state["tracks_with_warnings"]:
            print(f"{state['tracks_with_warnings']} of {state['tracks_done']} track(s) "
                  "reconstructed with warnings (all of them in warnings.csv), e.g.:", file=file)
            for key, texts in list(state["warnings"].items())[:5]:
                print(f"  {key}: {texts[0][:200]}", file=file)
    # residuals after the estimated offsets (those on the lines below)
    # and the sensors' sigmas estimated from them (sigma_estimates)
    print(f"{'sensor':<12}{'plots':>8}{'det.':>7}{'wild':>6}{'no ref':>7}{'range res.':>12}"
          f"{'sigma':>8}"
          f"{'az res.':>10}{'sigma':>8}{'est. sigma r / az / pos':>26}", file=file)
    for r in p["sensors"]:
        def f(v: Any, fmt: str) -> str:
            return format(v, fmt) if v is not None else "-"
        estimated = (f"{f(r.get('range_sigma_estimate_m'), '.1f')} / "
                     f"{f(r.get('azimuth_sigma_estimate_deg'), '.3f')} / "
                     f"{f(r.get('position_sigma_estimate_m'), '.1f')}")
        print(f"{r['sensor']:<12}{r['plots']:>8}{f(r['detection_rate'], '.2f'):>7}"
              f"{r['plots_wild']:>6}{r.get('plots_no_reference', 0):>7}"
              f"{f(r['range_residual_mean_m'], '.1f'):>12}"
              f"{f(r['range_residual_sigma_m'], '.1f'):>8}"
              f"{f(r['azimuth_residual_mean_deg'], '.3f'):>10}"
              f"{f(r['azimuth_residual_sigma_deg'], '.3f'):>8}{estimated:>26}", file=file)
    for r in p["sensors"]:
        if r.get("range_bias_m") is not None:
            print(f"{r['sensor']}: estimated offsets range {r['range_bias_m']:+.1f}"
                  f"{_pm(r, 'range_bias_sigma_m', '.1f')} m, azimuth "
                  f"{r['azimuth_bias_deg']:+.4f}{_pm(r, 'azimuth_bias_sigma_deg', '.4f')} deg, "
                  f"time {r['time_bias_s']:+.3f}{_pm(r, 'time_bias_sigma_s', '.3f')} s "
                  f"(pooled over {r['offset_tracks']} "
                  f"tracks, weighted by their precision; time against "
                  f"{r['time_bias_reference']}; to take them off every track it sees, those "
                  "it sees alone too, add them to its sensor-file entry's range_offset_m, "
                  "azimuth_offset_deg and time_offset_s)", file=file)
    for r in p["sensors"]:
        if r.get("along_track_residual_mean_m") is not None:
            print(f"{r['sensor']}: along the track {r['along_track_residual_mean_m']:+.1f} m "
                  f"(sigma {r['along_track_residual_sigma_m']:.1f}; a late report lies behind), "
                  f"across {r['cross_track_residual_mean_m']:+.1f} m "
                  f"(sigma {r['cross_track_residual_sigma_m']:.1f})"
                  + ("" if r.get("time_bias_s") is None
                     else f"; time offset {r['time_bias_s']:+.3f} s"), file=file)


def _pm(row: dict[str, Any], key: str, fmt: str) -> str:
    """`` +- value`` of ``row[key]``, or nothing where it is None."""
    return "" if row.get(key) is None else f" +- {format(row[key], fmt)}"


COMMANDS = ("reconstruct", "plot")
UNUSABLE_PATH = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)
"""A path given that cannot be read or written: a one-line error, exit status 2."""


def parser() -> argparse.ArgumentParser:
    """``trajrecon reconstruct ...`` and ``trajrecon plot ...`` (spec recordings.md)."""
    from .estimation import FILTER_NAMES

    ap = argparse.ArgumentParser(
        prog="trajrecon", description="Reconstruct every aircraft of a recording (ASTERIX "
        "CAT048/021/034, pcap, pcapng, or a CSV/Parquet plot table) with its sensors' "
        "statistics, and draw its figures. `trajrecon RECORDING ...` is `trajrecon "
        "reconstruct RECORDING ...`.")
    sub = ap.add_subparsers(dest="command", required=True, metavar="{reconstruct,plot}")
    rec = sub.add_parser("reconstruct", help="reconstruct every aircraft into --out",
                         description="Reconstruct every aircraft of RECORDING into --out "
                         "(Parquet, CSV, GeoJSON lines, sensor statistics, map, summary); "
                         "a rerun resumes.")
    _inputs(rec)
    rec.add_argument("--scheduler", default=None, help="address of an existing Dask "
                     "scheduler (default: an embedded LocalCluster)")
    rec.add_argument("--workers", type=_count, default=None, help="embedded cluster's worker "
                     "processes (default: the usable cores)")
    rec.add_argument("--time-limit", type=partial(_seconds, zero=True), default=300.0,
                     help="per-track limit (s; 0: none)")
    rec.add_argument("--decode", choices=("local", "cluster", "auto"), default="local",
                     help="where ASTERIX is decoded: in this process, a reading thread "
                     "overlapping the reconstruction (default; the faster on one machine, "
                     "benchmarks/results/recording.md), on the cluster's workers, or auto: "
                     "on the cluster when it has more than one worker")
    _method(rec, "refined")
    _bounds(rec, [])
    rec.add_argument("--filters", nargs="+", default=[], choices=FILTER_NAMES,
                     metavar="FILTER", help="recursive filters run beside the reconstruction "
                     f"into --out/filters.parquet ({', '.join(FILTER_NAMES)})")
    rec.add_argument("--filter-gate", type=_gate, default=FILTER_GATE_SIGMA, metavar="SIGMA",
                     help="the filters' validation gate: a plot farther than SIGMA sigmas from "
                     "a filter's prediction, and not borne out by the next plot, is left out "
                     f"(filters.parquet's gated column); 'off': every plot used (default "
                     f"{FILTER_GATE_SIGMA:g}; alpha_beta and fusion_* use every plot)")
    rec.add_argument("--aircraft", nargs="+", default=None, metavar="KEY",
                     help="reconstruct only these aircraft (keys as in tracks.parquet, e.g. a "
                     "Mode S address 3C6DD4, in either case; a key takes its later pieces "
                     "KEY#2 ... too); the whole recording is still read, and a key it does not "
                     "hold makes the exit status 2 after the others are written")
    rec.add_argument("--samples", type=_seconds, default=None, metavar="STEP",
                     help="also write every track's state every STEP seconds (from its first "
                     "plot to its last, with the covariance) into --out/samples.parquet")
    rec.add_argument("--figures", action="store_true", help="also draw every track's figure")
    rec.add_argument("--retry-failed", action="store_true", help="redo tracks that failed in "
                     "an earlier run")
    rec.add_argument("--no-progress", action="store_true", help="no progress bar")
    plot = sub.add_parser("plot", help="draw figures of named aircraft and the map",
                          description="Draw --out/figures/<aircraft>.png for each named "
                          "aircraft of RECORDING (its plots with their ellipses, the "
                          "reconstruction, the controls over time; reconstructed again here "
                          "with the method and bounds of the run in --out, if there is one) "
                          "and, with --map, --out/map.png from the tracks `reconstruct` wrote "
                          "there. The reading stops once every named aircraft is complete.")
    _inputs(plot)
    plot.add_argument("--aircraft", nargs="+", default=[], metavar="KEY",
                      help="aircraft keys as in tracks.parquet (e.g. a Mode S address 3C6DD4)")
    plot.add_argument("--map", action="store_true", help="redraw map.png and sensors.png "
                      "from --out's tracks")
    _method(plot, None)
    _bounds(plot, None)
    return ap


def _seconds(text: str, *, zero: bool = False) -> float:
    """A finite number of seconds: positive (``--samples``), or 0 too (``zero``:
    ``--time-limit``, where 0 is no limit)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not ((0 <= value) if zero else (0 < value)) or value == math.inf:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds >= 0" if zero
                                         else f"{text!r} is not a positive number of seconds")
    return value


def _gate(text: str) -> float | None:
    """``--filter-gate``: a positive number of sigmas, or ``off``."""
    if text.strip().lower() == "off":
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of sigmas or off")
    return value


def _count(text: str) -> int:
    """``--workers``: a positive whole number."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive whole number")
    return value


def _inputs(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("recording", help="raw ASTERIX file, pcap/pcapng capture, or "
                    ".csv/.parquet table")
    ap.add_argument("--sensors", required=True, help="sensor file (JSON, solver/io/README.md)")
    ap.add_argument("--out", required=True, help="output directory")


def _method(ap: argparse.ArgumentParser, default: str | None) -> None:
    """``--method`` and the sliding windows' settings (``default`` None: the run's in --out)."""
    d = ReconstructionConfig()
    run = "" if default else "; default: the run's in --out"
    ap.add_argument("--method", choices=("refined", "sliding"), default=default,
                    help="refined (the full-track NLP, default) or sliding (the seed's windows "
                    "alone, over every sensor's plots in time order; no covariance, no sensor "
                    f"offsets){run}")
    ap.add_argument("--window-plots", type=int, default=None, metavar="M",
                    help=f"sliding: plots per window (>= 2; default {d.window_plots}{run})")
    ap.add_argument("--trial-step", type=float, default=None, metavar="S",
                    help="sliding: spacing of the extra trial start points between plots (s, "
                    f"> 0; default {d.trial_step_s:g}{run})")
    ap.add_argument("--criterion", choices=("R1", "R2"), default=None,
                    help="sliding: window fit criterion, R1 plain least squares or R2 weighted "
                    f"by each plot's ellipse (default {d.criterion}{run})")


def _windows(args: argparse.Namespace, run: RunSettings) -> dict[str, Any]:
    """The sliding windows' settings given on the command line, else ``run``'s; checked
    (:class:`InputError` at ``window.plots`` / ``window.trial_step_s``)."""
    out = {"window_plots": run.window_plots if args.window_plots is None else args.window_plots,
           "trial_step_s": run.trial_step_s if args.trial_step is None else args.trial_step,
           "criterion": args.criterion or run.criterion}
    ReconstructionConfig(**out).validate()
    return out


def _bounds(ap: argparse.ArgumentParser, default: list[str] | None) -> None:
    d = Bounds()
    ap.add_argument("--bounds", nargs="+", default=default, metavar="NAME=MIN,MAX",
                    help="the aircraft model's bounds for every track: u (lateral "
                    "acceleration, m/s^2), w (longitudinal, m/s^2), v (ground speed, m/s); "
                    f"unnamed ones keep their defaults u={d.u[0]:g},{d.u[1]:g} "
                    f"w={d.w[0]:g},{d.w[1]:g} v={d.v[0]:g},{d.v[1]:g} (e.g. --bounds v=15,250 "
                    "for slower aircraft)" + ("" if default is not None else "; default: the "
                                              "run's in --out"))


def plot(args: argparse.Namespace) -> list[Path]:
    """The figures of ``trajrecon plot``; raises :class:`InputError` for an aircraft not in
    the recording or a map without tracks."""
    from .figures import save, track_figure
    from .reconstruct import reconstruct

    out = Path(args.out)
    if not args.aircraft and not args.map:
        raise InputError(("aircraft",), "name at least one aircraft, or --map")
    written: list[Path] = []
    wanted = {_normal_key(k) for k in args.aircraft}  # a Mode S address in either case
    run = stored_settings(out) or RunSettings()
    bounds = run.bounds if args.bounds is None else parse_bounds(args.bounds)
    # its plane: after the first part; its aircraft told apart as the run's
    loaded = stream(Path(args.recording), Path(args.sensors), max_speed=bounds.v[1])
    if wanted:
        config = RunSettings(args.method or run.method, bounds, **_windows(args, run)).config()
        for track in loaded.tracks:
            if track.key not in wanted:
                continue
            rec = reconstruct(track.table, config=config)
            written.append(save(track_figure(track.table, rec, title=track.key,
                                             times_of_day=bool(loaded.times_of_day)),
                                out / "figures" / f"{_safe(track.key)}.png"))
            wanted.discard(track.key)
            if not wanted:
                break
        if wanted:
            raise InputError(("aircraft",), f"{', '.join(sorted(wanted))} not in the "
                             f"recording (or too short to reconstruct: {out}/problems.txt "
                             "of a reconstruct run names them)")
    if args.map:
        path = write_map(out, loaded.sensors, frame=loaded.frame)
        if path is None:
            raise InputError(("out",), f"{out} holds no reconstructed track: run "
                             "`trajrecon reconstruct` first")
        written.append(path)
        radars = write_sensors_figure(out, [s.id for s in loaded.sensors.sensors])
        if radars is not None:
            written.append(radars)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """Exit status: 0 all tracks done (or figures drawn), 1 some failed (in this run, or in an
    earlier one of the output directory and not retried), 2 bad input (also a recording of
    which no aircraft's track could be read), 130 /
    143 stopped by SIGINT / SIGTERM (the cluster closed, the finished tracks kept: the same
    command resumes)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] not in (*COMMANDS, "-h", "--help"):
        argv.insert(0, "reconstruct")  # the form before the subcommands
    args = parser().parse_args(argv)
    if args.command == "plot":
        try:
            for path in plot(args):
                print(path)
        except (InputError, *UNUSABLE_PATH) as e:
            print(f"trajrecon: {e}", file=sys.stderr)
            return 2
        return 0
    quiet_interrupted_sync()
    try:
        with STOP_SIGNALS.installed():
            result = run(args)
    except (InputError, *UNUSABLE_PATH) as e:
        print(f"trajrecon: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        name = "SIGTERM" if isinstance(e, Stopped) else "SIGINT"
        print(f"trajrecon: stopped by {name}; {len(ledger_entries(args.out))} finished "
              f"tracks are kept in {args.out}: the same command resumes from there",
              file=sys.stderr)
        return 143 if isinstance(e, Stopped) else 130
    print_summary(result)
    if not result["tracks"] and result.get("aircraft") is None:
        print(f"trajrecon: no aircraft's track could be read from {args.recording} (what was "
              f"left out, and why: {Path(args.out) / 'problems.txt'})", file=sys.stderr)
        return 2
    if result.get("aircraft_not_found"):
        print(f"trajrecon: not in the recording (or too short to reconstruct: "
              f"{Path(args.out) / 'problems.txt'} names those): "
              f"{', '.join(result['aircraft_not_found'])}", file=sys.stderr)
        return 2
    return 1 if result["output"]["tracks_failed"] else 0


if __name__ == "__main__":
    # ``python -m solver.cli`` runs this file as ``__main__``, whose functions Dask pickles by
    # value: the task (8.5 KB) with its result class and helpers, and every result twice (plain
    # pickle, then cloudpickle on seeing ``__main__``; 3.1 ms a track instead of 1.1). The
    # importable module's ``main`` submits ``solver.cli.assess_track``, pickled by reference.
    from solver.cli import main as _main

    raise SystemExit(_main())
