"""The command line reads a recording in parts: the memory its reading and splitting hold is
the aircraft in the air, not the recording (a recording 6x as long peaks as high), and what
it keeps of the tracks it has reconstructed does not grow with their number."""

from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from test_io_asterix import SENSOR_FILE, SENSORS

import solver.cli as cli
import solver.io.reading as reading
import solver.sensor_stats as sensor_stats
from solver.frames import LocalFrame
from solver.io.problems import Problems
from solver.io.tables import PlotRows, write_table
from solver.run_settings import RunSettings
from solver.track_task import AssessedTrack


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
        s = reading.stream(path, sensors, read_ahead=4)
        tracks = plots = 0
        for tr in s.tracks:
            tracks += 1
            plots += len(tr.table)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert s.rows_read == plots
    return tracks, plots, peak


def _peaks(tmp_path, make, suffix: str, short_n: int, long_n: int) -> tuple[int, Path, int]:
    """Assert that a recording of ``long_n`` aircraft made by ``make(path, aircraft) -> rows``
    streams every aircraft as one track with every plot, and peaks below 1.5x one of
    ``short_n`` (after a small one warms imports and caches); the rows of the long one, its
    path and its peak."""
    sensors = tmp_path / "sensors.json"
    sensors.write_text(json.dumps(SENSOR_FILE))
    short, long = tmp_path / f"short{suffix}", tmp_path / f"long{suffix}"
    n_short, n_long = make(short, short_n), make(long, long_n)
    make(tmp_path / f"warm{suffix}", 2)
    _peak_while_streaming(tmp_path / f"warm{suffix}", sensors)
    tracks_s, plots_s, peak_s = _peak_while_streaming(short, sensors)
    tracks_l, plots_l, peak_l = _peak_while_streaming(long, sensors)
    assert (tracks_s, plots_s, tracks_l, plots_l) == (short_n, n_short, long_n, n_long)
    assert peak_l < 1.5 * peak_s, (peak_s, peak_l, long.stat().st_size)
    assert long.stat().st_size > 3 * short.stat().st_size
    return n_long, long, peak_l


def test_streamed_reading_memory_is_flat_in_the_recording_length(tmp_path, monkeypatch):
    monkeypatch.setattr(reading, "STREAM_BATCH_ROWS", 1000)
    sensors = tmp_path / "sensors.json"
    n_long, long, peak_l = _peaks(tmp_path, _table, ".csv", 16, 96)
    # the whole-recording reader holds every row: its peak grows with the length
    tracemalloc.start()
    try:
        loaded = reading.load(long, sensors)
        _, whole = tracemalloc.get_traced_memory()
        assert len(loaded.rows) == n_long
    finally:
        tracemalloc.stop()
    assert whole > 2 * peak_l, (whole, peak_l)


def _radar_table(path, aircraft: int) -> int:
    """:func:`_table`'s timing (200-s flights, one every 50 s) for aircraft without Mode S
    that R1 and R2 both see (each under its own track number): one track each by the
    association."""
    from test_io_association import Flight, recording

    flights = [Flight(20e3 + 100.0 * k - 200.0 * 50.0 * k, 10e3 + 1_000.0 * (k % 7), 200.0,
                      0.0, 50.0, {"R1": (k, 50.0 * k, 50.0 * k + 200.0),
                                  "R2": (1000 + k, 50.0 * k, 50.0 * k + 200.0)})
               for k in range(aircraft)]
    rows = recording(flights)
    write_table(rows, path)
    return len(rows)


def test_streamed_association_memory_is_flat_in_the_recording_length(tmp_path, monkeypatch):
    """Sensor tracks without Mode S are held until their associations are decided (issue
    16): still the aircraft in the air, a recording 6x as long peaks as high, each aircraft
    one track of both radars."""
    monkeypatch.setattr(reading, "STREAM_BATCH_ROWS", 300)
    _peaks(tmp_path, _radar_table, ".csv", 16, 96)


