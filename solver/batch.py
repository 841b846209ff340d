"""Many aircraft at once: :func:`reconstruct_many` over an executor, results streamed to disk.

The scale-out engine is Dask distributed (no home-made scheduler): by default an embedded
``LocalCluster`` of worker processes (one thread each, as many as usable cores), or the
cluster of an existing scheduler when its address is named; any ``concurrent.futures``-style
executor (``submit`` returning futures) works too. Each track is one task,
:func:`solve_track`, which never raises for a track's own failure: a bad table, a solver
failure or the per-track time limit (a deadline passed into the solver, so it works inside any
worker, no signals) come back as a ``failed`` :class:`TrackOutcome` with the reason, and the
other tracks go on. A task whose worker died (Dask retries it on another worker first) is
reported as failed too.

Memory is bounded however long the recording: the problems are consumed lazily with at most
``max_in_flight`` tasks submitted, and finished tracks are written as they come, in parts::

    OUT/tracks.parquet/part-000001.parquet    states at every plot (see TRACK_COLUMNS)
    OUT/segments.parquet/part-000001.parquet  constant-control segments (SEGMENT_COLUMNS)
    OUT/filters.parquet/part-000001.parquet   the recursive filters asked for (FILTER_COLUMNS)
    OUT/samples.parquet/part-000001.parquet   states on a regular time step, when asked
                                              (SAMPLE_COLUMNS)
    OUT/figure_data.parquet/part-000001.parquet  what the tracks' figures need beside these,
                                              when the task keeps it (a service job's:
                                              solver.figure_data.FIGURE_COLUMNS)
    OUT/progress.jsonl                        one line per finished track (the commit log)

A part is written to a temporary name and renamed, then its tracks' lines are appended to
``progress.jsonl`` (flushed and synced): a track is finished exactly when its line is there.
A rerun with the same ``OUT`` resumes: tracks with a line are skipped, parts without one (a
run killed between the two steps) are deleted, so every track appears once. Read the results
with ``pyarrow.parquet.read_table(OUT / "tracks.parquet")``.

The embedded cluster starts worker processes by spawning: a script that calls
:func:`reconstruct_many` without an executor must do so under ``if __name__ == "__main__":``.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import logging
import math
import os
import re
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from .config import FILTER_GATE_SIGMA, MAX_SAMPLES, ReconstructionConfig
from .figure_data import FIGURE_DATA
from .inputs import FloatArray
from .io.dates import UTC, utc_times
from .plots import PlotTable
from .results import PlotResiduals, StateSeries, full_turn, non_finite_part
from .stopping import STOP_SIGNALS

COV_COLUMNS = ("cov_x_x", "cov_x_z", "cov_x_vx", "cov_x_vz", "cov_z_z", "cov_z_vx", "cov_z_vz",
               "cov_vx_vx", "cov_vx_vz", "cov_vz_vz")
RESIDUAL_COLUMNS = ("plot_range_m", "plot_azimuth_deg", "plot_altitude_m", "range_residual_m",
                    "azimuth_residual_deg", "position_residual_m", "along_track_residual_m",
                    "cross_track_residual_m", "gated", "wild", "no_reference")
TRACK_COLUMNS = ("aircraft", "plot", "source", "sensor", "t", "time_of_day_s", "time_utc", "x",
                 "z", "lat_deg", "lon_deg", "vx", "vz", "speed", "heading_deg", *COV_COLUMNS,
                 "h_m", "h_sigma_m", *RESIDUAL_COLUMNS)
"""Columns of ``tracks.parquet``: one row per plot (``plot``: its index in the track's table, time
order; ``source``: where the plot is in the input, as the problems name places: ``byte 1234`` of
an ASTERIX file or capture, ``row 17`` of a plot table, ``tracks.A[3]`` of a job's JSON body;
null when the input has no such place), ``t`` (s; from the UTC midnight before the recording's
first plot when the recording is timed by time of day, as ASTERIX is) and ``time_of_day_s``
(``t`` modulo a day then, else null), ``time_utc`` (``t`` as a UTC time, timestamp[us, UTC],
where the recording's date is known: :mod:`solver.io.dates`; else null), positions in the
recording's plane (m; ``x`` north, ``z`` east) and on WGS-84, velocity in the plane (m/s),
speed over the ground (m/s) and heading from true north (deg clockwise;
:meth:`solver.results.StateSeries.heading_deg_and_speed`), the covariance over
``(x, z, vx, vz)`` (upper triangle), the estimated height with its sigma where it was
estimated (else null), and the plot against the state, as the sensors' statistics take it
(:func:`solver.refine.output.plot_residuals`): a radar plot's measured slant range and azimuth
(``plot_range_m``, ``plot_azimuth_deg``), the altitude a plot was placed at
(``plot_altitude_m``: Mode C made geometric by the aircraft's ADS-B where it could be,
:mod:`solver.io.altitudes`; ADS-B's geometric height; null without one) and its residuals
after the sensor's estimated offsets
(``range_residual_m``, ``azimuth_residual_deg``), a position plot's horizontal distance
(``position_residual_m``) and its parts along and across the track (``along_track_residual_m``:
ahead of the state positive, a late report's is negative; ``cross_track_residual_m``: right of
the track positive); null where they do not apply or the method gives none; ``gated``: given no
weight as wild; ``wild``: out of reach of the track's other plots, or far out in the sensor's
own residuals' spread (a radar's, :func:`solver.refine.output.statistics_wild`; another
sensor's gated plots); ``no_reference``: in a stretch the aircraft's bounds bend the track off,
where it is no reference for the sensors (:func:`solver.refine.output.no_reference_mask`). The
sensors' statistics (``sensors.json``, ``sensors.png``) leave out both."""
FILTER_COLUMNS = ("aircraft", "filter", "plot", "sensor", "t", "time_of_day_s", "time_utc", "x",
                  "z", "lat_deg", "lon_deg", "vx", "vz", *COV_COLUMNS, "gated")
"""Columns of ``filters.parquet``: each recursive filter's state after every plot (the names of
:data:`solver.estimation.FILTER_NAMES`), as ``tracks.parquet``; ``gated``: the filter left the
plot out, far from its prediction (:mod:`solver.estimation.gating`)."""
SAMPLE_COLUMNS = ("aircraft", "t", "time_of_day_s", "time_utc", "x", "z", "lat_deg", "lon_deg",
                  "vx", "vz", "speed", "heading_deg", *COV_COLUMNS, "h_m", "h_sigma_m")
"""Columns of ``samples.parquet``: the reconstructed state every ``sample_step_s`` from the
track's first plot to its last (the last plot's time always included), propagated from the
solution with its covariance, as the single-track answer's ``trajectory.samples``."""
SEGMENT_COLUMNS = ("aircraft", "t_start", "t_end", "time_utc_start", "time_utc_end", "x", "z",
                   "heading_deg", "speed", "u", "w")
"""Columns of ``segments.parquet``: the constant-control pieces, their ends' ``t`` and, as
``time_utc`` of ``tracks.parquet``, their UTC times (null without the date)."""
_TYPES = {"aircraft": pa.string(), "sensor": pa.string(), "filter": pa.string(),
          "source": pa.string(), "plot": pa.int32(), "gated": pa.bool_(),
          "wild": pa.bool_(), "no_reference": pa.bool_(), "time_utc": UTC,
          "time_utc_start": UTC, "time_utc_end": UTC}  # others: float64


def read_part(path: Path, names: Sequence[str] = TRACK_COLUMNS) -> pa.Table:
    """A Parquet part with exactly the columns ``names``, in that order. A part written before
    a column existed (a run resumed across an upgrade of this package) gets it as nulls, so
    parts of both kinds make one table (CSV, combined Parquet)."""
    table = pq.read_table(path)
    for name in names:
        if name not in table.column_names:
            table = table.append_column(name, pa.nulls(table.num_rows,
                                                       _TYPES.get(name, pa.float64())))
    return table.select(list(names))


LOG = logging.getLogger(__name__)
PROGRESS = "progress.jsonl"
_PART = re.compile(r"part-(\d{6})\.parquet|\.part-\d{6}\.parquet\.tmp")


@dataclass(frozen=True)
class TrackProblem:
    """One aircraft to reconstruct: its key and its validated plots table."""

    key: str
    table: PlotTable


@dataclass
class TrackOutcome:
    """What became of one track: ``done`` (with its rows) or ``failed`` (with the reason)."""

    key: str
    status: Literal["done", "failed"]
    plots: int
    elapsed_s: float
    error: str | None = None
    warnings: list[str] = field(default_factory=list)
    states: pa.Table | None = None
    segments: pa.Table | None = None
    extras: dict[str, Any] = field(default_factory=dict)
    filters: pa.Table | None = None
    samples: pa.Table | None = None
    cpu_s: float | None = None  # the task thread's CPU time (elapsed_s - cpu_s: waiting)
    diagnostics: dict[str, Any] | None = None
    altitude: dict[str, float] | None = None
    figure: pa.Table | None = None  # figure_data.parquet's rows (solver.figure_data)

    def ledger(self, part: str | None) -> dict[str, Any]:
        """The track's line of ``progress.jsonl``; ``diagnostics``: the reconstruction's
        (:meth:`solver.results.Diagnostics.as_dict` without the warnings, which are the
        track's), ``altitude``: the height estimated for the whole track (``m``, ``sigma_m``)
        where it was."""
        return {"aircraft": self.key, "status": self.status, "plots": self.plots,
                "elapsed_s": round(self.elapsed_s, 4),
                "cpu_s": None if self.cpu_s is None else round(self.cpu_s, 4), "error": self.error,
                "warnings": self.warnings, "part": part, "diagnostics": self.diagnostics,
                "altitude": self.altitude}


@dataclass
class BatchSummary:
    """Counts of one :func:`reconstruct_many` run (``skipped``: finished by an earlier run),
    the plots of the tracks reconstructed now and their rate, and every failure's reason."""

    tracks: int = 0
    done: int = 0
    failed: int = 0
    skipped: int = 0
    plots: int = 0
    elapsed_s: float = 0.0
    failures: dict[str, str] = field(default_factory=dict)

    @property
    def plots_per_s(self) -> float:
        return self.plots / self.elapsed_s if self.elapsed_s > 0 else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "plots_per_s": self.plots_per_s}


# ------------------------------------------------------------------------------- the task


def solve_track(key: str, table: PlotTable, config: ReconstructionConfig | None = None,
                time_limit_s: float | None = None,
                extras: Callable[[Any], dict[str, Any]] | None = None, *,
                filters: Sequence[str] = (), filter_gate: float | None = FILTER_GATE_SIGMA,
                times_of_day: bool = False, samples: bool = False,
                max_samples: int | None = MAX_SAMPLES, date: str | None = None) -> TrackOutcome:
    """Reconstruct one track (runs on a worker). Any ``Exception`` of the track (bad input,
    solver failure, the deadline ``time_limit_s`` after the start) is returned as a failed
    outcome naming it; the result's rows come back as Arrow tables. ``extras(reconstruction)``
    (e.g. per-sensor statistics, a figure) fills ``TrackOutcome.extras``, on the worker.
    ``filters``: recursive filters run beside (:data:`FILTER_COLUMNS`); one that cannot run on
    this track (e.g. a two-sensor fusion on one sensor) is a warning, not a failure;
    ``filter_gate``: their validation gate (sigmas; None: none, :mod:`solver.estimation.gating`).
    ``times_of_day``: ``t`` counts from a UTC midnight (``time_of_day_s`` is filled);
    ``date``: that midnight's UTC date (``time_utc`` is filled; :mod:`solver.io.dates`).
    ``samples``: keep the states every ``config.sample_step_s`` (:data:`SAMPLE_COLUMNS`);
    a track that would have more than ``max_samples`` (default
    :data:`solver.config.MAX_SAMPLES`; None: no limit) keeps none, with a warning. A failure's
    reason is one line (:func:`failure_reason`)."""
    from .reconstruct import reconstruct

    start, cpu = time.perf_counter(), time.thread_time()
    deadline = None if time_limit_s is None else time.monotonic() + time_limit_s
    config = config or ReconstructionConfig()
    warnings: list[str] = []
    try:
        if samples and max_samples is not None and len(table):
            span = float(table.t.max() - table.t.min())
            if span / config.sample_step_s >= max_samples:
                warnings.append(f"samples: none kept: sample_step_s {config.sample_step_s:g} "
                                f"gives {math.floor(span / config.sample_step_s) + 1} samples "
                                f"over the {span:g}-s track, the limit is {max_samples} (max_"
                                "samples); ask a step of at least "
                                f"{span / (max_samples - 1) if max_samples > 1 else span:.3g} s")
                samples, config = False, replace(config, sample_step_s=span / 2 or 1.0)
        rec = reconstruct(table, config=config, deadline=deadline)
        bad = non_finite_part(rec)
        if bad is not None:  # failed here, not stored (its every later read would fail)
            raise ArithmeticError(f"the result is not finite ({bad} holds NaN or infinity): "
                                  "the bounds, sensor errors or plots are too extreme for a "
                                  "numerical solution")
        clock = (times_of_day, date)
        states = _states_table(key, table, rec.at_plots, clock, rec.residuals)
        segments = _segments_table(key, rec, clock)
        sampled = _samples_table(key, table, rec.samples, clock) if samples else None
        more = extras(rec) if extras is not None else {}
        warnings += rec.diagnostics.warnings
        t_filters = time.perf_counter()
        filtered = _filters_table(key, table, filters, clock, warnings,
                                  rec.at_plots.h, filter_gate, rec.no_weight)
        filters_ms = 1e3 * (time.perf_counter() - t_filters) if filters else 0.0
        diagnostics = rec.diagnostics.as_dict()
        del diagnostics["warnings"]
        diagnostics["filters_ms"] = filters_ms
        altitude = (None if rec.altitude_m is None else
                    {"m": float(rec.altitude_m), "sigma_m": float(rec.altitude_sigma_m or 0.0)})
    except Exception as e:  # isolated: one track's failure is its own
        return TrackOutcome(key, "failed", len(table), time.perf_counter() - start,
                            failure_reason(key, e), cpu_s=time.thread_time() - cpu)
    return TrackOutcome(key, "done", len(table), time.perf_counter() - start, None,
                        warnings, states, segments, more, filtered, sampled,
                        cpu_s=time.thread_time() - cpu, diagnostics=diagnostics,
                        altitude=altitude)


def failure_reason(key: str, error: BaseException) -> str:
    """A track's failure as one line, ``Type: first line of the message`` (the summary's and
    ``progress.jsonl``'s reason); a longer message (Dask's error for a result it could not
    pickle holds a whole traceback: 2.9 KB over 40 lines for a tester's track) is logged
    whole here, with the traceback, and the line says so."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    reason = f"{type(error).__name__}: {lines[0]}" if lines else type(error).__name__
    if len(lines) > 1:
        LOG.error("track %s failed: %s", key, error, exc_info=error)
        reason += " (the rest in the log)"
    return reason


Clock = tuple[bool, str | None]
"""``(times_of_day, date)`` of :func:`solve_track`: how ``t`` is placed in the day."""


def _state_columns(key: str, table: PlotTable, s: StateSeries, clock: Clock
                   ) -> dict[str, Any]:
    """The columns shared by ``tracks.parquet`` and ``filters.parquet``."""
    cols = _kinematics(key, table, s, clock)
    cols.update(plot=pa.array(np.arange(len(s)), pa.int32()), sensor=pa.array(
        [table.sensors[k].id for k in table.sensor.tolist()], pa.string()))
    return cols


def _kinematics(key: str, table: PlotTable, s: StateSeries, clock: Clock
                ) -> dict[str, Any]:
    """Time, position (plane and WGS-84), velocity and covariance columns of ``s``."""
    n = len(s)
    cov = s.cov if s.cov is not None else np.full((n, 4, 4), np.nan)
    lat, lon = s.lat_deg, s.lon_deg
    if lat is None and table.frame is not None:
        lat, lon = table.frame.to_geodetic(s.x, s.z)
    cols: dict[str, Any] = {
        "aircraft": pa.array([key] * n, pa.string()),
        "t": s.t, "time_of_day_s": np.mod(s.t, 86_400.0) if clock[0] else None,
        "time_utc": utc_times(s.t, clock[1] if clock[0] else None),
        "x": s.x, "z": s.z, "lat_deg": lat, "lon_deg": lon, "vx": s.vx, "vz": s.vz}
    iu = np.triu_indices(4)
    cols.update(zip(COV_COLUMNS, cov[:, iu[0], iu[1]].T, strict=True))
    return cols


def _samples_table(key: str, table: PlotTable, s: StateSeries, clock: Clock
                   ) -> pa.Table:
    cols = _kinematics(key, table, s, clock)
    heading, speed = s.heading_deg_and_speed(table.frame)
    cols.update(speed=speed, heading_deg=heading, h_m=s.h, h_sigma_m=s.h_sigma)
    return _arrow(cols, SAMPLE_COLUMNS, len(s))


_NULLABLE = frozenset({"time_of_day_s", "lat_deg", "lon_deg", "h_m", "h_sigma_m",
                       *RESIDUAL_COLUMNS[:-2]})
"""Columns whose NaN means "not known" (null in Parquet); elsewhere a NaN stays a NaN."""


def _arrow(cols: dict[str, Any], names: Sequence[str], n: int) -> pa.Table:
    return pa.table({k: cols[k] if isinstance(cols[k], pa.Array) else
                     _nullable(cols[k], n) if k in _NULLABLE else
                     pa.array(np.asarray(cols[k], float), pa.float64()) for k in names})


def _states_table(key: str, table: PlotTable, s: StateSeries, clock: Clock,
                  residuals: PlotResiduals | None = None) -> pa.Table:
    cols = _state_columns(key, table, s, clock)
    heading, speed = s.heading_deg_and_speed(table.frame)
    cols.update(speed=speed, heading_deg=heading, h_m=s.h, h_sigma_m=s.h_sigma)
    n, res = len(s), residuals
    cols.update(  # the table's range and azimuth are NaN on position rows
        plot_range_m=table.range_m, plot_azimuth_deg=np.rad2deg(table.azimuth_rad),
        plot_altitude_m=table.altitude_m,
        range_residual_m=None if res is None else res.range_m,
        azimuth_residual_deg=None if res is None else np.rad2deg(res.azimuth_rad),
        position_residual_m=None if res is None else res.position_m,
        along_track_residual_m=None if res is None else res.along_m,
        cross_track_residual_m=None if res is None else res.cross_m,
        gated=pa.array(np.zeros(n, bool) if res is None else res.gated, pa.bool_()),
        wild=pa.array(np.zeros(n, bool) if res is None or res.wild is None else res.wild,
                      pa.bool_()),
        no_reference=pa.array(np.zeros(n, bool) if res is None or res.no_reference is None
                              else res.no_reference, pa.bool_()),
        source=pa.nulls(n, pa.string()))  # named by reconstruct_many (with_sources)
    return _arrow(cols, TRACK_COLUMNS, n)


def source_names(origin: np.ndarray, unit: str) -> pa.Array:
    """The ``source`` of plots at ``origin`` (``unit``: ``byte`` or ``row``, as
    :class:`solver.io.tables.PlotRows`): ``"byte 1234"``, as the problems name places."""
    numbers = pc.cast(pa.array(np.asarray(origin, dtype=np.int64)), pa.string())
    return pc.binary_join_element_wise(f"{unit} ", numbers, "")


def with_sources(states: pa.Table, names: pa.Array) -> pa.Table:
    """``states`` (:data:`TRACK_COLUMNS`) with ``source`` the names of its plots (``names[i]``:
    the track's plot ``i``)."""
    i = states.column_names.index("source")
    return states.set_column(i, "source", names.take(states.column("plot")))


def _filters_table(key: str, table: PlotTable, names: Sequence[str], clock: Clock,
                   warnings: list[str], heights: FloatArray | None = None,
                   gate: float | None = FILTER_GATE_SIGMA,
                   no_weight: np.ndarray | None = None) -> pa.Table | None:
    """Every named filter's states (:data:`FILTER_COLUMNS`); a filter that raises (its rows
    left out, the track kept) or falls back adds its reason to ``warnings``. ``heights``: the
    reconstruction's estimated heights, for radar plots without altitude
    (:func:`solver.estimation.measurements.at_estimated_heights`); ``gate``: the validation
    gate of the filters that have one; the gates' warnings
    (:func:`solver.estimation.gating.gate_warnings`; ``no_weight``: the reconstruction's wild
    plots)."""
    if not names:
        return None
    from .estimation import gate_param, run_filter
    from .estimation.gating import gate_warnings
    from .estimation.measurements import at_estimated_heights

    table = at_estimated_heights(table, heights)

    parts = []
    gated: dict[str, list[int]] = {}
    for name in names:
        try:
            est = run_filter(name, table, **gate_param(name, gate))
        except Exception as e:  # the reconstruction stands without this filter's rows
            warnings.append(f"filters.{name}: {e}" if isinstance(e, ValueError)
                            else f"filters.{name}: {type(e).__name__}: {e}")
            continue
        if "warning" in est.info:
            warnings.append(f"filters.{name}: {est.info['warning']}")
        cols = _state_columns(key, table, est.states, clock)
        cols["filter"] = pa.array([name] * len(table), pa.string())
        left_out = np.asarray(est.info.get("gated", np.zeros(len(table), bool)), bool)
        gated[name] = np.flatnonzero(left_out).tolist()
        cols["gated"] = pa.array(left_out, pa.bool_())
        parts.append(_arrow(cols, FILTER_COLUMNS, len(table)))
    warnings.extend(gate_warnings(gated, np.zeros(0, int) if no_weight is None else no_weight))
    return pa.concat_tables(parts) if parts else None


def _nullable(a: Any, n: int) -> pa.Array:
    if a is None:
        return pa.nulls(n, pa.float64())
    return pa.array(np.asarray(a, float), pa.float64(), from_pandas=True)


def _segments_table(key: str, rec: Any, clock: Clock) -> pa.Table:
    segs = rec.segments
    date = clock[1] if clock[0] else None
    return pa.table({
        "aircraft": pa.array([key] * len(segs), pa.string()),
        "t_start": pa.array([g.t_start for g in segs], pa.float64()),
        "t_end": pa.array([g.t_end for g in segs], pa.float64()),
        "time_utc_start": utc_times(np.array([g.t_start for g in segs], float), date),
        "time_utc_end": utc_times(np.array([g.t_end for g in segs], float), date),
        "x": pa.array([g.x for g in segs], pa.float64()),
        "z": pa.array([g.z for g in segs], pa.float64()),
        "heading_deg": pa.array([float(full_turn(np.rad2deg(g.heading), 360.0)) for g in segs],
                                pa.float64()),
        "speed": pa.array([g.speed for g in segs], pa.float64()),
        "u": pa.array([g.u for g in segs], pa.float64()),
        "w": pa.array([g.w for g in segs], pa.float64())})


# ------------------------------------------------------------------------------- output


def ledger_entries(out: str | Path) -> list[dict[str, Any]]:
    """The finished tracks' lines of ``OUT/progress.jsonl``, in order (none without it; a
    killed run's torn last line is not one)."""
    path = Path(out) / PROGRESS
    if not path.exists():
        return []
    entries = []
    for line in path.read_bytes().split(b"\n"):
        try:
            entries.append(json.loads(line))
        except ValueError:  # a torn last line of a killed run, or the empty tail
            continue
    return entries


def _upgrade(part: Path) -> None:
    """A committed ``tracks.parquet`` part written before a column of :data:`TRACK_COLUMNS`
    existed, rewritten with it (null) in place: reading the directory as one table takes the
    first part's schema, and a resumed run's ``source`` column was lost whole (a tester's)."""
    if tuple(pq.read_schema(part).names) == TRACK_COLUMNS:
        return
    tmp = part.with_name(f".{part.name}.tmp")
    pq.write_table(read_part(part), tmp)
    os.replace(tmp, part)
    LOG.info("upgraded %s to this version's columns", part)


class _Store:
    """The output directory: parts, the progress ledger, resume."""

    def __init__(self, out: Path):
        self.out = out
        self.tracks_dir = out / "tracks.parquet"
        self.segments_dir = out / "segments.parquet"
        self.filters_dir = out / "filters.parquet"  # made when a track has filters
        self.samples_dir = out / "samples.parquet"  # made when a track has samples
        self.figure_dir = out / FIGURE_DATA  # made when a track has figure data
        for d in (self.tracks_dir, self.segments_dir):
            d.mkdir(parents=True, exist_ok=True)
        self.ledger_path = out / PROGRESS
        self.finished: dict[str, str] = {}  # aircraft -> status, of the earlier runs
        parts: set[str] = set()
        if self.ledger_path.exists():
            lines = [x for x in self.ledger_path.read_bytes().split(b"\n") if x]
            entries = ledger_entries(out)
            for entry in entries:
                self.finished[entry["aircraft"]] = entry["status"]
                if entry.get("part"):
                    parts.add(entry["part"])
            if len(entries) != len(lines):  # the torn line dropped (written as commit() does)
                self._rewrite([json.dumps(e).encode() for e in entries])
        numbers = [0]
        for d in (self.tracks_dir, self.segments_dir, self.filters_dir, self.samples_dir,
                  self.figure_dir):
            if not d.is_dir():
                continue
            for f in d.iterdir():
                ours = _PART.fullmatch(f.name)
                if ours is None:
                    continue  # not this module's file: left alone
                if f.name not in parts:  # not committed: a killed run's, redone now
                    f.unlink()
                elif ours.group(1):
                    numbers.append(int(ours.group(1)))
                    if d == self.tracks_dir:
                        _upgrade(f)
        self.next_part = max(numbers) + 1

    def _rewrite(self, lines: list[bytes]) -> None:
        tmp = self.ledger_path.with_suffix(".tmp")
        tmp.write_bytes(b"".join(x + b"\n" for x in lines))
        os.replace(tmp, self.ledger_path)

    def commit(self, outcomes: list[TrackOutcome]) -> None:
        """Write the done tracks' rows as one part, then their ledger lines."""
        done = [o for o in outcomes if o.status == "done"]
        part = None
        if done:
            part = f"part-{self.next_part:06d}.parquet"
            self.next_part += 1
            for d, tables in ((self.tracks_dir, [o.states for o in done]),
                              (self.segments_dir, [o.segments for o in done]),
                              (self.filters_dir, [o.filters for o in done]),
                              (self.samples_dir, [o.samples for o in done]),
                              (self.figure_dir, [o.figure for o in done])):
                tables = [t for t in tables if t is not None]
                if not tables:
                    continue
                d.mkdir(exist_ok=True)
                tmp = d / f".{part}.tmp"
                pq.write_table(pa.concat_tables(tables), tmp)  # type: ignore[arg-type]
                os.replace(tmp, d / part)
        with open(self.ledger_path, "a", encoding="utf-8") as f:
            for o in outcomes:
                entry = o.ledger(part if o.status == "done" else None)
                f.write(json.dumps(entry) + "\n")  # not kept: a run gives a key once
            f.flush()
            os.fsync(f.fileno())


# ------------------------------------------------------------------------------- engine


def reconstruct_many(problems: Iterable[TrackProblem | Any], out_dir: str | Path, *,
                     config: ReconstructionConfig | None = None, executor: Any = None,
                     scheduler: str | None = None, workers: int | None = None,
                     time_limit_s: float | None = 300.0, max_in_flight: int | None = None,
                     flush_tracks: int = 32, flush_s: float = 5.0, retry_failed: bool = False,
                     on_outcome: Callable[[TrackOutcome], None] | None = None,
                     task: Callable[..., TrackOutcome] = solve_track,
                     sources: Callable[[Any], pa.Array | None] | None = None) -> BatchSummary:
    """Reconstruct every track of ``problems`` (objects with ``key`` and ``table``, e.g.
    :class:`TrackProblem` or :class:`solver.io.split.AircraftTrack`) into ``out_dir``.

    ``executor``: a Dask ``Client`` or any ``concurrent.futures``-style executor; else a Dask
    client of the scheduler at ``scheduler``; else an embedded ``LocalCluster`` of ``workers``
    processes (default: the usable cores), closed at the end. ``time_limit_s``: per track (None:
    none). At most ``max_in_flight`` tracks (default twice the workers) are submitted at once;
    finished tracks are written every ``flush_tracks`` tracks or ``flush_s`` seconds. Tracks
    already in ``out_dir`` are skipped (failed ones too, unless ``retry_failed``); a key given
    twice is refused (``ValueError``). ``on_outcome`` is called with each outcome once it is
    committed to ``out_dir`` (progress; what it records is then never reported twice by a
    resumed run; an exception it raises stops the run, committed tracks kept).
    ``task``: the function run per track, ``task(key, table, config, time_limit_s)``
    (default :func:`solve_track`). ``sources(problem)``: the names of its plots in the input,
    ``tracks.parquet``'s ``source`` (default: from the problem's ``origin`` and
    ``origin_unit`` where it has them, as :class:`solver.io.split.AircraftTrack`, by
    :func:`source_names`; else null). A problem's ``notes`` (where it has them) come first in
    its done track's warnings.
    """
    sources = sources or _origin_sources
    store = _Store(Path(out_dir))
    summary = BatchSummary()
    start = time.perf_counter()
    with _engine(executor, scheduler, workers, config) as (submit, wait, n_workers):
        limit = max_in_flight or max(2 * n_workers, 2)
        pending: dict[Any, str] = {}
        names: dict[str, pa.Array | None] = {}  # the pending tracks' plots' sources
        notes: dict[str, tuple[str, ...]] = {}  # what their answers say first (problem.notes)
        buffer: list[TrackOutcome] = []
        last_flush = time.monotonic()
        seen: set[str] = set()

        def collect(futures: Iterable[Any]) -> None:
            nonlocal last_flush
            for fut in futures:
                key = pending.pop(fut)
                try:
                    outcome: TrackOutcome = fut.result()
                except Exception as e:  # the task itself failed: a worker died repeatedly,
                    # or its result could not be sent back (Dask's error holds a traceback)
                    outcome = TrackOutcome(key, "failed", 0, 0.0, failure_reason(key, e))
                source = names.pop(key, None)
                if source is not None and outcome.states is not None:
                    outcome = replace(outcome, states=with_sources(outcome.states, source))
                said = notes.pop(key, ())
                if said and outcome.status == "done":
                    outcome = replace(outcome, warnings=[*said, *outcome.warnings])
                summary.done += outcome.status == "done"
                summary.failed += outcome.status == "failed"
                summary.plots += outcome.plots if outcome.status == "done" else 0
                if outcome.error is not None:
                    summary.failures[key] = outcome.error
                buffer.append(outcome)
            if buffer and (len(buffer) >= flush_tracks
                           or time.monotonic() - last_flush >= flush_s):
                flush()
                last_flush = time.monotonic()

        def flush() -> None:
            committed = list(buffer)
            store.commit(committed)
            buffer.clear()
            if on_outcome is not None:  # once on disk: a resumed run never reports it again
                for outcome in committed:
                    on_outcome(outcome)

        for problem in _problems(problems):
            key = problem.key
            if key in seen:
                raise ValueError(f"track key {key!r} given twice")
            seen.add(key)
            summary.tracks += 1
            prior = store.finished.get(key)
            if prior is not None and (prior == "done" or not retry_failed):
                summary.skipped += 1
                continue
            while len(pending) >= limit:
                collect(wait(list(pending)))
            names[key] = sources(problem)
            notes[key] = tuple(getattr(problem, "notes", ()))
            pending[submit(task, key, problem.table, config, time_limit_s)] = key
        while pending:
            collect(wait(list(pending)))
        if buffer:
            flush()
    summary.elapsed_s = time.perf_counter() - start
    return summary


def _origin_sources(problem: Any) -> pa.Array | None:
    origin = getattr(problem, "origin", None)
    return None if origin is None else source_names(origin, problem.origin_unit)


def _problems(problems: Iterable[Any]) -> Iterator[Any]:
    for p in problems:
        if not (hasattr(p, "key") and isinstance(getattr(p, "table", None), PlotTable)):
            raise TypeError(f"a problem needs .key and .table (a PlotTable), got {type(p)}")
        yield p


MMAP_THRESHOLD_BYTES = 32 << 20
"""glibc's ``M_MMAP_THRESHOLD`` in the embedded cluster's workers. Dask's nanny sets
``MALLOC_TRIM_THRESHOLD_`` for its workers, and setting any such parameter turns off glibc's
sliding mmap threshold: every array over 128 KiB was then mapped and unmapped afresh (page
faults each time). Measured on 25 tracks of the benchmark recording (13,295 plots), CPU of a
one-worker LocalCluster per plot: Dask's defaults 0.89-0.97 ms, this threshold and the
profiler off 0.68-0.72 ms, ``reconstruct`` in one process 0.58-0.61 ms."""


def dask_settings() -> dict[str, Any]:
    """Dask settings for the embedded cluster and the client (``dask.config.set``): short
    debugging logs (Dask keeps the last 1,000 messages of each batched stream, task messages
    with the tracks' plots among them: memory growing with the tracks), no statistical
    profiler in the workers (a stack sample every 10 ms), :data:`MMAP_THRESHOLD_BYTES`
    beside Dask's own worker environment, and :data:`QUIET_LOOPS`."""
    import dask

    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}) or {})
    environ["MALLOC_MMAP_THRESHOLD_"] = MMAP_THRESHOLD_BYTES
    return {"distributed.admin.low-level-log-length": 16,
            "distributed.worker.profile.enabled": False,
            "distributed.nanny.pre-spawn-environ": environ, **QUIET_LOOPS}


