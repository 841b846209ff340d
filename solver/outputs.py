"""A run's whole-recording output files, written from its output directory once every track
is in (the command line's and a service job's), reading the tracks' Parquet parts one at a time
(memory bounded by a part, not the run); the tables are written whole under another name and
then renamed (a stop leaves the old ones):

- ``tracks.csv`` and ``tracks.geojsonl`` from ``tracks.parquet/``: one GeoJSON LineString
  feature per aircraft, for maps; a MultiLineString cut at the antimeridian where a track
  crosses it (:func:`write_csv_and_geojson`, :func:`line_geometry`);
- ``manoeuvres.csv`` from ``segments.parquet/``: every track's turns and speed changes
  (:mod:`solver.manoeuvres`), with latitude and longitude at their start and end
  (:func:`write_manoeuvres`);
- ``map.png``: every track (thinned, :data:`MAP_POINTS_PER_TRACK`) with the radar
  sites (:func:`write_map`);
- ``warnings.csv`` (every track's warnings) with the state of the whole directory, this run's
  tracks and those of the runs it resumed (:func:`output_state`).
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from .batch import TRACK_COLUMNS, ledger_entries, read_part
from .frames import LocalFrame
from .io.dates import iso_utc, utc_times
from .io.sensors_file import SensorSet
from .io.split import recording_frame
from .io.tables import PlotRows
from .sensors import RadarSensor

MAP_POINTS_PER_TRACK = 200
"""A recording map draws every k-th point of a track, k its points // this (at most twice this
many points)."""
WARNING_EXAMPLES = 20  # tracks whose warnings summary.json repeats (warnings.csv has all)


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
    returns (rows, tracks). ``time_utc`` is ISO 8601 text ending in ``Z`` in the CSV, and a
    feature's ``time_utc_start`` / ``time_utc_end`` beside ``t_start`` / ``t_end`` (null
    where the recording's date is not known)."""
    parts = sorted((out / "tracks.parquet").glob("part-*.parquet"))
    rows = tracks = 0
    writer: pacsv.CSVWriter | None = None
    csv_tmp, geo_tmp = out / ".tracks.csv.tmp", out / ".tracks.geojsonl.tmp"
    with open(geo_tmp, "w", encoding="utf-8") as geo:
        for part in parts:
            table = read_part(part)
            text = table.set_column(table.column_names.index("time_utc"), "time_utc",
                                    iso_utc(table.column("time_utc")))
            if writer is None:
                writer = pacsv.CSVWriter(csv_tmp, text.schema)
            writer.write_table(text)
            rows += table.num_rows
            keys = table.column("aircraft").to_numpy(zero_copy_only=False)
            lat = table.column("lat_deg").to_numpy(zero_copy_only=False).astype(float)
            lon = table.column("lon_deg").to_numpy(zero_copy_only=False).astype(float)
            t = table.column("t").to_numpy()
            utc = iso_utc(table.column("time_utc")).to_pylist()
            for key, sel in _key_groups(keys):
                coords = [[round(b, 7), round(a, 7)]
                          for a, b in zip(lat[sel].tolist(), lon[sel].tolist(), strict=True)
                          if math.isfinite(a) and math.isfinite(b)]
                if len(coords) < 2:
                    continue
                first, last = sel[np.argmin(t[sel])], sel[np.argmax(t[sel])]
                feature = {"type": "Feature", "geometry": line_geometry(coords),
                           "properties": {"aircraft": key, "t_start": float(t[first]),
                                          "t_end": float(t[last]),
                                          "time_utc_start": utc[first],
                                          "time_utc_end": utc[last],
                                          "plots": int(sel.size)}}
                geo.write(json.dumps(feature) + "\n")
                tracks += 1
    if writer is None:  # no track: the header alone, as the other tables have theirs
        writer = pacsv.CSVWriter(csv_tmp, pa.schema(
            [(n, pa.string() if n in ("aircraft", "source", "sensor", "time_utc")
              else pa.float64()) for n in TRACK_COLUMNS]))
    writer.close()
    os.replace(csv_tmp, out / "tracks.csv")  # whole files only: a stop leaves the old ones
    os.replace(geo_tmp, out / "tracks.geojsonl")
    return rows, tracks


def write_manoeuvres(out: Path, frame: LocalFrame | None, date: str | None = None) -> int:
    """``manoeuvres.csv`` from the segments' Parquet parts (:mod:`solver.manoeuvres`), one part
    at a time, with latitude and longitude at both ends in the recording's plane ``frame``
    (empty without one) and the UTC times of both ends on ``date`` (``time_utc_start``,
    ``time_utc_end``: ISO 8601 ending in ``Z``; empty without a date); returns the rows
    written."""
    from .manoeuvres import Manoeuvre, from_segment_rows

    fields = list(Manoeuvre.__dataclass_fields__)
    schema = pa.schema([("aircraft", pa.string())] + [
        (k, pa.string() if k in ("kind", "direction") else pa.float64()) for k in fields] + [
        (k, pa.float64()) for k in ("lat_start_deg", "lon_start_deg", "lat_end_deg",
                                    "lon_end_deg")] + [
        (k, pa.string()) for k in ("time_utc_start", "time_utc_end")])
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
                cols[f"time_utc_{end}"] = (None if date is None else iso_utc(
                    utc_times(np.array(cols[f"t_{end}"], float), date)).to_pylist())
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