def _asterix(path, aircraft: int) -> int:
    """:func:`_table`'s flights as a raw ASTERIX recording (CAT021, libasterix encodes)."""
    from solver.io.asterix import encode_rows
    from solver.io.tables import read_table

    n = _table(path.with_suffix(".csv"), aircraft)
    rows, _ = read_table(path.with_suffix(".csv"))
    path.write_bytes(encode_rows(rows, SENSORS))
    return n


def test_streamed_asterix_memory_is_flat_in_the_recording_length(tmp_path, monkeypatch):
    """An ASTERIX file is memory-mapped and decoded unit by unit: the reading of a recording
    6x as long peaks as high (it was read whole: the peak grew with the file)."""
    monkeypatch.setattr(reading, "STREAM_CHUNK_BYTES", 1 << 12)
    _, long, _ = _peaks(tmp_path, _asterix, ".ast", 8, 48)
    assert long.stat().st_size > 5 * (tmp_path / "short.ast").stat().st_size


def _stub_task(key, table, config, time_limit_s, figures_dir=None, filters=(),
               filter_gate=None, times_of_day=False, samples=False, max_samples=None, date=None):
    """What :func:`solver.track_task.assess_track` returns, without the reconstruction: the
    track's rows and its sensor's statistics."""
    import pyarrow as pa

    from solver.batch import SEGMENT_COLUMNS, TRACK_COLUMNS

    n = len(table)
    cols = {c: pa.array(np.zeros(n)) for c in TRACK_COLUMNS}
    cols["time_utc"] = pa.nulls(n, pa.timestamp("us", tz="UTC"))
    cols["aircraft"] = pa.array([key] * n)
    cols["sensor"] = pa.array(["ADSB"] * n)
    cols["plot"] = pa.array(np.arange(n, dtype=np.int32))
    segments = {c: pa.array(np.zeros(3)) for c in SEGMENT_COLUMNS}
    segments["aircraft"] = pa.array([key] * 3)
    report = {"id": "ADSB", "kind": "position", "plots": n, "plots_gated": 0,
              "range_residual_mean_m": None, "position_residual_rms_m": 10.0 + n % 7,
              "range_bias_m": None, "span_s": float(np.ptp(table.t)), "median_step_s": 1.0}
    return AssessedTrack(key, "done", n, 0.0, None, [], pa.table(cols),
                         pa.table(segments), sensors=[report])


def _retained_by_the_run(tmp_path, tracks: int, client) -> int:
    """Bytes this process (the command line's, with the embedded cluster's scheduler) still
    holds after reconstructing ``tracks`` tracks of 200 plots through ``cli._reconstruct``
    on ``client`` (``_stub_task`` on the worker)."""
    import argparse
    import gc
    import time

    from solver.batch import TrackProblem
    from solver.plots import PlotTable

    adsb = SENSORS.sensors[-1]
    frame = LocalFrame(46.2, 14.5)
    t = np.arange(200.0)
    lat, lon = frame.to_geodetic(-20_000.0 + 200.0 * t, np.zeros_like(t))
    table = PlotTable.build([adsb], t, np.zeros(t.size, int), lat_deg=lat, lon_deg=lon)
    loaded = reading.Streamed(SENSORS, Problems(), (TrackProblem(f"A{k:05d}", table)
                                                    for k in range(tracks)))
    args = argparse.Namespace(method="refined", no_progress=True, figures=False,
                              time_limit=None, retry_failed=False)
    out = tmp_path / f"out{tracks}"
    gc.collect()
    tracemalloc.start()
    try:
        before, _ = tracemalloc.get_traced_memory()
        summary, _ = cli._reconstruct(args, RunSettings(), out, loaded, client,
                                      time.perf_counter())
        del loaded
        gc.collect()
        after, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert summary.done == tracks
    stats = sensor_stats.SensorStats(SENSORS, {})
    for reports in sensor_stats.iter_stats(out / "sensor_stats.jsonl"):
        stats.add(reports)
    row = {r["sensor"]: r for r in stats.rows()}["ADSB"]
    assert row["tracks"] == tracks and row["plots"] == 200 * tracks
    return after - before


