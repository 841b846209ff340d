"""A recording's plot rows -> one :class:`solver.plots.PlotTable` per aircraft.

Aircraft key of a row (``../shared/spec/recordings.md``), first that applies:

1. ``aircraft`` (the user's own key), as given;
2. the Mode S address, as 6 hex digits (``4CA2D1``): plots of every sensor with that address
   are one track (radar and ADS-B merged);
3. the sensor's track number: ``<sensor>:track:<number>``;
4. the Mode 3/A code: ``<sensor>:mode3a:<octal code>``.

Before keying, a sensor's track (sensor, track number) whose plots carry one single Mode S
address lends it to its plots without one, so a track with an intermittent address stays one
aircraft. Keys 2-4 are split where the aircraft is not seen for more than ``gap_s`` (default
300 s: track numbers and codes are reused, an address may fly twice in a recording); later
pieces get ``#2``, ``#3`` ... Rows without any key are reported (``no_aircraft_key``).

Each aircraft's rows are put in time order (stable); a sensor's second plot at the same time
of the same aircraft is reported (``duplicate_time``) and left out (the first is kept), as are
rows of sensors not in the sensor file (``unknown_sensor``), rows whose measurement does not
fit their sensor's kind (``wrong_measurement``), rows the plots table refuses (its message, the
row's byte offset or row number) and tracks of fewer than ``min_plots`` plots (``short_track``,
with their key and count). Nothing is dropped without a counted problem.

Every track is built in the recording's plane (:func:`recording_frame`), so all tracks share
one ``x``/``z`` plane.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..frames import LocalFrame
from ..inputs import InputError, format_loc
from ..plots import PlotTable
from ..sensors import RadarSensor
from .problems import Problems
from .sensors_file import SensorSet
from .tables import PlotRows

GAP_S = 300.0
MIN_PLOTS = 3
_MAX_ROW_RETRIES = 50


@dataclass(frozen=True)
class AircraftTrack:
    """One aircraft's plots: its ``key``, the validated ``table`` (rows in time order) and, for
    each table row, its index in the recording's :class:`PlotRows` (``rows``)."""

    key: str
    table: PlotTable
    rows: np.ndarray


def recording_frame(sensors: SensorSet, rows: PlotRows) -> LocalFrame | None:
    """The plane every track of a recording is reconstructed in: the sensor file's
    ``reference``, else the first radar's site, else the first position plot; None (flat, no
    geodesy) when there is none of these."""
    if sensors.reference is not None:
        return sensors.reference
    for s in sensors.sensors:
        if isinstance(s, RadarSensor) and s.site is not None:
            return LocalFrame(s.site.lat_deg, s.site.lon_deg)
    pos = np.flatnonzero(np.isfinite(rows.lat_deg) & np.isfinite(rows.lon_deg))
    if pos.size:
        return LocalFrame(float(rows.lat_deg[pos[0]]), float(rows.lon_deg[pos[0]]))
    return None


def aircraft_keys(rows: PlotRows, gap_s: float = GAP_S) -> np.ndarray:
    """The aircraft key of every row (``""``: none), see the module docstring."""
    n = len(rows)
    mode_s = rows.mode_s.copy()
    sensor = rows.sensor.astype(str)
    # a sensor's track with one single Mode S address lends it to its plots without one
    has_tn = rows.track_number >= 0
    if np.any(has_tn & (mode_s < 0)):
        tn_key = np.char.add(np.char.add(sensor, ":track:"), rows.track_number.astype(str))
        seg = _segments(np.where(has_tn, tn_key, ""), rows.t, gap_s)
        idx = np.flatnonzero(has_tn)
        for _, members in _groups(seg[idx]):
            m = idx[members]
            addresses = np.unique(mode_s[m][mode_s[m] >= 0])
            if addresses.size == 1:
                mode_s[m[mode_s[m] < 0]] = addresses[0]
    key = np.full(n, "", dtype=object)
    tn = np.char.add(np.char.add(sensor, ":track:"), rows.track_number.astype(str))
    code = np.char.add(np.char.add(sensor, ":mode3a:"),
                       np.array([f"{v:04o}" for v in rows.mode_3a.tolist()], dtype=str)
                       if n else np.array([], dtype=str))
    hexs = np.array([f"{v:06X}" for v in mode_s.tolist()], dtype=str) if n else np.array([])
    key = np.where(rows.mode_3a >= 0, code, key)
    key = np.where(rows.track_number >= 0, tn, key)
    key = np.where(mode_s >= 0, hexs, key)
    key = _segments(key.astype(str), rows.t, gap_s)
    user = rows.aircraft.astype(str) != ""
    key = np.where(user, rows.aircraft.astype(str), key)
    return key.astype(object)


