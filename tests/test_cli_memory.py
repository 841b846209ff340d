"""The command line reads a recording in parts: the memory its reading and splitting hold is
the aircraft in the air, not the recording (a recording 6x as long peaks as high)."""

from __future__ import annotations

import json
import tracemalloc

import numpy as np
from test_io_asterix import SENSOR_FILE

import solver.cli as cli
from solver.frames import LocalFrame
from solver.io.tables import PlotRows, write_table


def _table(path, aircraft: int) -> int:
    """ADS-B plots of ``aircraft`` straight flights of 200 s, one every 50 s (about four in
    the air at once), one plot a second."""
    frame = LocalFrame(46.2, 14.5)
    t = np.concatenate([50.0 * k + np.arange(200.0) for k in range(aircraft)])
    k = np.repeat(np.arange(aircraft), 200)
    x = -20_000.0 + 200.0 * (t - 50.0 * k) + 100.0 * k
    z = 1_000.0 * (k % 7)
    lat, lon = frame.to_geodetic(x, z)
    order = np.argsort(t, kind="stable")
    n = t.size
    rows = PlotRows.from_columns(n, t=t[order], sensor=np.full(n, "ADSB", dtype=object),
                                 lat_deg=lat[order], lon_deg=lon[order],
                                 mode_s=0x400000 + k[order])
    write_table(rows, path)
    return n


def _peak_while_streaming(path, sensors) -> tuple[int, int, int]:
    tracemalloc.start()
    try:
        s = cli.stream(path, sensors, read_ahead=4)
        tracks = plots = 0
        for tr in s.tracks:
            tracks += 1
            plots += len(tr.table)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert s.rows_read == plots
    return tracks, plots, peak


def test_streamed_reading_memory_is_flat_in_the_recording_length(tmp_path, monkeypatch):
    monkeypatch.setattr(cli, "STREAM_BATCH_ROWS", 1000)
    sensors = tmp_path / "sensors.json"
    sensors.write_text(json.dumps(SENSOR_FILE))
    short, long = tmp_path / "short.csv", tmp_path / "long.csv"
    n_short, n_long = _table(short, 16), _table(long, 96)
    _table(tmp_path / "warm.csv", 3)
    _peak_while_streaming(tmp_path / "warm.csv", sensors)  # imports and caches first
    tracks_s, plots_s, peak_s = _peak_while_streaming(short, sensors)
    tracks_l, plots_l, peak_l = _peak_while_streaming(long, sensors)
    assert (tracks_s, plots_s, tracks_l, plots_l) == (16, n_short, 96, n_long)
    assert peak_l < 1.5 * peak_s, (peak_s, peak_l)
    # the whole-recording reader holds every row: its peak grows with the length
    tracemalloc.start()
    try:
        loaded = cli.load(long, sensors)
        _, whole = tracemalloc.get_traced_memory()
        assert len(loaded.rows) == n_long
    finally:
        tracemalloc.stop()
    assert whole > 2 * peak_l, (whole, peak_l)