def test_the_command_lines_memory_is_flat_in_the_tracks(tmp_path, monkeypatch):
    """What the command line's process keeps of the tracks it has sent and received (the
    ledger, the sensors' statistics, Dask's message logs of the client and of the embedded
    cluster's scheduler) does not grow with their number: 360 tracks leave about as much
    as 60 (Dask's default logs kept the last 1,000 task messages, the tracks' plots in them,
    about 30 KB a track; the statistics of every track were kept to the end)."""
    monkeypatch.setattr(cli, "assess_track", _stub_task)
    with cli._cluster(None, 1) as client:
        _retained_by_the_run(tmp_path, 20, client)  # the cluster's first tasks
        short = _retained_by_the_run(tmp_path, 60, client)
        long = _retained_by_the_run(tmp_path, 360, client)
    assert long - short < 1_000_000, (short, long)


def _radar_report(k: int) -> dict:
    return {"id": "R1", "kind": "radar", "plots": 10 + k, "plots_gated": k % 2,
            "span_s": 100.0 + k, "median_step_s": 4.0 + 0.01 * (k % 5),
            "range_residual_mean_m": 1.0 + k % 3, "range_residual_rms_m": 50.0 + k % 4,
            "azimuth_residual_mean_rad": 1e-4 * (k % 3), "azimuth_residual_rms_rad": 1e-3,
            "position_residual_rms_m": None, "range_bias_m": float(k % 7),
            "azimuth_bias_rad": 1e-4 * (k % 5), "time_bias_s": 0.1 * (k % 3)}


def test_sensor_statistics_are_exact_below_their_sample_and_bounded_above(monkeypatch):
    """SensorStats pools the tracks' reports in fixed-size accumulators: with no more tracks
    than its median sample the medians and rates are the exact ones; beyond, what it holds
    stays at the sample's size."""
    monkeypatch.setattr(sensor_stats, "MEDIAN_SAMPLE", 8)
    reports = [_radar_report(k) for k in range(8)]
    stats = sensor_stats.SensorStats(SENSORS, {})
    for r in reports:
        stats.add([r])
    row = {r["sensor"]: r for r in stats.rows()}["R1"]
    period = float(np.median([r["median_step_s"] for r in reports]))
    expected = sum(r["span_s"] / period + 1 for r in reports)
    assert row["scan_period_s"] == period and row["tracks"] == 8
    assert row["detection_rate"] == pytest.approx(
        min(sum(r["plots"] for r in reports) / expected, 1.0), rel=1e-12)
    biases = np.median([[r["range_bias_m"], r["azimuth_bias_rad"], r["time_bias_s"]]
                        for r in reports], axis=0)
    assert row["range_bias_m"] == biases[0] and row["time_bias_s"] == biases[2]
    assert row["azimuth_bias_deg"] == pytest.approx(np.rad2deg(biases[1]), rel=1e-12)
    assert row["azimuth_bias_deg"] > 0.005  # degrees (the median report's 1.5e-4 rad)
    n = sum(r["plots"] - r["plots_gated"] for r in reports)
    mean = sum((r["plots"] - r["plots_gated"]) * r["range_residual_mean_m"]
               for r in reports) / n
    assert row["range_residual_mean_m"] == pytest.approx(mean, rel=1e-12)
    for k in range(8, 5000):
        stats.add([_radar_report(k)])
    acc = stats.acc["R1"]
    assert len(acc["steps"].values) == len(acc["biases"].values) == 8
    assert acc["steps"].seen == 5000 and stats.rows()[0]["tracks"] == 5000


def test_statistics_file_is_read_one_track_at_a_time_last_line_wins(tmp_path):
    path = tmp_path / "sensor_stats.jsonl"
    lines = [{"aircraft": "A", "sensors": [_radar_report(1)]},
             {"aircraft": "B", "sensors": [_radar_report(2)]},
             {"aircraft": "A", "sensors": [_radar_report(3)]}]
    path.write_text("".join(json.dumps(x) + "\n" for x in lines) + '{"aircraft": "C", "se')
    got = list(sensor_stats.iter_stats(path))
    assert got == [[_radar_report(2)], [_radar_report(3)]]
    assert list(sensor_stats.iter_stats(tmp_path / "none.jsonl")) == []
