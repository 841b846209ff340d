"""What a track's figure (:func:`solver.figures.draw_track_figure`) draws, apart from the
drawing, so that it can be drawn later from what a run stored rather than on the worker.

Built from a reconstruction and its plot table (:func:`from_reconstruction`, on the worker), or
from a run's stored rows (:func:`from_stored`): ``tracks.parquet`` (the states at the plots,
the plots' times, sensors and altitudes), ``segments.parquet`` (the controls) and
``figure_data.parquet`` (:data:`FIGURE_COLUMNS`: what no other output holds, the plots as
fixes in the plane with their one-sigma covariances and, unless ``samples.parquet`` keeps
them, the samples the reconstruction's line is drawn through). Numpy and Arrow only: no
matplotlib on a worker that draws nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from .inputs import FloatArray
from .io.dates import date_of, midnight_us
from .plots import PlotTable
from .results import Reconstruction, Segment

FIGURE_DATA = "figure_data.parquet"
"""The run's directory of :data:`FIGURE_COLUMNS` parts, beside ``tracks.parquet``'s (the same
part names: :func:`solver.batch.reconstruct_many` commits them together)."""
FIGURE_COLUMNS = ("aircraft", "item", "sensor_index", "sensor_kind", "t", "x", "z", "cov_x_x",
                  "cov_x_z", "cov_z_z", "speed", "h_m", "h_sigma_m")
"""Columns of ``figure_data.parquet``: a track's rows with ``item`` ``plot`` (one per plot, in
the table's order as ``tracks.parquet``'s ``plot``: its sensor's place in the track's sensors
and kind, the fix's centre ``x``, ``z`` in the plane (m) and its one-sigma covariance, m^2)
then ``sample`` (the reconstruction every ``sample_step_s``: ``t``, ``x``, ``z``, ground
speed in the plane ``hypot(vx, vz)``, the estimated height and its sigma, null where not
estimated); a column that does not apply to an item is null."""


@dataclass
class TrackFigureData:
    """A track's figure's content: its sensors ``(id, kind)`` in the table's order; per plot
    (table order) the sensor's index, time, fix centre and one-sigma covariance ``(xx, xz,
    zz)`` and altitude (NaN: unknown); the reconstructed position and covariance (None when
    there is none) at each plot; the samples (time, position, ground speed in the plane,
    height and its sigma where estimated); the segments."""

    sensors: tuple[tuple[str, str], ...]
    plot_sensor: np.ndarray
    plot_t: FloatArray
    plot_x: FloatArray
    plot_z: FloatArray
    plot_cov: FloatArray
    plot_altitude_m: FloatArray
    at_x: FloatArray
    at_z: FloatArray
    at_cov: FloatArray | None
    sample_t: FloatArray
    sample_x: FloatArray
    sample_z: FloatArray
    sample_speed: FloatArray
    sample_h: FloatArray | None
    sample_h_sigma: FloatArray | None
    segments: list[Segment]

    def __len__(self) -> int:
        return int(self.plot_t.shape[0])


def _upper(cov: FloatArray) -> FloatArray:
    """``(n, 3)`` terms ``xx, xz, zz`` of ``(n, >=2, >=2)`` covariances (the upper triangle,
    as ``tracks.parquet`` keeps them)."""
    return np.column_stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]])


def from_reconstruction(table: PlotTable, rec: Reconstruction) -> TrackFigureData:
    """The figure's content of a reconstruction of ``table``: each plot's fix (its error
    ellipse's axes ``A``, ``B`` at angle ``psi`` as the covariance
    ``R(psi) diag(B^2, A^2) R(psi)^T``)."""
    e = table.fixes().ellipses
    c, s = np.cos(e.psi), np.sin(e.psi)
    plot_cov = np.column_stack([c * c * e.B**2 + s * s * e.A**2, s * c * (e.B**2 - e.A**2),
                                s * s * e.B**2 + c * c * e.A**2])
    a, smp = rec.at_plots, rec.samples
    return TrackFigureData(
        sensors=tuple((sensor.id, sensor.kind) for sensor in table.sensors),
        plot_sensor=np.asarray(table.sensor, dtype=int), plot_t=table.t,
        plot_x=np.asarray(e.cx, dtype=float), plot_z=np.asarray(e.cz, dtype=float),
        plot_cov=plot_cov, plot_altitude_m=table.altitude_m, at_x=a.x, at_z=a.z,
        at_cov=None if a.cov is None else _upper(a.cov), sample_t=smp.t, sample_x=smp.x,
        sample_z=smp.z, sample_speed=smp.speed, sample_h=smp.h, sample_h_sigma=smp.h_sigma,
        segments=list(rec.segments))


def figure_rows(key: str, data: TrackFigureData, samples: bool = True) -> pa.Table:
    """``figure_data.parquet``'s rows of a track (:data:`FIGURE_COLUMNS`); ``samples``: with
    the sample rows (not when ``samples.parquet`` keeps the same samples)."""
    n = len(data)
    m = len(data.sample_t) if samples else 0
    nulls = np.full(m, np.nan)

    def col(plot: FloatArray | None, sample: FloatArray | None) -> pa.Array:
        """Floats of both items; NaN stays NaN, None (not applicable) is null."""
        parts = [np.full(n, np.nan) if plot is None else np.asarray(plot, float),
                 nulls if sample is None else np.asarray(sample, float)[:m]]
        mask = np.concatenate([np.full(n, plot is None), np.full(m, sample is None)])
        return pa.array(np.concatenate(parts), pa.float64(), mask=mask)

    kinds = [kind for _, kind in data.sensors]
    return pa.table({
        "aircraft": pa.array([key] * (n + m), pa.string()),
        "item": pa.array(["plot"] * n + ["sample"] * m, pa.string()),
        "sensor_index": pa.array(np.concatenate([data.plot_sensor, np.zeros(m, int)]),
                                 pa.int32(), mask=np.arange(n + m) >= n),
        "sensor_kind": pa.array([kinds[k] for k in data.plot_sensor.tolist()] + [None] * m,
                                pa.string()),
        "t": col(None, data.sample_t), "x": col(data.plot_x, data.sample_x),
        "z": col(data.plot_z, data.sample_z), "cov_x_x": col(data.plot_cov[:, 0], None),
        "cov_x_z": col(data.plot_cov[:, 1], None), "cov_z_z": col(data.plot_cov[:, 2], None),
        "speed": col(None, data.sample_speed), "h_m": col(None, data.sample_h),
        "h_sigma_m": col(None, data.sample_h_sigma)})


def _floats(table: pa.Table, name: str) -> FloatArray:
    """A float column as an array, null as NaN."""
    return np.asarray(table.column(name).to_numpy(zero_copy_only=False), dtype=float)


def _optional(table: pa.Table, name: str) -> FloatArray | None:
    """A float column, None when every value is null (the quantity was not estimated)."""
    column = table.column(name)
    return None if column.null_count == len(column) else _floats(table, name)


def from_stored(states: pa.Table, segments: pa.Table, rows: pa.Table,
                samples: pa.Table | None = None) -> TrackFigureData:
    """The figure's content from a track's stored rows: ``states`` (``tracks.parquet``),
    ``segments`` (``segments.parquet``), ``rows`` (``figure_data.parquet``) and, where the
    rows hold no samples, ``samples`` (``samples.parquet``; its speed is on the earth, the
    figure's in the plane: ``hypot(vx, vz)``). Raises ``ValueError`` when they do not
    belong together (a plot count or a sensor that differs)."""
    item = rows.column("item").to_numpy(zero_copy_only=False)
    plots, own = rows.filter(pa.array(item == "plot")), rows.filter(pa.array(item == "sample"))
    order = np.argsort(states.column("plot").to_numpy(), kind="stable")
    states = states.take(pa.array(order))
    if plots.num_rows != states.num_rows:
        raise ValueError(f"{plots.num_rows} plot rows of figure data for {states.num_rows} "
                         "states")
    index = plots.column("sensor_index").to_numpy(zero_copy_only=False).astype(int)
    ids = states.column("sensor").to_pylist()
    kinds = plots.column("sensor_kind").to_pylist()
    sensors: dict[int, tuple[str, str]] = {}
    for k, sid, kind in zip(index.tolist(), ids, kinds, strict=True):
        if sensors.setdefault(k, (sid, kind)) != (sid, kind):
            raise ValueError(f"sensor {k} is both {sensors[k]} and {(sid, kind)}")
    if sorted(sensors) != list(range(len(sensors))):
        raise ValueError(f"sensor indexes {sorted(sensors)} are not 0..{len(sensors) - 1}")
    if own.num_rows:
        t, x, z = (_floats(own, c) for c in ("t", "x", "z"))
        speed, h, h_sigma = _floats(own, "speed"), _optional(own, "h_m"), _optional(
            own, "h_sigma_m")
    elif samples is not None and samples.num_rows:
        t, x, z = (_floats(samples, c) for c in ("t", "x", "z"))
        speed = np.hypot(_floats(samples, "vx"), _floats(samples, "vz"))
        h, h_sigma = _optional(samples, "h_m"), _optional(samples, "h_sigma_m")
    else:
        raise ValueError("no samples of the reconstruction are stored")
    at_cov = np.column_stack([_floats(states, c) for c in ("cov_x_x", "cov_x_z", "cov_z_z")])
    segs = [Segment(float(r["t_start"]), float(r["t_end"]), float(r["x"]), float(r["z"]),
                    float(np.deg2rad(r["heading_deg"])), float(r["speed"]), float(r["u"]),
                    float(r["w"])) for r in segments.to_pylist()]
    return TrackFigureData(
        sensors=tuple(sensors[k] for k in range(len(sensors))), plot_sensor=index,
        plot_t=_floats(states, "t"), plot_x=_floats(plots, "x"), plot_z=_floats(plots, "z"),
        plot_cov=np.column_stack([_floats(plots, c) for c in ("cov_x_x", "cov_x_z",
                                                               "cov_z_z")]),
        plot_altitude_m=_floats(states, "plot_altitude_m"), at_x=_floats(states, "x"),
        at_z=_floats(states, "z"),
        at_cov=at_cov if np.isfinite(at_cov).all() else None,  # stored NaN: none
        sample_t=t, sample_x=x, sample_z=z, sample_speed=speed, sample_h=h,
        sample_h_sigma=h_sigma, segments=segs)


def read_stored(out: Path, part: str, key: str
                ) -> tuple[TrackFigureData, bool, str | None] | None:
    """The figure's content of the track ``key`` committed in ``part`` of the run in ``out``
    (:func:`from_stored`), whether its times are of the day (its ``time_of_day_s`` filled)
    and the date of the midnight they count from (``time_utc - t``; None when not known);
    None when the run kept no figure data for it."""
    path = out / FIGURE_DATA / part
    if not path.is_file():
        return None
    flt = pc.field("aircraft") == key
    rows = pq.read_table(path, filters=flt)
    if not rows.num_rows:
        return None
    states = pq.read_table(out / "tracks.parquet" / part, filters=flt)
    segments = pq.read_table(out / "segments.parquet" / part, filters=flt)
    samples = out / "samples.parquet" / part
    kept = pq.read_table(samples, filters=flt) if samples.is_file() else None
    return (from_stored(states, segments, rows, kept),
            states.column("time_of_day_s").null_count == 0, date_of(midnight_us(states)))