QUIET_LOOPS = {"distributed.admin.tick.interval": "1s",
               "distributed.worker.memory.monitor-interval": "500ms"}
"""Fewer periodic callbacks in the event loops of the scheduler, nannies and workers. Dask's
event-loop health tick runs every 20 ms in every server (it only measures how late it runs, to
warn past ``distributed.admin.tick.limit``, 3 s) and the memory monitors every 100 ms. Measured
on an idle embedded cluster of 2 workers (this machine, 20 s): CPU of a core 6.4% in the main
process and 2.3% in each worker with Dask's defaults, 1.4% and 0.5% with these: on a run of
the 2,000-aircraft benchmark recording (about 630 s on 2 workers) some 50 CPU-seconds, 0.05 ms
a plot, taken from the reconstruction's cores. Memory is still checked twice a second."""


def embedded_cluster(workers: int | None = None) -> Any:
    """A ``LocalCluster`` of ``workers`` single-threaded worker processes (default: the usable
    cores), with a free port for its dashboard (8787 may be another cluster's); create it under
    ``dask.config.set(dask_settings())``."""
    from distributed import LocalCluster

    n = workers or len(os.sched_getaffinity(0))
    return LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                        dashboard_address=":0", preload=[__name__])


def dask_setup(worker: Any) -> None:
    """Dask's preload hook, run in each embedded worker process as it starts: ignore SIGINT
    and drop the warning of a track cancelled by the stop. Ctrl-C in a terminal reaches every
    process of the foreground group; the command line closes its cluster itself, and a worker
    left to the signal printed a KeyboardInterrupt traceback of its own (as the service's
    workers, which ignore it too). Closing the cluster cancels the running tracks, and each
    worker then logged "Async instruction ... ended with CancelledError" (a line per track)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.getLogger("distributed.worker.state_machine").addFilter(_cancelled_by_the_stop)


def _cancelled_by_the_stop(record: Any) -> bool:
    """False for the worker's warning that a running task ended cancelled (the stop's own)."""
    return "ended with CancelledError" not in record.getMessage()


def quiet_interrupted_sync() -> None:
    """In a process whose Dask client a stop interrupts (Ctrl-C, or SIGTERM raised as
    ``KeyboardInterrupt``): drop the traceback Dask's ``distributed.utils.sync`` logs when the
    interrupt lands before its coroutine has made its future. Its ``cancel`` callback then
    reads the unassigned ``future`` (distributed 2026.8: ``NameError: cannot access free
    variable 'future'``, logged by tornado); there is nothing to cancel yet, the interrupt
    itself goes on as it should. Seen once in the test suite's SIGTERM test."""
    logging.getLogger("tornado.application").addFilter(_sync_cancel_before_start)