def _groups(keys: np.ndarray) -> Iterator[tuple[str, np.ndarray]]:
    """``(key, indexes)`` of every distinct non-empty key, indexes in row order."""
    if keys.size == 0:
        return
    uniq, inverse = np.unique(keys, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.flatnonzero(np.diff(inverse[order])) + 1
    for members in np.split(order, bounds):
        k = str(uniq[inverse[members[0]]])
        if k:
            yield k, members


def _segments(keys: np.ndarray, t: np.ndarray, gap_s: float) -> np.ndarray:
    """``keys`` with ``#2``, ``#3`` ... appended after each time gap of more than ``gap_s``."""
    out = keys.astype(object).copy()
    for k, members in _groups(keys):
        tm = t[members]
        order = np.argsort(tm, kind="stable")
        piece = np.concatenate([[0], np.cumsum(np.diff(tm[order]) > gap_s)])
        if piece[-1] == 0:
            continue
        labels = np.array([k if p == 0 else f"{k}#{p + 1}" for p in piece.tolist()],
                          dtype=object)
        out[members[order]] = labels
    return out


def split_aircraft(rows: PlotRows, sensors: SensorSet, *, reference: LocalFrame | None = None,
                   min_plots: int = MIN_PLOTS, gap_s: float = GAP_S,
                   problems: Problems | None = None) -> Iterator[AircraftTrack]:
    """Yield one :class:`AircraftTrack` per aircraft (in order of first plot), recording every
    row left out in ``problems`` (see the module docstring). ``reference``: the plane (default
    :func:`recording_frame`)."""
    problems = problems if problems is not None else Problems()
    frame = reference if reference is not None else recording_frame(sensors, rows)
    index = sensors.index()
    n = len(rows)
    sensor_idx = np.array([index.get(s, -1) for s in rows.sensor.tolist()], dtype=int)
    usable = np.ones(n, dtype=bool)
    for i in np.flatnonzero(sensor_idx < 0).tolist():
        problems.add("unknown_sensor", rows.where(i), f"sensor {rows.sensor[i]!r} is not in "
                     "the sensor file: its plots are left out", key=str(rows.sensor[i]),
                     dropped=1)
    usable &= sensor_idx >= 0
    is_radar_sensor = np.array([isinstance(s, RadarSensor) for s in sensors.sensors] + [False])
    radar_row = is_radar_sensor[sensor_idx]
    has_radar = rows.is_radar()
    has_pos = np.isfinite(rows.lat_deg) & np.isfinite(rows.lon_deg)
    wrong = usable & np.where(radar_row, ~has_radar | has_pos, has_radar | ~has_pos)
    for i in np.flatnonzero(wrong).tolist():
        s = sensors.sensors[sensor_idx[i]]
        need = "range_m + azimuth_deg" if isinstance(s, RadarSensor) else "lat_deg + lon_deg"
        problems.add("wrong_measurement", rows.where(i), f"a plot of {s.kind} sensor {s.id!r} "
                     f"must carry {need} only: left out", key=s.id, dropped=1)
    usable &= ~wrong

    keys = aircraft_keys(rows, gap_s)
    no_key = usable & (keys.astype(str) == "")
    for i in np.flatnonzero(no_key).tolist():
        problems.add("no_aircraft_key", rows.where(i), "plot without aircraft key, Mode S "
                     "address, track number or Mode 3/A code: left out", key=str(rows.sensor[i]),
                     dropped=1)
    usable &= ~no_key

    idx = np.flatnonzero(usable)
    groups = sorted(_groups(keys[idx].astype(str)), key=lambda g: int(g[1][0]))
    for key, members in groups:
        track = _build(key, idx[members], rows, sensors, sensor_idx, frame, min_plots, problems)
        if track is not None:
            yield track


def _build(key: str, members: np.ndarray, rows: PlotRows, sensors: SensorSet,
           sensor_idx: np.ndarray, frame: LocalFrame | None, min_plots: int,
           problems: Problems) -> AircraftTrack | None:
    """One aircraft's validated table, or None (reported) when too little is left."""
    m = members[np.argsort(rows.t[members], kind="stable")]
    # a sensor's second plot at the same instant: keep the first
    s, t = sensor_idx[m], rows.t[m]
    order = np.lexsort((np.arange(m.size), t, s))
    dup_sorted = np.zeros(m.size, dtype=bool)
    dup_sorted[1:] = (s[order][1:] == s[order][:-1]) & (t[order][1:] == t[order][:-1])
    dup = np.zeros(m.size, dtype=bool)
    dup[order] = dup_sorted
    for j in np.flatnonzero(dup).tolist():
        i = int(m[j])
        problems.add("duplicate_time", rows.where(i), f"aircraft {key}: a second plot of sensor "
                     f"{rows.sensor[i]!r} at t = {rows.t[i]:.3f} s: left out (the first is "
                     "kept)", key=key, dropped=1)
    m = m[~dup]
    for _ in range(_MAX_ROW_RETRIES):
        if m.size < min_plots:
            problems.add("short_track", f"aircraft {key}", f"{m.size} plot(s), fewer than the "
                         f"{min_plots} a reconstruction needs: left out", dropped=int(m.size))
            return None
        used = np.unique(sensor_idx[m])
        local = np.searchsorted(used, sensor_idx[m])
        try:
            table = PlotTable.build(
                [sensors.sensors[k] for k in used.tolist()], rows.t[m], local,
                range_m=rows.range_m[m], azimuth_rad=np.deg2rad(rows.azimuth_deg[m]),
                lat_deg=rows.lat_deg[m], lon_deg=rows.lon_deg[m],
                altitude_m=rows.altitude_m[m], reference=frame)
        except InputError as e:
            if len(e.loc) >= 2 and e.loc[0] == "plots" and isinstance(e.loc[1], int):
                i = int(m[e.loc[1]])
                problems.add("bad_plot", rows.where(i), f"aircraft {key}: "
                             f"{format_loc(e.loc[2:]) or 'plot'} {e.message}: left out",
                             dropped=1)
                m = np.delete(m, e.loc[1])
                continue
            problems.add("bad_track", f"aircraft {key}", f"{e}: left out",
                         dropped=int(m.size))
            return None
        return AircraftTrack(key, table, m)
    problems.add("bad_track", f"aircraft {key}", f"more than {_MAX_ROW_RETRIES} bad plots: "
                 "left out", dropped=int(m.size))
    return None


__all__ = ["AircraftTrack", "aircraft_keys", "recording_frame", "split_aircraft"]