def _sync_cancel_before_start(record: logging.LogRecord) -> bool:
    exc = record.exc_info[1] if record.exc_info else None
    if not isinstance(exc, NameError) or "'future'" not in str(exc) or exc.__traceback__ is None:
        return True
    tb = exc.__traceback__
    while tb.tb_next is not None:  # the frame that raised
        tb = tb.tb_next
    code = tb.tb_frame.f_code
    return not (code.co_name == "cancel" and "distributed" in code.co_filename)


class _engine:
    """``(submit, wait_first_completed, workers)`` of the chosen executor; closes what it
    started."""

    def __init__(self, executor: Any, scheduler: str | None, workers: int | None,
                 config: ReconstructionConfig | None = None):
        self.executor, self.scheduler, self.workers = executor, scheduler, workers
        self.config = config
        self.owned: list[Any] = []
        self.client: Any = None  # a Dask client: the warm-ups' (to cancel at the end)
        self.warming: list[Any] = []

    def __enter__(self) -> tuple[Callable[..., Any], Callable[[list[Any]], Any], int]:
        ex = self.executor
        if ex is None:
            import dask
            from distributed import Client

            try:  # a stop while the cluster starts: held until it can be closed
                with STOP_SIGNALS.deferred(), dask.config.set(dask_settings()):
                    if self.scheduler is not None:
                        ex = Client(self.scheduler)
                    else:
                        cluster = embedded_cluster(self.workers)
                        self.owned.append(cluster)
                        ex = Client(cluster)
                    self.owned.insert(0, ex)
            except BaseException:
                self._close()
                raise
        from distributed import Client
        from distributed import wait as dask_wait

        if isinstance(ex, Client):
            quiet_interrupted_sync()
            n_workers = max(len(ex.scheduler_info()["workers"]), 1)
            self.client = ex
            self.warming = warm_workers(ex, self.config)

            def submit(fn: Callable[..., Any], *args: Any) -> Any:
                return ex.submit(fn, *args, pure=False)

            def wait(fs: list[Any]) -> Any:
                return dask_wait(fs, return_when="FIRST_COMPLETED").done
        else:
            n_workers = getattr(ex, "_max_workers", None) or 1

            def submit(fn: Callable[..., Any], *args: Any) -> Any:
                return ex.submit(fn, *args)

            def wait(fs: list[Any]) -> Any:
                return cf.wait(fs, return_when=cf.FIRST_COMPLETED).done
        return submit, wait, n_workers

    def __exit__(self, *exc: object) -> None:
        if self.warming:  # done long ago, or pinned to a worker that died: not left behind
            self.client.cancel(self.warming)
        self._close()

    def _close(self) -> None:
        """Close the client and cluster started here; a stop meanwhile is held (a stop
        inside Dask's close left a worker process behind, :mod:`solver.stopping`)."""
        with STOP_SIGNALS.deferred():
            for thing in self.owned:
                thing.close()


def warm_workers(client: Any, config: ReconstructionConfig | None = None) -> list[Any]:
    """One :func:`solver.warmup.warm_refinement` on every worker of the Dask ``client``,
    submitted before any track and not waited for: Dask runs a client's tasks in the order
    they were submitted, so each worker warms up (imports, compiled code: 2.6 s in a fresh
    worker that compiles, under 1 s from the cache) while the first tracks are still being
    decoded, instead of in its first track. Returns the futures (to cancel at the end)."""
    from .warmup import warm_refinement

    return [client.submit(warm_refinement, config, workers=[address],
                          allow_other_workers=False, pure=False)
            for address in client.scheduler_info()["workers"]]
